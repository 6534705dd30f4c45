"""``jaxtalk train MODEL --init RUN`` fine-tunes: it starts from the run's parameters and config and, for a
turn model, keeps the run's normaliser (on resume too); what would not be a fine-tune is refused."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from helpers import cli_error, cli_ok
from jaxtalk.runs import RunRecord, load_run

# Few-step runs: compile time is what they spend (the shared runs were compiled this way too).
pytestmark = pytest.mark.slow


def test_timar_fine_tune_starts_from_the_runs_weights_and_keeps_its_normaliser(trained_timar, prepared_tiny, tmp_path):
    start = trained_timar.copy(tmp_path / "start")
    # Give the starting run a normaliser the new data would not fit, to see which one training uses.
    record = json.loads((start / "run.json").read_text())
    norm = record["extra"]["normalizer"]
    norm["motion_std"] = [2.0 * v for v in norm["motion_std"]]
    (start / "run.json").write_text(json.dumps(record))
    out = tmp_path / "tuned"
    common = ["train", "timar", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--init", start,
              "--no-progress", "--out", out, "--set", "batch_size=2"]
    # A learning rate of 1e-30: one step leaves the parameters where they started (to 1e-20), so the run
    # must have started there.
    output = cli_ok([*common, "--steps", "1", "--set", "lr=1e-30", "--set", "weight_decay=0"])
    assert f"fine-tuning from {start}" in output
    before, after = load_run(start), load_run(out)
    assert after.config == before.config and after.step == 1
    for a, b in zip(jax.tree.leaves(after.params), jax.tree.leaves(before.params), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-20)
    extra = RunRecord.load(out).extra
    assert extra["normalizer"] == norm and extra["init"] is True
    # Resumed without --init, it keeps the starting run's normaliser.
    cli_ok([*[a for a in common if a not in ("--init", start)], "--steps", "2", "--set", "lr=1e-30", "--set", "weight_decay=0"])
    assert RunRecord.load(out).extra["normalizer"] == norm


def test_init_refusals_are_one_line(trained_timar, trained_toktalk, prepared_tiny, tmp_path):
    base = ["train", "timar", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--steps", "1",
            "--no-progress"]
    cli_error([*base, "--init", trained_toktalk.dir, "--out", tmp_path / "a"], "is a toktalk run, not timar")
    cli_error([*base, "--init", trained_timar.dir, "--set", "width=64", "--out", tmp_path / "b"],
              "--set of model fields (width=64)")
    existing = trained_timar.copy(tmp_path / "existing")
    cli_error([*base[:-3], "--steps", "3", "--no-progress", "--init", trained_timar.dir, "--out", existing],
              "--init starts a new one")
    cli_error(["train", "ats", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--init",
               trained_timar.dir, "--out", tmp_path / "c"],
              "--init is not available for ats")
