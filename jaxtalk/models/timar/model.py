"""TIMAR parameters and the whole-window forward pass shared by training and offline sampling."""

from __future__ import annotations

import functools
from typing import Any

import jax

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.encoder import TimarEncoder, init_encoder
from jaxtalk.models.timar.head import init_head
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Bool, Float, PRNGKeyArray

__all__ = ["init_params", "encode_window"]


@functools.partial(jax.jit, static_argnums=0)
def init_params(config: TimarConfig, key: PRNGKeyArray) -> dict[str, Any]:
    """Initial parameters ``{"encoder": ..., "head": ...}``.

    Args:
        config: model config.
        key: PRNG key.

    Returns:
        Parameter pytree.
    """
    k_enc, k_head = jax.random.split(key)
    return {"encoder": init_encoder(config, k_enc), "head": init_head(config, k_head)}


def encode_window(
    params: dict[str, Any],
    config: TimarConfig,
    user_speech: Float[Array, "batch turns frames speech_dim"],
    user_motion: Float[Array, "batch turns frames param_dim"],
    agent_speech: Float[Array, "batch turns frames speech_dim"],
    agent_motion: Float[Array, "batch turns frames param_dim"] | None = None,
    agent_mask: Bool[Array, "batch turns frames"] | None = None,
    user_drop: Bool[Array, " batch"] | Bool[Array, "batch turns"] | None = None,
    *,
    dropout_key: PRNGKeyArray | None = None,
) -> Float[Array, "batch turns frames width"]:
    """Head conditions of every agent frame of a window of N turns (slots 0..N-1).

    Args:
        params: :func:`init_params` output.
        config: model config.
        user_speech, user_motion, agent_speech: ``(B, N, F, ...)`` turn-split streams.
        agent_motion: ``(B, N, F, 56)`` or None (all agent frames masked, as in sampling).
        agent_mask: ``(B, N, F)`` True = agent frame replaced by the mask token.
        user_drop: ``(B,)`` True = all of the example's user tokens replaced by the fake token;
            ``(B, N)``: per turn.
        dropout_key: enables encoder dropout (training) when given.

    Returns:
        ``(B, N, F, width)``.
    """
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    return compute_in(config.compute_dtype, TimarEncoder(config).apply)(
        {"params": params["encoder"]},
        user_speech,
        user_motion,
        agent_speech,
        agent_motion,
        agent_mask,
        user_drop,
        deterministic=dropout_key is None,
        rngs=rngs,
    )
