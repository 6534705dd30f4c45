"""Attention masks: static builders in NumPy, per-example padding in JAX, and the additive bias.

Convention everywhere: a boolean mask is ``True`` where a query MAY attend to a key. Static masks
(chunk, band, turn) depend only on static sizes, so they are built once in NumPy and enter compiled
programs as constants. Padding depends on the data, so :func:`padding_mask` and :func:`combine` are
written with ``jax.numpy`` and work on traced arrays inside ``jit``.

Fully padded query rows: a padded query would otherwise see no key at all, and a softmax over a row of
equal large negative logits is harmless but a row of ``-inf`` is NaN. :func:`combine` and
:func:`padding_mask` therefore let every padded query attend to itself (and only itself), so every row
has at least one allowed entry; its output is garbage by design and must be ignored by the loss.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Bool, Float, Int, Shaped

__all__ = [
    "chunk_mask",
    "band_mask",
    "turn_causal_mask",
    "padding_mask",
    "combine",
    "mask_to_bias",
    "BIAS_FRACTION",
]

# The "minus infinity" of the additive bias is finfo(dtype).min scaled by this fraction: adding two
# such biases (e.g. a mask bias plus a caller's own bias) or a logit of size up to |min|/2 can then
# never overflow to -inf (and -inf + inf = NaN), even in bfloat16/float16, while exp(bias - max) is
# still exactly 0 after the softmax shift.
BIAS_FRACTION = 0.25


def _positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def chunk_mask(
    num_frames: int, chunk_frames: int, left_chunks: int | None = None
) -> Bool[np.ndarray, "frames frames"]:
    """Block-causal (chunk-wise streaming) self-attention mask.

    Frame ``i`` lies in chunk ``c(i) = i // chunk_frames`` and sees frame ``j`` iff
    ``j < (c(i) + 1) * chunk_frames`` (its whole chunk and everything before it) and, when
    ``left_chunks`` is given, ``j >= (c(i) - left_chunks) * chunk_frames`` (at most ``left_chunks``
    whole chunks of left context). The last chunk may be shorter when ``chunk_frames`` does not
    divide ``num_frames``.

    Args:
        num_frames: sequence length T (> 0).
        chunk_frames: frames per chunk (> 0); ``chunk_frames >= num_frames`` gives a full mask.
        left_chunks: ``None`` for unlimited left context, else an integer >= 0.

    Returns:
        ``(T, T)`` bool NumPy array, ``[query, key]``.

    Raises:
        ValueError: non-positive sizes or negative ``left_chunks``.
    """
    t = _positive_int("num_frames", num_frames)
    c = _positive_int("chunk_frames", chunk_frames)
    chunk_of = np.arange(t) // c
    keys = np.arange(t)[None, :]
    mask = keys < ((chunk_of + 1) * c)[:, None]
    if left_chunks is not None:
        if isinstance(left_chunks, bool) or not isinstance(left_chunks, (int, np.integer)):
            raise ValueError(f"left_chunks must be None or an integer >= 0, got {left_chunks!r}")
        if left_chunks < 0:
            raise ValueError(f"left_chunks must be None or an integer >= 0, got {left_chunks!r}")
        mask &= keys >= ((chunk_of - int(left_chunks)) * c)[:, None]
    return mask


def band_mask(
    num_queries: int, num_keys: int, radius: float | int, frames_per_key: float | int = 1.0
) -> Bool[np.ndarray, "queries keys"]:
    """Band-diagonal alignment mask between query frames and key frames of another rate.

    Both sequences start at time 0. ``frames_per_key`` is the number of KEY frames per QUERY frame
    (key rate / query rate): 2.0 for 50 Hz audio features against 25 fps motion, 0.5 for 12.5 Hz tokens
    against 25 fps motion. Key ``k`` is aligned to the query position ``p_k = k / frames_per_key``
    (measured in query frames), and query ``i`` sees key ``k`` iff ``|i - p_k| <= radius``. With
    ``frames_per_key == 1`` this is exactly ``|i - k| <= radius``.

    Guarantee: every query sees at least one key. A query whose band holds no key (sparse keys with a
    small radius, or queries past the end of the keys) sees instead the key(s) nearest to it, i.e. all
    ``k`` minimising ``|i - p_k|`` (two keys on an exact tie).

    Args:
        num_queries: number of query frames (> 0).
        num_keys: number of key frames (> 0).
        radius: half-width of the band in query frames (>= 0, finite).
        frames_per_key: key frames per query frame (> 0, finite).

    Returns:
        ``(num_queries, num_keys)`` bool NumPy array.

    Raises:
        ValueError: non-positive sizes, negative or non-finite radius, non-positive ratio.
    """
    q = _positive_int("num_queries", num_queries)
    k = _positive_int("num_keys", num_keys)
    if not math.isfinite(radius) or radius < 0:
        raise ValueError(f"radius must be finite and >= 0, got {radius!r}")
    if not math.isfinite(frames_per_key) or frames_per_key <= 0:
        raise ValueError(f"frames_per_key must be finite and > 0, got {frames_per_key!r}")
    distance = np.abs(np.arange(q)[:, None] - np.arange(k)[None, :] / float(frames_per_key))
    # A tiny tolerance so that ratios like 1/3 do not drop a key lying exactly on the band edge.
    tol = 1e-9 * max(1.0, float(radius))
    mask = distance <= radius + tol
    nearest = distance <= distance.min(axis=1, keepdims=True) + 1e-9
    empty = ~mask.any(axis=1, keepdims=True)
    return mask | (empty & nearest)


def turn_causal_mask(turn_ids: Int[np.ndarray, " tokens"] | Any) -> Bool[np.ndarray, "tokens tokens"]:
    """Turn-causal mask (TIMAR): key ``k`` is visible to query ``q`` iff ``turn(k) <= turn(q)``.

    Tokens are bidirectional within a turn and causal across turns. Turn ids need not be sorted or
    contiguous; only their order matters.

    Args:
        turn_ids: ``(N,)`` integer turn index of every token (N > 0).

    Returns:
        ``(N, N)`` bool NumPy array, ``[query, key]``.

    Raises:
        ValueError: empty, not one-dimensional, or not integer.
    """
    ids = np.asarray(turn_ids)
    if ids.ndim != 1 or ids.size == 0:
        raise ValueError(f"turn_ids must be a non-empty 1-D array, got shape {ids.shape}")
    if not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"turn_ids must be integers, got dtype {ids.dtype}")
    return ids[None, :] <= ids[:, None]


def _valid_from(lengths_or_valid: Any, num_frames: int | None) -> Bool[Array, "batch frames"]:
    arr = lengths_or_valid
    if not hasattr(arr, "dtype"):
        arr = np.asarray(arr)
    if arr.dtype == bool:
        if arr.ndim != 2:
            raise ValueError(f"valid mask must have shape (batch, frames), got shape {arr.shape}")
        if num_frames is not None and arr.shape[1] != num_frames:
            raise ValueError(f"valid mask has {arr.shape[1]} frames but num_frames={num_frames}")
        return jnp.asarray(arr)
    if arr.ndim != 1:
        raise ValueError(f"lengths must have shape (batch,), got shape {arr.shape}")
    if not jnp.issubdtype(arr.dtype, jnp.integer):
        raise ValueError(f"lengths must be integers (or pass a bool valid mask), got dtype {arr.dtype}")
    if num_frames is None:
        raise ValueError("num_frames is required when lengths (not a valid mask) are given")
    _positive_int("num_frames", num_frames)
    if isinstance(arr, np.ndarray) and (arr.size == 0 or arr.min() < 0 or arr.max() > num_frames):
        raise ValueError(f"lengths must lie in [0, num_frames={num_frames}], got {arr.tolist()}")
    return jnp.arange(num_frames)[None, :] < jnp.asarray(arr)[:, None]


def padding_mask(
    lengths_or_valid: Int[Array, " batch"] | Bool[Array, "batch frames"] | Any,
    num_frames: int | None = None,
) -> Bool[Array, "batch 1 frames frames"]:
    """Per-example self-attention padding mask (works on traced arrays).

    Query ``q`` may attend key ``k`` iff both are valid frames, except that a padded query attends to
    itself only (so no softmax row is empty; see the module docstring).

    Args:
        lengths_or_valid: either ``(B,)`` integer lengths (then ``num_frames`` is required) or a
            ``(B, T)`` bool array, True on valid frames.
        num_frames: T, required with lengths.

    Returns:
        ``(B, 1, T, T)`` bool array (the singleton axis broadcasts over attention heads).

    Raises:
        ValueError: wrong shapes or dtypes, lengths outside ``[0, T]``.
    """
    valid = _valid_from(lengths_or_valid, num_frames)
    t = valid.shape[1]
    return combine(jnp.ones((t, t), dtype=bool), valid)


def combine(
    # Loose shape names so the square/length checks below raise a ValueError that names the problem.
    static_mask: Shaped[Array, "queries keys"] | Shaped[np.ndarray, "queries keys"],
    valid: Shaped[Array, "batch frames"] | Shaped[np.ndarray, "batch frames"],
) -> Bool[Array, "batch 1 frames frames"]:
    """AND a static ``(T, T)`` self-attention mask with per-example padding.

    Entry ``[b, 0, q, k]`` is ``static[q, k] & valid[b, q] & valid[b, k]``, except that padded
    queries (``~valid[b, q]``) see exactly themselves, so no row is empty. If the static mask itself
    has an empty row for a valid query, that row stays empty (the static builders here never produce
    one).

    Args:
        static_mask: ``(T, T)`` bool, ``[query, key]``.
        valid: ``(B, T)`` bool, True on real frames.

    Returns:
        ``(B, 1, T, T)`` bool array.

    Raises:
        ValueError: shape mismatch or non-bool inputs.
    """
    if static_mask.ndim != 2 or static_mask.shape[0] != static_mask.shape[1]:
        raise ValueError(f"static_mask must be square (T, T), got shape {static_mask.shape}")
    if valid.ndim != 2 or valid.shape[1] != static_mask.shape[0]:
        raise ValueError(f"valid must have shape (batch, {static_mask.shape[0]}), got shape {valid.shape}")
    if static_mask.dtype != bool or valid.dtype != bool:
        raise ValueError(f"masks must be bool, got static_mask {static_mask.dtype} and valid {valid.dtype}")
    static = jnp.asarray(static_mask)[None, :, :]
    v = jnp.asarray(valid)
    allowed = static & v[:, :, None] & v[:, None, :]
    eye = np.eye(static_mask.shape[0], dtype=bool)[None, :, :]  # a static constant (every converter folds it)
    allowed = allowed | (eye & ~v[:, :, None])
    return allowed[:, None, :, :]


def mask_to_bias(
    mask: Shaped[Array, "*shape"] | Shaped[np.ndarray, "*shape"], dtype: Any = jnp.float32
) -> Float[Array, "*shape"]:
    """Additive attention bias: 0 where allowed, ``BIAS_FRACTION * finfo(dtype).min`` where not.

    The value is finite and leaves headroom, so adding it to logits (or to another such bias) never
    overflows to ``-inf`` in bfloat16/float16, and a masked logit still underflows to exactly 0 after
    the softmax.

    Args:
        mask: bool array of any shape, True = may attend.
        dtype: a floating dtype for the bias (the logits' dtype).

    Returns:
        Array of ``mask``'s shape and ``dtype``.

    Raises:
        ValueError: non-bool mask or non-floating dtype.
    """
    if mask.dtype != bool:
        raise ValueError(f"mask must be bool, got dtype {mask.dtype}")
    if not jnp.issubdtype(jnp.dtype(dtype), jnp.floating):
        raise ValueError(f"dtype must be a floating dtype, got {dtype!r}")
    # float64 requested without x64 becomes float32: take finfo of the dtype we actually get.
    dtype = jax.dtypes.canonicalize_dtype(dtype)
    neg = jnp.asarray(BIAS_FRACTION * float(jnp.finfo(dtype).min), dtype=dtype)
    return jnp.where(jnp.asarray(mask), jnp.zeros((), dtype), neg)
