"""What an adversarial new user met, driven through ``jaxtalk``: resuming on other data, a
viewer port in use, a dataset whose every clip is rejected, advice naming no real option, options
checked only after the expensive work, options that did nothing, misleading messages.

Runs are made without training: a TokTalk run at its initial parameters (a step-0 checkpoint) and an
ATS run the same way, on the session's prepared SynthTalk tiny; a run record alone where the command
must refuse before opening anything.
"""

from __future__ import annotations

import dataclasses
import shutil
import socket
from pathlib import Path

import jax
import numpy as np
import optax
import pytest
import soundfile as sf

from helpers import cli_ok as _ok, cli_error as _error

DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "dualtalk_demo"


def _speech(path: Path, seconds: float, *, silent: bool = False) -> Path:
    t = np.arange(int(seconds * 16000)) / 16000
    audio = np.zeros_like(t) if silent else 0.3 * np.sin(2 * np.pi * 180 * t) * (1 + np.sin(2 * np.pi * 3 * t))
    sf.write(path, audio.astype(np.float32), 16000)
    return path


def _record(out: Path, model: str, config, data, extra: dict | None = None) -> None:
    from jaxtalk.runs import RunRecord

    RunRecord(model=model, preset="tiny", items=[], config=dataclasses.asdict(config), train={}, optim={},
              data={"spec": "synthtalk:tiny", "path": str(data.root), "key": data.key}, seed=0,
              extra=extra or {}).save(out)


def _step0_run(out: Path, model: str, config, params, data, extra: dict | None = None) -> Path:
    from jaxtalk.runs import checkpoint_dir, save_run_assets
    from jaxtalk.train import create_train_state, save_checkpoint

    save_checkpoint(checkpoint_dir(out), create_train_state(params, optax.identity(), jax.random.key(0)))
    _record(out, model, config, data, extra)
    save_run_assets(out, model, data, config)
    return out


@pytest.fixture(scope="module")
def toktalk_run(tmp_path_factory, prepared_tiny):
    from jaxtalk.models import toktalk

    m = prepared_tiny.manifest
    config = toktalk.TokTalkConfig.tiny(num_mid_blocks=0, speech_dim=m["token_dim"], token_rate=m["token_rate"])
    return _step0_run(tmp_path_factory.mktemp("toktalk_run"), "toktalk", config,
                      toktalk.init_params(config, jax.random.key(0)), prepared_tiny)


@pytest.fixture(scope="module")
def ats_run(tmp_path_factory, prepared_tiny):
    from jaxtalk.models.freetalk import ats
    from jaxtalk.models.freetalk.config import ATSConfig

    config = ATSConfig.small(speech_dim=prepared_tiny.manifest["speech_dim"], num_layers=1)
    extra = {"window": 50, "stats": {"mean": [0.0] * 3, "std": [1.0] * 3}}
    return _step0_run(tmp_path_factory.mktemp("ats_run"), "ats", config, ats.init_params(config, jax.random.key(0)),
                      prepared_tiny, extra)


@pytest.fixture
def speech(tmp_path):
    return _speech(tmp_path / "speech.wav", 5.0)


# ------------------------------------------------------------------ item 2: resuming on other data


@pytest.mark.parametrize("spec", ["synthtalk:tiny", "synthtalk:small"])
def test_resuming_a_run_refuses_data_other_than_its_own_even_the_default(tmp_path, prepared_tiny, spec):
    from jaxtalk.runs import RunRecord

    out = tmp_path / "x"
    prep1 = tmp_path / "prep1"
    prep1.mkdir()
    RunRecord(model="toktalk", preset="tiny", items=[], config={}, train={}, optim={},
              data={"spec": str(prep1), "path": str(prep1), "key": "k"}, seed=0, extra={}).save(out)
    line = _error(["train", "toktalk", "--data", spec, "--steps", "5", "--out", out])
    assert f"trained on --data {prep1}, not {spec}" in line and f"--data {prep1} (or no --data)" in line


# ------------------------------------------------------------------ item 4: the viewer's port


def test_view_on_a_port_in_use_says_so_in_one_line_and_suggests_port_0(tmp_path):
    from jaxtalk.export import export_face_model
    from jaxtalk.face import builtin_face

    export_face_model(builtin_face(0, resolution="low"), np.zeros((2, 56), np.float32), tmp_path / "a.glb")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        line = _error(["view", tmp_path, "--port", port])
    assert f"port {port} on 127.0.0.1 is in use" in line and "--port 0" in line


# ------------------------------------------------------------------ item 5: every clip rejected


def _flat_dualtalk(folder: Path, conversations: list[str]) -> None:
    """DualTalk's files (wav per side, npz of FLAME exp/pose for one side) with no split folders."""
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    for conv in conversations:
        for side in (1, 2):
            sf.write(folder / f"{conv}_speaker{side}.wav", (0.1 * rng.normal(size=16000 * 5)).astype(np.float32), 16000)
        np.savez(folder / f"{conv}_speaker2.npz", exp=rng.normal(size=(125, 50)).astype(np.float32) * 0.1,
                 pose=np.zeros((125, 6), np.float32), shape=np.zeros((125, 100), np.float32))


def _check_rejected_flat_folder(folder: Path, out: Path, count: int) -> None:
    line = _error(["prepare", folder, "--out", out, "--no-progress"])
    assert f"every clip of {folder} was rejected ({count} read as the generic layout; {count} of them: " in line
    assert "no 'fps' in the npz" in line  # the commonest reason, not the tokenizer
    assert "holds DualTalk files" in line and "put them under train/ and test/" in line
    rows = (out / "report.csv").read_text().splitlines()
    assert rows[0] == "file,reason" and len(rows) == 1 + count and all("no 'fps'" in r for r in rows[1:])


def test_prepare_of_flat_dualtalk_files_reports_every_clip_rejected_and_the_split_folders_to_make(tmp_path):
    folder = tmp_path / "flat"
    _flat_dualtalk(folder, ["convA", "convB"])
    _check_rejected_flat_folder(folder, tmp_path / "out", 2)
    # The advice works: the same files under train/ and test/ prepare.
    for conv, split in (("convA", "train"), ("convB", "test")):
        (folder / split).mkdir()
        for f in folder.glob(f"{conv}_*"):
            f.rename(folder / split / f.name)
    output = _ok(["prepare", folder, "--out", tmp_path / "out2", "--no-progress"])
    assert "prepared 4 clips" in output


@pytest.mark.skipif(not DEMO.is_dir(), reason="shared DualTalk demo data not available")
def test_prepare_of_the_dualtalk_demo_files_copied_flat_names_the_layout(tmp_path):
    folder = tmp_path / "flat"
    folder.mkdir()
    for f in [*DEMO.glob("*_speaker*.wav"), *DEMO.glob("*_speaker*.npz")]:
        shutil.copy(f, folder / f.name)
    _check_rejected_flat_folder(folder, tmp_path / "out", len(list(folder.glob("*.npz"))))


# ------------------------------------------------------------------ item 6: advice that exists


def test_silent_audio_error_names_no_python_keyword(toktalk_run, tmp_path):
    line = _error(["sample", toktalk_run, _speech(tmp_path / "quiet.wav", 2.0, silent=True)])
    assert "audio is silent" in line and "no speech to animate" in line
    assert "=True" not in line and "allow_silence" not in line


def test_mesh_units_error_uses_the_cli_spelling_only():
    from jaxtalk.geometry.canonical import detect_units

    with pytest.raises(ValueError) as err:
        detect_units(np.random.default_rng(0).normal(size=(50, 3)) * 1e4)
    assert "--units m, dm, cm, mm or um" in str(err.value) and "units='" not in str(err.value)


# ------------------------------------------------------------------ item 7: options checked first


def _no_loading(monkeypatch) -> None:
    """Fail the test if the command gets as far as loading a run's parameters or a mesh."""
    from jaxtalk.commands import inference
    from jaxtalk.geometry import canonical
    from jaxtalk.models.freetalk import animate

    def loaded(*args, **kwargs):
        raise AssertionError("the option was checked only after loading")

    monkeypatch.setattr(inference, "load_run", loaded)
    monkeypatch.setattr(canonical, "load_mesh", loaded)
    monkeypatch.setattr(animate, "prepare_user_mesh", loaded)


@pytest.mark.parametrize("command", ["sample", "stream"])
def test_nan_cfg_scale_is_refused_before_the_run_is_loaded(toktalk_run, speech, monkeypatch, command):
    _no_loading(monkeypatch)
    assert "--cfg-scale must be a finite number, got nan" in _error([command, toktalk_run, speech, "--cfg-scale", "nan"])


@pytest.mark.parametrize("command", ["sample", "stream"])
@pytest.mark.parametrize("value", ["-0.5", "nan", "inf"])
def test_negative_or_non_finite_temperature_is_refused_before_the_run_is_loaded(toktalk_run, speech, monkeypatch,
                                                                                command, value):
    _no_loading(monkeypatch)
    line = _error([command, toktalk_run, speech, "--temperature", value])
    assert f"--temperature must be a finite number >= 0, got {float(value)}" in line


def test_eval_refuses_a_temperature_for_a_model_without_sampler_noise(ats_run):
    line = _error(["eval", ats_run, "--temperature", "0.5"])
    assert f"--temperature scales TokTalk's and TIMAR's sampler noise; {ats_run} is a ats run" in line


@pytest.mark.parametrize("command", ["sample", "stream"])
def test_toktalk_at_temperature_zero_writes_the_same_motion_for_every_seed(toktalk_run, speech, tmp_path, command):
    """Temperature scales the starting noise: at 0 the seed has nothing left to change; at 1 it does."""
    from jaxtalk.data.formats import read_npz

    def run(seed: int, temperature: str) -> np.ndarray:
        out = tmp_path / f"{command}-{seed}-{temperature}.npz"
        _ok([command, toktalk_run, speech, "--out", out, "--sample-steps", "2", "--seed", seed,
             "--temperature", temperature])
        return read_npz(out).params

    np.testing.assert_array_equal(run(0, "0"), run(1, "0"))
    assert np.abs(run(0, "1") - run(1, "1")).max() > 1e-3


@pytest.mark.parametrize(("option", "message"), [
    (["--emotion", "furious"], "--emotion furious: not an emotion of this run; it knows: neutral,"),
    (["--intensity", "0"], "--intensity must lie in [1, 3] for this run, got 0"),
    (["--sample-steps", "0"], "--sample-steps must be >= 1, got 0"),
    (["--units", "inch"], "--units must be one of m, dm, cm, mm, um, got 'inch'"),
])
def test_freetalk_options_are_refused_before_the_mesh_is_aligned(ats_run, stm_run, speech, tmp_path, monkeypatch,
                                                                 option, message):
    _no_loading(monkeypatch)
    mesh = tmp_path / "face.obj"
    mesh.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    line = _error(["sample", ats_run, speech, "--stm", stm_run, "--mesh", mesh, *option])
    assert message in line and "[0.0" not in line


# ------------------------------------------------------------------ item 8: options that do nothing


def test_toktalk_run_refuses_freetalk_and_timar_options(toktalk_run, speech, monkeypatch):
    _no_loading(monkeypatch)
    line = _error(["sample", toktalk_run, speech, "--emotion", "happy", "--partner", speech])
    assert ("--partner, --emotion: not options of a TokTalk run (it takes --style, --cfg-scale, --temperature, "
            "--sample-steps, --seed)") in line
    line = _error(["stream", toktalk_run, speech, "--partner", speech])
    assert "--partner: not an option of a TokTalk run" in line


def test_freetalk_refuses_toktalk_options(ats_run, stm_run, speech, tmp_path, monkeypatch):
    _no_loading(monkeypatch)
    line = _error(["sample", ats_run, speech, "--stm", stm_run, "--mesh", tmp_path / "m.obj", "--style", speech])
    assert "--style: not an option of a FreeTalk run (it takes --stm, --mesh, --emotion" in line


@pytest.mark.slow
def test_sample_prints_the_duration_of_the_frames_written_and_no_more_than_the_audio(toktalk_run, speech, tmp_path):
    from jaxtalk.data.formats import read_npz

    out = tmp_path / "s.npz"
    output = _ok(["sample", toktalk_run, speech, "--out", out, "--sample-steps", "1"])
    frames = read_npz(out).params.shape[0]
    assert frames == 125  # 5.0 s at 25 fps, though the tokenizer may cover a little more
    assert f"{frames} frames (5.00 s) written to {out}" in output


def test_export_of_a_points_array_says_it_is_not_an_animation(tmp_path):
    np.save(tmp_path / "v.npy", np.zeros((10, 3), np.float32))
    line = _error(["export", tmp_path / "v.npy", "--out", tmp_path / "v.glb"])
    assert "holds a (10, 3) array: one set of 3-D points, not a (frames, vertices, 3) animation" in line
    assert "has 1 vertices" not in line


def test_reading_a_checkpoint_logs_nothing_about_a_read_only_directory(tmp_path, caplog):
    import logging

    import jax.numpy as jnp

    from jaxtalk.train import create_train_state, save_checkpoint
    from jaxtalk.train.checkpoint import latest_checkpoint_step

    save_checkpoint(tmp_path / "ckpt", create_train_state({"w": jnp.ones(2)}, optax.identity(), jax.random.key(0)))
    with caplog.at_level(logging.WARNING):  # orbax said "Given directory is read only=..." here
        assert latest_checkpoint_step(tmp_path / "ckpt") == 0
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
