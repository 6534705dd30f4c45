"""DDPM / DDIM samplers: analytic Gaussian targets (x0, eps, v), NumPy loop reference, gradients,
vmap, no recompilation on traced knobs, CFG batching, per-group clipping, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.samplers import diffusion as dif
from jaxtalk.samplers.flow import guided_apply
from jaxtalk.samplers.schedules import make_schedule, respace


# Compile time dominates these small programs.


MU = np.array([1.0, -2.0, 0.5])
S = np.array([0.5, 1.5, 1.0])
B, T, D = 2, 4, 3


def posterior_mean_x0(abar_table, mu=MU, s=S):
    """Exact E[x0 | x_t] for x0 ~ N(mu, diag s^2): x_t = sqrt(a) x0 + sqrt(1-a) eps is jointly Gaussian
    with x0, so E[x0 | x] = mu + s^2 sqrt(a) / (a s^2 + 1 - a) (x - sqrt(a) mu)."""
    table = jnp.asarray(abar_table, jnp.float32)
    mu_, s2 = jnp.asarray(mu, jnp.float32)[None, :], jnp.asarray(s, jnp.float32)[None, :] ** 2

    def x0_of(x, t):
        a = table[t.astype(jnp.int32)][:, None]
        return mu_ + s2 * jnp.sqrt(a) / (a * s2 + 1 - a) * (x - jnp.sqrt(a) * mu_)

    return table, x0_of


def gaussian_model(schedule, prediction):
    table, x0_of = posterior_mean_x0(schedule.alphas_cumprod)

    def apply_fn(x, t, cond):
        x0 = x0_of(x, t)
        a = table[t.astype(jnp.int32)][:, None]
        eps = (x - jnp.sqrt(a) * x0) / jnp.sqrt(1 - a)
        return {"x0": x0, "eps": eps, "v": jnp.sqrt(a) * eps - jnp.sqrt(1 - a) * x0}[prediction]

    return apply_fn


def affine_gain(r, s, kind, temperature=1.0):
    """Exact std gain of the sampler on Gaussian data with the exact predictor (every step is affine;
    DDPM's step noise times ``temperature``)."""
    gain, var = np.ones_like(s), np.ones_like(s)
    for i in range(r.num_steps - 1, -1, -1):
        a, ap = r.alphas_cumprod[i], r.alphas_cumprod_prev[i]
        g = s**2 * np.sqrt(a) / (a * s**2 + 1 - a)  # d x0_hat / d x
        if kind == "ddim":
            gain = gain * (np.sqrt(ap) * g + np.sqrt(1 - ap) * (1 - np.sqrt(a) * g) / np.sqrt(1 - a))
        else:
            m = r.posterior_coef_x0[i] * g + r.posterior_coef_xt[i]
            var = m**2 * var + (temperature**2 * np.exp(r.posterior_log_variance_clipped[i]) if i > 0 else 0.0)
    return gain if kind == "ddim" else np.sqrt(var)


@pytest.fixture(scope="module")
def noise():
    return jax.random.normal(jax.random.key(0), (20_000, 3))


@pytest.mark.parametrize("prediction", ["x0", "eps", "v"])
def test_ddim_reproduces_gaussian_target(noise, prediction):
    sched = make_schedule("cosine")
    r = respace(sched, 100)
    model = gaussian_model(sched, prediction)
    x = np.asarray(dif.sample_ddim(model, noise, {}, r, jax.random.key(1), prediction=prediction))
    np.testing.assert_allclose(x.mean(0), MU, atol=0.02 * S.max(), rtol=0.02)
    np.testing.assert_allclose(x.std(0), S, rtol=0.02)
    # Sharper: DDIM is affine in x_T here, so the sample std must equal the exact gain of the discrete
    # chain (which carries DDIM's own 1-2% discretisation error at 100 steps) to float32 accuracy.
    z = np.asarray(noise, np.float64)
    np.testing.assert_allclose(x.std(0) / z.std(0), affine_gain(r, S, "ddim"), rtol=2e-3)


def test_ddpm_fixed_small_equals_exact_chain(noise):
    sched = make_schedule("cosine")
    r = respace(sched, 100)
    x = np.asarray(
        dif.sample_ddpm(gaussian_model(sched, "eps"), noise, {}, r, jax.random.key(2), prediction="eps")
    )
    np.testing.assert_allclose(x.std(0), affine_gain(r, S, "ddpm"), rtol=0.02)
    np.testing.assert_allclose(x.mean(0), MU, atol=0.02 * S.max())
    # ...which is visibly below the target: the fixed posterior variance ignores Var[x0 | x_t].
    assert np.all(affine_gain(r, S, "ddpm") < 0.98 * S)


@pytest.mark.parametrize("temperature", [0.0, 0.5])
def test_ddpm_temperature_scales_every_steps_noise_as_the_affine_chain_predicts(noise, temperature):
    sched = make_schedule("cosine")
    r = respace(sched, 50)
    x = np.asarray(dif.sample_ddpm(gaussian_model(sched, "x0"), noise, {}, r, jax.random.key(2),
                                   temperature=temperature))
    z = np.asarray(noise, np.float64)
    gain = affine_gain(r, S, "ddpm", temperature)
    np.testing.assert_allclose(x.std(0) / z.std(0), gain, rtol=0.02 if temperature else 2e-3)
    np.testing.assert_allclose(x.mean(0), MU, atol=0.02 * S.max())
    # Cooler than 1, narrower than the temperature-1 chain: the noise, not only x_T, was scaled.
    assert np.all(gain < 0.9 * affine_gain(r, S, "ddpm"))


@pytest.mark.parametrize("prediction", ["x0", "v"])
def test_ddpm_with_exact_reverse_variance_reproduces_target(noise, prediction):
    """Learned-range variance set to the exact reverse variance of q(x_prev | x_t):
    posterior variance + coef_x0^2 Var[x0 | x_t], Var[x0 | x_t] = s^2 (1 - a) / (a s^2 + 1 - a)."""
    sched = make_schedule("cosine")
    r = respace(sched, 100)
    v_table = np.zeros((sched.num_timesteps, 3))
    for i in range(1, r.num_steps):
        a = r.alphas_cumprod[i]
        var = r.posterior_variance[i] + r.posterior_coef_x0[i] ** 2 * S**2 * (1 - a) / (a * S**2 + 1 - a)
        lo, hi = r.posterior_log_variance_clipped[i], r.log_betas[i]
        v_table[r.timesteps[i]] = 2 * (np.log(var) - lo) / (hi - lo) - 1
    pred = gaussian_model(sched, prediction)
    v_table = jnp.asarray(v_table, jnp.float32)

    def apply_fn(x, t, cond):
        return jnp.concatenate([pred(x, t, cond), v_table[t.astype(jnp.int32)]], axis=-1)

    x = np.asarray(
        dif.sample_ddpm(
            apply_fn, noise, {}, r, jax.random.key(3), prediction=prediction, variance="learned_range"
        )
    )
    np.testing.assert_allclose(x.mean(0), MU, atol=0.02 * S.max(), rtol=0.02)
    np.testing.assert_allclose(x.std(0), S, rtol=0.02)


# ---------------------------------------------------------------- a small nonlinear conditional model


def make_model(seed=0, calls=None, out_mult=1):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(D, D * out_mult)) / np.sqrt(D)
    u = rng.normal(size=(D, D * out_mult)) / np.sqrt(D)
    b = rng.normal(size=(D * out_mult,)) / 1000.0

    def apply_fn(x, t, cond):
        if calls is not None:
            calls.append(x.shape)
        return jnp.tanh(x @ w + cond["c"] @ u + t[:, None, None] * b[None, None, :])

    def apply_np(x, t, c):
        return np.tanh(x @ w + c @ u + t[:, None, None] * b[None, None, :])

    return apply_fn, apply_np


def reference_loop(apply_np, r, z, c, c_u, w, noises, kind, eta=0.0, prediction="x0", clip=(),
                   temperature=1.0, variance="fixed_small"):
    """Independent NumPy loop over respaced steps, written from the DDPM/DDIM formulas (a learned
    range: the second half of the output interpolates the log variance; guidance on the first half)."""
    x = z.copy()
    n = r.num_steps
    d = x.shape[-1]
    for j, i in enumerate(range(n - 1, -1, -1)):
        a, ap = r.alphas_cumprod[i], r.alphas_cumprod_prev[i]
        t = np.full((x.shape[0],), float(r.timesteps[i]))
        raw = apply_np(x, t, c)
        out, v = raw[..., :d], raw[..., d:]
        if c_u is not None:
            out = (1 + w) * out - w * apply_np(x, t, c_u)[..., :d]
        if prediction == "x0":
            x0 = out
        elif prediction == "eps":
            x0 = (x - np.sqrt(1 - a) * out) / np.sqrt(a)
        else:
            x0 = np.sqrt(a) * x - np.sqrt(1 - a) * out
        for idx, lo, hi in clip:
            x0[..., list(idx)] = np.clip(x0[..., list(idx)], lo, hi)
        if kind == "ddim":
            eps = (x - np.sqrt(a) * x0) / np.sqrt(1 - a)
            sigma = eta * np.sqrt((1 - ap) / (1 - a) * (1 - a / ap))
            x = np.sqrt(ap) * x0 + np.sqrt(max(1 - ap - sigma**2, 0.0)) * eps + (i > 0) * sigma * noises[j]
        else:
            beta = 1 - a / ap
            mean = beta * np.sqrt(ap) / (1 - a) * x0 + np.sqrt(1 - beta) * (1 - ap) / (1 - a) * x
            if variance == "learned_range":
                frac = (v + 1) / 2
                std = np.exp(0.5 * (frac * np.log(beta) + (1 - frac) * r.posterior_log_variance_clipped[i]))
            else:
                std = np.sqrt(r.posterior_variance[i])
            x = mean + (i > 0) * temperature * std * noises[j]
    return x


@pytest.mark.parametrize(
    "kind,kw",
    [
        ("ddim", dict(eta=0.0)),
        ("ddim", dict(eta=0.6, prediction="eps", clip=(((0, 2), -0.5, 0.5),))),
        ("ddpm", dict(prediction="v")),
        ("ddpm", dict(clip=(((1,), -0.2, 0.3),))),
        ("ddpm", dict(temperature=0.7, variance="learned_range")),
    ],
)
def test_scan_matches_numpy_loop(float64, kind, kw):
    apply_fn, apply_np = make_model(out_mult=2 if kw.get("variance") == "learned_range" else 1)
    rng = np.random.default_rng(1)
    z, c = rng.normal(size=(B, T, D)), rng.normal(size=(B, T, D))
    r = respace(make_schedule("cosine", 1000), 7)
    key = jax.random.key(5)
    noises = [np.asarray(jax.random.normal(k, (B, T, D), jnp.float64)) for k in jax.random.split(key, 7)]
    fn = dif.sample_ddim if kind == "ddim" else dif.sample_ddpm
    clip = [dif.ClipGroup(*g) for g in kw.get("clip", ())]
    got = fn(
        apply_fn,
        jnp.asarray(z),
        {"c": jnp.asarray(c)},
        r,
        key,
        uncond={"c": jnp.asarray(-0.5 * c)},
        cfg_scale=0.8,
        **{**kw, "clip": clip},
    )
    ref = reference_loop(apply_np, r, z, c, -0.5 * c, 0.8, noises, kind, **kw)
    assert got.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-6, rtol=0)


def test_public_steps_and_trajectory():
    apply_fn, _ = make_model()
    z = jax.random.normal(jax.random.key(1), (B, T, D))
    cond = {"c": jnp.ones((B, T, D))}
    r = respace(make_schedule("linear"), 5)
    key = jax.random.key(2)
    x, traj = dif.sample_ddim(apply_fn, z, cond, r, key, eta=0.5, return_trajectory=True)
    assert traj.shape == (6, B, T, D)
    tables = dif._tables(r.astype(jnp.float32), jnp.float32)
    state = dif.init(z)
    step = jax.jit(lambda st, row, k: dif.ddim_step(st, row, k, apply_fn=apply_fn, cond=cond, eta=0.5))
    for j, k in enumerate(jax.random.split(key, 5)):  # a caller's own loop
        state = step(state, dif.StepTables(*(f[j] for f in tables)), k)
        np.testing.assert_allclose(np.asarray(state.x), np.asarray(traj[j + 1]), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(traj[-1]), np.asarray(x))


@pytest.mark.parametrize("kind", ["ddim", "ddpm"])
def test_grad_wrt_condition_matches_finite_differences(float64, kind):
    apply_fn, _ = make_model(seed=3)
    rng = np.random.default_rng(4)
    z, c0 = jnp.asarray(rng.normal(size=(B, T, D))), jnp.asarray(rng.normal(size=(B, T, D)))
    weights = jnp.asarray(rng.normal(size=(B, T, D)))
    r = respace(make_schedule("linear"), 10)

    def loss(c, w):
        kw = dict(eta=0.3) if kind == "ddim" else {}
        fn = dif.sample_ddim if kind == "ddim" else dif.sample_ddpm
        x = fn(
            apply_fn, z, {"c": c}, r, jax.random.key(0), uncond={"c": 0 * c}, cfg_scale=w, remat=True, **kw
        )
        return jnp.sum(weights * jnp.sin(x))

    g_c, g_w = jax.grad(loss, argnums=(0, 1))(c0, jnp.asarray(0.5))
    eps = 1e-6
    for _ in range(2):
        d = jnp.asarray(rng.normal(size=(B, T, D)))
        fd = (loss(c0 + eps * d, 0.5) - loss(c0 - eps * d, 0.5)) / (2 * eps)
        assert float(jnp.vdot(g_c, d)) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
    fd_w = (loss(c0, 0.5 + eps) - loss(c0, 0.5 - eps)) / (2 * eps)
    assert float(g_w) == pytest.approx(float(fd_w), rel=1e-6, abs=1e-9)


def test_vmap_over_keys_and_cfg_scales():
    apply_fn, _ = make_model()
    cond, uncond = {"c": jnp.ones((B, T, D))}, {"c": jnp.zeros((B, T, D))}
    r = respace(make_schedule("linear"), 4).astype(jnp.float32)
    z = jax.random.normal(jax.random.key(1), (B, T, D))

    def run(key, w):
        return dif.sample_ddpm(apply_fn, z, cond, r, key, uncond=uncond, cfg_scale=w)

    keys = jax.random.split(jax.random.key(0), 3)
    scales = jnp.asarray([0.0, 1.0, 3.0])
    by_key = jax.vmap(run, in_axes=(0, None))(keys, 1.0)
    by_scale = jax.vmap(run, in_axes=(None, 0))(keys[0], scales)
    for i in range(3):
        np.testing.assert_allclose(np.asarray(by_key[i]), np.asarray(run(keys[i], 1.0)), atol=1e-5)
        np.testing.assert_allclose(np.asarray(by_scale[i]), np.asarray(run(keys[0], scales[i])), atol=1e-5)
    assert not np.allclose(np.asarray(by_key[0]), np.asarray(by_key[1]))


def test_traced_knobs_do_not_recompile():
    traces = []
    apply_fn, _ = make_model(calls=traces)
    z = np.random.default_rng(0).normal(size=(B, T, D)).astype(np.float32)
    cond, uncond = {"c": np.ones((B, T, D), np.float32)}, {"c": np.zeros((B, T, D), np.float32)}
    key = jax.random.key(0)
    lin, cos = respace(make_schedule("linear"), 6), respace(make_schedule("cosine"), 6)
    before = dif._sample._cache_size()
    outs = [
        dif.sample_ddim(apply_fn, z, cond, lin, key, uncond=uncond, cfg_scale=0.5, eta=0.0),
        dif.sample_ddim(apply_fn, z, cond, lin, key, uncond=uncond, cfg_scale=2.0, eta=0.0),
        dif.sample_ddim(apply_fn, z, cond, lin, key, uncond=uncond, cfg_scale=2.0, eta=1.0),
        dif.sample_ddim(apply_fn, z, cond, cos, key, uncond=uncond, cfg_scale=2.0, eta=1.0),
    ]
    assert len(traces) == 1 and dif._sample._cache_size() == before + 1
    for a, b in zip(outs, outs[1:]):
        assert not np.allclose(np.asarray(a), np.asarray(b))
    dif.sample_ddim(apply_fn, z, cond, respace(make_schedule("linear"), 7), key, uncond=uncond)
    assert len(traces) == 2  # a different step count is static: the counter is live


def test_cfg_one_batched_call_and_zero_scale_is_conditional():
    calls = []
    apply_fn, _ = make_model(calls=calls)
    z = jax.random.normal(jax.random.key(1), (B, T, D))
    cond, uncond = {"c": jnp.ones((B, T, D))}, {"c": jnp.zeros((B, T, D))}
    r = respace(make_schedule("linear"), 5)
    guided = dif.sample_ddpm(apply_fn, z, cond, r, jax.random.key(0), uncond=uncond, cfg_scale=0.0)
    assert calls == [(2 * B, T, D)]
    plain = dif.sample_ddpm(apply_fn, z, cond, r, jax.random.key(0))
    assert calls[1] == (B, T, D)
    np.testing.assert_allclose(np.asarray(guided), np.asarray(plain), atol=1e-6)
    strong = dif.sample_ddpm(apply_fn, z, cond, r, jax.random.key(0), uncond=uncond, cfg_scale=3.0)
    assert not np.allclose(np.asarray(strong), np.asarray(plain))


def test_learned_range_cfg_guides_prediction_only():
    apply_fn, apply_np = make_model(out_mult=2)
    rng = np.random.default_rng(0)
    x, c, cu = (rng.normal(size=(B, T, D)).astype(np.float32) for _ in range(3))
    t = np.full((B,), 7.0, np.float32)
    got = np.asarray(
        guided_apply(apply_fn, jnp.asarray(x), jnp.asarray(t), {"c": c}, {"c": cu}, 0.6, guided_channels=D)
    )
    out_c, out_u = apply_np(x, t, c), apply_np(x, t, cu)
    np.testing.assert_allclose(got[..., :D], 1.6 * out_c[..., :D] - 0.6 * out_u[..., :D], atol=1e-5)
    np.testing.assert_allclose(got[..., D:], out_c[..., D:], atol=1e-6)  # variance: conditional branch
    z = jax.random.normal(jax.random.key(1), (B, T, D))
    r = respace(make_schedule("linear"), 4)
    wrong, _ = make_model()
    with pytest.raises(ValueError, match="learned_range"):
        dif.sample_ddpm(wrong, z, {"c": jnp.ones((B, T, D))}, r, jax.random.key(0), variance="learned_range")


def test_clipping_bounds_the_x0_estimate_per_group():
    def apply_fn(x, t, cond):
        return 5.0 * jnp.ones_like(x) * jnp.asarray([1.0, -1.0, 1.0])[None, None, :]  # far outside the bounds

    z = jax.random.normal(jax.random.key(1), (B, T, D))
    r = respace(make_schedule("linear"), 5)
    clip = [dif.ClipGroup((0,), -1.0, 1.0), dif.ClipGroup((1,), -0.25, 0.0)]
    x = np.asarray(dif.sample_ddim(apply_fn, z, {}, r, jax.random.key(0), clip=clip))
    # DDIM's last step returns the (clipped) x0 estimate.
    np.testing.assert_allclose(x[..., 0], 1.0, atol=1e-5)
    np.testing.assert_allclose(x[..., 1], -0.25, atol=1e-5)
    np.testing.assert_allclose(x[..., 2], 5.0, atol=1e-4)  # unclipped group untouched


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(prediction="score"), "prediction"),
        (dict(variance="learned"), "variance"),
        (dict(clip=[dif.ClipGroup((0,), 1.0, -1.0)]), "low"),
        (dict(clip=[dif.ClipGroup((7,), -1.0, 1.0)]), "out of range"),
        (dict(noise=np.full((B, T, D), np.inf, np.float32)), "noise"),
        (dict(cfg_scale=np.ones(3)), "scalars"),
        (dict(uncond={"c": np.zeros((B, T, D + 1), np.float32)}), "uncond"),
        (dict(key=np.int32(3)), "key"),
    ],
)
def test_validation_errors(kwargs, match):
    apply_fn, _ = make_model()
    args = dict(
        noise=np.zeros((B, T, D), np.float32),
        cond={"c": np.zeros((B, T, D), np.float32)},
        schedule=respace(make_schedule("linear"), 3),
        key=jax.random.key(0),
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        dif.sample_ddim(
            apply_fn, args.pop("noise"), args.pop("cond"), args.pop("schedule"), args.pop("key"), **args
        )
