"""The DualTalk baseline's interface as the run format, the commands and the experiments see it
(:class:`jaxtalk.runs.ModelSpec`). It regresses, so it has no sampler."""

from __future__ import annotations

from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.models.dualtalk.evaluation import evaluate
from jaxtalk.models.dualtalk.loss import make_loss_fn
from jaxtalk.models.dualtalk.model import init_params
from jaxtalk.models.dualtalk.recipe import DEFAULTS, PRESET_DEFAULTS, train
from jaxtalk.runs import ModelSpec

__all__ = ["SPEC"]

SPEC = ModelSpec(
    name="dualtalk",
    title="DualTalk baseline",
    config_class=DualTalkConfig,
    presets=("paper", "small"),
    init_params=init_params,
    make_loss_fn=make_loss_fn,
    train=train,
    defaults=DEFAULTS,
    preset_defaults=dict(PRESET_DEFAULTS),
    evaluate=evaluate,
    eval_options=("--scoring",),
    sample_refusal="{run} is a DualTalk baseline run: an offline model scored with `jaxtalk eval {run}`; sample/stream "
                   "animate speech with toktalk or timar runs",
    data_fields=(("speech_dim", "turn_speech_dim"),),
    windows="whole turns (max_turns)",
    export_refusal="an offline baseline, scored with jaxtalk eval; it has no live stream to export",
)
