"""The training loop end to end on tiny models: convergence, exact resume after interruption, eval
callback, progress bar, frozen parameters, the best-validated checkpoint and history.jsonl, and every
bad-input path."""

from __future__ import annotations

import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.data.batching import BatchIterator
from jaxtalk.train import (
    Checkpointer,
    LoopSettings,
    NonFiniteLossError,
    OptimConfig,
    best_checkpoint_dir,
    make_schedule,
    read_best,
    read_history,
    train,
)

from helpers import crashing_batches, with_loop_settings

# Compile time dominates these tiny programs; all runs compared within a test share the setting.

# ---------------------------------------------------------------- tiny problems


def _regression_data(n=64, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 4)).astype(np.float32)
    w = rng.normal(size=(4, 2)).astype(np.float32)
    b = np.array([0.5, -1.0], np.float32)
    return {"x": x, "y": (x @ w + b).astype(np.float32)}, w, b


def _mlp_params(key):
    k1, k2 = jax.random.split(key)
    return {
        "l1": {"w": jax.random.normal(k1, (4, 16)) * 0.5, "b": jnp.zeros(16)},
        "l2": {"w": jax.random.normal(k2, (16, 2)) * 0.5, "b": jnp.zeros(2)},
    }


def _mlp_loss(p, batch, key):
    h = jnp.tanh(batch["x"] @ p["l1"]["w"] + p["l1"]["b"][None, :])
    h = h * jax.random.bernoulli(key, 0.8, h.shape) / 0.8  # dropout: the per-step key matters
    err = h @ p["l2"]["w"] + p["l2"]["b"][None, :] - batch["y"]
    return jnp.mean(err**2), {"max_err": jnp.max(jnp.abs(err))}


CFG = OptimConfig(lr=1e-2, weight_decay=1e-3, warmup_steps=3, total_steps=12, clip_norm=1.0, ema_decay=0.8)
QUIET = LoopSettings(progress=False)


def _bitwise_equal(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        assert x.tobytes() == y.tobytes()


def _run(tmp_path, name, **kw):
    data, _, _ = _regression_data()
    opts = dict(key=jax.random.key(3), ckpt_dir=tmp_path / name, progress=False, log_every=5)
    opts.update(kw)
    it = opts.pop("data_iter", None) or BatchIterator(data, 8, seed=4)
    return train(_mlp_loss, _mlp_params(jax.random.key(1)), it, CFG, **with_loop_settings(**opts))


# ---------------------------------------------------------------- behaviour


def test_linear_regression_reaches_the_true_weights(key):
    data, w_true, b_true = _regression_data()
    cfg = OptimConfig(lr=0.05, weight_decay=0.0, warmup_steps=10, total_steps=400, clip_norm=None)

    def loss_fn(p, batch, k):
        err = batch["x"] @ p["w"] + p["b"][None, :] - batch["y"]
        return jnp.mean(err**2), {}

    params = {"w": jnp.zeros((4, 2)), "b": jnp.zeros(2)}
    result = train(loss_fn, params, BatchIterator(data, 16, seed=0), cfg, key=key,
                   settings=LoopSettings(progress=False, log_every=50))
    np.testing.assert_allclose(np.asarray(result.state.params["w"]), w_true, atol=2e-3)
    np.testing.assert_allclose(np.asarray(result.state.params["b"]), b_true, atol=2e-3)
    hist = result.history
    assert [h["step"] for h in hist] == list(range(1, 401)) and hist[-1]["loss"] < 1e-5
    # The logged lr of update s is the schedule at s - 1 (warm-up starts at 0).
    np.testing.assert_allclose([h["metrics"]["lr"] for h in hist[:12]], make_schedule(cfg)(jnp.arange(12)), rtol=1e-6)
    assert int(result.state.step) == 400 and result.state.ema_params is None


@pytest.mark.slow
def test_interrupted_and_resumed_run_is_bitwise_equal(tmp_path):
    straight = _run(tmp_path, "straight")
    first = _run(tmp_path, "resumed", max_steps=7)
    assert int(first.state.step) == 7
    # A brand-new loop: fresh params, fresh iterator at position 0, same key; everything else
    # (step, Adam moments, EMA, RNG, data position) comes from the checkpoint.
    second = _run(tmp_path, "resumed")
    assert [h["step"] for h in second.history] == [8, 9, 10, 11, 12]
    _bitwise_equal(second.state.params, straight.state.params)
    _bitwise_equal(second.state.ema_params, straight.state.ema_params)
    _bitwise_equal(second.state.opt_state, straight.state.opt_state)
    assert [h["loss"] for h in second.history] == [h["loss"] for h in straight.history[7:]]
    # A finished run resumed again does nothing.
    assert _run(tmp_path, "resumed").history == []


def test_crash_mid_run_resumes_from_last_checkpoint_bitwise(tmp_path):
    straight = _run(tmp_path, "straight")
    data, _, _ = _regression_data()
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, "crashed", save_every=3, data_iter=crashing_batches(8, data, 8, seed=4))
    assert sorted(p.name for p in (tmp_path / "crashed").iterdir()) == ["3", "6"]
    resumed = _run(tmp_path, "crashed", save_every=3)
    assert resumed.history[0]["step"] == 7
    _bitwise_equal(resumed.state.params, straight.state.params)
    _bitwise_equal(resumed.state.ema_params, straight.state.ema_params)


def test_eval_callback_progress_bar_and_frozen_layer(tmp_path, capsys):
    calls = []
    init = _mlp_params(jax.random.key(1))

    def eval_fn(params, ema_params, step):
        calls.append(step)
        assert ema_params is not None
        return {"ema_l2_norm": jnp.sum(ema_params["l2"]["w"] ** 2)}

    result = _run(
        tmp_path,
        "eval",
        ckpt_dir=None,
        eval_fn=eval_fn,
        eval_every=5,
        progress=True,
        trainable=lambda path, leaf: path.startswith("l2"),
    )
    assert calls == [5, 10, 12]  # every 5 steps and at the end
    evals = {h["step"]: h["eval"] for h in result.history if "eval" in h}
    assert set(evals) == {5, 10, 12}
    np.testing.assert_allclose(evals[12]["ema_l2_norm"], float(jnp.sum(result.state.ema_params["l2"]["w"] ** 2)), rtol=1e-6)
    _bitwise_equal(result.state.params["l1"], init["l1"])  # frozen
    assert not np.allclose(np.asarray(result.state.params["l2"]["w"]), np.asarray(init["l2"]["w"]))
    err = capsys.readouterr().err
    assert "steps_per_s" in err and "loss=" in err and "12/12" in err


def test_bucketed_variable_length_batches_train(key):
    rng = np.random.default_rng(0)
    data = [{"x": rng.normal(size=(t, 3)).astype(np.float32)} for t in (2, 3, 5, 6, 7, 8, 3, 4)]

    def loss_fn(p, batch, k):
        m = batch["mask"].astype(jnp.float32)
        err = (batch["x"] @ p["w"] - batch["x"]) ** 2
        return jnp.sum(jnp.sum(err, axis=-1) * m) / jnp.sum(m), {}

    it = BatchIterator(data, 2, seed=0, buckets=(4, 8))
    cfg = OptimConfig(lr=0.05, warmup_steps=1, total_steps=6)
    result = train(loss_fn, {"w": jnp.zeros((3, 3))}, it, cfg, key=key, settings=QUIET)  # T varies: 4 or 8
    assert result.history[-1]["loss"] < result.history[0]["loss"]


# ---------------------------------------------------------------- best checkpoint and history.jsonl


def _scripted(values):
    """An eval_fn returning a scripted validation value per step (and one metric that never counts)."""

    def eval_fn(params, ema_params, step):
        return {"val": values[step], "ema_norm": jnp.sum(ema_params["l2"]["w"] ** 2)}

    return eval_fn


def _saved(directory, step=None):
    with Checkpointer(directory, read_only=True) as ckpt:
        return ckpt.restore_saved(step)


def test_best_checkpoint_holds_the_lowest_eval_step_and_history_has_the_curve(tmp_path):
    values = {2: 5.0, 4: 3.0, 6: 4.0, 8: 1.0, 10: 2.0, 12: 6.0}
    result = _run(tmp_path, "run", eval_fn=_scripted(values), eval_every=2, save_every=2, keep_checkpoints=10,
                  best_metric="val")
    run = tmp_path / "run"
    assert sorted(p.name for p in run.iterdir()) == ["10", "12", "2", "4", "6", "8", "best", "history.jsonl"]
    assert [p.name for p in best_checkpoint_dir(run).iterdir()] == ["8"]
    record = read_best(run)
    assert (record["metric"], record["mode"], record["value"], record["step"]) == ("val", "min", 1.0, 8)
    assert record["eval"]["val"] == 1.0 and result.best == record
    # The best checkpoint is the step-8 state exactly (the regular step-8 checkpoint is the reference).
    best_state, best_step = _saved(best_checkpoint_dir(run))
    regular_state, _ = _saved(run, 8)
    assert best_step == 8
    _bitwise_equal(best_state, regular_state)
    with Checkpointer(best_checkpoint_dir(run), read_only=True) as ckpt:
        meta = ckpt.read_metadata()
    assert meta["best"] == record and meta["step"] == 8 and meta["config"] == CFG.to_dict()
    # history.jsonl: every evaluation (with whether it improved) and the train curve up to step 12.
    rows = read_history(run)
    evals = [r for r in rows if r["type"] == "eval"]
    assert [(r["step"], r["eval"]["val"], r["best"]) for r in evals] == [
        (2, 5.0, True), (4, 3.0, True), (6, 4.0, False), (8, 1.0, True), (10, 2.0, False), (12, 6.0, False)
    ]
    trains = [r for r in rows if r["type"] == "train"]
    assert sum(r["window"] for r in trains) == 12 and trains[-1]["step"] == 12
    assert [r["step"] for r in trains] == sorted({r["step"] for r in trains})
    # Each train row's loss is the mean of its window of per-step losses.
    losses = {h["step"]: h["loss"] for h in result.history if "loss" in h}
    for r in trains:
        window = [losses[s] for s in range(r["step"] - r["window"] + 1, r["step"] + 1)]
        np.testing.assert_allclose(r["loss"], np.mean(window), rtol=1e-12)


@pytest.mark.parametrize("mode, sign", [("min", 1.0), ("max", -1.0)])
def test_best_checkpoint_survives_resume(tmp_path, mode, sign):
    values = {k: sign * v for k, v in {2: 5.0, 4: 1.0, 6: 3.0, 7: 4.0, 8: 2.0, 10: 1.5, 12: 3.0}.items()}
    opts = dict(eval_fn=_scripted(values), eval_every=2, best_metric="val", best_mode=mode)
    first = _run(tmp_path, "run", max_steps=7, **opts)
    assert first.best["step"] == 4
    # The resumed run's evaluations (steps 8, 10, 12) are all worse than step 4's: a run that forgot
    # the best-so-far would save step 8.
    second = _run(tmp_path, "run", **opts)
    assert [h["step"] for h in second.history if "eval" in h] == [8, 10, 12]
    assert second.best["step"] == 4 and second.best["value"] == sign * 1.0
    assert read_best(tmp_path / "run")["step"] == 4
    assert [p.name for p in best_checkpoint_dir(tmp_path / "run").iterdir()] == ["4"]
    rows = read_history(tmp_path / "run")
    assert [(r["step"], r["best"]) for r in rows if r["type"] == "eval"] == [
        (2, True), (4, True), (6, False), (7, False), (8, False), (10, False), (12, False)
    ]
    # A third run that improves replaces it.
    values[12] = sign * 0.5
    shutil.rmtree(tmp_path / "run" / "12")  # as if killed before its final checkpoint
    third = _run(tmp_path, "run", **opts)
    assert third.best["step"] == 12 and read_best(tmp_path / "run")["value"] == sign * 0.5
    assert [p.name for p in best_checkpoint_dir(tmp_path / "run").iterdir()] == ["12"]


def test_crash_after_a_best_save_resumes_without_duplicate_history(tmp_path):
    data, _, _ = _regression_data()
    values = {s: 10.0 - s if s <= 7 else 20.0 for s in range(1, 13)}  # improves at every step up to 7
    opts = dict(eval_fn=_scripted(values), eval_every=1, save_every=3, best_metric="val")
    with pytest.raises(KeyboardInterrupt):
        _run(tmp_path, "run", data_iter=crashing_batches(8, data, 8, seed=4), **opts)
    run = tmp_path / "run"
    # Killed during step 8: regular checkpoints at 3 and 6, the best (and history rows) reach step 7.
    assert read_best(run)["step"] == 7 and Checkpointer(run, read_only=True).all_steps() == [3, 6]
    assert max(r["step"] for r in read_history(run)) == 7
    with open(run / "history.jsonl", "a") as f:
        f.write('{"type": "eval", "st')  # and a torn last line
    # This time step 7 validates better than the best written after the step-6 checkpoint: it replaces it.
    values[7] = 0.5
    resumed = _run(tmp_path, "run", **opts)
    assert resumed.history[0]["step"] == 7
    record = read_best(run)
    assert record["step"] == 7 and record["value"] == 0.5
    assert [p.name for p in best_checkpoint_dir(run).iterdir()] == ["7"]
    assert [r["step"] for r in read_history(run) if r["type"] == "eval"] == list(range(1, 13))
    assert all(line.endswith("}") for line in (run / "history.jsonl").read_text().splitlines())
    trains = [r for r in read_history(run) if r["type"] == "train"]
    assert sum(r["window"] for r in trains) == 12


def test_history_file_switch_and_no_best_without_best_metric(tmp_path):
    _run(tmp_path, "plain", eval_fn=_scripted({12: float("nan")}))  # eval without best_metric: history, no best/
    assert sorted(p.name for p in (tmp_path / "plain").iterdir()) == ["12", "history.jsonl"]
    assert read_best(tmp_path / "plain") is None
    last = read_history(tmp_path / "plain")[-1]
    assert last["type"] == "eval" and "best" not in last
    assert np.isnan(last["eval"]["val"]) and '"val": null' in (tmp_path / "plain" / "history.jsonl").read_text()
    # A non-finite validation value is never the best.
    diverged = _run(tmp_path, "nan", eval_fn=_scripted({12: float("nan")}), best_metric="val")
    assert diverged.best is None and read_best(tmp_path / "nan") is None
    _run(tmp_path, "off", eval_fn=_scripted({12: 1.0}), write_history=False)
    assert sorted(p.name for p in (tmp_path / "off").iterdir()) == ["12"]
    _run(tmp_path, "on", write_history=True)  # no eval_fn: train rows only
    assert {r["type"] for r in read_history(tmp_path / "on")} == {"train"}


def test_best_metric_errors(tmp_path, key):
    with pytest.raises(ValueError, match="needs eval_fn and ckpt_dir"):
        _run(tmp_path, "a", best_metric="val")
    with pytest.raises(ValueError, match="needs eval_fn and ckpt_dir"):
        _run(tmp_path, "a", ckpt_dir=None, eval_fn=_scripted({12: 1.0}), best_metric="val")
    # (Under the suite's runtime type checking the Literal annotation rejects it first: a TypeError.)
    with pytest.raises((ValueError, TypeError), match="best_mode"):
        _run(tmp_path, "a", eval_fn=_scripted({12: 1.0}), best_metric="val", best_mode="lowest")
    with pytest.raises(ValueError, match="write_history=True needs ckpt_dir"):
        _run(tmp_path, "a", ckpt_dir=None, write_history=True)
    missing = r"best_metric 'loss' is not among the eval metrics at step 12: \['ema_norm', 'val'\]"
    with pytest.raises(ValueError, match=missing):
        _run(tmp_path, "b", eval_fn=_scripted({12: 1.0}), best_metric="loss")
    _run(tmp_path, "c", max_steps=4, eval_fn=_scripted({4: 1.0}), best_metric="val")
    with pytest.raises(ValueError, match=r"chosen by 'val' \(min\), this run asks for 'val' \(max\)"):
        _run(tmp_path, "c", eval_fn=_scripted({12: 1.0}), best_metric="val", best_mode="max")
    shutil.rmtree(tmp_path / "c" / "4")  # only the best checkpoint is left: still not overwritten silently
    with pytest.raises(ValueError, match="best.*already holds checkpoints"):
        _run(tmp_path, "c", eval_fn=_scripted({12: 1.0}), best_metric="val", resume=False)


# ---------------------------------------------------------------- bad input


class _Batches:
    """A plain iterator over a fixed list of batches (no position state)."""

    def __init__(self, batches):
        self.batches = iter(batches)

    def __iter__(self):
        return self

    def __next__(self):
        return next(self.batches)


def _good_batch(seed):
    data, _, _ = _regression_data(8, seed)
    return data


def test_nan_batch_is_rejected_before_its_step(key):
    bad = _good_batch(2)
    bad["x"][3, 1] = np.nan
    batches = [_good_batch(0), _good_batch(1), bad]
    with pytest.raises(ValueError, match=r"\['x'\] at step 3 has 1 NaN/inf"):
        train(_mlp_loss, _mlp_params(key), _Batches(batches), CFG, key=key, settings=QUIET)
    # With the check off, the NaN reaches the loss and the loop stops naming the step.
    with pytest.raises(NonFiniteLossError, match="at step 3") as info, pytest.warns(UserWarning, match="ended after step 3"):
        train(_mlp_loss, _mlp_params(key), _Batches(batches), CFG, key=key,
              settings=LoopSettings(progress=False, check_batches=False))
    assert info.value.step == 3 and [h["step"] for h in info.value.history] == [1, 2]


def test_batch_shape_or_structure_change_names_the_array(key):
    wide = {"x": np.zeros((8, 5), np.float32), "y": np.zeros((8, 2), np.float32)}
    with pytest.raises(ValueError, match=r"\['x'\] at step 2 has shape \(8, 5\), but the model was set up for shape \(8, 4\)"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), wide]), CFG, key=key, settings=QUIET)
    missing = {"x": np.zeros((8, 4), np.float32)}
    with pytest.raises(ValueError, match=r"missing arrays \[\"\['y'\]\"\]"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), missing]), CFG, key=key, settings=QUIET)
    as_f64 = {k: v.astype(np.float64) for k, v in _good_batch(1).items()}
    with pytest.raises(ValueError, match="dtype float64, expected float32"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), as_f64]), CFG, key=key, settings=QUIET)


def test_nan_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path, key):
    # The batch is finite but makes the loss NaN at step 5 (log of a negative number).
    batches = [{"x": np.ones((4, 4), np.float32), "s": np.full((4,), 2.0 if i != 4 else -1.0, np.float32)} for i in range(12)]

    def loss_fn(p, batch, k):
        return jnp.mean(jnp.log(batch["s"])) + jnp.sum(p["w"] ** 2), {}

    cfg = OptimConfig(lr=0.1, warmup_steps=1, total_steps=12)
    ckpt = tmp_path / "run"
    with pytest.raises(NonFiniteLossError, match=r"loss is nan at step 5.*last good checkpoint is step 3") as info:
        # log_every=10: the NaN is found when step 6's checkpoint flushes the metrics, before it is written.
        train(loss_fn, {"w": jnp.ones(3)}, _Batches(batches), cfg, key=key, ckpt_dir=ckpt,
              settings=LoopSettings(save_every=3, progress=False, log_every=10))
    assert info.value.step == 5 and info.value.last_checkpoint_step == 3
    assert sorted(p.name for p in ckpt.iterdir()) == ["3"]


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"max_steps": 0}, "max_steps must be >= 1"),
        ({"eval_every": 5}, "eval_every is set but eval_fn is None"),
        ({"save_every": 0}, "save_every must be >= 1"),
        ({"trainable": lambda path, leaf: False}, "no parameter"),
    ],
)
def test_bad_settings_raise(key, kw, msg):
    with pytest.raises(ValueError, match=msg):
        train(_mlp_loss, _mlp_params(key), _Batches([]), CFG, key=key, **with_loop_settings(progress=False, **kw))
