"""TokTalk streaming engine: one compiled program after the first chunk, fixed-size state, exact
window bookkeeping (equals the offline core on a hand-built window), overlap frames kept, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt

import jaxtalk.models.toktalk.streaming as stream_mod
from jaxtalk.models.toktalk.sampling import default_grid, generate_frames

CFG = tt.TokTalkConfig.tiny()  # chunk 4 frames (2 tokens), context 8, overlap 2
B = 2


@pytest.fixture(scope="module")
def params():
    return tt.init_params(CFG, jax.random.key(0), adapter_src_dim=48)


def test_stream_compiles_once_and_keeps_fixed_state(params):
    rng = np.random.default_rng(0)
    style = rng.normal(size=(B, CFG.style_vector_dim)).astype(np.float32)
    state = tt.init_stream(CFG, jax.random.key(1), batch=B)
    shapes = jax.tree.map(jnp.shape, state)
    ct = tt.tokens_per_chunk(CFG)
    assert ct == 2
    outs = []
    for i in range(6):
        chunk = rng.normal(size=(B, ct, CFG.speech_dim)).astype(np.float32)
        state, out = tt.stream_step(params, CFG, state, chunk, style, cfg_scale=0.5 + 0.1 * i)
        outs.append(np.asarray(out))
        if i == 0:
            compiled = stream_mod._stream_step._cache_size()
        assert jax.tree.map(jnp.shape, state) == shapes
    assert stream_mod._stream_step._cache_size() == compiled
    assert int(state.position) == 6 * CFG.chunk_frames and int(state.step) == 6
    # The window's last context frames hold the emitted output (the next chunk's known overlap).
    emitted = np.concatenate(outs, axis=1)
    np.testing.assert_array_equal(np.asarray(state.motion)[:, -CFG.chunk_frames:], outs[-1])
    np.testing.assert_array_equal(
        np.asarray(state.motion)[:, : CFG.context_frames], emitted[:, -CFG.window_frames : -CFG.chunk_frames]
    )
    assert np.asarray(state.valid).all()


@pytest.mark.slow
def test_stream_step_equals_offline_core_on_the_same_window(params):
    rng = np.random.default_rng(1)
    style = jnp.asarray(rng.normal(size=(B, CFG.style_vector_dim)), jnp.float32)
    ct, c, ctx = tt.tokens_per_chunk(CFG), CFG.chunk_frames, CFG.context_frames
    n_chunks = 2
    tokens = rng.normal(size=(B, n_chunks * ct, CFG.speech_dim)).astype(np.float32)
    state = tt.init_stream(CFG, jax.random.key(2), batch=B)
    outs = []
    for i in range(n_chunks):
        state, out = tt.stream_step(params, CFG, state, tokens[:, i * ct : (i + 1) * ct], style)
        outs.append(np.asarray(out))
    emitted = np.concatenate(outs, axis=1)
    # Rebuild the last chunk's window by hand: 3 chunks of context (first one padding) + the chunk.
    w = CFG.window_frames
    start = (n_chunks - 1) * c - ctx  # absolute frame of the window's first row (negative = padding)
    frames = start + np.arange(w)
    valid = frames >= 0
    win_tokens = np.zeros((B, w // 2, CFG.speech_dim), np.float32)
    tok_idx = frames[::2] // 2
    win_tokens[:, valid[::2]] = tokens[:, tok_idx[valid[::2]]]
    known = np.zeros((B, w, 56), np.float32)
    known[:, valid & (frames < (n_chunks - 1) * c)] = emitted[:, frames[valid & (frames < (n_chunks - 1) * c)]]
    known_mask = valid & (np.arange(w) >= ctx - CFG.overlap_frames) & (np.arange(w) < ctx)
    noise = np.asarray(tt.stream_noise(CFG, jax.random.key(2), w, batch=B, first_frame=start))
    expect = generate_frames(
        params, CFG, jnp.asarray(win_tokens), style, jnp.asarray(noise), jnp.asarray(default_grid(CFG)),
        jnp.asarray(CFG.cfg_scale), known=jnp.asarray(known),
        known_mask=jnp.asarray(np.broadcast_to(known_mask, (B, w))),
        mask=jnp.asarray(np.broadcast_to(valid, (B, w))), chunked=jnp.ones((), bool),
    )
    np.testing.assert_allclose(outs[-1], np.asarray(expect)[:, ctx:], atol=1e-5)


def test_stream_whole_sequence_and_errors(params):
    rng = np.random.default_rng(2)
    tokens = rng.normal(size=(1, 7, CFG.speech_dim)).astype(np.float32)  # 3.5 chunks
    out = tt.stream(params, CFG, tokens, np.zeros((1, CFG.style_vector_dim), np.float32), jax.random.key(0))
    assert out.shape == (1, 14, 56) and bool(jnp.all(jnp.isfinite(out)))
    state = tt.init_stream(CFG, jax.random.key(0), batch=1)
    with pytest.raises(ValueError, match="one chunk of 4 frames"):
        tt.stream_step(params, CFG, state, tokens[:, :3], np.zeros((1, CFG.style_vector_dim), np.float32))
    with pytest.raises(ValueError, match="not a whole number of tokens"):
        tt.init_stream(tt.TokTalkConfig.tiny(token_rate=10.0), jax.random.key(0))


# ------------------------------------------------------------------------------ causality
def _change_after(x, start, rng):
    changed = np.array(x, copy=True)
    changed[:, start:] += rng.normal(size=changed[:, start:].shape).astype(changed.dtype)
    return changed


def _assert_causal(run, inputs, cut_input, cut_frame, rng):
    """Changing every input from ``cut_input`` on leaves the frames before ``cut_frame`` bitwise
    unchanged and changes the frames after it (so the check is not vacuous)."""
    before = np.asarray(run(inputs))
    after = np.asarray(run(_change_after(inputs, cut_input, rng)))
    np.testing.assert_array_equal(before[:, :cut_frame], after[:, :cut_frame])
    assert np.abs(before[:, cut_frame:] - after[:, cut_frame:]).max(axis=-1).min() > 1e-6


@pytest.mark.slow
def test_stream_with_base_tokens_is_causal(params):
    rng = np.random.default_rng(3)
    tokens = rng.normal(size=(B, 8, CFG.speech_dim)).astype(np.float32)  # 4 chunks of 2 tokens
    style = np.zeros((B, CFG.style_vector_dim), np.float32)
    run = lambda tok: tt.stream(params, CFG, tok, style, jax.random.key(0))  # noqa: E731
    for chunk in (1, 2):
        _assert_causal(run, tokens, chunk * 2, chunk * CFG.chunk_frames, rng)


@pytest.mark.slow
def test_stream_with_source_tokens_is_causal_and_equals_offline_adaptation(params):
    rng = np.random.default_rng(4)
    src = rng.normal(size=(B, 16, 48)).astype(np.float32)  # 25 Hz: 4 chunks of 4 source tokens
    assert tt.source_tokens_per_chunk(CFG, 25.0) == 4
    style = rng.normal(size=(B, CFG.style_vector_dim)).astype(np.float32)
    run = lambda s: tt.stream(params, CFG, s, style, jax.random.key(0), src_rate=25.0)  # noqa: E731
    for chunk in (1, 3):
        _assert_causal(run, src, chunk * 4, chunk * CFG.chunk_frames, rng)
    # The streaming adapter (carried buffer, continuing positions) computes the offline adapter.
    streamed = run(src)
    offline = tt.stream(params, CFG, tt.adapt_tokens(params, CFG, src, 25.0), style, jax.random.key(0))
    np.testing.assert_allclose(np.asarray(streamed), np.asarray(offline), atol=1e-5)
    # A long stream keeps its adapter state fixed and reproduces the offline adapter past the buffer.
    long_src = rng.normal(size=(1, 4 * 12, 48)).astype(np.float32)
    state = tt.init_stream(CFG, jax.random.key(1), batch=1, source_dim=48)
    adapted = []
    for i in range(12):
        state, _ = tt.stream_step(params, CFG, state, long_src[:, 4 * i : 4 * i + 4], style[:1], src_rate=25.0)
        adapted.append(np.asarray(state.tokens[:, -2:]))
    np.testing.assert_allclose(np.concatenate(adapted, axis=1),
                               np.asarray(tt.adapt_tokens(params, CFG, long_src, 25.0)), atol=1e-5)
    assert int(state.adapter.position) == 24


def test_a_sixty_second_source_token_stream_adapts_exactly_as_offline_adaptation(params):
    # 60 s at 25 Hz: the stream's adapter positions run to 750 base tokens, counted from the start as
    # offline adaptation counts them.
    rng = np.random.default_rng(8)
    src = rng.normal(size=(1, 1500, 48)).astype(np.float32)
    style = np.zeros((1, CFG.style_vector_dim), np.float32)
    state = tt.init_stream(CFG, jax.random.key(1), batch=1, source_dim=48)
    adapted = []
    for i in range(1500 // 4):
        state, _ = tt.stream_step(params, CFG, state, src[:, 4 * i : 4 * i + 4], style, src_rate=25.0)
        adapted.append(np.asarray(state.tokens[:, -2:]))
    assert int(state.adapter.position) == 750
    np.testing.assert_allclose(np.concatenate(adapted, axis=1),
                               np.asarray(tt.adapt_tokens(params, CFG, src, 25.0)), atol=1e-5)


def test_offline_sample_with_chunk_mask_is_causal(params):
    rng = np.random.default_rng(5)
    tokens = rng.normal(size=(B, 8, CFG.speech_dim)).astype(np.float32)
    style = np.zeros((B, CFG.style_vector_dim), np.float32)
    run = lambda tok: tt.sample(params, CFG, tok, style, jax.random.key(0), chunked=True)  # noqa: E731
    for chunk in (1, 3):
        _assert_causal(run, tokens, chunk * 2, chunk * CFG.chunk_frames, rng)


@pytest.mark.slow
def test_stream_equals_offline_chunked_sample_when_the_window_holds_the_whole_past():
    # No overlap inpainting and a left context as long as the utterance: every chunk's window is the
    # whole past with the same noise, which is exactly the offline chunk-masked computation.
    cfg = tt.TokTalkConfig.tiny(overlap_frames=0, context_frames=12)
    p = tt.init_params(cfg, jax.random.key(3))
    rng = np.random.default_rng(6)
    tokens = rng.normal(size=(B, 8, cfg.speech_dim)).astype(np.float32)  # 16 frames
    style = rng.normal(size=(B, cfg.style_vector_dim)).astype(np.float32)
    streamed = tt.stream(p, cfg, tokens, style, jax.random.key(4))
    noise = tt.stream_noise(cfg, jax.random.key(4), 16, batch=B)
    offline = tt.sample(p, cfg, tokens, style, noise=noise, chunked=True)
    np.testing.assert_allclose(np.asarray(streamed), np.asarray(offline), atol=2e-5)


def test_offline_model_refuses_to_stream():
    cfg = tt.TokTalkConfig.tiny(causal=False)
    with pytest.raises(ValueError, match="offline model"):
        tt.init_stream(cfg, jax.random.key(0))


def test_source_token_stream_bad_input_errors(params):
    style = np.zeros((1, CFG.style_vector_dim), np.float32)
    src_chunk = np.zeros((1, 4, 48), np.float32)
    base = tt.init_stream(CFG, jax.random.key(0), batch=1)
    with pytest.raises(ValueError, match="src_rate given but the stream takes base tokens"):
        tt.stream_step(params, CFG, base, src_chunk, style, src_rate=25.0)
    source = tt.init_stream(CFG, jax.random.key(0), batch=1, source_dim=48)
    with pytest.raises(ValueError, match="pass their rate, src_rate"):
        tt.stream_step(params, CFG, source, src_chunk, style)
    with pytest.raises(ValueError, match=r"must have shape \(1, 4, 48\)"):
        tt.stream_step(params, CFG, source, src_chunk[:, :3], style, src_rate=25.0)
    with pytest.raises(ValueError, match="made for 40-d source tokens"):
        tt.stream_step(params, CFG, tt.init_stream(CFG, jax.random.key(0), source_dim=40),
                       src_chunk[..., :40], style, src_rate=25.0)
    with pytest.raises(ValueError, match="no 'adapter'"):
        tt.stream({k: params[k] for k in ("decoder", "style", "norm")}, CFG, src_chunk, style, jax.random.key(0),
                  src_rate=25.0)
    with pytest.raises(ValueError, match="not a whole number of tokens"):
        tt.source_tokens_per_chunk(CFG, 10.0)  # 4 frames at 10 Hz = 1.6 source tokens


def test_stream_and_stream_step_leave_every_caller_argument_usable(params):
    rng = np.random.default_rng(3)
    tokens = jnp.asarray(rng.normal(size=(B, 5, CFG.speech_dim)).astype(np.float32))
    style = jnp.asarray(rng.normal(size=(B, CFG.style_vector_dim)).astype(np.float32))
    key = jax.random.key(4)
    tt.stream(params, CFG, tokens, style, key)
    state = tt.init_stream(CFG, key, batch=B)
    tt.stream_step(params, CFG, state, tokens[:, :2], style)
    for leaf in jax.tree.leaves((params, tokens, style, state)):
        assert not leaf.is_deleted()
    assert not key.is_deleted()
    jax.random.fold_in(key, 1)
