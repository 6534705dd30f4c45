"""Every recipe called from Python with ``run_dir=`` writes a complete run folder: ``run.json``,
``config.json``, the checkpoint and the inference assets, which :func:`jaxtalk.runs.load_run` loads and
``jaxtalk sample`` opens, exactly as a run made by ``jaxtalk train``.

Each model trains two steps at its smallest graph on prepared SynthTalk tiny (compile time dominates).
"""

from __future__ import annotations

import dataclasses
import json

import jax
import numpy as np
import pytest
import soundfile as sf
from typer.testing import CliRunner

from jaxtalk.cli import app
from jaxtalk.runs import CONFIG_FILE, REGISTRY, RunRecord, load_run

runner = CliRunner()

# The smallest graphs of each model (as tests/test_cli_train.py and tests/test_dualtalk_model.py shrink them).
SMALL = {
    "toktalk": ("tiny", {"num_mid_blocks": 0}),
    "timar": ("small", {"width": 32, "num_layers": 1, "num_heads": 2, "head_width": 32, "head_blocks": 1,
                        "max_turns": 2, "sample_steps": 2}),
    "dualtalk": ("small", {"width": 16, "num_layers": 1, "num_heads": 2, "lstm_layers": 1, "max_turns": 2}),
    "ats": ("small", {"width": 32, "num_layers": 1, "num_heads": 2, "ff_dim": 32, "sample_steps": 4}),
    "stm": ("small", {"encoder_blocks": 1, "decoder_blocks": 1, "num_eigenpairs": 16}),
}
# STM on one small mesh (rendering the default three takes minutes), scored on one held-out mesh. Every
# model samples one validation clip (side).
RECIPE_KW = {"stm": {"meshes": ((1, "decimated"),), "held_out": ((3, "retriangulated"),), "val_clips": 1},
             "toktalk": {"val_clips": 1}, "ats": {"val_clips": 1}, "timar": {"val_clips": 1},
             "dualtalk": {"val_clips": 1}}


def _config(model: str, data):
    """The model's small config with the input widths of ``data`` (what ``jaxtalk train`` derives)."""
    spec = REGISTRY[model]
    preset, fields = SMALL[model]
    widths = {field: data.manifest[key] for field, key in spec.data_fields}
    return getattr(spec.config_class, preset)(**fields, **widths)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, prepared_tiny):
    """One two-step run per model, each trained by calling its recipe from Python."""
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig

    root = tmp_path_factory.mktemp("recipe_runs")
    out = {}
    for model, spec in REGISTRY.items():
        spec.train(_config(model, prepared_tiny), prepared_tiny, OptimConfig(lr=1e-3, warmup_steps=0, total_steps=2),
                   key=jax.random.key(0), run=RunSettings(steps=2, batch_size=2, run_dir=root / model,
                                                          loop=LoopSettings(progress=False)),
                   **RECIPE_KW.get(model, {}))
        out[model] = root / model
    return out


@pytest.fixture(scope="module")
def wav(tmp_path_factory, synthtalk_tiny):
    """Two seconds of a test clip's speech at 16 kHz."""
    path = tmp_path_factory.mktemp("recipe_runs_audio") / "speech.wav"
    sf.write(path, synthtalk_tiny.audio(synthtalk_tiny.split("test")[0])[: 2 * 16000], 16000)
    return path


def _invoke(args: list) -> tuple[int, str]:
    result = runner.invoke(app, [str(a) for a in args])
    return result.exit_code, result.output


@pytest.mark.slow
@pytest.mark.parametrize("model", list(REGISTRY))
def test_recipe_called_from_python_writes_a_run_that_load_run_restores(runs, prepared_tiny, model):
    run = runs[model]
    record = RunRecord.load(run)
    config = _config(model, prepared_tiny)
    assert record.model == model and record.config == json.loads(json.dumps(dataclasses.asdict(config)))
    assert json.loads((run / CONFIG_FILE).read_text()) == record.config
    # A config equal to no preset records none; the settings are the ones the recipe ran with.
    assert record.preset is None and record.items == []
    assert record.train["batch_size"] == 2 and record.optim["total_steps"] == 2 and record.seed == 0
    assert record.data == {"spec": str(prepared_tiny.root), "path": str(prepared_tiny.root.absolute()),
                           "key": prepared_tiny.key}
    assert record.extra  # what the recipe fitted (normalisers, windows, meshes)
    assert json.loads((run / "features.json").read_text())["audio"] == "logmel"
    loaded = load_run(run)
    assert loaded.step == 2 and loaded.config == config
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in jax.tree.leaves(loaded.params))


@pytest.mark.slow
@pytest.mark.parametrize("model", ["toktalk", "timar"])
def test_jaxtalk_sample_opens_a_speech_model_run_made_from_python(runs, wav, tmp_path, model):
    out = tmp_path / "motion.npz"
    code, output = _invoke(["sample", runs[model], wav, "--out", out, "--sample-steps", "2"])
    assert code == 0, output
    params = np.load(out)["params"]
    assert params.shape[1] == 56 and params.shape[0] >= 25 and np.isfinite(params).all()


@pytest.mark.slow
def test_jaxtalk_sample_animates_a_mesh_with_ats_and_stm_runs_made_from_python(runs, wav, tmp_path):
    import trimesh

    from jaxtalk.face import builtin_face

    face = builtin_face(3, resolution="low")
    trimesh.Trimesh(np.asarray(face.template), np.asarray(face.faces), process=False).export(tmp_path / "face.ply")
    out = tmp_path / "anim.npy"
    code, output = _invoke(["sample", runs["ats"], wav, "--stm", runs["stm"], "--mesh", tmp_path / "face.ply",
                            "--out", out])
    assert code == 0, output
    verts = np.load(out)
    assert verts.shape == (50, face.template.shape[0], 3) and np.isfinite(verts).all()


@pytest.mark.slow
def test_jaxtalk_sample_reads_a_dualtalk_run_made_from_python_and_points_to_eval(runs, wav):
    # The baseline is offline and scored by `jaxtalk eval`: sample reads the run's model and says so.
    code, output = _invoke(["sample", runs["dualtalk"], wav])
    assert code == 2 and "is a DualTalk baseline run" in output and f"jaxtalk eval {runs['dualtalk']}" in output


def test_write_run_names_the_preset_a_config_equals_and_takes_the_callers_run_info(prepared_tiny, tmp_path):
    from jaxtalk.models.freetalk.config import STMConfig
    from jaxtalk.runs import RunInfo, write_run
    from jaxtalk.train import OptimConfig
    from jaxtalk.train.recipes import TrainSettings

    optim, settings = OptimConfig(warmup_steps=0, total_steps=3), TrainSettings(batch_size=3)
    made = write_run(tmp_path / "a", "stm", STMConfig.small(), prepared_tiny, optim, seed=1, extra={"window": 16},
                     settings=settings)
    assert RunRecord.load(tmp_path / "a") == made and made.preset == "small" and made.train["batch_size"] == 3
    custom = write_run(tmp_path / "b", "stm", STMConfig.small(decoder_blocks=1), prepared_tiny, optim, seed=1,
                       extra={}, settings=settings)
    assert custom.preset is None
    cli = RunInfo(preset="small", items=("decoder_blocks=1", "batch_size=4"), data_spec="synthtalk:tiny",
                  settings=TrainSettings(batch_size=4))
    told = write_run(tmp_path / "c", "stm", STMConfig.small(decoder_blocks=1), prepared_tiny, optim, seed=1,
                     extra={}, settings=settings, info=cli)
    assert (told.preset, told.items, told.data["spec"], told.train["batch_size"]) == (
        "small", ["decoder_blocks=1", "batch_size=4"], "synthtalk:tiny", 4)
    assert json.loads((tmp_path / "c" / CONFIG_FILE).read_text())["decoder_blocks"] == 1


def test_run_settings_refuse_bad_values_and_loop_settings_that_are_the_runs():
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings

    for bad, message in (({"steps": 0}, "steps must be >= 1"), ({"batch_size": 0}, "batch_size must be >= 1"),
                         ({"eval_every": 0}, "eval_every must be >= 1"), ({"window_frames": -1}, "window_frames")):
        with pytest.raises(ValueError, match=message):
            RunSettings(**bad)
    for loop, named in ((LoopSettings(max_steps=5), "max_steps"), (LoopSettings(eval_every=5), "eval_every"),
                        (LoopSettings(best_metric="FD", best_mode="max"), "best_metric, best_mode")):
        with pytest.raises(ValueError, match=f"RunSettings.loop sets {named}"):
            RunSettings(loop=loop)
    # (Under the suite's runtime type checking the Literal annotation rejects it first: a TypeError.)
    with pytest.raises((ValueError, TypeError), match="best_mode"):
        LoopSettings(best_mode="lowest")
    assert RunSettings(run_dir="r").ckpt_path.as_posix() == "r/checkpoint"
    assert RunSettings(run_dir="r", ckpt_dir="c").ckpt_path.as_posix() == "c" and RunSettings().ckpt_path is None
    assert RunSettings(observers=[]) == RunSettings()  # a list of observers is kept as a tuple


@pytest.mark.parametrize("model", ["timar", "dualtalk"])
def test_a_turn_recipe_refuses_a_window_length(model, prepared_tiny):
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import OptimConfig

    spec = REGISTRY[model]
    with pytest.raises(ValueError, match=f"window_frames is not a {model} setting"):
        spec.train(_config(model, prepared_tiny), prepared_tiny, OptimConfig(total_steps=1, warmup_steps=0),
                   key=jax.random.key(0), run=RunSettings(window_frames=10))
