"""Euler flow-matching sampler: analytic Gaussian target, NumPy loop reference, gradients, vmap,
no recompilation on traced knobs, CFG batching, inpainting."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.samplers import flow
from jaxtalk.samplers.schedules import cosine_grid, uniform_grid


# Compile time dominates these small programs.


SIGMA_MIN = 1e-6
B, T, D = 2, 6, 3


def gaussian_velocity(mu, s, sigma_min=SIGMA_MIN):
    """Exact CFM velocity E[x1 - (1 - sigma_min) z | x_t = x] for x1 ~ N(mu, diag s^2), z ~ N(0, I).

    x_t = c z + t x1 with c = 1 - (1 - sigma_min) t is Gaussian with mean t mu and variance
    c^2 + t^2 s^2; the conditional means of x1 and z given x_t follow from joint Gaussian regression:
    E[x1 | x] = mu + t s^2 / var (x - t mu), E[z | x] = c / var (x - t mu).
    """

    def apply_fn(x, t, cond):
        t = t[:, None]
        c = 1 - (1 - sigma_min) * t
        var = c**2 + t**2 * s[None, :] ** 2
        r = x - t * mu[None, :]
        return mu[None, :] + (t * s[None, :] ** 2 / var) * r - (1 - sigma_min) * (c / var) * r

    return apply_fn


def make_model(seed=0, calls=None):
    """A small nonlinear conditional velocity model and its NumPy twin."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(D, D)) / np.sqrt(D)
    u = rng.normal(size=(D, D)) / np.sqrt(D)
    b = rng.normal(size=(D,))

    def apply_fn(x, t, cond):
        if calls is not None:
            calls.append(x.shape)  # runs at trace time only
        return jnp.tanh(x @ w + cond["c"] @ u + t[:, None, None] * b[None, None, :]) - 0.3 * x

    def apply_np(x, t, c):
        return np.tanh(x @ w + c @ u + t[:, None, None] * b[None, None, :]) - 0.3 * x

    return apply_fn, apply_np


def euler_reference(apply_np, z, cond, uncond, w, ts, known=None, mask=None, sigma_min=SIGMA_MIN):
    """Plain NumPy loop: Euler with CFG and path-consistent inpainting, written from the definitions."""
    x = z.copy()
    if known is not None:
        x = np.where(mask, (1 - (1 - sigma_min) * ts[0]) * z + ts[0] * known, x)
    for k in range(len(ts) - 1):
        t = np.full((x.shape[0],), ts[k])
        v_c = apply_np(x, t, cond)
        v = v_c if uncond is None else (1 + w) * v_c - w * apply_np(x, t, uncond)
        x = x + (ts[k + 1] - ts[k]) * v
        if known is not None:
            x = np.where(mask, (1 - (1 - sigma_min) * ts[k + 1]) * z + ts[k + 1] * known, x)
    if known is not None:
        x = np.where(mask, known, x)
    return x


def _inputs(seed=1, dtype=np.float32):
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(B, T, D)).astype(dtype)
    c = rng.normal(size=(B, T, D)).astype(dtype)
    known = rng.normal(size=(B, T, D)).astype(dtype)
    mask = np.zeros((B, T, 1), bool)
    mask[:, :2] = True
    return z, c, known, mask


@pytest.mark.parametrize("grid", ["uniform", "cosine"])
def test_gaussian_target_is_reproduced(grid):
    # s >= 0.3: for a much narrower target the flow is stiff near t = 1 and 200 Euler steps have a
    # true discretisation error above 2% (0.1 -> 2.2%), see the exact check below.
    mu = np.array([1.0, -2.0, 0.5])
    s = np.array([0.5, 1.5, 0.3])
    z = jax.random.normal(jax.random.key(0), (20_000, 3))
    ts = uniform_grid(200) if grid == "uniform" else cosine_grid(200)
    x = np.asarray(flow.sample_euler(gaussian_velocity(jnp.asarray(mu), jnp.asarray(s)), z, {}, ts))
    np.testing.assert_allclose(x.mean(0), mu, atol=0.02 * s.max(), rtol=0.02)
    np.testing.assert_allclose(x.std(0), s, rtol=0.02)
    # For Gaussian data every Euler step is affine in x, so the sampler is x = g * z + m with a gain
    # g = prod_k (1 + h_k b_k) computable exactly: the sample must match it to float32 accuracy.
    zs = np.asarray(z, np.float64)
    gain = np.ones(3)
    for k in range(200):
        t, h = ts[k], ts[k + 1] - ts[k]
        c = 1 - (1 - SIGMA_MIN) * t
        var = c**2 + t**2 * s**2
        gain *= 1 + h * (t * s**2 / var - (1 - SIGMA_MIN) * c / var)
    np.testing.assert_allclose(x.std(0) / zs.std(0), gain, rtol=2e-4)


def test_wrong_velocity_sign_is_caught():
    # Guard for the test above: a sampler that got the path sign wrong lands far from the target.
    mu, s = jnp.asarray([1.0]), jnp.asarray([0.5])
    good = gaussian_velocity(mu, s)
    z = jax.random.normal(jax.random.key(0), (5000, 1))
    x = np.asarray(flow.sample_euler(lambda x, t, c: -good(x, t, c), z, {}, uniform_grid(50)))
    assert abs(x.mean() - 1.0) > 0.2


def test_scan_matches_numpy_loop(float64):
    apply_fn, apply_np = make_model()
    z, c, known, mask = _inputs(dtype=np.float64)
    ts = np.sort(np.r_[0.0, np.random.default_rng(3).uniform(size=7), 1.0])  # an irregular grid
    cases = [
        dict(),
        dict(uncond={"c": np.zeros_like(c)}, cfg_scale=0.7),
        dict(uncond={"c": -c}, cfg_scale=1.3, known=known, known_mask=mask),
    ]
    for kw in cases:
        got = flow.sample_euler(apply_fn, jnp.asarray(z), {"c": jnp.asarray(c)}, jnp.asarray(ts), **kw)
        ref = euler_reference(
            apply_np,
            z,
            c,
            None if "uncond" not in kw else np.asarray(kw["uncond"]["c"]),
            kw.get("cfg_scale", 0.0),
            ts,
            kw.get("known"),
            kw.get("known_mask"),
        )
        assert got.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(got), ref, atol=1e-6, rtol=0)


def test_public_step_loop_matches_scan_and_trajectory():
    apply_fn, _ = make_model()
    z, c, _, _ = _inputs()
    ts = jnp.asarray(cosine_grid(5), jnp.float32)
    x, traj = flow.sample_euler(apply_fn, z, {"c": c}, ts, return_trajectory=True)
    assert traj.shape == (6, B, T, D)
    state = flow.init(jnp.asarray(z), ts[0])
    np.testing.assert_array_equal(np.asarray(traj[0]), z)
    step = jax.jit(lambda st, t1: flow.step(st, t1, apply_fn=apply_fn, cond={"c": jnp.asarray(c)}))
    for k in range(1, 6):  # a caller's own loop over the public step (streaming use)
        state = step(state, ts[k])
        np.testing.assert_allclose(np.asarray(traj[k]), np.asarray(state.x), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(traj[-1]), np.asarray(x))


def test_grad_wrt_condition_matches_finite_differences(float64):
    # remat=False here; the diffusion tests differentiate through the remat (jax.checkpoint) path.
    remat = False
    apply_fn, _ = make_model(seed=4)
    z, c, _, _ = _inputs(seed=5, dtype=np.float64)
    ts = jnp.asarray(cosine_grid(10))
    weights = jnp.asarray(np.random.default_rng(6).normal(size=(B, T, D)))

    def loss(cond, w):
        x = flow.sample_euler(
            apply_fn,
            jnp.asarray(z),
            {"c": cond},
            ts,
            uncond={"c": jnp.zeros_like(cond)},
            cfg_scale=w,
            remat=remat,
        )
        return jnp.sum(weights * jnp.sin(x))

    c0, w0 = jnp.asarray(c), jnp.asarray(0.7)
    g_c, g_w = jax.grad(loss, argnums=(0, 1))(c0, w0)
    assert bool(jnp.any(g_c != 0))
    eps = 1e-6
    rng = np.random.default_rng(7)
    for _ in range(3):
        direction = jnp.asarray(rng.normal(size=c.shape))
        fd = (loss(c0 + eps * direction, w0) - loss(c0 - eps * direction, w0)) / (2 * eps)
        assert float(jnp.vdot(g_c, direction)) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
    fd_w = (loss(c0, w0 + eps) - loss(c0, w0 - eps)) / (2 * eps)
    assert float(g_w) == pytest.approx(float(fd_w), rel=1e-6, abs=1e-9)


def test_vmap_over_keys_and_cfg_scales():
    apply_fn, _ = make_model()
    _, c, _, _ = _inputs()
    cond, uncond = {"c": jnp.asarray(c)}, {"c": jnp.zeros((B, T, D))}
    ts = jnp.asarray(cosine_grid(4), jnp.float32)

    def run(key, w):
        z = jax.random.normal(key, (B, T, D))
        return flow.sample_euler(apply_fn, z, cond, ts, uncond=uncond, cfg_scale=w)

    keys = jax.random.split(jax.random.key(0), 3)
    scales = jnp.asarray([0.0, 0.7, 2.0])
    by_key = jax.vmap(run, in_axes=(0, None))(keys, 0.7)
    by_scale = jax.vmap(run, in_axes=(None, 0))(keys[0], scales)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(by_key[i]), np.asarray(run(keys[i], 0.7)), atol=1e-5)
        np.testing.assert_allclose(np.asarray(by_scale[i]), np.asarray(run(keys[0], scales[i])), atol=1e-5)
    assert not np.allclose(np.asarray(by_scale[0]), np.asarray(by_scale[2]))


def test_traced_knobs_do_not_recompile():
    traces = []
    apply_fn, _ = make_model(calls=traces)
    z, c, known, mask = _inputs()
    cond, uncond = {"c": c}, {"c": np.zeros_like(c)}
    before = flow._sample_euler._cache_size()
    outs = [
        flow.sample_euler(apply_fn, z, cond, cosine_grid(6), uncond=uncond, cfg_scale=0.5),
        flow.sample_euler(apply_fn, z, cond, cosine_grid(6), uncond=uncond, cfg_scale=1.5),
        flow.sample_euler(apply_fn, z, cond, uniform_grid(6), uncond=uncond, cfg_scale=jnp.asarray(0.2)),
        flow.sample_euler(apply_fn, z + 1, {"c": c * 2}, uniform_grid(6) ** 2, uncond=uncond, cfg_scale=3),
    ]
    assert len(traces) == 1
    assert flow._sample_euler._cache_size() == before + 1
    assert not np.allclose(np.asarray(outs[0]), np.asarray(outs[1]))
    assert not np.allclose(np.asarray(outs[1]), np.asarray(outs[2]))
    # A static change (the number of steps) does recompile: the counter is live.
    flow.sample_euler(apply_fn, z, cond, cosine_grid(7), uncond=uncond, cfg_scale=0.5)
    assert len(traces) == 2


def test_parameters_in_a_partial_are_traced_not_recompiled():
    traces = []

    def velocity(params, x, t, cond):
        traces.append(1)
        return jnp.tanh(x @ params["w"] + cond["c"]) * t[:, None, None]

    z, c, _, _ = _inputs()
    ts = cosine_grid(4)
    rng = np.random.default_rng(0)
    outs = [
        flow.sample_euler(
            jax.tree_util.Partial(velocity, {"w": jnp.asarray(rng.normal(size=(D, D)), jnp.float32)}),
            z,
            {"c": c},
            ts,
        )
        for _ in range(3)
    ]
    assert len(traces) == 1
    assert not np.allclose(np.asarray(outs[0]), np.asarray(outs[1]))
    with pytest.raises(ValueError, match="callable"):
        flow.as_model(3)


def test_cfg_is_one_batched_call_and_zero_scale_is_conditional():
    calls = []
    apply_fn, _ = make_model(calls=calls)
    z, c, _, _ = _inputs()
    ts = cosine_grid(5)
    guided = flow.sample_euler(apply_fn, z, {"c": c}, ts, uncond={"c": np.zeros_like(c)}, cfg_scale=0.0)
    assert calls == [(2 * B, T, D)]  # one call (the scanned step body) with the doubled batch
    plain = flow.sample_euler(apply_fn, z, {"c": c}, ts)
    assert calls[1] == (B, T, D)
    np.testing.assert_allclose(np.asarray(guided), np.asarray(plain), atol=1e-6)
    # Outside scan: the public step calls apply_fn exactly once per step.
    calls.clear()
    state = flow.init(jnp.asarray(z))
    for k in range(1, 6):
        state = flow.step(
            state,
            jnp.asarray(ts[k], jnp.float32),
            apply_fn=apply_fn,
            cond={"c": jnp.asarray(c)},
            uncond={"c": jnp.zeros((B, T, D))},
            cfg_scale=0.7,
        )
        assert calls == [(2 * B, T, D)] * k


def test_inpainting_keeps_known_frames_exactly_and_on_the_path():
    apply_fn, _ = make_model()
    z, c, known, mask = _inputs()
    ts = jnp.asarray(cosine_grid(8), jnp.float32)
    x, traj = flow.sample_euler(
        apply_fn, z, {"c": c}, ts, known=known, known_mask=mask, return_trajectory=True
    )
    full = np.broadcast_to(mask, x.shape)
    np.testing.assert_array_equal(np.asarray(x)[full], known[full])
    assert not np.allclose(np.asarray(x)[~full], known[~full])
    # Intermediate states hold known entries on the sample's own path (same z).
    for k in (1, 4, 7):
        t = float(ts[k])
        on_path = (1 - (1 - SIGMA_MIN) * t) * z + t * known
        np.testing.assert_allclose(np.asarray(traj[k])[full], on_path[full], atol=1e-6)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(ts=np.array([0.0])), "ts"),
        (dict(ts=np.zeros((2, 2))), "ts"),
        (dict(ts=np.array([0.0, np.nan, 1.0])), "ts"),
        (dict(noise=np.full((B, T, D), np.nan, np.float32)), "noise"),
        (dict(known=np.zeros((B, T, D), np.float32)), "together"),
        (dict(known=np.zeros((B, T, D), np.float32), known_mask=np.ones((B, T), bool)), "known_mask"),
        (dict(known=np.zeros((B, T, D), np.float32), known_mask=np.ones((B, T, 1), np.float32)), "bool"),
        (dict(known=np.zeros((B, T + 1, D), np.float32), known_mask=np.ones((B, T, 1), bool)), "known"),
        (dict(uncond={"d": np.zeros((B, T, D), np.float32)}), "structure"),
        (dict(cond={"c": np.zeros((B + 1, T, D), np.float32)}), "batch"),
        (dict(cfg_scale=np.ones(2)), "cfg_scale"),
    ],
)
def test_validation_errors(kwargs, match):
    apply_fn, _ = make_model()
    z, c, _, _ = _inputs()
    args = dict(noise=z, cond={"c": c}, ts=uniform_grid(3))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        flow.sample_euler(apply_fn, args.pop("noise"), args.pop("cond"), args.pop("ts"), **args)
