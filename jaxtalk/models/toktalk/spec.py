"""TokTalk's interface as the run format, the commands and the experiments see it (:class:`jaxtalk.runs.ModelSpec`)."""

from __future__ import annotations

from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.evaluation import evaluate
from jaxtalk.models.toktalk.inference import TOKEN_INPUT, read_speech, rest_note, sample_speech, step_frames, stream_speech
from jaxtalk.models.toktalk.live import live_model
from jaxtalk.models.toktalk.loss import make_loss_fn
from jaxtalk.models.toktalk.model import init_params
from jaxtalk.models.toktalk.portable import export_stream
from jaxtalk.models.toktalk.recipe import DEFAULTS, train
from jaxtalk.models.toktalk.sampling import sample
from jaxtalk.models.toktalk.streaming import init_stream, stream, stream_step
from jaxtalk.models.toktalk.validation import plan_voice_validation
from jaxtalk.runs import ModelSpec, SpeechAnimator, Streamer

__all__ = ["SPEC"]

SPEC = ModelSpec(
    name="toktalk",
    title="TokTalk",
    config_class=TokTalkConfig,
    presets=("paper", "small", "tiny"),
    init_params=init_params,
    make_loss_fn=make_loss_fn,
    train=train,
    defaults=DEFAULTS,
    sample=sample,
    guided=True,
    streamer=Streamer(init_stream, stream_step, stream),
    evaluate=evaluate,
    eval_options=("--flame", "--sample-steps", "--offline", "--temperature"),
    animator=SpeechAnimator(options=("--style", "--cfg-scale", "--temperature"), read=read_speech, sample=sample_speech,
                            stream=stream_speech, step_frames=step_frames, other_inputs=(TOKEN_INPUT,),
                            rest_note=rest_note),
    live=live_model,
    data_fields=(("speech_dim", "token_dim"), ("token_rate", "token_rate")),
    style_asset=True,
    reads="audio tokens (the clips' own, or a VQ tokenizer's of the log-mel)",
    voice_validation=plan_voice_validation,
    export_stream=export_stream,
)
