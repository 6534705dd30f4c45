"""The run folder ``jaxtalk train`` leaves for a researcher: ``metrics.jsonl`` and TensorBoard events with
every evaluation and the training scalars, a resume after a kill that repeats no step, and commands that
read the run (``eval``, ``sample``, a resumed ``train``) without library warnings on the terminal.

One short TokTalk run (the tiny preset, SynthTalk tiny, six steps validated every two) is shared by the
tests; the resume test works on a copy of it.
"""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pytest
import soundfile as sf

from jaxtalk.train import read_metrics
from helpers import event_files, read_event_file, scalars, cli_ok as _ok


STEPS, EVERY = 6, 2
TINY = ["--preset", "tiny", "--set", "num_mid_blocks=0", "--set", "batch_size=2"]
TRAIN_SCALARS = {"train/loss", "train/lr", "train/grad_norm", "train/steps_per_s"}


def _no_warnings(output: str, caplog, capfd) -> None:
    """Nothing a library warned about reached the terminal or the logging system."""
    err = capfd.readouterr().err
    lines = [ln for ln in (output + "\n" + err).splitlines() if "warn" in ln.lower()]
    assert lines == [], lines
    logged = [f"{r.name}: {r.getMessage()}" for r in caplog.records if r.levelno >= logging.WARNING]
    assert logged == [], logged


@pytest.fixture(scope="module")
def trained(prepared_tiny, tmp_path_factory):
    cache = str(prepared_tiny.root.parent)
    out = tmp_path_factory.mktemp("run_folder") / "toktalk"
    _ok(["train", "toktalk", "--data", "synthtalk:tiny", "--cache-dir", cache, "--steps", str(STEPS), *TINY,
         "--set", f"eval_every={EVERY}", "--no-progress", "--out", str(out)])
    return {"dir": out, "cache": cache}


@pytest.mark.slow
def test_metrics_jsonl_holds_every_evaluation_and_the_training_scalars_of_each_step(trained):
    rows = read_metrics(trained["dir"])
    steps = [r["step"] for r in rows]
    assert steps == list(range(1, STEPS + 1))  # the CLI checkpoints every step of so short a run: a row each
    assert all(TRAIN_SCALARS <= set(r) for r in rows)
    assert [r["step"] for r in rows if "eval/val_loss" in r] == list(range(EVERY, STEPS + 1, EVERY))
    assert all(np.isfinite(r["train/loss"]) and r["train/lr"] > 0 for r in rows)


@pytest.mark.slow
def test_event_file_holds_every_evaluation_and_the_training_scalars(trained):
    events = scalars(trained["dir"])
    assert TRAIN_SCALARS | {"eval/val_loss"} <= set(events)
    assert [s for s, _ in events["eval/val_loss"]] == list(range(EVERY, STEPS + 1, EVERY))
    assert [s for s, _ in events["train/loss"]] == list(range(1, STEPS + 1))
    rows = {r["step"]: r for r in read_metrics(trained["dir"])}
    for step, value in events["eval/val_loss"]:
        assert value == pytest.approx(rows[step]["eval/val_loss"], rel=1e-6)


@pytest.mark.slow
def test_eval_and_sample_print_no_library_warnings(trained, tmp_path, caplog, capfd):
    capfd.readouterr()
    with caplog.at_level(logging.WARNING):
        output = _ok(["eval", str(trained["dir"]), "--max-clips", "1"])
        audio = 0.1 * np.random.default_rng(0).standard_normal(16000).astype(np.float32)
        sf.write(tmp_path / "speech.wav", audio, 16000)
        output += _ok(["sample", str(trained["dir"]), str(tmp_path / "speech.wav"), "--out", str(tmp_path / "s.npz")])
    assert (tmp_path / "s.npz").is_file()
    _no_warnings(output, caplog, capfd)


@pytest.mark.slow
def test_resume_after_a_kill_repeats_no_step_and_prints_no_library_warnings(trained, tmp_path, caplog, capfd):
    run = tmp_path / "toktalk"
    shutil.copytree(trained["dir"], run)
    # A run killed after its checkpoint of step 4 had logged steps 5 and 6: remove their checkpoints.
    for step in (5, 6):
        shutil.rmtree(run / "checkpoint" / str(step))
    old_file = event_files(run)[0]
    capfd.readouterr()
    with caplog.at_level(logging.WARNING):
        output = _ok(["train", "toktalk", "--data", "synthtalk:tiny", "--cache-dir", trained["cache"], "--steps",
                      str(STEPS + 2), *TINY, "--set", f"eval_every={EVERY}", "--no-progress", "--out", str(run)])
    assert "resuming toktalk" in output and f"step 4 -> {STEPS + 2}" in output
    _no_warnings(output, caplog, capfd)
    rows = read_metrics(run)
    assert [r["step"] for r in rows] == list(range(1, STEPS + 3))
    assert [r["step"] for r in rows if "eval/val_loss" in r] == list(range(EVERY, STEPS + 3, EVERY))
    assert max(e.step for e in read_event_file(old_file)) == 4
    assert len(event_files(run)) == 2
    for tag, points in scalars(run).items():
        steps = [s for s, _ in points]
        assert steps == sorted(set(steps)), f"{tag} repeats a step: {steps}"
    assert [s for s, _ in scalars(run)["eval/val_loss"]] == list(range(EVERY, STEPS + 3, EVERY))
