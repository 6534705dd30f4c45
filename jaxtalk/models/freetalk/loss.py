"""FreeTalk's unified motion loss (equation 15): position + velocity + acceleration errors.

The same loss trains ATS (points = 68 landmarks, weights 0.3 / 0.1) and STM (points = mesh vertices,
weights 0.5 / 0.2). Each term is a mean of squared L2 norms over the valid (frame, point) pairs; a
velocity (acceleration) term exists only where both (all three) frames it spans are valid, so padding
never leaks into a difference.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxtalk.types import Array, Bool, Float

__all__ = ["motion_loss"]


def _masked_mean_sq(diff: Array, frame_ok: Array, point_ok: Array) -> Array:
    # diff (B, T', K, 3); frame_ok (B, T'); point_ok (B, K)
    sq = jnp.sum(diff * diff, axis=-1)
    w = frame_ok[:, :, None] * point_ok[:, None, :]
    return jnp.sum(sq * w) / jnp.maximum(jnp.sum(w), 1.0)


def motion_loss(
    pred: Float[Array, "batch frames points 3"],
    target: Float[Array, "batch frames points 3"],
    frame_mask: Bool[Array, "batch frames"] | None = None,
    point_mask: Bool[Array, "batch points"] | None = None,
    *,
    velocity_weight: float = 0.3,
    acceleration_weight: float = 0.1,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """``L_pos + w_v L_vel + w_a L_acc`` with ``v(Y_t) = Y_{t+1} - Y_t``, ``a = Y_{t+2} - 2Y_{t+1} + Y_t``.

    Args:
        pred: ``(B, T, K, 3)`` predicted motion.
        target: ``(B, T, K, 3)`` ground truth.
        frame_mask: ``(B, T)`` True on real frames (default all).
        point_mask: ``(B, K)`` True on real points, e.g. not padding vertices (default all).
        velocity_weight: ``w_v``.
        acceleration_weight: ``w_a``.

    Returns:
        ``(loss, {"position", "velocity", "acceleration"})`` scalars. With fewer than 2 (3) frames the
        velocity (acceleration) term is 0.
    """
    b, t, k, _ = pred.shape
    fm = jnp.ones((b, t), pred.dtype) if frame_mask is None else frame_mask.astype(pred.dtype)
    pm = jnp.ones((b, k), pred.dtype) if point_mask is None else point_mask.astype(pred.dtype)
    err = pred - target
    pos = _masked_mean_sq(err, fm, pm)
    zero = jnp.zeros((), pred.dtype)
    vel = _masked_mean_sq(err[:, 1:] - err[:, :-1], fm[:, 1:] * fm[:, :-1], pm) if t > 1 else zero
    acc = (
        _masked_mean_sq(err[:, 2:] - 2 * err[:, 1:-1] + err[:, :-2], fm[:, 2:] * fm[:, 1:-1] * fm[:, :-2], pm)
        if t > 2
        else zero
    )
    loss = pos + velocity_weight * vel + acceleration_weight * acc
    return loss, {"position": pos, "velocity": vel, "acceleration": acc}
