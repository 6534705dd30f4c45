"""Optimiser, schedule, EMA, trainable masks and the jitted train step, against hand-written references."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.train import (
    OptimConfig,
    create_train_state,
    ema_update,
    make_optimizer,
    make_schedule,
    make_train_step,
    trainable_mask,
)


def _bits(x):
    return np.asarray(x).view(np.uint32)


def test_schedule_warmup_then_cosine_hand_values():
    cfg = OptimConfig(lr=2.0, warmup_steps=4, total_steps=12, final_lr_ratio=0.25)
    lr = np.asarray(make_schedule(cfg)(jnp.arange(14)))
    # Linear warm-up from 0, peak at warmup_steps.
    np.testing.assert_allclose(lr[:5], [0.0, 0.5, 1.0, 1.5, 2.0], rtol=1e-6)
    # Cosine from 2.0 to 0.5 over steps 4..12: midpoint (step 8) is the mean, the end is the floor.
    np.testing.assert_allclose(lr[8], 1.25, rtol=1e-6)
    np.testing.assert_allclose(lr[6], 0.5 + 0.75 * (1 + np.cos(np.pi / 4)), rtol=1e-6)
    np.testing.assert_allclose(lr[12:], [0.5, 0.5], rtol=1e-6)


def _adamw_reference(params, grads_seq, cfg):
    """NumPy AdamW: clip by global norm, Adam moments with bias correction, decoupled decay x lr."""
    sched = jax.jit(make_schedule(cfg))
    p = {k: np.asarray(v, np.float64) for k, v in params.items()}
    m = {k: np.zeros_like(v) for k, v in p.items()}
    v = {k: np.zeros_like(x) for k, x in p.items()}
    for t, g in enumerate(grads_seq, start=1):
        g = {k: np.asarray(x, np.float64) for k, x in g.items()}
        norm = np.sqrt(sum(np.sum(x**2) for x in g.values()))
        scale = min(1.0, cfg.clip_norm / norm)
        lr = float(sched(t - 1))
        for k in p:
            gk = g[k] * scale
            m[k] = cfg.b1 * m[k] + (1 - cfg.b1) * gk
            v[k] = cfg.b2 * v[k] + (1 - cfg.b2) * gk**2
            mhat, vhat = m[k] / (1 - cfg.b1**t), v[k] / (1 - cfg.b2**t)
            p[k] = p[k] - lr * (mhat / (np.sqrt(vhat) + cfg.eps) + cfg.weight_decay * p[k])
    return p


def test_optimizer_matches_numpy_adamw_with_clipping_and_decay():
    cfg = OptimConfig(lr=0.1, weight_decay=0.3, warmup_steps=2, total_steps=6, clip_norm=0.5, b1=0.8, b2=0.95)
    rng = np.random.default_rng(0)
    params = {"a": rng.normal(size=(3, 2)).astype(np.float32), "b": rng.normal(size=(4,)).astype(np.float32)}
    grads_seq = [{k: rng.normal(size=x.shape).astype(np.float32) * 2 for k, x in params.items()} for _ in range(4)]
    tx = make_optimizer(cfg)
    p = jax.tree.map(jnp.asarray, params)
    state = tx.init(p)
    update = jax.jit(tx.update)
    for g in grads_seq:
        updates, state = update(jax.tree.map(jnp.asarray, g), state, p)
        p = jax.tree.map(lambda a, u: a + u, p, updates)
    ref = _adamw_reference(params, grads_seq, cfg)
    for k in params:
        np.testing.assert_allclose(np.asarray(p[k]), ref[k], rtol=2e-5, atol=2e-6)


def test_trainable_mask_forms_and_errors():
    params = {"base": {"w": jnp.ones((2, 2)), "b": jnp.zeros(2)}, "adapter": {"w": jnp.ones((2, 2))}}
    by_name = trainable_mask(params, lambda path, leaf: path.startswith("adapter/"))
    assert by_name == {"base": {"w": False, "b": False}, "adapter": {"w": True}}
    by_ndim = trainable_mask(params, lambda path, leaf: leaf.ndim == 2)
    assert by_ndim == {"base": {"w": True, "b": False}, "adapter": {"w": True}}
    explicit = {"base": {"w": True, "b": False}, "adapter": {"w": False}}
    assert trainable_mask(params, explicit) == explicit
    assert trainable_mask(params, None) == {"base": {"w": True, "b": True}, "adapter": {"w": True}}
    with pytest.raises(ValueError, match="structure"):
        trainable_mask(params, {"base": True, "adapter": True})
    with pytest.raises(ValueError, match="no parameter"):
        trainable_mask(params, lambda path, leaf: False)


@pytest.mark.parametrize(
    "field, value",
    [("lr", 0.0), ("lr", float("nan")), ("warmup_steps", 20), ("clip_norm", 0.0), ("b2", 1.0), ("ema_decay", 1.0)],
)
def test_optim_config_rejects_bad_values(field, value):
    kwargs = {"lr": 1e-3, "warmup_steps": 2, "total_steps": 10, field: value}
    with pytest.raises(ValueError, match=f"OptimConfig.{field}"):
        OptimConfig(**kwargs)


def test_ema_update_hand_values_and_mask():
    ema = {"a": jnp.array([1.0, 2.0]), "b": jnp.array([-0.0, 3.0])}
    new = {"a": jnp.array([3.0, 0.0]), "b": jnp.array([5.0, 5.0])}
    out = ema_update(ema, new, 0.75, {"a": True, "b": False})
    np.testing.assert_allclose(np.asarray(out["a"]), [1.5, 1.5])
    np.testing.assert_array_equal(_bits(out["b"]), _bits(ema["b"]))  # masked: untouched, -0.0 kept


# ---------------------------------------------------------------- the train step (frozen leaves)
def _adapter_problem():
    rng = np.random.default_rng(1)
    params = {
        "base": {"w": jnp.asarray(rng.normal(size=(3, 3)), jnp.float32), "z": jnp.array([-0.0, 0.0, -0.0])},
        "adapter": {"w": jnp.asarray(rng.normal(size=(3, 2)) * 0.1, jnp.float32)},
    }
    batch = {"x": jnp.asarray(rng.normal(size=(8, 3)), jnp.float32), "y": jnp.asarray(rng.normal(size=(8, 2)), jnp.float32)}

    def loss_fn(p, b, key):
        h = jnp.tanh(b["x"] @ p["base"]["w"] + p["base"]["z"][None, :])
        err = h @ p["adapter"]["w"] - b["y"]
        return jnp.mean(err**2), {"abs_err": jnp.mean(jnp.abs(err))}

    return params, batch, loss_fn


def test_frozen_leaves_stay_bitwise_and_match_adapter_only_training(key):
    params, batch, loss_fn = _adapter_problem()
    cfg = OptimConfig(lr=0.05, weight_decay=0.5, warmup_steps=1, total_steps=5, clip_norm=0.01, ema_decay=0.5)
    mask = trainable_mask(params, lambda path, leaf: path.startswith("adapter"))
    tx = make_optimizer(cfg, mask)
    state = create_train_state(params, tx, key, ema=True)
    step = make_train_step(loss_fn, tx, cfg, mask=mask)
    for _ in range(4):
        state, metrics = step(state, batch)

    for name in ("w", "z"):  # frozen, with large weight decay and signed zeros: bitwise equal
        np.testing.assert_array_equal(_bits(state.params["base"][name]), _bits(params["base"][name]))
        np.testing.assert_array_equal(_bits(state.ema_params["base"][name]), _bits(params["base"][name]))
    assert not np.allclose(np.asarray(state.params["adapter"]["w"]), np.asarray(params["adapter"]["w"]))
    # No Adam moments are kept for frozen leaves.
    moment_shapes = [x.shape for x in jax.tree.leaves(state.opt_state) if x.ndim]
    assert moment_shapes == [(3, 2), (3, 2)]  # mu and nu of the adapter only

    # Reference: a model whose only parameter is the adapter (base closed over as a constant). Same
    # clipping norm (over trainable grads only), decay and updates -> same adapter.
    base = params["base"]
    ref_cfg = cfg
    ref_tx = make_optimizer(ref_cfg)
    ref_state = create_train_state({"w": params["adapter"]["w"]}, ref_tx, key)
    ref_step = make_train_step(lambda p, b, k: loss_fn({"base": base, "adapter": p}, b, k), ref_tx, ref_cfg)
    for _ in range(4):
        ref_state, ref_metrics = ref_step(ref_state, batch)
    np.testing.assert_allclose(np.asarray(state.params["adapter"]["w"]), np.asarray(ref_state.params["w"]), rtol=1e-6)
    np.testing.assert_allclose(float(metrics["grad_norm"]), float(ref_metrics["grad_norm"]), rtol=1e-6)


def test_train_step_metrics_ema_and_keys(key):
    params, batch, loss_fn = _adapter_problem()
    cfg = OptimConfig(lr=0.1, weight_decay=0.0, warmup_steps=2, total_steps=8, ema_decay=0.9)
    tx = make_optimizer(cfg)
    state = create_train_state(params, tx, key, ema=True)

    def noisy_loss(p, b, k):
        loss, m = loss_fn(p, b, k)
        return loss, {**m, "u": jax.random.uniform(k)}

    step = make_train_step(noisy_loss, tx, cfg, donate=False)
    p0 = state.params
    s1, m1 = step(state, batch)
    s2, m2 = step(s1, batch)
    assert int(s2.step) == 2
    np.testing.assert_allclose(float(m1["lr"]), 0.0)  # warm-up starts at 0: first update is a no-op
    np.testing.assert_allclose(float(m2["lr"]), 0.05, rtol=1e-6)
    assert set(m2) == {"loss", "grad_norm", "lr", "abs_err", "u"}
    # Step s draws from fold_in(key, s): fresh per step, reproducible from (key, step) alone.
    assert float(m1["u"]) == float(jax.random.uniform(jax.random.fold_in(key, 0)))
    assert float(m2["u"]) == float(jax.random.uniform(jax.random.fold_in(key, 1)))
    # Bias-corrected EMA by hand: e1 = p1 (no weight on p0), e2 = (0.9 * 0.1 p1 + 0.1 p2) / (1 - 0.9^2).
    for a, b in zip(jax.tree.leaves(s1.params), jax.tree.leaves(s1.ema_params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    e2 = jax.tree.map(lambda a, b: (0.09 * a + 0.1 * b) / 0.19, s1.params, s2.params)
    for a, b in zip(jax.tree.leaves(e2), jax.tree.leaves(s2.ema_params)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    assert jax.tree.structure(p0) == jax.tree.structure(s2.ema_params)
    # The caller's params are copied, never donated.
    assert np.isfinite(np.asarray(params["adapter"]["w"])).all()


def test_train_step_rejects_bad_loss_outputs(key):
    params, batch, _ = _adapter_problem()
    cfg = OptimConfig(lr=0.1, warmup_steps=1, total_steps=4)
    tx = make_optimizer(cfg)
    cases = [
        (lambda p, b, k: (jnp.sum(p["adapter"]["w"], axis=0), {}), "scalar loss"),
        (lambda p, b, k: (jnp.sum(p["adapter"]["w"]), {"loss": 1.0}), "reserved"),
        (lambda p, b, k: (jnp.sum(p["adapter"]["w"]), {"m": jnp.ones(2)}), "'m' must be a scalar"),
    ]
    for fn, msg in cases:
        state = create_train_state(params, tx, key)
        with pytest.raises(ValueError, match=msg):
            make_train_step(fn, tx, cfg)(state, batch)


def test_create_train_state_validates(key):
    cfg = OptimConfig(lr=0.1, warmup_steps=1, total_steps=4)
    tx = make_optimizer(cfg)
    with pytest.raises(ValueError, match="NaN or inf"):
        create_train_state({"w": jnp.array([1.0, jnp.nan])}, tx, key)
    with pytest.raises(ValueError, match="dtype int32"):
        create_train_state({"w": jnp.array([1, 2])}, tx, key)
    with pytest.raises(ValueError, match="typed PRNG key"):
        create_train_state({"w": jnp.ones(2)}, tx, jax.random.PRNGKey(0))


def test_recipe_warmup_is_whole_from_ten_warmups_on_and_a_capped_one_is_stated():
    from jaxtalk.train.recipes import TrainSettings

    settings = TrainSettings(lr=1e-4, warmup_steps=100)
    assert settings.optim(1000).warmup_steps == 100 and settings.optim(50_000).warmup_steps == 100
    assert settings.describe(1000) == "learning rate 0.0001, warm-up 100 steps"
    assert settings.optim(400).warmup_steps == 40
    assert settings.describe(400) == "learning rate 0.0001, warm-up 40 steps (capped from 100 at a tenth of this 400-step run)"


def test_freetalk_paper_presets_train_with_the_papers_optimiser_and_ats_on_whole_clips():
    from jaxtalk.runs import REGISTRY

    ats, stm = REGISTRY["ats"].settings("paper"), REGISTRY["stm"].settings("paper")
    for s in (ats, stm):  # AdamW 1e-4, weight decay 1e-2, constant rate (no schedule is stated)
        assert (s.lr, s.weight_decay, s.warmup_steps, s.final_lr_ratio) == (1e-4, 1e-2, 0, 1.0)
    assert ats.window_frames == 0 and ats.batch_size == 16 and ats.clip_norm == 1.0
    assert REGISTRY["ats"].settings("small").window_frames is None
