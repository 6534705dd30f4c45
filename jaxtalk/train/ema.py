"""Exponential moving average of parameters (evaluation / sampling weights), with bias correction.

A plain EMA started at the initial parameters keeps weight ``decay**t`` on them after ``t`` updates
(37% after 1,000 steps at ``decay=0.999``), so early in training the "EMA model" is mostly the random
initialisation. The train loop therefore keeps the *bias-corrected* average, as Adam does for its
moments and ``optax.ema(debias=True)`` for parameters::

    ema_t = sum_{i=1..t} (1 - d) d**(t - i) p_i / (1 - d**t)

i.e. the normalised exponentially weighted mean of the parameters after updates ``1..t``; the
initial parameters get weight exactly 0. Rather than a raw buffer (initialised at zero) plus a
division on every read, the state holds this debiased value itself and updates it with the
equivalent recursion ``ema_t = k_t ema_{t-1} + (1 - k_t) p_t`` where
``k_t = d (1 - d**(t-1)) / (1 - d**t)`` (:func:`ema_decay_at`; ``k_1 = 0``, ``k_t -> d``). The step
count ``t`` is the train state's ``step``, so the checkpointed ``ema_params`` are already the value
every reader wants (``state.eval_params``, :func:`jaxtalk.runs.load_run`), the checkpoint
layout is unchanged, and resuming is bitwise exact because the update depends only on the stored
``(ema_params, params, step)``.

A checkpoint written before the correction existed resumes with its plain average as ``ema_{t-1}``:
the recursion then continues correctly, but the initialisation weight already in that buffer only
decays from there on (by about ``d`` per step).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["ema_update", "ema_decay_at"]

PyTree = Any


def ema_decay_at(decay: float | jax.Array, step: int | jax.Array, dtype: Any = jnp.float32) -> jax.Array:
    """Weight ``k_t`` kept on the previous bias-corrected average at update ``t``.

    ``k_t = d (1 - d**(t-1)) / (1 - d**t)``: 0 at ``t = 1`` (the first average is the first
    parameters, whatever the buffer held before) and increasing towards ``d``.

    ``1 - d**t`` is evaluated as ``-expm1(t * log(d))``: for ``d`` close to 1 and small ``t`` the direct
    form cancels catastrophically in float32 (``1 - 0.999**2`` would keep ~4 significant digits).

    Args:
        decay: EMA decay ``d`` in [0, 1).
        step: 1-based index ``t`` of this update (>= 1), e.g. the train state's step after the update.
        dtype: floating dtype of the result.

    Returns:
        Scalar ``k_t`` of ``dtype``.

    Raises:
        ValueError: a concrete (Python int) ``step`` below 1. A traced step cannot be checked; values
            below 1 are treated as 1.
    """
    if isinstance(step, int) and step < 1:
        raise ValueError(f"step must be >= 1 (the first update is step 1), got {step}")
    d = jnp.asarray(decay, dtype)
    t = jnp.maximum(jnp.asarray(step, dtype), 1)
    log_d = jnp.log1p(d - 1)  # d - 1 is exact for d in [0.5, 1); -inf for d = 0
    norm_t = -jnp.expm1(t * log_d)  # 1 - d**t, in (0, 1]
    # (t - 1) * log_d is 0 * -inf = NaN when d = 0 and t = 1; the weight is 0 there anyway.
    norm_prev = jnp.where(t > 1, -jnp.expm1((t - 1) * log_d), jnp.zeros((), dtype))
    return d * norm_prev / norm_t


def ema_update(
    ema_params: PyTree,
    params: PyTree,
    decay: float | jax.Array,
    mask: PyTree | None = None,
    *,
    step: int | jax.Array | None = None,
) -> PyTree:
    """One EMA update leaf-wise; masked-out leaves are passed through bitwise.

    With ``step`` (what the train step uses) this is the bias-corrected update
    ``ema <- k_t ema + (1 - k_t) params`` with ``k_t = ema_decay_at(decay, step)``: after updates
    ``1..t`` the result is ``sum_i (1 - d) d**(t-i) p_i / (1 - d**t)`` regardless of the initial
    buffer. Without ``step`` it is the plain constant-decay update ``ema <- d ema + (1 - d) params``,
    which keeps weight ``d**t`` on the initial buffer (useful only when that buffer is meant to anchor
    the average, e.g. pretrained weights).

    Frozen leaves (``mask`` False) keep the EMA buffer untouched rather than recomputing
    ``k p + (1 - k) p``, which is not bitwise ``p`` in floating point.

    Args:
        ema_params: current average, same structure as ``params``.
        params: new parameters.
        decay: EMA decay in [0, 1).
        mask: optional pytree of Python bools (True: update this leaf).
        step: 1-based index of this update for the bias-corrected form (None: plain EMA).

    Returns:
        The new average (same structure and dtypes as ``ema_params``).

    Raises:
        ValueError: a concrete ``step`` below 1 (see :func:`ema_decay_at`).
    """
    if isinstance(step, int) and step < 1:
        raise ValueError(f"step must be >= 1 (the first update is step 1), got {step}")

    keeps: dict[Any, jax.Array] = {}  # one weight per compute dtype, not one per leaf in the program

    def one(e, p, m=True):
        if not m:
            return e
        # Low-precision parameters (bf16) are averaged in float32: 1 - 0.999 is 0 in bf16.
        ct = jnp.promote_types(e.dtype, jnp.float32)
        if ct not in keeps:
            keeps[ct] = jnp.asarray(decay, ct) if step is None else ema_decay_at(decay, step, ct)
        keep = keeps[ct]
        e32, p32 = e.astype(ct), p.astype(ct)
        # e + (1 - k)(p - e) rounds once on the large term and leaves a constant leaf bitwise
        # constant; where k = 0 (the first debiased update, or decay 0) the result is p itself, so
        # the initial buffer's weight is exactly 0 rather than a rounding residue of p - e.
        new = e32 + (1 - keep) * (p32 - e32)
        new = jnp.where(keep == 0, p32, new)
        return new.astype(e.dtype)

    if mask is None:
        return jax.tree.map(one, ema_params, params)
    return jax.tree.map(one, ema_params, params, mask)
