"""Exponential moving average of parameters (evaluation / sampling weights)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["ema_update"]

PyTree = Any


def ema_update(ema_params: PyTree, params: PyTree, decay: float | jax.Array, mask: PyTree | None = None) -> PyTree:
    """``ema <- decay * ema + (1 - decay) * params`` leaf-wise; masked-out leaves are passed through.

    Frozen leaves (``mask`` False) keep the EMA buffer untouched rather than recomputing
    ``decay * p + (1 - decay) * p``, which is not bitwise ``p`` in floating point.

    Args:
        ema_params: current average, same structure as ``params``.
        params: new parameters.
        decay: EMA decay in [0, 1).
        mask: optional pytree of Python bools (True: update this leaf).

    Returns:
        The new average (same structure and dtypes as ``ema_params``).
    """

    def one(e, p, m=True):
        if not m:
            return e
        d = jnp.asarray(decay, dtype=e.dtype)
        # e + (1 - d) * (p - e) is the same average with one rounding less on the large term.
        return e + (1 - d) * (p - e)

    if mask is None:
        return jax.tree.map(one, ema_params, params)
    return jax.tree.map(one, ema_params, params, mask)
