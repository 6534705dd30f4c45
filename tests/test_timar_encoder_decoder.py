"""TIMAR's MAE-style encoder-decoder variant (Table 2): the encoder sees only the visible tokens, turn
causality, streaming == whole-window sampling, training, config validation."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import timar_streams

from jaxtalk.models.timar import TimarConfig, encode_window, init_params, loss, sample
from jaxtalk.models.timar.encoder import TimarEncoder
from jaxtalk.models.turns.streams import to_turns
from jaxtalk.models.timar.sampling import conditions
from jaxtalk.models.timar.streaming import stream_condition, stream, init_stream
from jaxtalk.models.timar.tokens import agent_token_mask, turn_layout
from jaxtalk.masks import mask_to_bias


B, N, F = 2, 3, 5
CFG = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, head_blocks=1, speech_dim=8, max_turns=N,
                        frames_per_turn=F, architecture="encoder_decoder", decoder_layers=1)


@pytest.fixture(scope="module")
def params():
    p = init_params(CFG, jax.random.key(0))
    # Zero-initialised adaLN layers make a fresh head output exactly 0; perturb so tests see signal
    # (NumPy noise: a jitted perturbation of ~100 leaves costs more compile time than the tests).
    rng = np.random.default_rng(5)
    return jax.tree.map(lambda x: jnp.asarray(x + 0.05 * rng.normal(size=x.shape), jnp.float32), p)


def _streams(seed=0, n=N):
    return timar_streams(B, n * F, seed)


def _turns(s):
    return [to_turns(jnp.asarray(s[k]), F) for k in ("user_speech", "user_motion", "agent_speech", "agent_motion")]


def _fixed_mask():
    # One pattern for every example (so the visible tokens gather with one index), at least one
    # visible and one masked agent frame in every turn.
    m = np.ones((N, F), bool)
    m[0, [1, 3]] = False
    m[1, 0] = False
    m[2, [2, 4]] = False
    return np.broadcast_to(m, (B, N, F)).copy()


_encode = jax.jit(encode_window, static_argnums=1)


def _module(config, params, method, *args):
    return TimarEncoder(config).apply({"params": params["encoder"]}, *args, method=method)


_apply = jax.jit(_module, static_argnums=(0, 2))


def _embedded(config, params, turns, mask):
    return _apply(config, params, TimarEncoder.embed, *turns, jnp.asarray(mask), None)


def _causal_mask():
    return jnp.asarray(turn_layout(F).attention_mask(N, causal=True))


def _encoder_on_visible_tokens_alone(module, tokens, keep, visibility):
    # MAE's encoder written out: embed + positions, DROP the masked tokens, then the same blocks
    # under the same per-token mask restricted to the kept tokens.
    b, n, tpt, w = tokens.shape
    x = module.in_norm(tokens.reshape(b, n * tpt, w)) + module.pos_embed[None, : n * tpt]
    x = x[:, keep]
    bias = mask_to_bias(visibility[np.ix_(keep, keep)])
    for block in module.blocks:
        x = block(x, bias=bias)
    return module.out_norm(x)


def test_encoder_outputs_at_visible_positions_equal_the_encoder_run_on_the_visible_tokens_alone(params):
    mask = _fixed_mask()
    tokens = _embedded(CFG, params, _turns(_streams()), mask)
    visibility = _causal_mask()
    got = _apply(CFG, params, TimarEncoder.encode_visible, tokens, jnp.asarray(mask), visibility)
    keep = np.flatnonzero(~np.asarray(agent_token_mask(mask[0])).reshape(-1))
    assert keep.size == N * CFG.tokens_per_turn - int(mask[0].sum())
    reference = jax.jit(lambda p, tok: TimarEncoder(CFG).apply(
        {"params": p}, tok, keep, np.asarray(visibility), method=_encoder_on_visible_tokens_alone))
    ref = reference(params["encoder"], tokens)
    got_visible = np.asarray(got).reshape(B, N * CFG.tokens_per_turn, CFG.width)[:, keep]
    np.testing.assert_allclose(got_visible, np.asarray(ref), rtol=1e-5, atol=1e-5)
    assert np.abs(np.asarray(ref)).max() > 0.1


def test_masked_agent_tokens_change_nothing_anywhere_in_the_encoder_decoder_but_do_in_the_encoder_only_model(params):
    mask = _fixed_mask()
    turns = _turns(_streams())
    tokens = _embedded(CFG, params, turns, mask)
    # Overwrite every masked agent-motion token with noise: the encoder never reads it (no key in
    # any layer) and the decoder replaces it by the mask token.
    hidden = np.asarray(agent_token_mask(mask))[..., None]
    noise = jnp.asarray(np.random.default_rng(7).normal(size=tokens.shape) * 10.0, jnp.float32)
    garbled = jnp.where(hidden, noise, tokens)
    visibility = _causal_mask()
    m = jnp.asarray(mask)
    for method in (TimarEncoder.encode_visible, TimarEncoder.fuse):
        a = np.asarray(_apply(CFG, params, method, tokens, m, visibility))
        b = np.asarray(_apply(CFG, params, method, garbled, m, visibility))
        if method is TimarEncoder.encode_visible:  # its outputs AT masked positions are discarded
            a, b = a[~hidden[..., 0]], b[~hidden[..., 0]]
        np.testing.assert_array_equal(a, b)
    # Through the public window pass: the masked frames' ground truth changes nothing either.
    am = np.asarray(turns[3]).copy()
    am[mask] += 3.0
    z0 = np.asarray(_encode(params, CFG, *turns[:3], turns[3], m))
    z1 = np.asarray(_encode(params, CFG, *turns[:3], jnp.asarray(am), m))
    np.testing.assert_array_equal(z0, z1)
    # The same noise does reach TIMAR's encoder-only model, where masked tokens are keys: the test
    # above would see a leak.
    enc_only = dataclasses.replace(CFG, architecture="encoder")
    a = np.asarray(_apply(enc_only, params, TimarEncoder.fuse, tokens, m, visibility))
    b = np.asarray(_apply(enc_only, params, TimarEncoder.fuse, garbled, m, visibility))
    assert np.abs(a - b).max() > 1e-3


@pytest.mark.slow
def test_encoder_decoder_changing_turn_t_plus_1_leaves_turns_up_to_t_bitwise_unchanged(params):
    s = _streams()
    mask = jnp.asarray(_fixed_mask())
    key = jax.random.key(1)
    z0 = np.asarray(_encode(params, CFG, *_turns(s), mask))
    x0 = np.asarray(sample(params, CFG, s["user_speech"], s["user_motion"], s["agent_speech"], key))
    s2 = {k: v.copy() for k, v in s.items()}
    for v in s2.values():
        v[:, 2 * F :] += 5.0  # every stream of turn 2 (0-based), visible agent frames included
    z1 = np.asarray(_encode(params, CFG, *_turns(s2), mask))
    x1 = np.asarray(sample(params, CFG, s2["user_speech"], s2["user_motion"], s2["agent_speech"], key))
    np.testing.assert_array_equal(z0[:, :2], z1[:, :2])
    np.testing.assert_array_equal(x0[:, : 2 * F], x1[:, : 2 * F])
    assert np.abs(z0[:, 2] - z1[:, 2]).max() > 1e-3 and np.abs(x0[:, 2 * F :] - x1[:, 2 * F :]).max() > 1e-3
    # Under bidirectional attention (encoder and decoder) the change reaches turn 0.
    bi = dataclasses.replace(CFG, attention="bidirectional")
    zb0 = np.asarray(_encode(params, bi, *_turns(s), mask))
    zb1 = np.asarray(_encode(params, bi, *_turns(s2), mask))
    assert np.abs(zb0[:, 0] - zb1[:, 0]).max() > 1e-4


_conditions = jax.jit(conditions, static_argnums=1, static_argnames="guidance")


@pytest.mark.slow
def test_encoder_decoder_stream_equals_whole_window_sample_and_sliding_window_recomputation(params):
    s = _streams()
    streams = (s["user_speech"], s["user_motion"], s["agent_speech"])
    # Window filling (context N - 1): the stream equals one whole-window sample. Temperature 0 makes
    # DDIM deterministic, so the per-turn keys of the stream do not matter.
    kw = dict(cfg_scale=0.5, sampler="ddim", temperature=0.0)
    whole = np.asarray(sample(params, CFG, *streams, jax.random.key(0), **kw))
    streamed = np.asarray(stream(params, CFG, *streams, jax.random.key(1), context=N - 1, **kw))
    np.testing.assert_allclose(streamed, whole, rtol=1e-5, atol=1e-5)
    assert np.abs(whole).max() > 1e-3
    # Sliding (context 1 over 5 turns): every turn's conditions == recomputing its window offline.
    long = _streams(seed=3, n=5)
    long = (long["user_speech"], long["user_motion"], long["agent_speech"])
    state = init_stream(CFG, jax.random.key(0), batch=B, context=1)
    for t in range(5):
        sl = slice(t * F, (t + 1) * F)
        state, z = stream_condition(params, CFG, state, *(x[:, sl] for x in long))
        lo = max(0, t - 1)
        win = [to_turns(jnp.asarray(x[:, lo * F : (t + 1) * F]), F) for x in long]
        zc, zu = _conditions(params, CFG, *win)
        ref = np.concatenate([np.asarray(zc[:, -1]), np.asarray(zu[:, -1])])
        np.testing.assert_allclose(np.asarray(z), ref, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_encoder_decoder_loss_is_finite_on_masked_frames_with_a_gradient_in_encoder_and_decoder(params):
    cfg = dataclasses.replace(CFG, mask_ratio_min=0.7)  # some agent frames visible, as in the paper
    batch = _streams(seed=4)
    loss_fn = jax.jit(jax.value_and_grad(lambda p, k: loss(p, cfg, batch, k), has_aux=True))
    (value, metrics), grads = loss_fn(params, jax.random.key(2))
    assert np.isfinite(float(value)) and float(value) > 0
    # The loss covers the masked frames only: exactly ceil(r L) per example.
    expected = B * math.ceil(round(float(metrics["mask_ratio"]) * N * F, 4))
    assert float(metrics["masked_frames"]) == expected
    g = grads["encoder"]
    norms = {name: float(sum(jnp.abs(x).sum() for x in jax.tree.leaves(g[name])))
             for name in ("block_0", "decoder_block_0", "decoder_embed", "decoder_pos_embed", "mask_token")}
    assert all(np.isfinite(v) and v > 0 for v in norms.values()), norms
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(grads))


def test_config_rejects_unknown_architecture_and_non_positive_decoder_layers():
    assert TimarConfig.small().architecture == "encoder" and TimarConfig.small().decoder_layers == 2
    assert TimarConfig.paper().decoder_layers == 8
    with pytest.raises(ValueError, match="architecture must be one of"):
        TimarConfig.small(architecture="mae")
    for bad in (0, -1):
        with pytest.raises(ValueError, match="decoder_layers must be a positive integer"):
            TimarConfig.small(decoder_layers=bad)
