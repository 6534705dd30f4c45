"""FreeTalk's two models as the run format, the commands and the experiments see them
(:class:`jaxtalk.runs.ModelSpec`): ATS (audio -> landmark displacements, sampled by DDIM) and STM
(landmark displacements -> any mesh, deterministic)."""

from __future__ import annotations

from jaxtalk.models.freetalk import ats, stm
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.evaluation import evaluate_ats, evaluate_stm
from jaxtalk.models.freetalk.recipe import ATS_PRESET_DEFAULTS, DEFAULTS, STM_PRESET_DEFAULTS, train_ats, train_stm
from jaxtalk.runs import ModelSpec

__all__ = ["ATS", "STM"]

ATS = ModelSpec(
    name="ats",
    title="FreeTalk ATS",
    config_class=ATSConfig,
    presets=("paper", "small"),
    init_params=ats.init_params,
    make_loss_fn=ats.make_loss_fn,
    train=train_ats,
    defaults=DEFAULTS,
    preset_defaults=dict(ATS_PRESET_DEFAULTS),
    sample=ats.sample,
    evaluate=evaluate_ats,
    sample_refusal="{run} is a FreeTalk ATS run: sample it onto a mesh with --stm RUN_STM --mesh FILE (and --emotion, "
                   "--intensity); stream is for toktalk and timar runs",
    animates_user_meshes=True,
    data_fields=(("speech_dim", "speech_dim"),),
    family="freetalk",
    fine_tune_refusal="its recipe standardises the displacements with statistics of the new data, which the "
                      "starting weights were not trained with",
    export_refusal="its denoiser converts, but its DDIM sampler splits PRNG keys, which ONNX has no operator for "
                   "(docs/onnx.md)",
)

STM = ModelSpec(
    name="stm",
    title="FreeTalk STM",
    config_class=STMConfig,
    presets=("paper", "small"),
    init_params=stm.init_params,
    make_loss_fn=stm.make_loss_fn,
    train=train_stm,
    defaults=DEFAULTS,
    preset_defaults=dict(STM_PRESET_DEFAULTS),
    evaluate=evaluate_stm,
    sample_refusal="{run} is a stm run; sample/stream animate speech with toktalk, timar or (with --stm and --mesh) ats "
                   "runs; an stm run goes after an ats run: jaxtalk sample RUN_ATS AUDIO --stm RUN_STM",
    family="freetalk",
    reads="landmarks",
    export_refusal="its graph converts, but onnxruntime rejects the attention's einsum inside the per-frame loop "
                   "(docs/onnx.md)",
)
