"""Time grids, DDPM tables, respacing (reference convention) and posterior coefficients."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.samplers import schedules as S


def test_grids():
    np.testing.assert_allclose(S.uniform_grid(4), [0, 0.25, 0.5, 0.75, 1.0])
    n = 10
    ts = S.cosine_grid(n)
    assert ts.shape == (n + 1,) and ts.dtype == np.float64
    for k in range(n + 1):
        assert ts[k] == pytest.approx(1 - math.cos(k / n * math.pi / 2), abs=1e-15)
    assert ts[0] == 0.0 and ts[-1] == 1.0
    assert np.all(np.diff(ts) > 0)
    # The cosine grid crowds steps at the noise end (t = 0).
    assert np.diff(ts)[0] < np.diff(ts)[-1]


def test_linear_table():
    s = S.make_schedule("linear", 1000)
    assert s.betas.dtype == np.float64
    assert s.betas[0] == pytest.approx(1e-4) and s.betas[-1] == pytest.approx(0.02)
    np.testing.assert_allclose(np.diff(s.betas), (0.02 - 1e-4) / 999, rtol=1e-9)
    # alpha_bar by a plain product loop
    prod, ref = 1.0, []
    for b in s.betas:
        prod *= 1 - b
        ref.append(prod)
    np.testing.assert_allclose(s.alphas_cumprod, ref, rtol=1e-12)


def test_cosine_table_follows_alpha_bar_formula():
    t_max = 1000
    s = S.make_schedule("cosine", t_max)

    def f(t):
        return math.cos((t / t_max + 0.008) / 1.008 * math.pi / 2) ** 2

    # Below the cap, alpha_bar_t = f(t+1)/f(0) exactly (telescoping product).
    for t in (0, 1, 10, 500, 900, 990):
        assert s.alphas_cumprod[t] == pytest.approx(f(t + 1) / f(0), rel=1e-9)
    assert s.betas.max() == pytest.approx(0.999)
    assert s.betas[-1] == pytest.approx(0.999)  # the last beta is capped
    assert np.all(np.diff(s.alphas_cumprod) < 0)


def test_space_timesteps_reference_convention():
    np.testing.assert_array_equal(S.space_timesteps(1000, 5), [0, 250, 500, 749, 999])
    steps = S.space_timesteps(1000, 100)
    assert steps.shape == (100,)
    np.testing.assert_array_equal(steps[:5], [0, 10, 20, 30, 40])
    np.testing.assert_array_equal(steps[-2:], [989, 999])
    # Round-to-nearest of i * 999/99 (no exact .5 ties for these sizes).
    np.testing.assert_array_equal(steps, np.floor(np.arange(100) * 999 / 99 + 0.5).astype(int))
    np.testing.assert_array_equal(S.space_timesteps(1000, 1000), np.arange(1000))
    np.testing.assert_array_equal(S.space_timesteps(1000, 1), [0])
    np.testing.assert_array_equal(S.space_timesteps(10, 2), [0, 9])


def test_respace_tables_and_posterior():
    base = S.make_schedule("linear", 1000)
    r = S.respace(base, 5)
    steps = [0, 250, 500, 749, 999]
    np.testing.assert_array_equal(r.timesteps, steps)
    np.testing.assert_allclose(r.alphas_cumprod, base.alphas_cumprod[steps], rtol=0)
    np.testing.assert_allclose(r.alphas_cumprod_prev, np.r_[1.0, base.alphas_cumprod[steps[:-1]]], rtol=0)
    for i in range(5):
        a, ap = r.alphas_cumprod[i], r.alphas_cumprod_prev[i]
        beta = 1 - a / ap
        # Gaussian conditioning by hand: x_t = sqrt(a/ap) x_prev + sqrt(beta) n and
        # x_prev = sqrt(ap) x0 + sqrt(1-ap) e, so the posterior precision is 1/(1-ap) + (a/ap)/beta
        # and the mean is var * (sqrt(ap) x0 / (1-ap) + sqrt(a/ap) x_t / beta).
        if i == 0:
            assert r.posterior_variance[0] == 0.0
            assert r.posterior_coef_x0[0] == pytest.approx(1.0)
            assert r.posterior_coef_xt[0] == pytest.approx(0.0, abs=1e-15)
            continue
        var = 1.0 / (1.0 / (1 - ap) + (a / ap) / beta)
        assert r.posterior_variance[i] == pytest.approx(var, rel=1e-9)
        assert r.posterior_coef_x0[i] == pytest.approx(var * math.sqrt(ap) / (1 - ap), rel=1e-9)
        assert r.posterior_coef_xt[i] == pytest.approx(var * math.sqrt(a / ap) / beta, rel=1e-9)
        assert r.log_betas[i] == pytest.approx(math.log(beta), rel=1e-12)
    # Clipped log variance: entry 0 copies entry 1.
    assert r.posterior_log_variance_clipped[0] == r.posterior_log_variance_clipped[1]
    assert r.log_betas[0] == pytest.approx(math.log(r.posterior_variance[1]))
    assert np.all(np.isfinite(r.posterior_log_variance_clipped))


def test_full_respace_equals_base_betas():
    base = S.make_schedule("cosine", 50)
    r = S.respace(base, 50)
    np.testing.assert_allclose(np.exp(r.log_betas[1:]), base.betas[1:], rtol=1e-9)


def test_posterior_coefficients_numpy_and_jax_agree():
    a = np.array([0.5, 0.1, 0.01])
    ap = np.array([0.9, 0.5, 0.1])
    npc = S.posterior_coefficients(a, ap)
    jc = S.posterior_coefficients(jnp.asarray(a, jnp.float32), jnp.asarray(ap, jnp.float32))
    for x, y in zip(npc, jc):
        assert isinstance(y, jnp.ndarray) and y.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(y), x, rtol=1e-5)


def test_astype_is_the_single_dtype_boundary():
    r = S.respace(S.make_schedule("linear", 100), 10)
    assert all(f.dtype in (np.float64, np.int64) for f in r)
    r32 = r.astype(jnp.float32)
    assert all(isinstance(f, jnp.ndarray) and f.dtype == jnp.float32 for f in r32)
    np.testing.assert_allclose(np.asarray(r32.alphas_cumprod), r.alphas_cumprod, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(r32.timesteps), r.timesteps.astype(np.float32))


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: S.uniform_grid(0), "num_steps"),
        (lambda: S.cosine_grid(-3), "num_steps"),
        (lambda: S.linear_betas(10, 0.1, 0.01), "beta_start"),
        (lambda: S.cosine_betas(10, max_beta=1.5), "max_beta"),
        (lambda: S.make_schedule("quadratic"), "quadratic"),
        (lambda: S.space_timesteps(10, 11), "num_steps=11"),
        (lambda: S.space_timesteps(10, 0), "num_steps"),
        (lambda: S.DiffusionSchedule.from_betas(np.array([0.1, 0.0])), "betas"),
        (lambda: S.DiffusionSchedule.from_betas(np.zeros((0,))), "betas"),
    ],
)
def test_validation_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()
