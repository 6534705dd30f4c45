"""TokTalk offline sampling: equals a naive Python-loop Euler/CFG/inpainting reference, traced knobs do
not recompile, gradients through the whole scan sampler match finite differences, bad input errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt

import jaxtalk.models.toktalk.sampling as sample_mod
from jaxtalk.samplers import cosine_grid, uniform_grid

CFG = tt.TokTalkConfig.tiny()
B, TT = 2, 8  # 8 tokens at 12.5 Hz = 16 frames


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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


# ------------------------------------------------------------------ sample_long


def test_sample_long_is_bitwise_sample_when_the_input_fits_one_window(params):
    tokens, style, *_ = _inputs()
    key = jax.random.key(3)
    whole = np.asarray(tt.sample(params, CFG, tokens, style, key))
    np.testing.assert_array_equal(tt.sample_long(params, CFG, tokens, style, key, window_frames=2 * TT), whole)


@pytest.mark.slow
def test_sample_long_windows_equal_whole_sequence_sample_of_their_tokens_with_earlier_frames_known(params):
    # 25 tokens = 50 frames in 20-frame windows with 6 frames of context: windows start at frames 0, 14,
    # 28 and 30 (the last moved back to end at frame 50, so it re-reads 18 known frames). Window k is
    # exactly the whole-sequence sample of its own tokens with the frames generated before it as known
    # frames and fold_in(key, k) noise.
    rng = np.random.default_rng(7)
    tokens = rng.normal(size=(1, 25, CFG.speech_dim)).astype(np.float32)
    style = rng.normal(size=(1, CFG.style_vector_dim)).astype(np.float32)
    key = jax.random.key(5)
    out = tt.sample_long(params, CFG, tokens, style, key, window_frames=20, context_frames=6)
    assert out.shape == (1, 50, CFG.param_dim)
    ref = np.zeros_like(out)
    ref[:, :20] = np.asarray(tt.sample(params, CFG, tokens[:, :10], style, key))
    for k, (start, done) in enumerate([(14, 20), (28, 34), (30, 48)], start=1):
        known_mask = np.zeros((1, 20), bool)
        known_mask[:, : done - start] = True
        win = tt.sample(params, CFG, tokens[:, start // 2:start // 2 + 10], style, jax.random.fold_in(key, k),
                        known=ref[:, start:start + 20], known_mask=known_mask)
        ref[:, done:start + 20] = np.asarray(win)[:, done - start:]
    np.testing.assert_allclose(out, ref, atol=1e-5)
    assert np.all(np.abs(out).sum(-1) > 0)  # every frame generated


@pytest.mark.slow
@pytest.mark.optimized  # ten minutes of sampling: run time dominates
def test_sample_long_peak_memory_does_not_grow_from_150_s_to_10_minutes():
    # Whole-sequence sample at this preset peaked at 1.6 GB for 150 s and 4.5 GB for 300 s (O(T^2)
    # attention; experiments/bench_long_sample.py); windowed, 10 minutes must fit in what 150 s took.
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent('''
        import resource, jax, numpy as np
        from jaxtalk.models import toktalk as tt
        cfg = tt.TokTalkConfig.tiny()
        params = tt.init_params(cfg, jax.random.key(0))
        style = np.zeros((1, cfg.style_vector_dim), np.float32)
        peaks = []
        for minutes in (2.5, 10):
            tokens = np.ones((1, int(minutes * 60 * cfg.token_rate), cfg.speech_dim), np.float32)
            out = tt.sample_long(params, cfg, tokens, style, jax.random.key(1))
            assert out.shape[1] == minutes * 60 * cfg.fps and np.isfinite(out).all()
            peaks.append(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)
        print(peaks[0], peaks[1])
    ''')
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    short_mb, long_mb = map(float, proc.stdout.split())
    assert long_mb - short_mb < 100, (short_mb, long_mb)
