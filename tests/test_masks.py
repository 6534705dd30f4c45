"""Masks: every entry against brute-force loops over the definitions, padding semantics, bias safety."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk import masks


def _chunk_reference(t, c, left):
    out = np.zeros((t, t), dtype=bool)
    for i in range(t):
        for j in range(t):
            ok = j < (i // c + 1) * c
            if left is not None:
                ok = ok and j >= (i // c - left) * c
            out[i, j] = ok
    return out


def test_chunk_mask_matches_definition():
    # Grid includes chunk sizes that do not divide T, chunk > T, and left limits beyond T.
    for t, c, left in itertools.product([1, 2, 5, 7, 10, 16, 23], [1, 2, 3, 4, 10, 30], [None, 0, 1, 2, 5]):
        got = masks.chunk_mask(t, c, left)
        assert got.dtype == bool and got.shape == (t, t)
        np.testing.assert_array_equal(got, _chunk_reference(t, c, left), err_msg=f"{t=} {c=} {left=}")


def test_chunk_mask_hand_case():
    # T=5, chunk 2, one chunk of left context: chunks {0,1} {2,3} {4}.
    expected = np.array(
        [
            [1, 1, 0, 0, 0],
            [1, 1, 0, 0, 0],
            [1, 1, 1, 1, 0],
            [1, 1, 1, 1, 0],
            [0, 0, 1, 1, 1],
        ],
        dtype=bool,
    )
    np.testing.assert_array_equal(masks.chunk_mask(5, 2, left_chunks=1), expected)


def _band_reference(q, k, r, f):
    out = np.zeros((q, k), dtype=bool)
    for i in range(q):
        dist = [abs(i - kk / f) for kk in range(k)]
        for kk in range(k):
            out[i, kk] = dist[kk] <= r + 1e-9
        if not out[i].any():
            best = min(dist)
            for kk in range(k):
                out[i, kk] = abs(dist[kk] - best) <= 1e-9
    return out


def test_band_mask_matches_definition():
    sizes = [(1, 1), (4, 9), (10, 10), (10, 20), (10, 5), (13, 7), (25, 50), (7, 30)]
    for (q, k), r, f in itertools.product(sizes, [0, 0.5, 1, 2, 3.5], [1.0, 2.0, 0.5, 1 / 3, 4.0, 1.25]):
        got = masks.band_mask(q, k, r, f)
        assert got.shape == (q, k) and got.dtype == bool
        np.testing.assert_array_equal(got, _band_reference(q, k, r, f), err_msg=f"{q=} {k=} {r=} {f=}")
        assert got.any(axis=1).all(), "every query must see at least one key"


@pytest.mark.parametrize("n,r", [(1, 0), (6, 0), (9, 2), (12, 3)])
def test_band_mask_unit_ratio_is_abs_diff(n, r):
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    np.testing.assert_array_equal(masks.band_mask(n, n, r), np.abs(i - j) <= r)


def test_band_mask_audio_rate_hand_case():
    # 50 Hz keys vs 25 fps queries, radius 0: query i sees exactly key 2i.
    got = masks.band_mask(3, 6, 0, frames_per_key=2.0)
    expected = np.zeros((3, 6), dtype=bool)
    expected[[0, 1, 2], [0, 2, 4]] = True
    np.testing.assert_array_equal(got, expected)
    # 12.5 Hz keys, radius 0: odd queries sit between keys 0.5 away and see both neighbours.
    got = masks.band_mask(4, 2, 0, frames_per_key=0.5)
    np.testing.assert_array_equal(got, np.array([[1, 0], [1, 1], [0, 1], [0, 1]], dtype=bool))


def test_turn_causal_matches_definition():
    rng = np.random.default_rng(0)
    for ids in ([0], [0, 0, 1, 1, 1, 2], rng.integers(0, 5, size=17), [3, 1, 2, 1]):
        ids = np.asarray(ids)
        got = masks.turn_causal_mask(ids)
        ref = np.array([[ids[k] <= ids[q] for k in range(len(ids))] for q in range(len(ids))])
        np.testing.assert_array_equal(got, ref)


def test_padding_and_combine_match_definition():
    t = 6
    static = masks.chunk_mask(t, 2)
    lengths = np.array([6, 3, 0, 1])
    valid = np.arange(t)[None, :] < lengths[:, None]
    got = np.asarray(masks.combine(static, valid))
    assert got.shape == (4, 1, t, t)
    for b, q, k in itertools.product(range(4), range(t), range(t)):
        if valid[b, q]:
            want = static[q, k] and valid[b, k]
        else:
            want = q == k  # padded query sees only itself
        assert got[b, 0, q, k] == want, (b, q, k)
    np.testing.assert_array_equal(
        np.asarray(masks.padding_mask(lengths, t)), np.asarray(masks.combine(np.ones((t, t), bool), valid))
    )
    np.testing.assert_array_equal(
        np.asarray(masks.padding_mask(jnp.asarray(valid))), np.asarray(masks.padding_mask(lengths, t))
    )


def test_padding_works_under_jit_and_softmax_has_no_nan():
    t = 5
    static = masks.chunk_mask(t, 2)

    @jax.jit
    def attend(valid, logits):
        bias = masks.mask_to_bias(masks.combine(static, valid), logits.dtype)
        return jax.nn.softmax(logits + bias, axis=-1)

    valid = jnp.asarray([[True] * 5, [True, True, False, False, False], [False] * 5])
    for dtype in (jnp.float32, jnp.bfloat16, jnp.float16):
        logits = jnp.full((3, 1, t, t), 3.0, dtype)
        p = attend(valid, logits)
        assert bool(jnp.all(jnp.isfinite(p)))
        # Masked keys get exactly zero weight.
        allowed = np.asarray(masks.combine(static, np.asarray(valid)))
        assert float(jnp.max(jnp.where(allowed, 0.0, p.astype(jnp.float32)))) == 0.0


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.bfloat16, jnp.float16, jnp.float64])
def test_mask_to_bias_values_and_no_overflow(dtype):
    # The one mask-to-bias helper of jaxtalk (every attention layer's bias comes from it): entry by
    # entry, an allowed position is exactly 0 and a blocked one exactly BIAS_FRACTION * finfo.min.
    m = np.array([[True, False], [False, True]])
    b = masks.mask_to_bias(m, dtype)
    got = jax.dtypes.canonicalize_dtype(dtype)  # float64 becomes float32 without x64
    assert b.dtype == got and b.shape == m.shape
    blocked = np.asarray(masks.BIAS_FRACTION * float(jnp.finfo(got).min), got)
    for idx in np.ndindex(m.shape):
        want = 0.0 if m[idx] else blocked
        assert float(b[idx]) == float(want), (idx, float(b[idx]))
    assert masks.mask_to_bias(jnp.asarray(m)).dtype == jnp.float32  # default dtype, traced-array input
    # Two biases plus a large logit stay finite.
    assert bool(jnp.all(jnp.isfinite(b + b + jnp.asarray(-1e3, b.dtype))))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.bfloat16])
def test_softmax_gives_a_blocked_logit_exactly_zero(dtype):
    # Logits of both signs and sizes, one key blocked per row, a row with a single allowed key.
    logits = jnp.asarray([[3.0, -2.0, 40.0, 0.5], [-30.0, 1.0, 2.0, 3.0], [1.0, 1.0, 1.0, 1.0]], dtype)
    m = np.array([[True, True, False, True], [False, True, True, True], [False, False, True, False]])
    p = jax.nn.softmax(logits + masks.mask_to_bias(m, dtype), axis=-1)
    assert p.dtype == jnp.dtype(dtype)
    assert np.all(np.asarray(p, np.float32)[~m] == 0.0)
    np.testing.assert_allclose(np.asarray(p, np.float32).sum(-1), 1.0, rtol=1e-2)
    assert float(p[2, 2]) == 1.0
    # Formed in float32 from lower-precision logits (as jaxtalk.nn's attention does): also exactly 0.
    q = jax.nn.softmax(logits.astype(jnp.float32) + masks.mask_to_bias(m), axis=-1)
    assert np.all(np.asarray(q)[~m] == 0.0)


def test_mask_to_bias_float64_under_x64(float64):
    b = masks.mask_to_bias(np.array([True, False]), jnp.float64)
    assert b.dtype == jnp.float64
    assert float(b[1]) == 0.25 * float(jnp.finfo(jnp.float64).min)
    assert bool(jnp.all(jnp.isfinite(b + b)))


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: masks.chunk_mask(0, 2), "num_frames"),
        (lambda: masks.chunk_mask(4, 0), "chunk_frames"),
        (lambda: masks.chunk_mask(4, 2, left_chunks=-1), "left_chunks"),
        (lambda: masks.band_mask(0, 3, 1), "num_queries"),
        (lambda: masks.band_mask(3, -1, 1), "num_keys"),
        (lambda: masks.band_mask(3, 3, -1), "radius"),
        (lambda: masks.band_mask(3, 3, float("nan")), "radius"),
        (lambda: masks.band_mask(3, 3, 1, 0.0), "frames_per_key"),
        (lambda: masks.turn_causal_mask([]), "turn_ids"),
        (lambda: masks.turn_causal_mask([0.5, 1.0]), "integers"),
        (lambda: masks.padding_mask(np.array([3, 7]), 5), "lengths"),
        (lambda: masks.padding_mask(np.array([3, 2])), "num_frames"),
        (lambda: masks.padding_mask(np.ones((2, 3, 3), bool)), "valid"),
        (lambda: masks.combine(np.ones((3, 4), bool), np.ones((1, 3), bool)), "square"),
        (lambda: masks.combine(np.ones((3, 3), bool), np.ones((1, 4), bool)), "valid"),
        (lambda: masks.mask_to_bias(np.ones(3), jnp.float32), "bool"),
        (lambda: masks.mask_to_bias(np.ones(3, bool), jnp.int32), "floating"),
    ],
)
def test_validation_errors(call, match):
    with pytest.raises(ValueError, match=match):
        call()
