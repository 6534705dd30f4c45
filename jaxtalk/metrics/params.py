"""Errors per group of the 56-d head vector ``[exp 50 | jaw 3 | neck 3]``.

TIMAR's loss and the DualTalk baseline's are the sum over the groups of each group's mean squared
error (TIMAR Appendix 7.2), so the three groups weigh the same however many parameters each has.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from jaxtalk.types import EXP_SLICE, JAW_SLICE, NECK_SLICE, Array, Float

__all__ = ["LOSS_GROUPS", "grouped_mse"]

# (name, start, stop) of each group in the 56-d vector.
LOSS_GROUPS: tuple[tuple[str, int, int], ...] = (
    ("exp", EXP_SLICE.start, EXP_SLICE.stop),
    ("jaw", JAW_SLICE.start, JAW_SLICE.stop),
    ("neck", NECK_SLICE.start, NECK_SLICE.stop),
)


def grouped_mse(
    pred: Float[Array, "*frames param_dim"], target: Float[Array, "*frames param_dim"]
) -> tuple[Float[Array, "*frames"], dict[str, Float[Array, "*frames"]]]:
    """Per-frame sum over (exp, jaw, neck) of each group's mean squared error.

    Args:
        pred: ``(*F, 56)`` prediction.
        target: ``(*F, 56)`` ground truth.

    Returns:
        ``(*F,)`` summed loss and the per-group ``(*F,)`` terms.
    """
    err = (pred - target) ** 2
    groups = {name: jnp.mean(err[..., lo:hi], axis=-1) for name, lo, hi in LOSS_GROUPS}
    return functools.reduce(jnp.add, groups.values()), groups
