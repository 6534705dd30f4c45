"""TIMAR's training objective: masked agent motion, per-frame x0-prediction diffusion, CFG dropout.

Per batch (Sec. 3.4 and the public code):

1. a mask ratio ``r`` is drawn from a normal with mean 1 and std 0.25 truncated to
   ``[mask_ratio_min, 1]``; in every example exactly ``ceil(r L)`` of the ``L = N F`` agent-motion
   tokens, chosen uniformly at random, are replaced by the learned mask token (MAR's recipe);
2. with probability ``cfg_dropout`` all of an example's user tokens become the learned fake token;
3. every frame gets its own timesteps ``t ~ U{0..T-1}`` and noises (``diffusion_batch_mul`` draws,
   MAR's recipe, sharing the frame's one encoder feature); the head predicts x0 from
   ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps`` and the encoder feature of that frame;
4. the loss of a frame is the sum over the groups (exp, jaw, neck) of the group's mean squared error
   (plus, with a learned variance, improved diffusion's variational bound with the mean frozen),
   averaged over the draws and over the MASKED frames only.

The MLP-head ablation regresses x0 directly from the feature with the same grouped loss. The
MAE-style encoder-decoder variant (``architecture="encoder_decoder"``) trains with the same masks and
loss: its encoder ignores the masked frames and its decoder's outputs there are the features.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.models.turns.streams import check_streams, to_turns
from jaxtalk.metrics.params import grouped_mse  # shared with the DualTalk baseline; part of this API
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.head import apply_head
from jaxtalk.models.timar.model import encode_window
from jaxtalk.samplers.schedules import make_schedule, respace
from jaxtalk.types import Array, Bool, Float, PRNGKeyArray

__all__ = [
    "STREAMS",
    "sample_mask_ratio",
    "random_agent_mask",
    "grouped_mse",
    "diffusion_tables",
    "loss",
    "masked_loss",
    "make_loss_fn",
]

STREAMS = ("user_speech", "user_motion", "agent_speech", "agent_motion")


def sample_mask_ratio(config: TimarConfig, key: PRNGKeyArray) -> Float[Array, ""]:
    """Mask ratio ~ N(1, std^2) truncated to ``[mask_ratio_min, 1]``.

    Args:
        config: model config (``mask_ratio_min``, ``mask_ratio_std``).
        key: PRNG key.

    Returns:
        ``()`` float32 ratio.
    """
    if config.mask_ratio_min >= 1.0:
        # Every agent frame masked, as at inference (the truncated normal would be degenerate).
        return jnp.ones((), jnp.float32)
    std = config.mask_ratio_std
    lower = (config.mask_ratio_min - 1.0) / std
    z = jax.random.truncated_normal(key, lower, 0.0, (), jnp.float32)
    # Clip guards the ends against float rounding of the truncated sample.
    return jnp.clip(1.0 + std * z, config.mask_ratio_min, 1.0)


def random_agent_mask(
    key: PRNGKeyArray, ratio: Float[Array, ""] | float, batch: int, length: int
) -> Bool[Array, "batch length"]:
    """Per example, exactly ``ceil(ratio * length)`` positions chosen uniformly at random.

    Args:
        key: PRNG key.
        ratio: ``()`` masking ratio in [0, 1] (traced).
        batch: B.
        length: L tokens per example.

    Returns:
        ``(B, L)`` bool, True = masked.
    """
    scores = jax.random.uniform(key, (batch, length))
    ranks = jnp.argsort(jnp.argsort(scores, axis=-1), axis=-1)
    # Round before ceil so that e.g. 0.7 * 200 = 140.00000001 in float32 still masks 140.
    count = jnp.ceil(jnp.round(jnp.asarray(ratio, jnp.float32) * length, 4))
    return ranks < count


@functools.lru_cache(maxsize=8)
def _full_tables(schedule: str, num_timesteps: int) -> dict[str, np.ndarray]:
    # The training tables are the schedule "respaced" to all of its own steps (float64 NumPy, once).
    s = respace(make_schedule(schedule, num_timesteps), num_timesteps)
    return {
        "alpha_bar": s.alphas_cumprod,
        "coef_x0": s.posterior_coef_x0,
        "coef_xt": s.posterior_coef_xt,
        "log_var_small": s.posterior_log_variance_clipped,
        "log_beta": s.log_betas,
    }


def diffusion_tables(config: TimarConfig) -> dict[str, Float[Array, " timesteps"]]:
    """Training tables of the config's schedule (``alpha_bar`` and posterior terms), float32.

    Args:
        config: model config (``schedule``, ``num_timesteps``).

    Returns:
        name -> ``(T,)`` float32 arrays.
    """
    return {k: jnp.asarray(v, jnp.float32) for k, v in _full_tables(config.schedule, config.num_timesteps).items()}


def _vlb_bits(
    tables: dict[str, Array], t: Array, x0: Array, xt: Array, x0_hat: Array, var_values: Array
) -> Array:
    """Improved diffusion's variational-bound term per frame (bits per dim), mean frozen."""
    pick = lambda name: tables[name][t][..., None]  # noqa: E731
    mean_q = pick("coef_x0") * x0 + pick("coef_xt") * xt
    mean_p = pick("coef_x0") * jax.lax.stop_gradient(x0_hat) + pick("coef_xt") * xt
    frac = (var_values + 1.0) / 2.0
    log_var_p = frac * pick("log_beta") + (1.0 - frac) * pick("log_var_small")
    log_var_q = pick("log_var_small")
    kl = 0.5 * (-1.0 + log_var_p - log_var_q + jnp.exp(log_var_q - log_var_p) + (mean_q - mean_p) ** 2 * jnp.exp(-log_var_p))
    # At t = 0 the bound's term is the decoder's negative log-likelihood of x0 (continuous data:
    # a Gaussian, where image models use a discretised one).
    nll = 0.5 * (math.log(2 * math.pi) + log_var_p + (x0 - mean_p) ** 2 * jnp.exp(-log_var_p))
    bits = jnp.where((t == 0)[..., None], nll, kl) / math.log(2.0)
    return jnp.mean(bits, axis=-1)


def loss(
    params: dict[str, Any], config: TimarConfig, batch: dict[str, Any], key: PRNGKeyArray
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """TIMAR's training loss on a batch of N-turn windows.

    Args:
        params: ``{"encoder", "head"}`` parameters.
        batch: ``user_speech``/``agent_speech`` ``(B, N F, speech_dim)`` and
            ``user_motion``/``agent_motion`` ``(B, N F, 56)`` (normalised), N <= ``max_turns``.
        key: PRNG key of this step.
        config: model config.

    Returns:
        ``(loss, metrics)``: the scalar loss and ``mask_ratio``, ``masked_frames`` and the per-group
        losses (``loss_exp``, ``loss_jaw``, ``loss_neck``, and ``loss_vlb`` with a learned variance).

    Raises:
        ValueError: missing streams or bad shapes (see :func:`check_streams`).
    """
    missing = [name for name in STREAMS if name not in batch]
    if missing:
        raise ValueError(f"batch is missing streams {missing}; it has {sorted(batch)}")
    check_streams(config, {k: batch[k] for k in STREAMS}, max_turns=config.max_turns)
    f = config.frames_per_turn
    us, um, as_, am = (to_turns(jnp.asarray(batch[k], jnp.float32), f) for k in STREAMS)
    b, n = am.shape[:2]
    k_ratio, k_mask, k_drop, k_rest = jax.random.split(key, 4)
    ratio = sample_mask_ratio(config, k_ratio)
    mask = random_agent_mask(k_mask, ratio, b, n * f).reshape(b, n, f)
    user_drop = jax.random.bernoulli(k_drop, config.cfg_dropout, (b,))
    loss, metrics = masked_loss(params, config, (us, um, as_, am), am, mask, user_drop, k_rest)
    metrics["mask_ratio"] = ratio
    return loss, metrics


def masked_loss(
    params: dict[str, Any],
    config: TimarConfig,
    turns: tuple[Float[Array, "batch turns frames speech_dim"], Float[Array, "batch turns frames param_dim"],
                 Float[Array, "batch turns frames speech_dim"], Float[Array, "batch turns frames param_dim"]],
    targets: Float[Array, "batch turns frames param_dim"],
    mask: Bool[Array, "batch turns frames"],
    user_drop: Bool[Array, " batch"],
    key: PRNGKeyArray,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """The loss for a given agent mask and CFG dropout (the deterministic core of :func:`loss`).

    Args:
        params: model parameters.
        config: model config.
        turns: ``(user_speech, user_motion, agent_speech, agent_motion)`` split into turns; the
            agent motion is the INPUT (visible where ``mask`` is False).
        targets: ``(B, N, F, 56)`` the clean frames to reconstruct (the agent motion in training).
        mask: ``(B, N, F)`` True where the agent frame is masked (and only there is a loss).
        user_drop: ``(B,)`` True where the example's user tokens become the fake token.
        key: PRNG key for timesteps, noise and dropout.

    Returns:
        ``(loss, metrics)`` as :func:`loss` (without ``mask_ratio``).
    """
    us, um, as_, am = turns
    k_t, k_noise, k_dropout = jax.random.split(key, 3)
    z = encode_window(
        params, config, us, um, as_, am, mask, user_drop,
        dropout_key=k_dropout if config.dropout > 0 else None,
    )
    metrics: dict[str, Array] = {}
    weight = mask.astype(jnp.float32)
    if config.head == "diffusion":
        # diffusion_batch_mul draws of (t, noise) per frame on a leading axis, all reading the same
        # encoder feature (broadcast, not copied, into the vmapped head).
        m = config.diffusion_batch_mul
        tables = diffusion_tables(config)
        t = jax.random.randint(k_t, (m, *mask.shape), 0, config.num_timesteps)
        abar = tables["alpha_bar"][t][..., None]
        eps = jax.random.normal(k_noise, (m, *targets.shape), targets.dtype)
        x0 = jnp.broadcast_to(targets, eps.shape)
        xt = jnp.sqrt(abar) * x0 + jnp.sqrt(1.0 - abar) * eps
        out = apply_head(params["head"], config, jnp.broadcast_to(z, (m, *z.shape)), xt, t.astype(jnp.float32))
        x0_hat = out[..., : config.param_dim]
        per_frame, groups = grouped_mse(x0_hat, x0)
        if config.learn_sigma:
            vlb = _vlb_bits(tables, t, x0, xt, x0_hat, out[..., config.param_dim :])
            groups["vlb"] = vlb
            per_frame = per_frame + config.vlb_weight * vlb
        # Average over the draws: the loss keeps the scale of one draw per frame.
        per_frame = jnp.mean(per_frame, axis=0)
        groups = {name: jnp.mean(value, axis=0) for name, value in groups.items()}
    else:
        per_frame, groups = grouped_mse(apply_head(params["head"], config, z), targets)
    denom = jnp.maximum(jnp.sum(weight), 1.0)
    loss = jnp.sum(per_frame * weight) / denom
    for name, value in groups.items():
        metrics[f"loss_{name}"] = jnp.sum(value * weight) / denom
    metrics["masked_frames"] = jnp.sum(weight)
    return loss, metrics


def make_loss_fn(config: TimarConfig) -> Callable[[Any, Any, Any], tuple[Array, dict[str, Array]]]:
    """``loss_fn(params, batch, key)`` for :func:`jaxtalk.train.train`.

    Args:
        config: model config.

    Returns:
        The loss function with the config bound.
    """
    return functools.partial(_bound_loss, config)


def _bound_loss(config: TimarConfig, params: dict[str, Any], batch: dict[str, Any], key: PRNGKeyArray):
    return loss(params, config, batch, key)
