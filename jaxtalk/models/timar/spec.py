"""TIMAR's interface as the run format, the commands and the experiments see it (:class:`jaxtalk.runs.ModelSpec`)."""

from __future__ import annotations

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.evaluation import evaluate
from jaxtalk.models.timar.inference import read_speech, sample_speech, step_frames, stream_speech
from jaxtalk.models.timar.loss import make_loss_fn
from jaxtalk.models.timar.model import init_params
from jaxtalk.models.timar.recipe import DEFAULTS, PRESET_DEFAULTS, train
from jaxtalk.models.timar.sampling import sample
from jaxtalk.models.timar.streaming import init_stream, stream, stream_step
from jaxtalk.runs import ModelSpec, SpeechAnimator, Streamer

__all__ = ["SPEC"]

SPEC = ModelSpec(
    name="timar",
    title="TIMAR",
    config_class=TimarConfig,
    presets=("paper", "small", "reference"),
    init_params=init_params,
    make_loss_fn=make_loss_fn,
    train=train,
    defaults=DEFAULTS,
    preset_defaults=dict(PRESET_DEFAULTS),
    sample=sample,
    guided=True,
    streamer=Streamer(init_stream, stream_step, stream),
    evaluate=evaluate,
    eval_options=("--temperature", "--scoring"),
    animator=SpeechAnimator(options=("--partner", "--cfg-scale", "--temperature"), read=read_speech, sample=sample_speech,
                            stream=stream_speech, step_frames=step_frames),
    data_fields=(("speech_dim", "turn_speech_dim"),),
    windows="whole turns (max_turns)",
    export_refusal="its per-frame diffusion head is vmapped, and jax2onnx's Dense has no batching rule; the sampler "
                   "also splits PRNG keys, which ONNX has no operator for (docs/onnx.md)",
)
