"""Attention with an additive bias and the transformer blocks built on it.

Brute-force references, masking semantics, cached (chunk-by-chunk) decoding == one full pass, and the
pre-LN wiring of the blocks checked against a composition of their parts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import erf

from jaxtalk.masks import mask_to_bias
from jaxtalk.nn import (
    DecoderBlock,
    MultiHeadAttention,
    TransformerBlock,
    dot_product_attention,
)

from test_nn_support import random_params



def _reference_attention(q, k, v, bias):
    """Per-head NumPy loop in float64: softmax(q k^T / sqrt(d) + bias) v."""
    q, k, v, bias = (np.asarray(a, np.float64) for a in (q, k, v, bias))
    *batch, q_len, heads, d = q.shape
    out = np.zeros((*batch, q_len, heads, v.shape[-1]))
    for idx in np.ndindex(*batch):
        for h in range(heads):
            logits = q[idx][:, h] @ k[idx][:, h].T / np.sqrt(d) + np.broadcast_to(
                bias, (*batch, heads, q_len, k.shape[-3])
            )[idx][h]
            w = np.exp(logits - logits.max(-1, keepdims=True))
            w /= w.sum(-1, keepdims=True)
            out[idx][:, h] = w @ v[idx][:, h]
    return out


def _block_causal(length: int, chunk: int) -> np.ndarray:
    """Query i sees key j iff j < (i // chunk + 1) * chunk (CosyVoice's chunk mask)."""
    i = np.arange(length)[:, None]
    j = np.arange(length)[None, :]
    return j < (i // chunk + 1) * chunk


def test_dot_product_attention_matches_bruteforce_with_two_batch_axes(key):
    kq, kk, kv, kb = jax.random.split(key, 4)
    q = jax.random.normal(kq, (2, 3, 5, 2, 4))
    k = jax.random.normal(kk, (2, 3, 7, 2, 4))
    v = jax.random.normal(kv, (2, 3, 7, 2, 6))
    bias = jax.random.normal(kb, (3, 1, 5, 7))  # broadcast over the first batch axis and heads
    out = dot_product_attention(q, k, v, bias)
    assert out.shape == (2, 3, 5, 2, 6)
    np.testing.assert_allclose(out, _reference_attention(q, k, v, bias), atol=1e-5)


def test_blocked_keys_are_ignored_exactly_like_removing_them(key):
    kq, kk, kv = jax.random.split(key, 3)
    q = jax.random.normal(kq, (4, 2, 8))
    k = jax.random.normal(kk, (6, 2, 8))
    v = jax.random.normal(kv, (6, 2, 8))
    visible = np.array([True, False, True, True, False, True])
    bias = mask_to_bias(np.broadcast_to(visible, (4, 6)))
    masked = dot_product_attention(q, k, v, bias)
    removed = dot_product_attention(q, k[visible], v[visible])
    np.testing.assert_allclose(masked, removed, atol=1e-6)


def test_fully_blocked_row_is_finite(key):
    # The bias values themselves are pinned once, in tests/test_masks.py (the one helper's tests).
    mask = np.array([[True, False], [False, False]])
    q = k = v = jax.random.normal(key, (2, 1, 4))
    out = dot_product_attention(q, k, v, mask_to_bias(mask))
    assert np.all(np.isfinite(out))
    # A row with every key blocked falls back to a uniform average instead of NaN.
    np.testing.assert_allclose(out[1], v.mean(0), atol=1e-6)


def test_key_value_permutation_invariance(key):
    """Attention without a bias is a set operation over (key, value) pairs."""
    x = jax.random.normal(key, (5, 12))
    memory = jax.random.normal(jax.random.fold_in(key, 1), (9, 10))
    mha = MultiHeadAttention(num_heads=3, head_dim=4)
    params = random_params(mha, x, memory)
    perm = np.random.default_rng(0).permutation(9)
    np.testing.assert_allclose(
        mha.apply(params, x, memory), mha.apply(params, x, memory[perm]), atol=1e-5
    )


def test_parameter_shapes_no_qkv_bias_and_default_out_width(key):
    x = jnp.zeros((2, 5, 16))
    mha = MultiHeadAttention(num_heads=8, head_dim=4, qkv_bias=False)
    params = jax.eval_shape(mha.init, key, x)["params"]
    assert set(params) == {"query", "key", "value", "out"}
    for name in ("query", "key", "value"):
        assert set(params[name]) == {"kernel"}
        assert params[name]["kernel"].shape == (16, 8, 4)
    assert params["out"]["kernel"].shape == (8, 4, 16)
    y, _ = jax.eval_shape(MultiHeadAttention(num_heads=2, head_dim=3, out_features=7).init_with_output, key, x)
    assert y.shape == (2, 5, 7)


def test_module_matches_reference_built_from_its_parameters(key):
    x = jax.random.normal(key, (2, 5, 6))
    mha = MultiHeadAttention(num_heads=2, head_dim=3)
    params = random_params(mha, x)["params"]
    bias = jax.random.normal(jax.random.fold_in(key, 2), (5, 5))
    p = jax.tree_util.tree_map(np.asarray, params)
    proj = lambda q: np.einsum("btf,fhd->bthd", x, q["kernel"]) + q["bias"]  # noqa: E731
    heads = _reference_attention(proj(p["query"]), proj(p["key"]), proj(p["value"]), bias)
    expected = np.einsum("bthd,hdf->btf", heads, p["out"]["kernel"]) + p["out"]["bias"]
    # A static NumPy bias is accepted as well as a JAX one.
    np.testing.assert_allclose(mha.apply({"params": params}, x, bias=np.asarray(bias)), expected, atol=1e-5)


@pytest.mark.slow
def test_chunked_decoding_with_kv_cache_equals_full_pass(key):
    """Block-causal self-attention run chunk by chunk with a cache == one pass over the sequence."""
    length, chunk = 12, 4
    x = jax.random.normal(key, (2, length, 16))
    mha = MultiHeadAttention(num_heads=4, head_dim=8, qkv_bias=False)
    params = random_params(mha, x)
    bias = mask_to_bias(_block_causal(length, chunk))
    full = jax.jit(lambda p, x: mha.apply(p, x, bias=bias))(params, x)

    @jax.jit
    def step(params, x_chunk, cache, bias_rows):
        return mha.apply(params, x_chunk, bias=bias_rows, kv_cache=cache, return_kv=True)

    outputs, cache = [], None
    for start in range(0, length, chunk):
        stop = start + chunk
        rows = bias[start:stop, :stop]
        if cache is None:
            out, cache = mha.apply(params, x[:, start:stop], bias=rows, return_kv=True)
        else:
            out, cache = step(params, x[:, start:stop], cache, rows)
        outputs.append(out)
        assert cache[0].shape == (2, stop, 4, 8)
    np.testing.assert_allclose(jnp.concatenate(outputs, axis=1), full, atol=1e-5)
    # The full pass's own keys are the cache's keys.
    _, (full_k, _) = mha.apply(params, x, return_kv=True)
    np.testing.assert_allclose(cache[0], full_k, atol=1e-6)


def test_cross_attention_with_precomputed_memory(key):
    x = jax.random.normal(key, (3, 4, 8))
    memory = jax.random.normal(jax.random.fold_in(key, 1), (3, 6, 5))
    mha = MultiHeadAttention(num_heads=2, head_dim=4)
    params = random_params(mha, x, memory)
    keys, values = mha.apply(params, memory, method=MultiHeadAttention.project_kv)
    reused = mha.apply(params, x, keys, values, method=MultiHeadAttention.attend)
    np.testing.assert_allclose(reused, mha.apply(params, x, memory), atol=1e-6)


def test_attention_dropout_is_active_only_when_not_deterministic(key):
    x = jax.random.normal(key, (2, 6, 8))
    mha = MultiHeadAttention(num_heads=2, head_dim=4, dropout_rate=0.5)
    params = random_params(mha, x)
    plain = MultiHeadAttention(num_heads=2, head_dim=4).apply(params, x)
    np.testing.assert_allclose(mha.apply(params, x, deterministic=True), plain, atol=1e-6)
    rngs = {"dropout": jax.random.key(3)}
    dropped = mha.apply(params, x, deterministic=False, rngs=rngs)
    assert np.abs(dropped - plain).max() > 1e-3
    np.testing.assert_array_equal(dropped, mha.apply(params, x, deterministic=False, rngs=rngs))


def test_attention_errors(key):
    x = jnp.zeros((2, 5, 8))
    mha = MultiHeadAttention(num_heads=2, head_dim=4)
    params = random_params(mha, x)
    with pytest.raises(ValueError, match="does not broadcast"):
        mha.apply(params, x, bias=jnp.zeros((5, 4)))
    with pytest.raises(ValueError, match="more axes"):
        mha.apply(params, x, bias=jnp.zeros((1, 2, 2, 5, 5)))
    bad_cache = (jnp.zeros((2, 3, 4, 4)), jnp.zeros((2, 3, 4, 4)))  # 4 heads, module has 2
    with pytest.raises(ValueError, match="kv_cache"):
        mha.apply(params, x, kv_cache=bad_cache)
    with pytest.raises(ValueError, match="dropout_rng"):
        dot_product_attention(jnp.zeros((3, 1, 2)), jnp.zeros((3, 1, 2)), jnp.zeros((3, 1, 2)), dropout_rate=0.1)
    with pytest.raises(ValueError, match="positive"):
        jax.eval_shape(MultiHeadAttention(num_heads=0, head_dim=4).init, key, x)


# ---------------------------------------------------------------------------------------------
# Transformer blocks


def _layer_norm(x, p, eps=1e-5):
    x = np.asarray(x, np.float64)
    mu = x.mean(-1, keepdims=True)
    var = x.var(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * np.asarray(p["scale"]) + np.asarray(p["bias"])


def _feed_forward(x, p):
    h = x @ np.asarray(p["dense_0"]["kernel"]) + np.asarray(p["dense_0"]["bias"])
    h = 0.5 * h * (1 + erf(h / np.sqrt(2)))  # exact GELU
    return h @ np.asarray(p["dense_1"]["kernel"]) + np.asarray(p["dense_1"]["bias"])


def _attention(p, x, memory=None, bias=None):
    mha = MultiHeadAttention(num_heads=2, head_dim=4)
    return np.asarray(mha.apply({"params": p}, jnp.asarray(x, jnp.float32), memory, bias=bias))


def test_blocks_are_pre_layer_norm_compositions_of_their_parts(key):
    x = jax.random.normal(key, (2, 5, 8))
    memory = jax.random.normal(jax.random.fold_in(key, 1), (2, 3, 6))
    bias = jax.random.normal(jax.random.fold_in(key, 2), (5, 5))
    cross_bias = jax.random.normal(jax.random.fold_in(key, 3), (5, 3))

    block = TransformerBlock(num_heads=2, head_dim=4)
    p = random_params(block, x)["params"]
    h = np.asarray(x) + _attention(
        p["self_attention"]["attention"], _layer_norm(x, p["self_attention"]["norm"]), bias=bias
    )
    ff = p["feed_forward"]
    expected = h + _feed_forward(_layer_norm(h, ff["norm"]), ff["feed_forward"]["mlp"])
    np.testing.assert_allclose(block.apply({"params": p}, x, bias=bias), expected, atol=2e-5)

    decoder = DecoderBlock(num_heads=2, head_dim=4)
    p = random_params(decoder, x, memory)["params"]
    h = np.asarray(x) + _attention(
        p["self_attention"]["attention"], _layer_norm(x, p["self_attention"]["norm"]), bias=bias
    )
    ca = p["cross_attention"]
    h = h + _attention(ca["attention"], _layer_norm(h, ca["norm"]), memory, bias=cross_bias)
    ff = p["feed_forward"]
    expected = h + _feed_forward(_layer_norm(h, ff["norm"]), ff["feed_forward"]["mlp"])
    out = decoder.apply({"params": p}, x, memory, self_bias=bias, cross_bias=cross_bias)
    np.testing.assert_allclose(out, expected, atol=2e-5)


def test_stacked_blocks_decode_chunk_by_chunk_like_the_full_pass(key):
    """Two decoder blocks, each carrying its own self-attention cache across chunks."""
    length, chunk = 9, 3
    x = jax.random.normal(key, (2, length, 8))
    memory = jax.random.normal(jax.random.fold_in(key, 1), (2, 4, 8))
    block = DecoderBlock(num_heads=2, head_dim=4, qkv_bias=False)
    params = [random_params(block, x, memory, seed=i) for i in range(2)]  # two layers
    bias = mask_to_bias(_block_causal(length, chunk))
    apply = jax.jit(block.apply, static_argnames="return_kv")

    full = x
    for p in params:
        full = apply(p, full, memory, self_bias=bias)

    caches = [None, None]
    outputs = []
    for start in range(0, length, chunk):
        stop = start + chunk
        h = x[:, start:stop]
        for i, p in enumerate(params):
            h, caches[i] = apply(
                p, h, memory, self_bias=bias[start:stop, :stop], kv_cache=caches[i], return_kv=True
            )
        outputs.append(h)
    np.testing.assert_allclose(jnp.concatenate(outputs, axis=1), full, atol=1e-5)


def test_band_bias_limits_what_a_frame_sees(key):
    length, radius = 8, 2
    x = jax.random.normal(key, (length, 8))
    i, j = np.indices((length, length))
    bias = mask_to_bias(np.abs(i - j) <= radius)
    block = TransformerBlock(num_heads=2, head_dim=4)
    params = random_params(block, x)
    apply = jax.jit(lambda x: block.apply(params, x, bias=bias))
    # A random (not constant) change: LayerNorm would erase a constant shift of the frame.
    delta = apply(x.at[0].add(jax.random.normal(jax.random.fold_in(key, 1), (8,)))) - apply(x)
    changed = np.abs(np.asarray(delta)).max(axis=-1) > 1e-6
    np.testing.assert_array_equal(changed, np.arange(length) <= radius)


def test_cross_bias_hides_memory_frames(key):
    x = jax.random.normal(key, (4, 8))
    memory = jax.random.normal(jax.random.fold_in(key, 1), (6, 8))
    visible = np.array([True, True, True, False, False, True])
    cross_bias = mask_to_bias(np.broadcast_to(visible, (4, 6)))
    decoder = DecoderBlock(num_heads=2, head_dim=4)
    params = random_params(decoder, x, memory)
    apply = jax.jit(lambda m: decoder.apply(params, x, m, cross_bias=cross_bias))
    base = apply(memory)
    np.testing.assert_allclose(apply(memory.at[3:5].set(5.0)), base, atol=1e-6)
    assert np.abs(apply(memory.at[0].set(5.0)) - base).max() > 1e-3


def test_block_dropout_needs_deterministic_false(key):
    x = jax.random.normal(key, (2, 5, 8))
    block = TransformerBlock(num_heads=2, head_dim=4, dropout_rate=0.3, attention_dropout_rate=0.3)
    params = random_params(block, x)
    plain = TransformerBlock(num_heads=2, head_dim=4).apply(params, x)
    np.testing.assert_allclose(block.apply(params, x), plain, atol=1e-6)
    dropped = block.apply(params, x, deterministic=False, rngs={"dropout": jax.random.key(1)})
    assert np.abs(dropped - plain).max() > 1e-3
    with pytest.raises(Exception, match="dropout"):
        block.apply(params, x, deterministic=False)  # no "dropout" RNG stream given
