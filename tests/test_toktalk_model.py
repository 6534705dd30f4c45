"""TokTalk model pieces: config checks, attention bias, decoder structure (block causality, padding
invariance, condition dropout), style encoder, adapter, token interpolation, bad-input errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.model import check_tokens

CFG = tt.TokTalkConfig.tiny()  # the causal (streaming) model, the default
OFFLINE = tt.TokTalkConfig.tiny(causal=False)
B, T = 2, 16


@pytest.fixture(scope="module")
def params():
    return tt.init_params(CFG, jax.random.key(0), adapter_src_dim=48)


def _cond(rng, t=T, chunked=False, keep=1.0, mask=None):
    return tt.Condition(
        tokens=jnp.asarray(rng.normal(size=(B, t, CFG.speech_dim)), jnp.float32),
        style=jnp.asarray(rng.normal(size=(B, CFG.style_vector_dim)), jnp.float32),
        known=jnp.asarray(rng.normal(size=(B, t, CFG.param_dim)), jnp.float32),
        known_mask=jnp.asarray(np.arange(t)[None, :] < 3).repeat(B, 0),
        keep=jnp.full((B,), keep, jnp.float32),
        mask=jnp.ones((B, t), bool) if mask is None else mask,
        chunked=jnp.full((B,), chunked),
    )


_decoder_apply = jax.jit(lambda cfg, p, x, t, c: tt.Decoder(cfg).apply({"params": p}, x, t, *c), static_argnums=0)


# ------------------------------------------------------------------------------------- config
def test_presets_and_config_errors():
    paper, small = tt.TokTalkConfig.paper(), tt.TokTalkConfig.small()
    assert (paper.width, paper.num_mid_blocks, paper.transformer_blocks, paper.num_heads, paper.head_dim) == (
        256, 12, 4, 8, 64)
    assert (paper.chunk_frames, paper.overlap_frames, paper.sample_steps, paper.cfg_scale) == (10, 5, 10, 0.7)
    assert small.width < paper.width and small.window_frames == 30
    # The paper preset is the paper's objective; the small one keeps jaxtalk's named departures.
    assert (paper.noise_frames, paper.style_anchor, paper.style_source, paper.latent_input, paper.temperature) == (
        0.0, False, "target", True, 1.0)
    # The small preset: the target's crop as the style, the anchor centring the flow, and the decoder
    # reading neither the anchor nor the latent (what keeps held-out speakers under the mean pose).
    assert (small.noise_frames, small.style_anchor, small.style_source, small.temperature) == (2.0, True, "target", 0.25)
    assert (small.anchor_input, small.latent_input) == (False, False)
    assert tt.TokTalkConfig.paper(noise_frames=2.0).noise_frames == 2.0
    with pytest.raises(ValueError, match="chunk_frames=7 must be even"):
        tt.TokTalkConfig.small(chunk_frames=7)
    with pytest.raises(ValueError, match="context_frames=15"):
        tt.TokTalkConfig.small(context_frames=15)
    with pytest.raises(ValueError, match="cfg_dropout"):
        tt.TokTalkConfig.small(cfg_dropout=1.5)
    with pytest.raises(ValueError, match="style_source"):
        tt.TokTalkConfig.small(style_source="another")


@pytest.mark.slow
def test_paper_decoder_has_about_82m_parameters():
    # eval_shape: counts parameters without allocating or compiling anything.
    shapes = jax.eval_shape(lambda k: tt.init_params(tt.TokTalkConfig.paper(), k), jax.random.key(0))
    n = sum(int(np.prod(x.shape)) for x in jax.tree.leaves(shapes["decoder"]))
    assert 80e6 < n < 84e6


# ---------------------------------------------------------------------------------- attention
def test_attention_bias_matches_hand_built_masks():
    valid = jnp.asarray([[True] * 6, [True] * 4 + [False] * 2])
    bias = np.asarray(tt.attention_bias(valid, jnp.asarray([True, False]), 2))
    allowed = bias == 0
    # Example 0, chunk mask with chunks {0,1},{2,3},{4,5}: query i sees keys j < (i//2+1)*2.
    expect0 = np.array([[j < (i // 2 + 1) * 2 for j in range(6)] for i in range(6)])
    np.testing.assert_array_equal(allowed[0, 0], expect0)
    # Example 1, full mask with 2 padded frames: real queries see the 4 real keys; padded see themselves.
    expect1 = np.zeros((6, 6), bool)
    expect1[:4, :4] = True
    expect1[4, 4] = expect1[5, 5] = True
    np.testing.assert_array_equal(allowed[0 + 1, 0], expect1)
    assert bias.min() < -1e30


# ------------------------------------------------------------------------------------ decoder
def _perturb_from(x, cond, start):
    later = (jnp.arange(x.shape[1]) >= start)[None, :, None]
    return jnp.where(later, x + 1.0, x), cond._replace(tokens=jnp.where(later, cond.tokens * -2.0, cond.tokens))


def _decoder_inputs(cfg):
    """Fresh decoder parameters, noisy motion, flow times and a chunk-masked condition."""
    p = tt.init_params(cfg, jax.random.key(1))["decoder"]
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=(B, T, 56)), jnp.float32)
    return p, x, jnp.asarray([0.3, 0.8], jnp.float32), _cond(rng, chunked=True)


@pytest.mark.slow
def test_causal_decoder_under_chunk_mask_ignores_later_chunks_bitwise():
    p, x, t, c_chunk = _decoder_inputs(CFG)
    y1 = np.asarray(_decoder_apply(CFG, p, x, t, c_chunk))
    # Perturb every input from frame 8 on (chunks of 4: chunks 2 and 3): chunks 0 and 1 stay bitwise.
    for start in (8, 12):
        x2, c2 = _perturb_from(x, c_chunk, start)
        y2 = np.asarray(_decoder_apply(CFG, p, x2, t, c2))
        np.testing.assert_array_equal(y1[:, :start], y2[:, :start])
        assert np.abs(y1[:, start:] - y2[:, start:]).min(axis=-1).max() > 1e-4  # the change is seen
    # With full attention the future leaks into the past.
    x2, c2 = _perturb_from(x, c_chunk, 8)
    f1 = _decoder_apply(CFG, p, x, t, c_chunk._replace(chunked=jnp.zeros((B,), bool)))
    f2 = _decoder_apply(CFG, p, x2, t, c2._replace(chunked=jnp.zeros((B,), bool)))
    assert float(jnp.max(jnp.abs(f1[:, :8] - f2[:, :8]))) > 1e-4


@pytest.mark.slow
def test_offline_decoder_sees_the_next_chunk_through_its_convolutions():
    p, x, t, c_chunk = _decoder_inputs(OFFLINE)
    x2, c2 = _perturb_from(x, c_chunk, 8)
    y1 = _decoder_apply(OFFLINE, p, x, t, c_chunk)
    y2 = _decoder_apply(OFFLINE, p, x2, t, c2)
    assert float(jnp.max(jnp.abs(y1[:, :8] - y2[:, :8]))) > 1e-4


def test_decoder_padding_invariance_and_masked_output(params):
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(B, T, 56)), jnp.float32)
    t = jnp.asarray([0.1, 0.6], jnp.float32)
    cond = _cond(rng)
    y = _decoder_apply(CFG, params["decoder"], x, t, cond)
    # The same sequences padded to 24 frames with garbage after frame 16.
    pad = 8
    garbage = lambda a: jnp.concatenate([a, 100.0 * jnp.ones(a.shape[:1] + (pad,) + a.shape[2:], a.dtype)], 1)  # noqa: E731
    mask = jnp.concatenate([jnp.ones((B, T), bool), jnp.zeros((B, pad), bool)], 1)
    cond_p = cond._replace(tokens=garbage(cond.tokens), known=garbage(cond.known),
                           known_mask=jnp.concatenate([cond.known_mask, jnp.ones((B, pad), bool)], 1), mask=mask)
    yp = _decoder_apply(CFG, params["decoder"], garbage(x), t, cond_p)
    np.testing.assert_allclose(yp[:, :T], y, atol=2e-4, rtol=1e-4)
    np.testing.assert_array_equal(np.asarray(yp[:, T:]), 0.0)


def test_condition_dropout_removes_tokens_style_and_known(params):
    rng = np.random.default_rng(2)
    x = jnp.asarray(rng.normal(size=(B, T, 56)), jnp.float32)
    t = jnp.asarray([0.4, 0.4], jnp.float32)
    c1, c2 = _cond(rng, keep=0.0), _cond(rng, keep=0.0)
    y1 = _decoder_apply(CFG, params["decoder"], x, t, c1)
    y2 = _decoder_apply(CFG, params["decoder"], x, t, c2._replace(known_mask=c1.known_mask))
    np.testing.assert_allclose(y1, y2, atol=1e-6)
    y3 = _decoder_apply(CFG, params["decoder"], x, t, c1._replace(keep=jnp.ones((B,))))
    assert float(jnp.max(jnp.abs(y3 - y1))) > 1e-3


@pytest.mark.slow
# ------------------------------------------------------------------------------- style/adapter
def test_style_encoder_ignores_padding_and_uses_frame_positions(params):
    rng = np.random.default_rng(3)
    clip = jnp.asarray(rng.normal(size=(B, 20, 56)), jnp.float32)
    v = tt.encode_style(params, CFG, clip)
    assert v.shape == (B, CFG.style_vector_dim)
    padded = jnp.concatenate([clip, 50.0 * jnp.ones((B, 6, 56))], 1)
    mask = jnp.asarray(np.arange(26)[None, :] < 20).repeat(B, 0)
    np.testing.assert_allclose(tt.encode_style(params, CFG, padded, mask), v, atol=1e-4)
    # A real per-frame positional encoding: for a constant clip, the transformer's per-frame outputs
    # away from the conv edges differ from frame to frame (the reference's one constant vector would
    # make them identical).
    _, inter = tt.StyleEncoder(CFG).apply({"params": params["style"]}, jnp.ones((1, 20, 56)),
                                          capture_intermediates=True)
    frames = inter["intermediates"]["transformer"]["__call__"][0][0]
    middle = frames[4:16]
    assert float(jnp.max(jnp.abs(middle - middle[:1]))) > 1e-3


def test_adapter_maps_rate_and_width(params):
    rng = np.random.default_rng(4)
    src = jnp.asarray(rng.normal(size=(B, 16, 48)), jnp.float32)  # 25 Hz -> 8 tokens at 12.5 Hz
    out = tt.adapt_tokens(params, CFG, src, 25.0)
    assert out.shape == (B, 8, CFG.speech_dim)
    with pytest.raises(ValueError, match="width 40, expected 48"):
        tt.adapt_tokens(params, CFG, src[..., :40], 25.0)
    with pytest.raises(ValueError, match="no 'adapter'"):
        tt.adapt_tokens({k: params[k] for k in ("decoder", "style")}, CFG, src, 25.0)


def test_interpolate_tokens_matches_numpy_reference_in_both_alignments():
    rng = np.random.default_rng(5)
    tok = rng.normal(size=(2, 5, 3)).astype(np.float32)
    linear = np.asarray(tt.interpolate_tokens(jnp.asarray(tok), 12.5, 25, 10, "linear"))
    previous = np.asarray(tt.interpolate_tokens(jnp.asarray(tok), 12.5, 25, 10, "previous"))
    for j in range(10):
        p = j / 2
        lo, hi = int(np.floor(p)), min(int(np.floor(p)) + 1, 4)
        w = 0.0 if lo >= 4 else p - lo
        np.testing.assert_allclose(linear[:, j], (1 - w) * tok[:, lo] + w * tok[:, hi], atol=1e-6)
        np.testing.assert_array_equal(previous[:, j], tok[:, j // 2])  # frame j: token j // 2, never j // 2 + 1
    assert CFG.token_alignment == "previous" and OFFLINE.token_alignment == "linear"


def test_source_resampling_averages_every_source_token():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(2, 9, 4)).astype(np.float32)  # 25 Hz -> 12.5 Hz: round(4.5) = 5 tokens
    out = np.asarray(tt.source_to_base_rate(jnp.asarray(src), 25.0, CFG))
    assert out.shape == (2, 5, 4)
    for j in range(4):
        np.testing.assert_allclose(out[:, j], 0.5 * (src[:, 2 * j] + src[:, 2 * j + 1]), atol=1e-6)
    np.testing.assert_allclose(out[:, 4], src[:, 8], atol=1e-6)  # the last span holds one source token
    # 6.25 Hz -> 12.5 Hz repeats each source token.
    up = np.asarray(tt.source_to_base_rate(jnp.asarray(src[:, :3]), 6.25, CFG))
    np.testing.assert_allclose(up, np.repeat(src[:, :3], 2, axis=1), atol=1e-6)


def test_causal_adapter_output_ignores_later_source_tokens_bitwise(params):
    rng = np.random.default_rng(7)
    src = rng.normal(size=(B, 24, 48)).astype(np.float32)  # 25 Hz -> 12 base tokens
    out = np.asarray(tt.adapt_tokens(params, CFG, src, 25.0))
    for cut in (6, 13):  # source token index: base tokens < cut // 2 only read source tokens < cut
        changed = src.copy()
        changed[:, cut:] += rng.normal(size=changed[:, cut:].shape)
        out2 = np.asarray(tt.adapt_tokens(params, CFG, changed, 25.0))
        np.testing.assert_array_equal(out[:, : cut // 2], out2[:, : cut // 2])
        assert np.abs(out[:, cut // 2 :] - out2[:, cut // 2 :]).min(axis=-1).max() > 1e-4


def test_causal_adapter_attends_to_a_bounded_past(params):
    cfg = CFG
    k = tt.adapter.receptive_field(cfg)
    assert k == cfg.adapter_layers * (cfg.adapter_context - 1) + cfg.adapter_kernel - 1
    rng = np.random.default_rng(8)
    base = jnp.asarray(rng.normal(size=(1, k + 6, 48)), jnp.float32)
    out = np.asarray(tt.adapter_apply(params, cfg, base))
    changed = base.at[:, 0].add(1.0)  # the first token is just out of reach of the last 5 outputs
    out2 = np.asarray(tt.adapter_apply(params, cfg, changed))
    np.testing.assert_array_equal(out[:, k + 1 :], out2[:, k + 1 :])
    assert np.abs(out[:, k] - out2[:, k]).max() > 1e-5  # ... and within reach of output k


# ------------------------------------------------------------------------------------- errors
def test_bad_tokens_and_style_raise_clear_errors(params):
    good = np.zeros((1, 8, 64), np.float32)
    assert check_tokens(good, width=64, rate=12.5, fps=25) == 16
    with pytest.raises(ValueError, match="width 48, expected 64"):
        check_tokens(np.zeros((1, 8, 48)), width=64, rate=12.5, fps=25)
    with pytest.raises(ValueError, match="NaN"):
        check_tokens(np.full((1, 8, 64), np.nan), width=64, rate=12.5, fps=25)
    with pytest.raises(ValueError, match="token rate wrong"):
        # 16 tokens offered for 16 frames: a 25 Hz stream given to a 12.5 Hz model.
        check_tokens(np.zeros((1, 16, 64)), width=64, rate=12.5, fps=25, num_frames=16)
    with pytest.raises(ValueError, match="shorter than the minimum"):
        tt.encode_style(params, CFG, np.zeros((1, CFG.style_min_frames - 1, 56), np.float32))
    with pytest.raises(ValueError, match=r"shape \(batch, frames, 56\)"):
        tt.encode_style(params, CFG, np.zeros((1, 20, 50), np.float32))
