"""Input checks shared by the metrics: clear errors at the API boundary, before any XLA work.

Metrics take NumPy or JAX arrays (evaluation code usually holds NumPy). Checks that need values
(NaN, index ranges) run only on concrete arrays, so the vertex metrics stay usable inside a caller's
``jit``/``grad`` (e.g. LVE as a training loss), where shapes are still checked.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite

# Metrics accept host (NumPy) or device (JAX) arrays.
AnyArray = jax.Array | np.ndarray


def _is_tracer(x: object) -> bool:
    return isinstance(x, jax.core.Tracer)


def as_sequence_array(x: AnyArray, name: str, *, trailing: tuple[int, ...] | None = None,
                      ndim: int | None = None, min_frames: int = 1) -> jax.Array:
    """Validate a (frames, ...) array and return it as a floating JAX array.

    Args:
        x: the array.
        name: its name in error messages.
        trailing: required trailing shape (e.g. ``(3,)`` for vertices), or None.
        ndim: required rank, or None.
        min_frames: smallest allowed length of the leading (time) axis.

    Raises:
        ValueError: wrong rank or trailing shape, too few frames, or non-finite values.
    """
    shape = tuple(np.shape(x))
    if ndim is not None and len(shape) != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {shape}")
    if len(shape) < 1:
        raise ValueError(f"{name} must have a leading frames axis, got a scalar")
    if trailing is not None and shape[len(shape) - len(trailing):] != trailing:
        raise ValueError(f"{name} must have trailing shape {trailing}, got shape {shape}")
    if shape[0] < min_frames:
        raise ValueError(f"{name} needs at least {min_frames} frame(s), got {shape[0]} (shape {shape})")
    check_finite(x, name)
    arr = jnp.asarray(x)
    if not jnp.issubdtype(arr.dtype, jnp.floating):
        arr = arr.astype(jnp.result_type(float))
    return arr


def check_same_shape(a: AnyArray, b: AnyArray, name_a: str, name_b: str) -> None:
    """Raise ValueError naming both shapes if ``a`` and ``b`` differ in shape."""
    if tuple(np.shape(a)) != tuple(np.shape(b)):
        raise ValueError(f"{name_a} and {name_b} must have the same shape, got "
                         f"{tuple(np.shape(a))} and {tuple(np.shape(b))}")


def as_index_array(idx: AnyArray | Sequence[int], name: str, size: int) -> np.ndarray:
    """Validate a 1-D, non-empty array of indices into an axis of length ``size``.

    Returns:
        The indices as a read-only int32 NumPy array (a constant in jitted code).

    Raises:
        ValueError: empty, not 1-D, not integer, or out of range ``[0, size)``.
    """
    if _is_tracer(idx):
        raise ValueError(f"{name} must be a concrete index array (region indices are static), got a tracer")
    arr = np.asarray(idx)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array of vertex indices, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty: the region has no vertices")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must hold integers, got dtype {arr.dtype}")
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= size:
        raise ValueError(f"{name} has indices out of range [0, {size}): min {lo}, max {hi}")
    out = arr.astype(np.int32)
    out.setflags(write=False)
    return out
