"""TIMAR sampling: CFG algebra, scale sweep by vmap without recompiling, samplers, bad input."""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models.timar import TimarConfig, init_params, sample
from jaxtalk.models.timar.head import apply_head, init_head
from jaxtalk.models.turns.streams import to_turns
from jaxtalk.models.timar.sampling import respaced_schedule
from jaxtalk.models.timar.sampling import conditions as _conditions_eager
from jaxtalk.models.timar.sampling import sample_frames as _sample_frames_eager

# The package re-exports the function ``sample``; the module is needed for its jit cache.
import jaxtalk.models.timar.sampling as sample_mod

conditions = jax.jit(_conditions_eager, static_argnums=1, static_argnames="guidance")
sample_frames = jax.jit(_sample_frames_eager, static_argnums=1, static_argnames=("sample_steps", "sampler", "precompute"))

CFG = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=8, max_turns=4, frames_per_turn=5)
B, N, F = 2, 2, 5



@jax.jit
def _perturb(p, key):
    # Zero-initialised adaLN layers make a fresh head output exactly 0; perturb so tests see signal.
    leaves, tree = jax.tree.flatten(p)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


@pytest.fixture(scope="module")
def params():
    p = init_params(CFG, jax.random.key(0))
    return _perturb(p, jax.random.key(7))


def _streams(seed=0, n=N):
    rng = np.random.default_rng(seed)
    t = n * F
    return (rng.normal(size=(B, t, 8)).astype(np.float32), rng.normal(size=(B, t, 56)).astype(np.float32),
            rng.normal(size=(B, t, 8)).astype(np.float32))


@pytest.mark.slow
def test_guidance_weight_zero_is_conditional_and_minus_one_is_unconditional(params):
    us, um, as_ = _streams()
    key = jax.random.key(3)
    cond_only = np.asarray(sample(params, CFG, us, um, as_, key, guidance=False))
    np.testing.assert_allclose(np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=0.0)), cond_only, atol=1e-5)
    # w = -1 (the paper's omega = 0): the sample ignores the user entirely.
    us2, um2 = us + 1.0, um * 2.0
    u0 = np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=-1.0))
    u1 = np.asarray(sample(params, CFG, us2, um2, as_, key, cfg_scale=-1.0))
    np.testing.assert_allclose(u0, u1, atol=1e-5)
    assert np.abs(np.asarray(sample(params, CFG, us2, um2, as_, key, cfg_scale=0.0)) - cond_only).max() > 1e-3


def test_cfg_sweep_is_a_vmap_and_never_recompiles(params):
    us, um, as_ = _streams()
    key = jax.random.key(4)
    scales = jnp.asarray([0.0, 1.0, 2.5])
    sweep = jax.vmap(lambda s: sample(params, CFG, us, um, as_, key, cfg_scale=s))(scales)
    assert sweep.shape == (3, B, N * F, 56)
    for i, s in enumerate([0.0, 1.0, 2.5]):
        np.testing.assert_allclose(np.asarray(sweep[i]), np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=s)),
                                   atol=2e-5)
    before = sample_mod._sample._cache_size()
    for s in (0.3, 1.7, 4.0):
        sample(params, CFG, us, um, as_, key, cfg_scale=s, eta=s / 10)
    assert sample_mod._sample._cache_size() == before


@pytest.mark.slow
def test_guided_sample_equals_eq9_applied_to_head_outputs_with_one_step(params):
    # With one respaced step (t = 0: x0 estimate returned directly) the sample is exactly
    # out_u + omega (out_c - out_u) of the x0 predictions at the initial noise, omega = 1 + cfg_scale.
    us, um, as_ = _streams()
    key = jax.random.key(5)
    omega = 1.7
    got = np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=omega - 1, sample_steps=1))
    zc, zu = conditions(params, CFG, *(to_turns(jnp.asarray(x), F) for x in (us, um, as_)))
    k_noise, _ = jax.random.split(key)
    noise = jax.random.normal(k_noise, zc.shape[:-1] + (56,))

    t = jnp.zeros(zc.shape[:-1])
    oc, ou = apply_head(params["head"], CFG, zc, noise, t), apply_head(params["head"], CFG, zu, noise, t)
    np.testing.assert_allclose(got, np.asarray(ou + omega * (oc - ou)).reshape(B, N * F, 56), atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("learn_sigma", [False, True])
def test_sampler_equals_a_python_loop_ddim_reference(params, learn_sigma):
    # Independent reference: the plain per-frame head (nothing hoisted, t broadcast to every frame),
    # Eq. (9) guidance, and deterministic DDIM written out step by step in float64. Both sampler
    # paths (modulations precomputed for every step before the scan, or computed inside it) must
    # match it.
    cfg = TimarConfig.small(**{**CFG.__dict__, "learn_sigma": learn_sigma})
    # Only the head changes with a learned variance (112 outputs): re-initialise it alone.
    p = params if not learn_sigma else {**params, "head": _perturb(init_head(cfg, jax.random.key(0)), jax.random.key(8))}
    us, um, as_ = _streams()
    zc, zu = conditions(p, cfg, *(to_turns(jnp.asarray(x), F) for x in (us, um, as_)))
    key, omega, steps = jax.random.key(9), 1.6, 4
    sched = respaced_schedule(cfg.schedule, cfg.num_timesteps, steps)
    k_noise, _ = jax.random.split(key)
    x = np.asarray(jax.random.normal(k_noise, zc.shape[:-1] + (56,)), np.float64)
    for i in reversed(range(steps)):  # noisiest first
        t = jnp.full(zc.shape[:-1], float(sched.timesteps[i]))
        xf = jnp.asarray(x, jnp.float32)
        oc = np.asarray(apply_head(p["head"], cfg, zc, xf, t), np.float64)[..., :56]
        ou = np.asarray(apply_head(p["head"], cfg, zu, xf, t), np.float64)[..., :56]
        x0 = ou + omega * (oc - ou)
        abar, abar_prev = sched.alphas_cumprod[i], sched.alphas_cumprod_prev[i]
        eps = (x - np.sqrt(abar) * x0) / np.sqrt(1 - abar)
        x = np.sqrt(abar_prev) * x0 + np.sqrt(1 - abar_prev) * eps
    assert np.abs(x).max() > 0.1
    got = {pc: np.asarray(sample_frames(p, cfg, zc, zu, key, cfg_scale=omega - 1, sample_steps=steps, precompute=pc))
           for pc in (True, False)}
    # float32 sampler vs the float64 reference: a few float32 ulps of the O(1) values.
    for pc in (True, False):
        np.testing.assert_allclose(got[pc], x, atol=5e-5, rtol=1e-5)
    # The optimised sampler vs the previous one (modulations in the loop): same float32 math.
    np.testing.assert_allclose(got[True], got[False], atol=1e-5, rtol=1e-5)


def test_paper_default_ddpm_reads_the_learned_variance_and_scales_each_steps_noise_like_a_loop(params):
    # The paper preset's sampler (MAR's): ancestral DDPM over the respaced steps, the head's second
    # half interpolating each step's log variance, Eq. (9) guidance on the first half only, and the
    # temperature on every step's noise (x_T unscaled). Written out in float64 with the same draws.
    cfg = TimarConfig.small(**{**CFG.__dict__, "learn_sigma": True, "sampler": "ddpm"})
    assert TimarConfig.paper().sampler == "ddpm" and TimarConfig.paper().learn_sigma
    p = {**params, "head": _perturb(init_head(cfg, jax.random.key(0)), jax.random.key(8))}
    us, um, as_ = _streams()
    zc, zu = conditions(p, cfg, *(to_turns(jnp.asarray(x), F) for x in (us, um, as_)))
    key, omega, steps, tau = jax.random.key(9), 1.6, 4, 0.6
    sched = respaced_schedule(cfg.schedule, cfg.num_timesteps, steps)
    k_noise, k_steps = jax.random.split(key)
    x = np.asarray(jax.random.normal(k_noise, zc.shape[:-1] + (56,)), np.float64)
    step_keys = jax.random.split(k_steps, steps)
    for j, i in enumerate(reversed(range(steps))):  # noisiest first
        t = jnp.full(zc.shape[:-1], float(sched.timesteps[i]))
        xf = jnp.asarray(x, jnp.float32)
        oc = np.asarray(apply_head(p["head"], cfg, zc, xf, t), np.float64)
        ou = np.asarray(apply_head(p["head"], cfg, zu, xf, t), np.float64)
        x0 = ou[..., :56] + omega * (oc[..., :56] - ou[..., :56])
        frac = (oc[..., 56:] + 1) / 2
        log_var = frac * sched.log_betas[i] + (1 - frac) * sched.posterior_log_variance_clipped[i]
        mean = sched.posterior_coef_x0[i] * x0 + sched.posterior_coef_xt[i] * x
        z = np.asarray(jax.random.normal(step_keys[j], x.shape, jnp.float32), np.float64)
        x = mean + (i > 0) * tau * np.exp(0.5 * log_var) * z
    got = np.asarray(sample_frames(p, cfg, zc, zu, key, cfg_scale=omega - 1, sample_steps=steps, temperature=tau))
    np.testing.assert_allclose(got, x, atol=5e-5, rtol=1e-5)
    # The temperature acts: 0 leaves only x_T's randomness, and a cooler chain differs from a warmer one.
    cold = [np.asarray(sample_frames(p, cfg, zc, zu, k, cfg_scale=omega - 1, sample_steps=steps, temperature=0.0))
            for k in (key, jax.random.key(10))]
    assert np.abs(cold[0] - got).max() > 1e-3 and np.abs(cold[0] - cold[1]).max() > 1e-3


@pytest.mark.slow
def test_ddpm_and_step_counts_and_mlp_head(params):
    us, um, as_ = _streams()
    x = sample(params, CFG, us, um, as_, jax.random.key(1), sampler="ddpm", sample_steps=3)
    assert x.shape == (B, N * F, 56) and np.all(np.isfinite(np.asarray(x)))
    mlp = TimarConfig.small(**{**CFG.__dict__, "head": "mlp"})
    pm = init_params(mlp, jax.random.key(0))
    y = sample(pm, mlp, us, um, as_, jax.random.key(1), cfg_scale=0.0)
    zc, _ = conditions(pm, mlp, *(to_turns(jnp.asarray(a), F) for a in (us, um, as_)), guidance=False)
    ref = sample_frames(pm, mlp, zc, None, jax.random.key(0), cfg_scale=0.0, sample_steps=1)
    np.testing.assert_allclose(np.asarray(y), np.asarray(ref).reshape(B, N * F, 56), atol=1e-5)


def test_sample_rejects_bad_input(params):
    us, um, as_ = _streams()
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="multiple of frames_per_turn"):
        sample(params, CFG, us[:, :7], um[:, :7], as_[:, :7], key)
    with pytest.raises(ValueError, match="aligned"):
        sample(params, CFG, us, um[:, :5], as_, key)
    with pytest.raises(ValueError, match="NaN"):
        sample(params, CFG, us, np.full_like(um, np.nan), as_, key)
    with pytest.raises(ValueError, match="channels"):
        sample(params, CFG, us[..., :5], um, as_, key)
    long = _streams(n=5)
    with pytest.raises(ValueError, match="max_turns"):
        sample(params, CFG, *long, key)
    with pytest.raises(ValueError, match="sampler"):
        sample(params, CFG, us, um, as_, key, sampler="euler")
    with pytest.raises(ValueError, match="sample_steps"):
        sample(params, CFG, us, um, as_, key, sample_steps=0)
    with pytest.raises(ValueError, match="scalar"):
        sample(params, CFG, us, um, as_, key, cfg_scale=jnp.ones(2))


def test_ddim_temperature_scales_the_initial_noise(params):
    us, um, as_ = _streams()
    zc, zu = conditions(params, CFG, *(to_turns(jnp.asarray(x), F) for x in (us, um, as_)))
    k1, k2 = jax.random.key(1), jax.random.key(2)
    run = lambda k, tau, steps=4: np.asarray(  # noqa: E731
        sample_frames(params, CFG, zc, zu, k, cfg_scale=0.5, sample_steps=steps, temperature=tau))
    # 1 is the plain sampler; 0 is deterministic (DDIM, eta = 0: the initial noise is the only randomness).
    np.testing.assert_array_equal(run(k1, 1.0), np.asarray(sample_frames(params, CFG, zc, zu, k1, cfg_scale=0.5, sample_steps=4)))
    np.testing.assert_array_equal(run(k1, 0.0), run(k2, 0.0))
    assert np.abs(run(k1, 1.0) - run(k2, 1.0)).max() > 1e-3
    # One step from x_T = 0 at t = 0 is the guided head output at x = 0 (sample(temperature=...) too).
    t = jnp.zeros(zc.shape[:-1])
    zero = jnp.zeros(zc.shape[:-1] + (56,))
    oc, ou = apply_head(params["head"], CFG, zc, zero, t), apply_head(params["head"], CFG, zu, zero, t)
    np.testing.assert_allclose(run(k1, 0.0, steps=1), np.asarray(ou + 1.5 * (oc - ou)), atol=1e-5)
    got = sample(params, CFG, us, um, as_, k2, cfg_scale=0.5, sample_steps=1, temperature=0.0)
    np.testing.assert_allclose(np.asarray(got), np.asarray(ou + 1.5 * (oc - ou)).reshape(B, N * F, 56), atol=1e-5)
    with pytest.raises(ValueError, match="temperature"):
        sample(params, CFG, us, um, as_, k1, temperature=-1.0)
    with pytest.raises(ValueError, match="temperature"):
        sample(params, CFG, us, um, as_, k1, temperature=jnp.ones(2))


def test_mean_sampler_is_the_guided_head_output_at_the_last_timestep(params):
    # sampler="mean": one head call at t = T - 1 on the initial noise, guided (Eq. 9); without
    # guidance it is posterior_mean's estimate given the same noise.
    us, um, as_ = _streams()
    zc, zu = conditions(params, CFG, *(to_turns(jnp.asarray(x), F) for x in (us, um, as_)))
    key, omega = jax.random.key(4), 1.3
    k_noise, _ = jax.random.split(key)
    noise = jax.random.normal(k_noise, zc.shape[:-1] + (56,))
    t = jnp.full(zc.shape[:-1], CFG.num_timesteps - 1.0)
    oc, ou = apply_head(params["head"], CFG, zc, noise, t), apply_head(params["head"], CFG, zu, noise, t)
    got = sample_frames(params, CFG, zc, zu, key, cfg_scale=omega - 1, sample_steps=5, sampler="mean")
    np.testing.assert_allclose(np.asarray(got), np.asarray(ou + omega * (oc - ou)), atol=1e-5)
    cond = sample(params, CFG, us, um, as_, key, sampler="mean", guidance=False)
    np.testing.assert_allclose(np.asarray(cond), np.asarray(oc).reshape(B, N * F, 56), atol=1e-5)


def test_a_concrete_zero_weight_skips_the_unconditional_branch_with_the_same_sample(params, monkeypatch):
    us, um, as_ = _streams()
    key = jax.random.key(5)
    # A traced weight of 0 runs both branches and mixes them as c + 0 (c - u).
    both = np.asarray(jax.vmap(lambda s: sample(params, CFG, us, um, as_, key, cfg_scale=s))(jnp.zeros(1))[0])
    compiled, seen = sample_mod._sample, []
    monkeypatch.setattr(sample_mod, "_sample", lambda *a: seen.append(a[-1]) or compiled(*a))
    skipped = np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=0.0))
    guided = np.asarray(sample(params, CFG, us, um, as_, key, cfg_scale=0.5))
    assert seen == [False, True]  # the last argument of the compiled sampler: guidance
    np.testing.assert_allclose(skipped, both, atol=1e-6)
    assert np.abs(guided - skipped).max() > 1e-3
    assert sample_mod.without_guidance(0.0) and sample_mod.without_guidance(jnp.zeros(()))
    assert not sample_mod.without_guidance(0.5) and not sample_mod.without_guidance(jnp.asarray(-1.0))
