"""Frame-rate conversion of feature streams (audio features, token embeddings, vertices) in time.

Input frame ``i`` of a stream at ``src_rate`` sits at time ``i / src_rate``; output frame ``j`` at
``j / dst_rate``. Positions are computed in exact rational arithmetic on the host, so "the latest input
frame at or before time t" is never off by one through float rounding (which would break causality),
and the gather indices and weights enter one jitted kernel as arrays: converting between other rates
with the same shapes does not recompile.
"""

from __future__ import annotations

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int

from jaxtalk.types import Array

__all__ = ["resample_features", "default_num_frames", "interpolation_plan", "area_weights"]

_MODES = ("linear", "previous")
# Rates are turned into exact fractions; 1e-6 resolution covers 29.97 fps, 12.5 Hz, 44.1 kHz exactly.
_MAX_RATE_DENOMINATOR = 1_000_000


def _as_fraction(rate: float | int, name: str) -> Fraction:
    if isinstance(rate, bool) or not isinstance(rate, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number of frames per second, got {rate!r}")
    if not np.isfinite(rate) or rate <= 0:
        raise ValueError(f"{name} must be a positive finite rate, got {rate!r}")
    # str() turns 12.5 or 29.97 into the decimal the user wrote, not its binary float expansion.
    return Fraction(str(float(rate))).limit_denominator(_MAX_RATE_DENOMINATOR)


def default_num_frames(num_input: int, src_rate: float | int, dst_rate: float | int) -> int:
    """Output length for a stream of ``num_input`` frames: ``round(num_input * dst / src)``, >= 1.

    Rounds halves up. A centred log-mel stream of ``d`` seconds has ``100 d + 1`` frames and maps to
    ``25 d`` motion frames at 25 fps; a 12.5 Hz token stream of ``12.5 d`` tokens maps to ``25 d``.
    """
    ratio = _as_fraction(dst_rate, "dst_rate") / _as_fraction(src_rate, "src_rate")
    n = (2 * num_input * ratio.numerator + ratio.denominator) // (2 * ratio.denominator)
    return max(1, int(n))


def interpolation_plan(
    num_input: int,
    src_rate: float | int,
    dst_rate: float | int,
    num_frames: int,
    mode: str = "linear",
) -> tuple[Int[np.ndarray, " out"], Int[np.ndarray, " out"], Float[np.ndarray, " out"]]:
    """Gather indices and weights: ``out[j] = (1 - w[j]) * x[lo[j]] + w[j] * x[hi[j]]``.

    Output frame ``j`` is at input position ``p = j * src_rate / dst_rate`` (exact). ``"linear"``
    blends frames ``floor(p)`` and ``floor(p) + 1``; ``"previous"`` takes frame ``floor(p)``, the
    latest input frame at a time ``<= j / dst_rate`` (causal). Positions past the last input frame
    hold the last frame.

    Args:
        num_input: number of input frames (>= 1).
        src_rate: input frame rate.
        dst_rate: output frame rate.
        num_frames: number of output frames (>= 1).
        mode: ``"linear"`` or ``"previous"``.

    Returns:
        ``(lo, hi, w)``: int32 ``(num_frames,)`` indices and float64 ``(num_frames,)`` weights in [0, 1).

    Raises:
        ValueError: for a bad rate, length or mode.
    """
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    if num_input < 1:
        raise ValueError(f"need at least one input frame, got {num_input}")
    if (
        isinstance(num_frames, bool)
        or not isinstance(num_frames, (int, np.integer))
        or num_frames < 1
    ):
        raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
    ratio = _as_fraction(src_rate, "src_rate") / _as_fraction(dst_rate, "dst_rate")
    num, den = ratio.numerator, ratio.denominator
    if num * num_frames < 2**62:
        scaled = np.arange(num_frames, dtype=np.int64) * num
        floor, frac = scaled // den, (scaled % den) / den
    else:  # j * numerator would overflow int64: exact Python integers (slow, rare)
        scaled_py = [j * num for j in range(int(num_frames))]
        floor = np.array([s // den for s in scaled_py], dtype=np.int64)
        frac = np.array([(s % den) / den for s in scaled_py], dtype=np.float64)
    last = num_input - 1
    lo = np.minimum(floor, last)
    if mode == "previous":
        return lo.astype(np.int32), lo.astype(np.int32), np.zeros(num_frames)
    hi = np.minimum(floor + 1, last)
    weight = np.where(floor >= last, 0.0, frac)
    return lo.astype(np.int32), hi.astype(np.int32), weight


def area_weights(
    num_input: int, src_rate: float | int, dst_rate: float | int, num_frames: int
) -> Float[np.ndarray, "out inp"]:
    """Time-overlap (box-filter) resampling weights: ``out = W @ x`` with ``W`` ``(num_frames, num_input)``.

    Output frame ``j`` spans ``[j / dst, (j + 1) / dst)`` and input frame ``i`` spans
    ``[i / src, (i + 1) / src)``; ``W[j, i]`` is their overlap as a fraction of the part of output
    frame ``j`` that the input covers (rows sum to 1). Downsampling 25 -> 12.5 Hz averages each pair
    of inputs (none is dropped); upsampling repeats each input. Output frame ``j`` only reads inputs
    that overlap its own span, so a stream cut at a common boundary resamples piece by piece exactly
    as a whole. Output frames past the end of the input hold the last input. Exact rational
    arithmetic on the host.

    Raises:
        ValueError: for a bad rate or a non-positive length.
    """
    if num_input < 1 or isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
        raise ValueError(f"need positive lengths, got num_input={num_input!r}, num_frames={num_frames!r}")
    src, dst = _as_fraction(src_rate, "src_rate"), _as_fraction(dst_rate, "dst_rate")
    w = np.zeros((int(num_frames), int(num_input)))
    for j in range(int(num_frames)):
        start, end = Fraction(j) / dst, Fraction(j + 1) / dst
        first = min(int(start * src), num_input - 1)  # floor: the input frame that holds `start`
        last = min(-(-int((end * src).numerator) // (end * src).denominator), num_input)  # ceil, exclusive
        total = Fraction(0)
        row = {}
        for i in range(first, max(last, first + 1)):
            overlap = min(end, Fraction(i + 1) / src) - max(start, Fraction(i) / src)
            if overlap > 0:
                row[i] = overlap
                total += overlap
        if not row:  # past the end of the input: hold the last frame
            w[j, num_input - 1] = 1.0
            continue
        for i, overlap in row.items():
            w[j, i] = float(overlap / total)
    return w


@jax.jit
def _blend(x, lo, hi, weight):
    weight = weight.astype(x.dtype)[:, None]
    return x[lo] * (1 - weight) + x[hi] * weight


def resample_features(
    x: Float[Array | np.ndarray, "frames dim"],
    src_rate: float | int,
    dst_rate: float | int,
    num_frames: int | None = None,
    mode: str = "linear",
) -> Float[Array, "new_frames dim"]:
    """Convert a feature stream from ``src_rate`` to ``dst_rate`` frames per second.

    ``"linear"`` interpolates between the two input frames around each output time (smooth; looks
    one input frame ahead). ``"previous"`` takes the latest input frame at or before each output time,
    so output frame ``j`` depends only on input frames at times ``<= j / dst_rate``: use it in
    streaming, where future input does not exist yet. Beyond the last input frame both hold it.

    Args:
        x: ``(frames, dim)`` stream (NumPy or JAX; may be traced inside an outer jit).
        src_rate: its frame rate (e.g. 100 for log-mel, 50 for HuBERT, 12.5 for Mimi tokens).
        dst_rate: wanted frame rate (e.g. 25 for motion).
        num_frames: output length; default ``default_num_frames(frames, src_rate, dst_rate)``.
        mode: ``"linear"`` or ``"previous"``.

    Returns:
        ``(num_frames, dim)`` stream in ``x``'s float dtype.

    Raises:
        ValueError: for a non-2-D or empty stream, NaN/inf values (when ``x`` is concrete), a
            non-positive rate or length, or an unknown mode.
    """
    # Check finiteness on the host when the input is NumPy (no device round trip, no compile).
    finite = bool(np.all(np.isfinite(x))) if isinstance(x, np.ndarray) else None
    if not isinstance(x, jax.core.Tracer):
        x = jnp.asarray(x)
    if x.ndim != 2:
        raise ValueError(f"resample_features expects a (frames, dim) array, got shape {x.shape}")
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"resample_features got an empty stream of shape {x.shape}")
    if num_frames is None:
        num_frames = default_num_frames(x.shape[0], src_rate, dst_rate)
    lo, hi, weight = interpolation_plan(x.shape[0], src_rate, dst_rate, num_frames, mode)
    if finite is None and not isinstance(x, jax.core.Tracer):
        finite = bool(jnp.all(jnp.isfinite(x)))
    if finite is False:
        raise ValueError("resample_features: the stream contains NaN or inf values")
    return _blend(x, jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(weight, dtype=x.dtype))
