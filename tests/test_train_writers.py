"""The run folder's metric writers (``metrics.jsonl`` + TensorBoard events, :mod:`jaxtalk.train.writers`)
through the training loop: what a row holds, the event file agreeing with it, resumes that never repeat
a step; the batch a small training split allows; and checkpoints opened without orbax's warnings.

Event files are read back with tensorboardX's protobufs and the TFRecord framing, checksums verified,
independently of the library's own reading code (``helpers.read_event_file``).
"""

from __future__ import annotations

import json
import logging
import math
import struct

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.data.batching import BatchIterator
from jaxtalk.train import (Checkpointer, OptimConfig, make_schedule, read_history, read_metrics, save_checkpoint,
                           train)
from jaxtalk.train.recipes import usable_batch_size
from jaxtalk.train.writers import METRICS_FILE, RunMetrics
from helpers import event_files, read_event_file, scalars, crashing_batches, with_loop_settings


CFG = OptimConfig(lr=1e-2, weight_decay=1e-3, warmup_steps=3, total_steps=12, clip_norm=1.0)


# ---------------------------------------------------------------- tiny problem


def _data(n=64, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 4)).astype(np.float32)
    return {"x": x, "y": (x @ rng.normal(size=(4, 2))).astype(np.float32)}


def _params():
    return {"w": jnp.zeros((4, 2)), "b": jnp.zeros(2)}


def _loss(p, batch, key):
    err = batch["x"] @ p["w"] + p["b"][None, :] - batch["y"]
    return jnp.mean(err**2), {"max_err": jnp.max(jnp.abs(err))}


def _eval(params, ema, step):
    return {"val_loss": 1.0 / step, "val_w": float(jnp.sum(params["w"]))}


def _train(run_dir, data_iter=None, **kw):
    opts = dict(key=jax.random.key(0), ckpt_dir=run_dir / "checkpoint", log_dir=run_dir, progress=False,
                log_every=2, eval_fn=_eval, eval_every=4, save_every=4)
    opts.update(kw)
    return train(_loss, _params(), data_iter or BatchIterator(_data(), 8, seed=1), CFG, **with_loop_settings(**opts))


# ---------------------------------------------------------------- the loop's rows


def test_metrics_rows_hold_window_means_schedule_lr_rate_and_merged_evaluations(tmp_path):
    run = tmp_path / "run"
    result = _train(run)
    rows = read_metrics(run)
    assert [r["step"] for r in rows] == [2, 4, 6, 8, 10, 12]  # one row per log flush, evaluations merged
    by_step = {h["step"]: h for h in result.history}
    schedule = make_schedule(CFG)
    for row in rows:
        s = row["step"]
        window = [by_step[s - 1], by_step[s]]
        assert row["train/loss"] == pytest.approx(np.mean([h["loss"] for h in window]), rel=1e-6)
        assert row["train/grad_norm"] == pytest.approx(np.mean([h["metrics"]["grad_norm"] for h in window]), rel=1e-6)
        assert row["train/max_err"] == pytest.approx(np.mean([h["metrics"]["max_err"] for h in window]), rel=1e-6)
        assert row["train/lr"] == pytest.approx(float(schedule(s - 1)), rel=1e-6)  # the update reaching step s
        assert row["train/steps_per_s"] > 0 and row["wall_time"] > 0
        if s % 4 == 0:
            assert row["eval/val_loss"] == pytest.approx(1.0 / s) and "eval/val_w" in row
        else:
            assert not any(k.startswith("eval/") for k in row)
    # The gradient norm is the one before clipping (clip_norm=1): the first steps' exceed it.
    assert rows[0]["train/grad_norm"] > CFG.clip_norm


def test_event_file_holds_the_same_scalars_as_metrics_jsonl(tmp_path):
    run = tmp_path / "run"
    _train(run)
    rows = read_metrics(run)
    events = scalars(run)
    assert len(event_files(run)) == 1
    want: dict[str, list[tuple[int, float]]] = {}
    for row in rows:
        for tag, value in row.items():
            if tag not in ("step", "wall_time"):
                want.setdefault(tag, []).append((row["step"], value))
    assert set(events) == set(want) >= {"train/loss", "train/lr", "train/grad_norm", "train/steps_per_s",
                                        "eval/val_loss", "eval/val_w"}
    for tag, points in want.items():
        assert [s for s, _ in events[tag]] == [s for s, _ in points], tag
        np.testing.assert_allclose([v for _, v in events[tag]], [v for _, v in points], rtol=1e-6)


def test_resume_after_a_kill_drops_what_followed_the_last_checkpoint_from_both_files(tmp_path):
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        _train(run, crashing_batches(11, _data(), 8, seed=1))  # steps 1..10 done, checkpoints at 4 and 8
    assert [r["step"] for r in read_metrics(run)] == [2, 4, 6, 8, 10]
    killed_file = event_files(run)[0]
    assert max(e.step for e in read_event_file(killed_file)) == 10

    import time

    resumed_at = time.time()
    _train(run)
    rows = read_metrics(run)
    assert [r["step"] for r in rows] == [2, 4, 6, 8, 10, 12]
    assert rows[4]["wall_time"] > resumed_at  # step 10 is the resumed run's row, not the killed run's
    assert [r["step"] for r in read_history(run / "checkpoint") if r["type"] == "eval"] == [4, 8, 12]
    # One new event file per resume; the old one keeps only what the checkpoint covers.
    files = event_files(run)
    assert len(files) == 2 and killed_file in files
    assert max(e.step for e in read_event_file(killed_file)) == 8
    new = read_event_file(next(f for f in files if f != killed_file))
    purge = [e for e in new if e.HasField("session_log")]
    assert len(purge) == 1 and purge[0].step == 9  # TensorBoard discards steps >= 9 it had already loaded
    for tag, points in scalars(run).items():
        steps = [s for s, _ in points]
        assert steps == sorted(set(steps)), f"{tag} repeats a step: {steps}"
    assert [s for s, _ in scalars(run)["eval/val_loss"]] == [4, 8, 12]


def test_a_finished_run_resumed_with_nothing_to_train_repeats_no_step(tmp_path):
    run = tmp_path / "run"
    _train(run)
    before = (run / METRICS_FILE).read_text()
    _train(run)  # re-evaluates step 12, which both files already hold
    assert (run / METRICS_FILE).read_text() == before
    for tag, points in scalars(run).items():
        steps = [s for s, _ in points]
        assert len(steps) == len(set(steps)), f"{tag} repeats a step: {steps}"


def test_only_the_loop_with_log_dir_writes_metrics(tmp_path):
    _train(tmp_path / "run", log_dir=None)
    assert not (tmp_path / "run" / METRICS_FILE).exists() and event_files(tmp_path / "run") == []


# ---------------------------------------------------------------- the writer on its own


def test_non_finite_values_are_json_null_and_read_back_as_nan(tmp_path):
    log = RunMetrics(tmp_path, start_step=0, tensorboard=False)
    log.log(1, {"train/loss": math.nan, "train/lr": math.inf})
    log.close()
    assert json.loads((tmp_path / METRICS_FILE).read_text())["train/loss"] is None
    row = read_metrics(tmp_path)[0]
    assert math.isnan(row["train/loss"]) and math.isnan(row["train/lr"])


def test_a_torn_last_line_and_a_torn_event_record_are_dropped_on_reopening(tmp_path):
    log = RunMetrics(tmp_path, start_step=0)
    for step in (1, 2):
        log.log(step, {"train/loss": float(step)})
        log.flush()
    log.close()
    with open(tmp_path / METRICS_FILE, "a") as f:
        f.write('{"step": 3, "train/lo')  # killed mid-append
    [path] = event_files(tmp_path)
    with open(path, "ab") as f:
        f.write(struct.pack("<Q", 100) + b"\0\0\0\0partial")  # killed mid-record
    assert [r["step"] for r in read_metrics(tmp_path)] == [1, 2]
    RunMetrics(tmp_path, start_step=2).close()
    assert (tmp_path / METRICS_FILE).read_text().count("\n") == 2
    assert [e.step for e in read_event_file(path) if e.summary.value] == [1, 2]  # readable to the end again


def test_scalars_of_one_step_share_a_row_and_rows_only_go_forward(tmp_path):
    log = RunMetrics(tmp_path, start_step=0, tensorboard=False)
    log.log(4, {"train/loss": 1.0})
    log.log(4, {"eval/val_loss": 2.0})
    log.flush()
    log.log(3, {"train/loss": 5.0})  # behind the last row: dropped rather than written out of order
    log.flush()
    assert read_metrics(tmp_path) == [{"step": 4, "wall_time": pytest.approx(read_metrics(tmp_path)[0]["wall_time"]),
                                       "train/loss": 1.0, "eval/val_loss": 2.0}]


# ---------------------------------------------------------------- batch size of a small split


@pytest.mark.parametrize(
    ("windows", "batch", "processes", "multiple", "want"),
    [(40, 16, 1, 1, 16), (16, 16, 1, 1, 16), (6, 16, 1, 1, 6), (6, 16, 2, 1, 3), (7, 16, 1, 4, 4), (13, 8, 2, 2, 6)],
)
def test_usable_batch_size_is_the_request_or_the_largest_that_fits(windows, batch, processes, multiple, want):
    got = usable_batch_size(windows, batch, processes=processes, multiple=multiple)
    assert got == want and got * processes <= windows and got % multiple == 0


def test_usable_batch_size_refuses_fewer_windows_than_one_per_device():
    with pytest.raises(ValueError, match="3 windows"):
        usable_batch_size(3, 16, processes=1, multiple=4)


# ---------------------------------------------------------------- orbax's warnings


def test_opening_a_checkpoint_read_only_logs_no_warning(tmp_path, caplog, capfd):
    import optax

    from jaxtalk.train import create_train_state

    save_checkpoint(tmp_path / "ckpt", create_train_state(_params(), optax.identity(), jax.random.key(0)))
    capfd.readouterr()
    with caplog.at_level(logging.INFO):
        with Checkpointer(tmp_path / "ckpt", read_only=True) as ckpt:
            state, step = ckpt.restore_saved()
    assert step == 0 and "params" in state
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []
    assert "WARNING" not in capfd.readouterr().err


def test_only_orbax_expected_messages_are_quieted_other_absl_warnings_still_show(tmp_path, caplog):
    from absl import logging as absl_logging

    Checkpointer(tmp_path / "ckpt").close()
    with caplog.at_level(logging.WARNING):
        # orbax's own wording (checkpoint_manager.py) for a save that waited on the previous one
        absl_logging.warning("Waiting for previous save to complete took %f seconds. If this number is high, "
                             "consider checkpointing less frequently.", 2.5)
        absl_logging.warning("Given directory is missing=%s", tmp_path)  # close to, but not, a quieted one
    messages = [r.getMessage() for r in caplog.records]
    assert not any("Waiting for previous save" in m for m in messages)
    assert any("Given directory is missing" in m for m in messages)
