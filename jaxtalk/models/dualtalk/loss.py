"""The DualTalk baseline's training objective: plain regression of the agent's motion over the window.

Per window, DualTalk's loss: the sum over the groups (exp, jaw, neck) of each group's mean squared
error, plus ``velocity_weight`` x the mean squared error of the frame-to-frame differences (all 56
channels), averaged over frames. Every agent frame is a target; no agent frame is an input.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax.numpy as jnp

from jaxtalk.models.turns.streams import check_streams
from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.metrics.params import grouped_mse
from jaxtalk.models.dualtalk.model import apply
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = ["STREAMS", "loss", "make_loss_fn", "regression_loss"]

STREAMS = ("user_speech", "user_motion", "agent_speech", "agent_motion")


def regression_loss(
    pred: Float[Array, "batch frames param_dim"],
    target: Float[Array, "batch frames param_dim"],
    velocity_weight: float,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """DualTalk's loss of a predicted window against the truth.

    Args:
        pred: ``(B, T, 56)`` prediction.
        target: ``(B, T, 56)`` ground truth.
        velocity_weight: weight of the velocity term.

    Returns:
        ``(loss, metrics)``: the scalar loss and ``loss_exp``, ``loss_jaw``, ``loss_neck``,
        ``loss_velocity`` (the unweighted velocity MSE; 0 for one-frame windows).
    """
    per_frame, groups = grouped_mse(pred, target)
    metrics = {f"loss_{name}": jnp.mean(value) for name, value in groups.items()}
    if pred.shape[1] > 1:
        velocity = jnp.mean((jnp.diff(pred, axis=1) - jnp.diff(target, axis=1)) ** 2)
    else:
        velocity = jnp.zeros((), pred.dtype)
    metrics["loss_velocity"] = velocity
    return jnp.mean(per_frame) + velocity_weight * velocity, metrics


def loss(
    params: dict[str, Any], config: DualTalkConfig, batch: dict[str, Any], key: PRNGKeyArray
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """The baseline's training loss on a batch of N-turn windows.

    Args:
        params: model parameters.
        batch: ``user_speech``/``agent_speech`` ``(B, N F, speech_dim)`` and
            ``user_motion``/``agent_motion`` ``(B, N F, 56)`` (normalised), N <= ``max_turns``; the
            agent's motion is only the target.
        key: PRNG key of this step (dropout).
        config: model config.

    Returns:
        ``(loss, metrics)`` as :func:`regression_loss`.

    Raises:
        ValueError: missing streams or bad shapes (see :func:`~jaxtalk.models.turns.streams.check_streams`).
    """
    missing = [name for name in STREAMS if name not in batch]
    if missing:
        raise ValueError(f"batch is missing streams {missing}; it has {sorted(batch)}")
    check_streams(config, {k: batch[k] for k in STREAMS}, max_turns=config.max_turns)
    # No cast: the loader's float32 stays float32, and a float64 batch (gradient checks) stays float64.
    us, um, as_, am = (jnp.asarray(batch[k]) for k in STREAMS)
    dropout = config.dropout > 0 or config.feature_dropout > 0
    pred = apply(params, config, us, um, as_, dropout_key=key if dropout else None)
    return regression_loss(pred, am, config.velocity_weight)


def make_loss_fn(config: DualTalkConfig) -> Callable[[Any, Any, Any], tuple[Array, dict[str, Array]]]:
    """``loss_fn(params, batch, key)`` for :func:`jaxtalk.train.train`.

    Args:
        config: model config.

    Returns:
        The loss function with the config bound.
    """
    return functools.partial(_bound_loss, config)


def _bound_loss(config: DualTalkConfig, params: dict[str, Any], batch: dict[str, Any], key: PRNGKeyArray):
    return loss(params, config, batch, key)

