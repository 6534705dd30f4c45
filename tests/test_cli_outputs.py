"""No command destroys a user's file.

Every command that writes runs in a folder where each name it would write already holds a user's
file: every user file's hash must be unchanged afterwards (the command stops first with a one-line
error naming the file and ``--overwrite``, having written nothing), and ``--overwrite`` then replaces
exactly the outputs, nothing else. A command never writes over one of its own inputs, whatever the
options.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pygltflib
import pytest
import soundfile

from jaxtalk.data.formats import MotionClip, save_npz

from helpers import cli_ok as _ok, cli_error as _refused


def _hashes(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _user_files(folder: Path, names: list[str]) -> dict[str, str]:
    """A user's own bytes under each of ``names`` (folders created), and their hashes."""
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(f"the user's own {name}".encode())
    return _hashes(folder)



@pytest.fixture(scope="module")
def run(trained_toktalk):
    """The session's tiny TokTalk run (what is sampled does not matter here; every command that would
    write into it must refuse, so it is read, never written)."""
    return trained_toktalk.dir


@pytest.fixture
def talk(tmp_path):
    """A folder holding only the user's ``talk.wav`` (44.1 kHz stereo float, as a user's recording often is)."""
    rate = 44_100
    t = np.arange(3 * rate) / rate
    wav = np.stack([0.3 * np.sin(2 * np.pi * 180 * t), 0.2 * np.sin(2 * np.pi * 240 * t)], axis=1)
    soundfile.write(tmp_path / "talk.wav", wav.astype(np.float32), rate, subtype="FLOAT")
    return tmp_path


@pytest.mark.slow
def test_sample_and_stream_keep_a_user_file_at_the_default_name_until_overwrite_replaces_only_it(run, talk):
    before = _user_files(talk, ["talk_params.npz"])
    for command in ("sample", "stream"):
        _refused([command, run, talk / "talk.wav"], "talk_params.npz", "--overwrite")
        assert _hashes(talk) == before
    _ok(["sample", run, talk / "talk.wav", "--overwrite"])
    after = _hashes(talk)
    assert after["talk.wav"] == before["talk.wav"] and after["talk_params.npz"] != before["talk_params.npz"]
    assert set(after) == set(before)
    assert np.load(talk / "talk_params.npz")["params"].shape[1] == 56


@pytest.mark.slow
def test_sample_never_writes_over_an_input_even_with_out_and_overwrite(run, talk):
    _ok(["sample", run, talk / "talk.wav", "--out", talk / "style.npz"])
    before = _hashes(talk)
    run_before = _hashes(run)
    _refused(["sample", run, talk / "talk.wav", "--style", talk / "style.npz", "--out", talk / "style.npz",
              "--overwrite"], "is an input")
    _refused(["sample", run, talk / "talk.wav", "--out", run / "tokenizer.npz", "--overwrite"], "is an input")
    assert _hashes(talk) == before and _hashes(run) == run_before


@pytest.mark.slow
def test_an_explicit_out_replaces_its_file_and_a_folder_or_a_path_under_a_file_is_refused_before_work(run, talk):
    (talk / "mine.npz").write_bytes(b"old")
    _ok(["sample", run, talk / "talk.wav", "--out", talk / "mine.npz"])
    assert np.load(talk / "mine.npz")["params"].shape[1] == 56
    (talk / "d.npz").mkdir()
    _refused(["sample", run, talk / "talk.wav", "--out", talk / "d.npz"], "is a folder")
    _refused(["sample", run, talk / "talk.wav", "--out", talk / "talk.wav" / "x.npz"], "is a file, not a folder")
    _ok(["sample", run, talk / "talk.wav", "--out", talk / "new" / "deeper" / "x.npz"])  # folders are created


@pytest.mark.slow
def test_export_writes_its_audio_beside_the_glb_without_touching_the_recording(run, talk):
    # A user's session: sample -> talk.npz, export -> talk.glb; talk.wav stays the user's.
    _ok(["sample", run, talk / "talk.wav", "--out", talk / "talk.npz"])
    before = _hashes(talk)
    output = _ok(["export", talk / "talk.npz", "--out", talk / "talk.glb"])
    assert "talk.glb.wav" in output
    after = _hashes(talk)
    assert after["talk.wav"] == before["talk.wav"] and set(after) == set(before) | {"talk.glb", "talk.glb.wav"}
    assert pygltflib.GLTF2().load(str(talk / "talk.glb")).asset.extras == {"audio": "talk.glb.wav"}
    wav, rate = soundfile.read(talk / "talk.glb.wav")
    assert rate == 16_000 and wav.ndim == 1

    # The audio's name is the command's own choice: a user's file there needs --overwrite.
    (talk / "talk.glb.wav").write_bytes(b"the user's")
    before = _hashes(talk)
    _refused(["export", talk / "talk.npz", "--out", talk / "talk.glb"], "talk.glb.wav", "--overwrite")
    assert _hashes(talk) == before
    _ok(["export", talk / "talk.npz", "--out", talk / "talk.glb", "--overwrite"])
    after = _hashes(talk)
    changed = {name for name in after if after[name] != before.get(name)}
    assert changed == {"talk.glb.wav"}  # the .glb is rewritten byte-identically (the export is deterministic)
    # Audio given as the very file the export would write beside the .glb: an input, never replaced.
    soundfile.write(talk / "x.glb.wav", np.zeros(16_000, np.float32), 16_000)
    before = _hashes(talk)
    _refused(["export", talk / "talk.npz", "--audio", talk / "x.glb.wav", "--out", talk / "x.glb", "--overwrite"],
             "x.glb.wav", "is an input")
    assert _hashes(talk) == before


@pytest.mark.slow
def test_every_writing_command_leaves_user_files_under_its_names_unchanged(run, talk, monkeypatch):
    monkeypatch.chdir(talk)
    save_npz(talk / "clip.npz", MotionClip(name="clip", fps=25, params=np.zeros((30, 56), np.float32)))
    src = talk / "dataset"
    src.mkdir()
    save_npz(src / "a.npz", MotionClip(name="a", fps=25, params=np.zeros((30, 56), np.float32)))
    names = ["talk_params.npz",  # sample / stream default
             "render.mp4", "anim.glb", "anim.glb.wav",  # render / export defaults and the side file
             "prep/manifest.json", "prep/report.csv", "prep/tokenizer.npz",  # prepare into a folder of the user's
             "runs/toktalk/tokenizer.npz", "runs/toktalk/run.txt",  # train into a folder of the user's
             "generic/clip00000.wav", "generic/metadata.csv",  # data --out
             "jaxtalk-demo/report.md", "jaxtalk-demo/animation.mp4",  # demo
             "experiments/results/bench_all.json",  # bench's default
             "retarget.glb", "rig.csv", "side.json"]  # retarget's default and the side files of a named .glb
    before = _user_files(talk, names)
    commands = [
        (["sample", run, "talk.wav"], "talk_params.npz"),
        (["stream", run, "talk.wav"], "talk_params.npz"),
        (["render", "clip.npz"], "render.mp4"),
        (["export", "clip.npz"], "anim.glb"),
        (["prepare", src, "--out", "prep", "--no-progress"], "manifest.json"),
        (["train", "toktalk", "--out", "runs/toktalk", "--steps", "1"], "no jaxtalk run"),
        (["data", "--size", "tiny", "--no-tokens", "--cache-dir", talk / "cache", "--out", "generic"], "clip00000.wav"),
        (["demo", "--size", "tiny", "--steps", "1"], "jaxtalk-demo/"),
        (["eval", run, "--json", run / "run.json"], "is an input"),
        (["eval", run, "--best", "--json", run / "checkpoint" / "history.jsonl"], "is an input"),
        (["sample", run, "talk.wav", "--out", run / "checkpoint" / "mine.npz"], "is an input"),
        (["bench", "--model", "toktalk"], "bench_all.json"),
        (["retarget", "clip.npz"], "retarget.glb"),
        (["retarget", "clip.npz", "--out", "rig.glb"], "rig.csv"),  # --out names the .glb, not its side files
        (["retarget", "clip.npz", "--out", "side.glb"], "side.json"),
    ]
    for args, word in commands:
        _refused(args, word)
        now = _hashes(talk)
        assert {k: now[k] for k in before} == before, args
    # Render, export and retarget: --overwrite replaces exactly their outputs.
    _ok(["render", "clip.npz", "--overwrite", "--size", "32"])
    _ok(["export", "clip.npz", "--overwrite"])
    _ok(["retarget", "clip.npz", "--out", "rig.glb", "--overwrite"])
    after = _hashes(talk)
    assert {name for name in before if after[name] != before[name]} == {"render.mp4", "anim.glb", "rig.csv"}
