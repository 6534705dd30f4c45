"""Training objectives: the conditional flow-matching loss (stage 1) and the adaptation loss (stage 2).

CFM (``papers/NOTES.md``): ``t ~ U(0, 1)``, ``z ~ N(0, I)``, ``x_t = (1 - (1 - sigma_min) t) z + t x1``,
target ``u = x1 - (1 - sigma_min) z``; the loss is the squared error summed over real frames and
channels divided by (real frames x channels). Per example, with probability ``cfg_dropout`` the
tokens, style and known frames are dropped together (CFG); with probability ``known_prob`` a random
contiguous segment of up to ``known_max_fraction`` of the real frames is given as known frames (the
reference uses a prefix; a segment anywhere also covers the streaming window, whose known overlap
sits just before the new chunk). Per batch, the chunk mask is used with probability
``chunk_mask_prob`` (else full attention), so one model serves streaming and offline.

Batches are dicts: ``motion (B, T, D)``, ``tokens (B, Tt, speech_dim)`` at the base token rate,
``style (B, S, D)`` reference clips, ``mask (B, T)`` bool; stage 2 adds ``src_tokens (B, Ts, src_dim)``.

With ``config.style_anchor`` the flow runs in coordinates centred on the reference clip's mean pose
(:func:`~jaxtalk.models.toktalk.model.to_flow_space`), so ``x1`` above is the target relative to it. That
centring is a change of coordinates, not a condition: the CFG-dropped branch runs in the same coordinates
(it learns the average motion around a speaker's resting pose).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.noise import prior_noise
from jaxtalk.models.toktalk.model import (
    Condition,
    adapter_forward,
    anchor_pose,
    interpolate_tokens,
    join_style,
    style_distribution,
    to_flow_space,
    velocity,
)
from jaxtalk.models.toktalk.style import kl_divergence
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray

__all__ = ["loss", "make_loss_fn", "adapter_loss", "adapter_positions", "random_known_mask", "flow_matching_terms"]

PyTree = Any


def flow_matching_terms(
    x1: Float[Array, "*shape"], z: Float[Array, "*shape"], t: Float[Array, "*tshape"], sigma_min: float
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """The CFM path point ``x_t`` and its target velocity ``u`` (``t`` broadcast from the left).

    Args:
        x1: data sample.
        z: Gaussian noise of the same shape.
        t: flow times with ``x1``'s leading axes (e.g. ``(B,)``).
        sigma_min: minimum noise level.

    Returns:
        ``(x_t, u)``.
    """
    tt = t.reshape(t.shape + (1,) * (x1.ndim - t.ndim))
    x_t = (1 - (1 - sigma_min) * tt) * z + tt * x1
    u = x1 - (1 - sigma_min) * z
    return x_t, u


def random_known_mask(
    key: PRNGKeyArray, valid: Bool[Array, "batch frames"], probability: float | int, max_fraction: float | int
) -> Bool[Array, "batch frames"]:
    """Per example, with ``probability``, a random contiguous known segment inside the real frames.

    The segment length is uniform in ``[1, max(1, floor(max_fraction * length))]`` and its start
    uniform over the positions where it fits inside the example's real frames.

    Args:
        key: PRNG key.
        valid: ``(B, T)`` True on real frames (a prefix of each row).
        probability: chance that an example has a known segment.
        max_fraction: longest segment as a fraction of the example's real length.

    Returns:
        ``(B, T)`` bool known mask (False everywhere for examples without a segment).
    """
    b, t = valid.shape
    k_has, k_len, k_start = jax.random.split(key, 3)
    length = jnp.sum(valid, axis=1)
    longest = jnp.maximum(jnp.floor(max_fraction * length).astype(jnp.int32), 1)
    seg = 1 + jnp.floor(jax.random.uniform(k_len, (b,)) * longest).astype(jnp.int32)
    seg = jnp.minimum(seg, jnp.maximum(length, 1))
    start = jnp.floor(jax.random.uniform(k_start, (b,)) * (length - seg + 1)).astype(jnp.int32)
    frames = jnp.arange(t)[None, :]
    inside = (frames >= start[:, None]) & (frames < (start + seg)[:, None])
    has = jax.random.bernoulli(k_has, probability, (b,)) & (length > 0)
    return inside & valid & has[:, None]


def _check_batch(batch: dict[str, Any], config: TokTalkConfig) -> None:
    # Trace-time shape checks: a wrong batch fails with a message, not deep inside the decoder.
    motion, tokens, mask = batch["motion"], batch["tokens"], batch["mask"]
    if motion.ndim != 3 or motion.shape[-1] != config.param_dim:
        raise ValueError(f"batch['motion'] must be (B, T, {config.param_dim}), got {motion.shape}")
    if mask.shape != motion.shape[:2]:
        raise ValueError(f"batch['mask'] must be (B, T) = {motion.shape[:2]}, got {mask.shape}")
    if tokens.ndim != 3 or tokens.shape[-1] != config.speech_dim:
        raise ValueError(f"batch['tokens'] must be (B, Tt, {config.speech_dim}), got {tokens.shape}")
    expected = motion.shape[1] * config.token_rate / config.fps
    if abs(tokens.shape[1] - expected) > 0.5:
        raise ValueError(
            f"batch['tokens'] has {tokens.shape[1]} tokens for {motion.shape[1]} frames; at "
            f"{config.token_rate} Hz and {config.fps} fps expected {expected:g}"
        )


def _flow_loss(
    params: PyTree, batch: dict[str, Any], tokens: Array, key: PRNGKeyArray, config: TokTalkConfig
) -> tuple[Array, dict[str, Array]]:
    valid = jnp.asarray(batch["mask"]).astype(bool)
    k_t, k_z, k_drop, k_known, k_chunk, k_style, k_dropout = jax.random.split(key, 7)
    style_clip = batch["style"]
    style_mask = batch.get("style_mask")
    dropout_key = k_dropout if config.dropout > 0 else None
    mu, logvar = style_distribution(params, config, style_clip, style_mask, dropout_key=dropout_key)
    latent = mu + jnp.exp(0.5 * logvar) * jax.random.normal(k_style, mu.shape, mu.dtype)
    style = join_style(config, latent, anchor_pose(params, style_clip, style_mask))
    # The flow runs on standardised motion (unit-variance noise needs unit-spread data per channel),
    # centred on the reference clip's anchor pose when the style carries one.
    x1 = to_flow_space(params, config, batch["motion"], style) * valid[..., None].astype(batch["motion"].dtype)
    b, t, d = x1.shape
    times = jax.random.uniform(k_t, (b,), x1.dtype)
    if config.time_sampling == "cosine":
        times = 1.0 - jnp.cos(times * (0.5 * jnp.pi))
    z = prior_noise(k_z, x1.shape, config.noise_frames, x1.dtype)
    x_t, u = flow_matching_terms(x1, z, times, config.sigma_min)

    known_mask = random_known_mask(k_known, valid, config.known_prob, config.known_max_fraction)
    keep = jax.random.bernoulli(k_drop, 1.0 - config.cfg_dropout, (b,)).astype(x1.dtype)
    chunked = jnp.broadcast_to(jax.random.bernoulli(k_chunk, config.chunk_mask_prob), (b,))
    cond = Condition(
        tokens=interpolate_tokens(tokens, config.token_rate, config.fps, t, config.token_alignment),
        style=style,
        known=x1,
        known_mask=known_mask,
        keep=keep,
        mask=valid,
        chunked=chunked,
    )
    v = velocity(params, config, x_t, times, cond, dropout_key=dropout_key)
    w = valid.astype(x1.dtype)[..., None]
    count = jnp.maximum(jnp.sum(w) * d, 1.0)
    flow = jnp.sum(jnp.square(v - u) * w) / count
    kl = kl_divergence(mu, logvar)
    return flow + config.kl_weight * kl, {"flow": flow, "kl": kl}


def loss(
    params: PyTree, config: TokTalkConfig, batch: dict[str, Any], key: PRNGKeyArray
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Stage-1 loss: masked CFM + ``kl_weight`` x style KL (see the module docstring).

    Args:
        params: ``{"decoder", "style"}`` parameters.
        batch: ``motion``, ``tokens``, ``style``, ``mask`` (optional ``style_mask``).
        key: PRNG key.
        config: model settings (:func:`make_loss_fn` binds them for the train loop).

    Returns:
        ``(loss, {"flow", "kl"})``.

    Raises:
        ValueError: (at trace time) batch arrays of the wrong shapes or a token count that does not
            match the frames at the configured rate.
    """
    _check_batch(batch, config)
    return _flow_loss(params, batch, batch["tokens"], key, config)


def make_loss_fn(config: TokTalkConfig) -> Callable[[PyTree, dict[str, Any], PRNGKeyArray], tuple[Array, dict[str, Array]]]:
    """``loss_fn(params, batch, key)`` for :func:`jaxtalk.train.train`: :func:`loss` with ``config`` bound."""
    return functools.partial(_bound_loss, config)


def _bound_loss(config: TokTalkConfig, params: PyTree, batch: dict[str, Any], key: PRNGKeyArray):
    return loss(params, config, batch, key)


def adapter_positions(config: TokTalkConfig, key: PRNGKeyArray, tokens: int) -> Int[Array, " tokens"]:
    """The absolute positions a stage-2 training window of ``tokens`` base tokens is placed at.

    Streams and whole utterances number the adapter's tokens from the start of the utterance, so they
    reach positions far beyond a training window; training at positions ``0 .. tokens-1`` only would
    leave every later position untrained. The window starts uniformly in
    ``[0, adapter_max_position - tokens]`` instead.
    """
    start = jax.random.randint(key, (), 0, max(config.adapter_max_position - tokens, 0) + 1)
    return start + jnp.arange(tokens, dtype=jnp.int32)


def adapter_loss(
    params: PyTree,
    config: TokTalkConfig,
    batch: dict[str, Any],
    key: PRNGKeyArray,
    *,
    src_rate: float | int,
    flow_weight: float = 1.0,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """Stage-2 loss: ``||A(e_src) - e_base||^2 + flow_weight * L_CFM(frozen base on A(e_src))``.

    The alignment term is the mean squared error over real tokens and channels (a token is real when
    the frame it starts on is). The window is placed at :func:`adapter_positions` (a random start), so
    the adapter is trained at the positions a stream counts from the start of the utterance. Freeze
    everything but ``params["adapter"]`` in the train loop.

    Args:
        params: ``{"decoder", "style", "adapter"}``.
        config: model settings.
        batch: stage-1 keys plus ``src_tokens (B, Ts, src_dim)`` at ``src_rate``.
        key: PRNG key.
        src_rate: source token rate (Hz).
        flow_weight: lambda.

    Returns:
        ``(loss, {"align", "flow", "kl"})``.
    """
    _check_batch(batch, config)
    base = batch["tokens"]
    k_ad, k_flow = jax.random.split(key)
    positions = adapter_positions(config, jax.random.fold_in(key, 2), base.shape[1])
    adapted = adapter_forward(params, config, batch["src_tokens"], src_rate, positions=positions,
                              dropout_key=k_ad if config.dropout > 0 else None)
    if adapted.shape != base.shape:
        raise ValueError(
            f"adapted tokens {adapted.shape} do not line up with the base tokens {base.shape}: "
            f"is src_rate={src_rate} right?"
        )
    frames = jnp.asarray(batch["mask"]).astype(bool)
    idx = jnp.minimum(jnp.round(jnp.arange(base.shape[1]) * config.frames_per_token).astype(jnp.int32),
                      frames.shape[1] - 1)
    tok_valid = frames[:, idx].astype(base.dtype)[..., None]
    align = jnp.sum(jnp.square(adapted - base) * tok_valid) / jnp.maximum(jnp.sum(tok_valid) * base.shape[-1], 1.0)
    flow_total, metrics = _flow_loss(params, batch, adapted, k_flow, config)
    return align + flow_weight * flow_total, {"align": align, **metrics}
