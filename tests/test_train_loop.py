"""The training loop end to end on tiny models: convergence, exact resume after interruption, eval
callback, progress bar, frozen parameters, and every bad-input path."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.data.batching import BatchIterator
from jaxtalk.train import NonFiniteLossError, OptimConfig, make_schedule, train

# Compile time dominates these tiny programs; all runs compared within a test share the setting.
pytestmark = pytest.mark.usefixtures("fast_compile")

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
    return train(_mlp_loss, _mlp_params(jax.random.key(1)), it, CFG, **opts)


class _Crashing(BatchIterator):
    """A BatchIterator whose process 'dies' when asked for batch number ``crash_at`` (1-based)."""

    def __init__(self, *args, crash_at, **kw):
        super().__init__(*args, **kw)
        self.crash_at, self.served = crash_at, 0

    def __next__(self):
        self.served += 1
        if self.served == self.crash_at:
            raise KeyboardInterrupt("simulated kill")
        return super().__next__()


# ---------------------------------------------------------------- behaviour


def test_linear_regression_reaches_the_true_weights(key):
    data, w_true, b_true = _regression_data()
    cfg = OptimConfig(lr=0.05, weight_decay=0.0, warmup_steps=10, total_steps=400, clip_norm=None)

    def loss_fn(p, batch, k):
        err = batch["x"] @ p["w"] + p["b"][None, :] - batch["y"]
        return jnp.mean(err**2), {}

    params = {"w": jnp.zeros((4, 2)), "b": jnp.zeros(2)}
    result = train(loss_fn, params, BatchIterator(data, 16, seed=0), cfg, key=key, progress=False, log_every=50)
    np.testing.assert_allclose(np.asarray(result.state.params["w"]), w_true, atol=2e-3)
    np.testing.assert_allclose(np.asarray(result.state.params["b"]), b_true, atol=2e-3)
    hist = result.history
    assert [h["step"] for h in hist] == list(range(1, 401)) and hist[-1]["loss"] < 1e-5
    # The logged lr of update s is the schedule at s - 1 (warm-up starts at 0).
    np.testing.assert_allclose([h["metrics"]["lr"] for h in hist[:12]], make_schedule(cfg)(jnp.arange(12)), rtol=1e-6)
    assert int(result.state.step) == 400 and result.state.ema_params is None


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
        _run(tmp_path, "crashed", save_every=3, data_iter=_Crashing(data, 8, seed=4, crash_at=8))
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
    result = train(loss_fn, {"w": jnp.zeros((3, 3))}, it, cfg, key=key, progress=False)  # T varies: 4 or 8
    assert result.history[-1]["loss"] < result.history[0]["loss"]


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
        train(_mlp_loss, _mlp_params(key), _Batches(batches), CFG, key=key, progress=False)
    # With the check off, the NaN reaches the loss and the loop stops naming the step.
    with pytest.raises(NonFiniteLossError, match="at step 3") as info, pytest.warns(UserWarning, match="ended after step 3"):
        train(_mlp_loss, _mlp_params(key), _Batches(batches), CFG, key=key, progress=False, check_batches=False)
    assert info.value.step == 3 and [h["step"] for h in info.value.history] == [1, 2]


def test_batch_shape_or_structure_change_names_the_array(key):
    wide = {"x": np.zeros((8, 5), np.float32), "y": np.zeros((8, 2), np.float32)}
    with pytest.raises(ValueError, match=r"\['x'\] at step 2 has shape \(8, 5\), but the model was set up for shape \(8, 4\)"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), wide]), CFG, key=key, progress=False)
    missing = {"x": np.zeros((8, 4), np.float32)}
    with pytest.raises(ValueError, match=r"missing arrays \[\"\['y'\]\"\]"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), missing]), CFG, key=key, progress=False)
    as_f64 = {k: v.astype(np.float64) for k, v in _good_batch(1).items()}
    with pytest.raises(ValueError, match="dtype float64, expected float32"):
        train(_mlp_loss, _mlp_params(key), _Batches([_good_batch(0), as_f64]), CFG, key=key, progress=False)


def test_nan_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path, key):
    # The batch is finite but makes the loss NaN at step 5 (log of a negative number).
    batches = [{"x": np.ones((4, 4), np.float32), "s": np.full((4,), 2.0 if i != 4 else -1.0, np.float32)} for i in range(12)]

    def loss_fn(p, batch, k):
        return jnp.mean(jnp.log(batch["s"])) + jnp.sum(p["w"] ** 2), {}

    cfg = OptimConfig(lr=0.1, warmup_steps=1, total_steps=12)
    ckpt = tmp_path / "run"
    with pytest.raises(NonFiniteLossError, match=r"loss is nan at step 5.*last good checkpoint is step 3") as info:
        # log_every=10: the NaN is found when step 6's checkpoint flushes the metrics, before it is written.
        train(loss_fn, {"w": jnp.ones(3)}, _Batches(batches), cfg, key=key, ckpt_dir=ckpt, save_every=3, progress=False, log_every=10)
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
        train(_mlp_loss, _mlp_params(key), _Batches([]), CFG, key=key, progress=False, **kw)
