"""TokTalk offline sampling: equals a naive Python-loop Euler/CFG/inpainting reference, traced knobs do
not recompile, gradients through the whole scan sampler match finite differences, bad input errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
import importlib

sample_mod = importlib.import_module("jaxtalk.models.toktalk.sample")  # the package re-exports sample()
from jaxtalk.samplers import cosine_grid, uniform_grid

CFG = tt.TokTalkConfig.tiny()
B, TT = 2, 8  # 8 tokens at 12.5 Hz = 16 frames
pytestmark = pytest.mark.usefixtures("fast_compile")


@pytest.fixture(scope="module")
def params():
    return tt.init_params(CFG, jax.random.key(0), adapter_src_dim=48)


def _inputs(seed=0):
    rng = np.random.default_rng(seed)
    tokens = rng.normal(size=(B, TT, CFG.speech_dim)).astype(np.float32)
    style = rng.normal(size=(B, CFG.style_vector_dim)).astype(np.float32)
    noise = rng.normal(size=(B, 2 * TT, CFG.param_dim)).astype(np.float32)
    known = rng.normal(size=(B, 2 * TT, CFG.param_dim)).astype(np.float32)
    known_mask = np.zeros((B, 2 * TT), bool)
    known_mask[:, 2:5] = True
    mask = np.ones((B, 2 * TT), bool)
    mask[1, 12:] = False
    return tokens, style, noise, known, known_mask, mask


def _reference(params, tokens, style, noise, known, known_mask, mask, ts, w):
    """Euler with CFG and inpainting written out step by step (no scan, no sampler module).

    The flow runs centred on the style's anchor pose (its last param_dim entries; the fresh params'
    standardiser is the identity): known frames go in minus the anchor, the result comes out plus it.
    """
    t_frames = noise.shape[1]
    anchor = style[:, None, CFG.style_dim :]
    known = known - anchor
    cond = tt.Condition(
        tokens=tt.interpolate_tokens(jnp.asarray(tokens), CFG.token_rate, CFG.fps, t_frames),
        style=jnp.asarray(style),
        known=jnp.asarray(known),
        known_mask=jnp.asarray(known_mask & mask),
        keep=jnp.ones((B,)),
        mask=jnp.asarray(mask),
        chunked=jnp.zeros((B,), bool),
    )
    km = (known_mask & mask)[..., None]
    s = CFG.sigma_min
    x = np.where(km, (1 - (1 - s) * ts[0]) * noise + ts[0] * known, noise)
    for k in range(len(ts) - 1):
        t = jnp.full((B,), ts[k], jnp.float32)
        vc = tt.velocity(params, CFG, jnp.asarray(x), t, cond)
        vu = tt.velocity(params, CFG, jnp.asarray(x), t, cond.unconditional())
        v = np.asarray((1 + w) * vc - w * vu)
        x = x + (ts[k + 1] - ts[k]) * v
        x = np.where(km, (1 - (1 - s) * ts[k + 1]) * noise + ts[k + 1] * known, x)
    x = np.where(km, known, x) + anchor
    return x * mask[..., None]


def test_sample_equals_python_loop_reference(params):
    tokens, style, noise, known, known_mask, mask = _inputs()
    ts = cosine_grid(CFG.sample_steps)
    out = tt.sample(params, CFG, tokens, style, noise=noise, known=known, known_mask=known_mask, mask=mask,
                    cfg_scale=0.7)
    ref = _reference(params, tokens, style, noise, known, known_mask, mask, ts, 0.7)
    np.testing.assert_allclose(np.asarray(out), ref, atol=2e-4, rtol=1e-4)
    # Known frames come back exactly; padded frames are zero.
    np.testing.assert_array_equal(np.asarray(out)[known_mask & mask], known[known_mask & mask])
    np.testing.assert_array_equal(np.asarray(out)[1, 12:], 0.0)


def test_traced_knobs_do_not_recompile(params):
    tokens, style, noise, *_ = _inputs(1)
    tt.sample(params, CFG, tokens, style, noise=noise, cfg_scale=0.0)
    before = sample_mod._sample._cache_size()
    out_a = tt.sample(params, CFG, tokens, style, noise=noise, cfg_scale=1.5)
    out_b = tt.sample(params, CFG, tokens, style * 2, noise=noise, ts=uniform_grid(CFG.sample_steps), cfg_scale=0.3)
    assert sample_mod._sample._cache_size() == before
    assert float(jnp.max(jnp.abs(out_a - out_b))) > 1e-4
    # A style clip is encoded to a vector first: same sampler program.
    clip = np.random.default_rng(2).normal(size=(B, 12, 56)).astype(np.float32)
    assert tt.sample(params, CFG, tokens, clip, jax.random.key(3)).shape == (B, 16, 56)
    assert sample_mod._sample._cache_size() == before


def test_grad_through_sampler_matches_finite_differences(params, float64):
    p64 = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), params)
    tokens, style, noise, *_ = _inputs(3)
    tokens, style, noise = (jnp.asarray(a, jnp.float64) for a in (tokens, style, noise))
    weights = jnp.asarray(np.random.default_rng(4).normal(size=noise.shape))

    def loss(style_vec, tok):
        x = tt.sample(p64, CFG, tok, style_vec, noise=noise, cfg_scale=0.7, remat=True)
        return jnp.sum(x * weights)

    g_style, g_tok = jax.grad(loss, argnums=(0, 1))(style, tokens)
    rng = np.random.default_rng(5)
    for which, (g, arg) in enumerate(((g_style, style), (g_tok, tokens))):
        d = jnp.asarray(rng.normal(size=arg.shape))
        # The shared attention forms its logits in float32 even under x64 (for bf16 safety), so
        # the loss carries ~1e-7 relative noise: a larger step keeps the difference quotient clean.
        eps = 1e-3
        args_p = [style, tokens]
        args_m = [style, tokens]
        args_p[which] = arg + eps * d
        args_m[which] = arg - eps * d
        fd = (loss(*args_p) - loss(*args_m)) / (2 * eps)
        np.testing.assert_allclose(float(jnp.sum(g * d)), float(fd), rtol=2e-3)
        assert abs(float(fd)) > 1e-6


def test_sample_bad_input_errors(params):
    tokens, style, noise, known, known_mask, _ = _inputs()
    with pytest.raises(ValueError, match="width 48, expected 64"):
        tt.sample(params, CFG, tokens[..., :48], style, jax.random.key(0))
    with pytest.raises(ValueError, match="token rate wrong"):
        tt.sample(params, CFG, tokens, style, jax.random.key(0), num_frames=8)
    bad = tokens.copy()
    bad[0, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        tt.sample(params, CFG, bad, style, jax.random.key(0))
    with pytest.raises(ValueError, match="given together"):
        tt.sample(params, CFG, tokens, style, jax.random.key(0), known=known)
    with pytest.raises(ValueError, match="style must be"):
        tt.sample(params, CFG, tokens, style[:, :5], jax.random.key(0))
    with pytest.raises(ValueError, match="shorter than the minimum"):
        tt.sample(params, CFG, tokens, np.zeros((B, 3, 56), np.float32), jax.random.key(0))
    with pytest.raises(ValueError, match="PRNG key"):
        tt.sample(params, CFG, tokens, style)
