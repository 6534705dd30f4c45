"""Offline sampling: the whole sequence at once with the Euler flow sampler, CFG and the cosine grid.

One jitted program per (config, shapes, number of steps); the guidance weight, the time grid values,
the style vector and the token embeddings are traced, so sweeping them never recompiles. The sampler
is a ``lax.scan`` over the grid and is differentiable end to end (w.r.t. style vector and tokens).
"""

from __future__ import annotations

import functools
from fractions import Fraction
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite, check_temperature
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.model import (
    Condition,
    check_style_clip,
    check_tokens,
    interpolate_tokens,
    sampler_model,
    from_flow_space,
    style_vector,
    to_flow_space,
)
from jaxtalk.models.toktalk.noise import prior_noise
from jaxtalk.samplers import cosine_grid, sample_euler
from jaxtalk.types import Array, Bool, Float, PRNGKeyArray

__all__ = ["sample", "sample_long", "resolve_style", "default_grid", "LONG_WINDOW_FRAMES", "LONG_CONTEXT_FRAMES"]

# Offline sampling of an input longer than this runs window by window (:func:`sample_long`). The
# decoder's attention is O(T^2) in memory (a 20-minute clip asked for 45 GB); 1,500 frames (60 s at
# 25 fps) keep one window's attention under ~0.5 GB at the paper preset.
LONG_WINDOW_FRAMES = 1500
# Frames of already generated motion each later window re-reads as inpainted known frames (2 s).
LONG_CONTEXT_FRAMES = 50

PyTree = Any


def default_grid(config: TokTalkConfig, sample_steps: int | None = None) -> np.ndarray:
    """The cosine time grid ``t_k = 1 - cos(k / N * pi / 2)`` with ``N = sample_steps or config.sample_steps``."""
    return cosine_grid(config.sample_steps if sample_steps is None else sample_steps)


def resolve_style(params: PyTree, config: TokTalkConfig, style: Any, batch: int) -> Array:
    """A ``(B, style_vector_dim)`` style vector from a vector or a ``(B, S, param_dim)`` reference clip.

    Args:
        params: model parameters (the style encoder is used for clips).
        config: model settings.
        style: ``(B, style_vector_dim)`` vector, ``(style_vector_dim,)`` for every example, or a clip.
        batch: the batch size B.

    Returns:
        ``(B, style_vector_dim)``.

    Raises:
        ValueError: a shape that is neither, a batch mismatch, a too-short clip, NaN/inf.
    """
    shape = tuple(np.shape(style))
    if len(shape) == 3:
        check_style_clip(style, config)
        vec = style_vector(params, config, jnp.asarray(style))
    elif len(shape) in (1, 2) and shape[-1] == config.style_vector_dim:
        check_finite(style, "style vector")
        vec = jnp.asarray(style)
        if vec.ndim == 1:
            vec = jnp.broadcast_to(vec[None], (batch, config.style_vector_dim))
    else:
        raise ValueError(
            f"style must be a (batch, {config.style_vector_dim}) vector or a (batch, frames, {config.param_dim}) "
            f"reference clip, got shape {shape}"
        )
    if vec.shape[0] != batch:
        raise ValueError(f"style has batch {vec.shape[0]} but tokens have batch {batch}")
    return vec


def sample(
    params: PyTree,
    config: TokTalkConfig,
    tokens: Float[Array, "batch tokens width"] | Float[np.ndarray, "batch tokens width"],
    style: Any,
    key: PRNGKeyArray | None = None,
    *,
    num_frames: int | None = None,
    sample_steps: int | None = None,
    ts: Any = None,
    cfg_scale: Float[Array, ""] | float | None = None,
    temperature: Float[Array, ""] | float | None = None,
    known: Any = None,
    known_mask: Any = None,
    mask: Any = None,
    chunked: bool | Bool[Array, ""] = False,
    noise: Any = None,
    remat: bool = False,
    guidance: bool = True,
) -> Float[Array, "batch frames param"]:
    """Generates motion for whole token sequences (offline, one Euler/CFG pass over all frames).

    Args:
        params: model parameters.
        config: model settings.
        tokens: ``(B, Tt, speech_dim)`` base-space token embeddings at ``config.token_rate``.
        style: ``(B, style_vector_dim)`` style vector(s) or a ``(B, S, param_dim)`` reference clip.
        key: PRNG key for the starting noise (required unless ``noise`` is given).
        num_frames: expected number of frames (checked against the token count and rate).
        sample_steps: Euler steps (default ``config.sample_steps``; static).
        ts: an explicit ``(N + 1,)`` time grid instead (traced values); default: the cosine grid of
            ``sample_steps`` steps.
        cfg_scale: guidance weight w (traced; default ``config.cfg_scale``).
        temperature: scale of the starting noise, drawn or given (traced; default ``config.temperature``).
        known: ``(B, T, param_dim)`` frames to inpaint, with ``known_mask`` ``(B, T)`` bool.
        known_mask: see ``known``.
        mask: ``(B, T)`` True on real frames (None: all real).
        chunked: use the block-causal chunk attention (as in streaming) instead of full attention.
        noise: ``(B, T, param_dim)`` explicit starting noise (else drawn from ``key``).
        remat: checkpoint each Euler step (memory O(1) in N when differentiating).
        guidance: run the unconditional branch (static; False: the conditional model alone, half the
            work, ``cfg_scale`` ignored; equal to ``cfg_scale=0``).

    Returns:
        ``(B, T, param_dim)`` motion; padded frames are zero.

    Raises:
        ValueError: tokens of the wrong width or rate, NaN/inf, bad style, bad known/mask shapes,
            neither ``key`` nor ``noise``.
    """
    batch = int(np.shape(tokens)[0]) if np.ndim(tokens) == 3 else 0
    frames = check_tokens(tokens, width=config.speech_dim, rate=config.token_rate, fps=config.fps,
                          num_frames=num_frames)
    style_vec = resolve_style(params, config, style, batch)
    motion_shape = (batch, frames, config.param_dim)
    if ts is None:
        ts = default_grid(config, sample_steps)
    ts = jnp.asarray(ts)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"ts must be a 1-D time grid with at least 2 entries, got shape {ts.shape}")
    if noise is None:
        if key is None:
            raise ValueError("sample needs a PRNG key (or explicit noise)")
        noise = prior_noise(key, motion_shape, config.noise_frames, jnp.result_type(float))
    elif tuple(np.shape(noise)) != motion_shape:
        raise ValueError(f"noise must have shape {motion_shape}, got {tuple(np.shape(noise))}")
    check_finite(noise, "noise")
    mask_arr = jnp.ones(motion_shape[:2], bool) if mask is None else jnp.asarray(mask)
    if mask_arr.shape != motion_shape[:2] or mask_arr.dtype != bool:
        raise ValueError(f"mask must be bool of shape {motion_shape[:2]}, got {mask_arr.dtype} {mask_arr.shape}")
    if (known is None) != (known_mask is None):
        raise ValueError("known and known_mask must be given together")
    if known is not None:
        if tuple(np.shape(known)) != motion_shape:
            raise ValueError(f"known must have shape {motion_shape}, got {tuple(np.shape(known))}")
        km = jnp.asarray(known_mask)
        if km.shape != motion_shape[:2] or km.dtype != bool:
            raise ValueError(f"known_mask must be bool of shape {motion_shape[:2]}, got {km.dtype} {km.shape}")
        check_finite(known, "known")
        known, known_mask = jnp.asarray(known), km
    w = config.cfg_scale if cfg_scale is None else cfg_scale
    noise = jnp.asarray(noise)
    return _sample(
        params,
        jnp.asarray(tokens),
        style_vec,
        noise,
        check_temperature(temperature, noise.dtype, default=config.temperature),
        ts,
        jnp.asarray(w, noise.dtype),
        known,
        known_mask,
        mask_arr,
        jnp.asarray(chunked, bool),
        config,
        bool(remat),
        bool(guidance),
    )


def sample_long(
    params: PyTree,
    config: TokTalkConfig,
    tokens: Float[np.ndarray, "batch tokens width"],
    style: Any,
    key: PRNGKeyArray,
    *,
    sample_steps: int | None = None,
    cfg_scale: Float[Array, ""] | float | None = None,
    temperature: Float[Array, ""] | float | None = None,
    window_frames: int = LONG_WINDOW_FRAMES,
    context_frames: int = LONG_CONTEXT_FRAMES,
) -> Float[np.ndarray, "batch frames param"]:
    """:func:`sample` of any length in bounded memory: window by window for long inputs.

    An input of at most ``window_frames`` frames is one :func:`sample` call (bitwise the same result).
    A longer one is cut into windows of exactly ``window_frames`` frames (one compiled program): window
    ``k > 0`` starts ``context_frames`` before the first frame not yet generated and holds the frames
    already generated as known (inpainted) frames, as the streaming engine continues a chunk; the last
    window is moved back to end at the last frame, so it holds more known frames rather than another
    shape. Window ``k`` draws its noise from ``fold_in(key, k)``.

    Why windows and not an exact split: the offline decoder's attention is full (every frame attends
    to every frame, and even the chunk mask has an unbounded past), so no frame's output depends on a
    bounded stretch of input and no split reproduces the whole-sequence computation beyond one window.
    Memory is O(window^2) for attention plus O(T) for the tokens and the output.

    Args:
        params, config, tokens, style, key, sample_steps, cfg_scale, temperature: as :func:`sample` (batch
            of any size).
        window_frames: frames per window (rounded down to whole tokens).
        context_frames: known frames re-read at the start of each later window (rounded down to whole
            tokens; less than ``window_frames``).

    Returns:
        ``(B, T, param_dim)`` NumPy motion, ``T`` as :func:`sample` gives for these tokens.

    Raises:
        ValueError: as :func:`sample`; a window not longer than its context.
    """
    frames = check_tokens(tokens, width=config.speech_dim, rate=config.token_rate, fps=config.fps)
    if frames <= window_frames:
        return np.asarray(sample(params, config, tokens, style, key, sample_steps=sample_steps, cfg_scale=cfg_scale,
                                 temperature=temperature))
    # Windows start on tokens whose first frame is a whole frame: q tokens span p frames exactly.
    per_token = Fraction(config.fps) / Fraction(str(float(config.token_rate)))
    p, q = per_token.numerator, per_token.denominator
    win_t = (window_frames // p) * q
    ctx_t = (context_frames // p) * q
    if ctx_t >= win_t or win_t == 0:
        raise ValueError(f"window_frames={window_frames} must exceed context_frames={context_frames} by whole tokens")
    tokens = np.asarray(tokens, np.float32)
    batch, num_tokens = tokens.shape[:2]
    style_vec = resolve_style(params, config, style, batch)
    out = np.zeros((batch, frames, config.param_dim), np.float32)
    done_t, k = 0, 0  # tokens whose frames are generated; window index
    while done_t < num_tokens:
        start_t = 0 if k == 0 else min(done_t - ctx_t, (num_tokens - win_t) // q * q)
        stop_t = start_t + win_t if start_t + win_t + q <= num_tokens else num_tokens  # the last takes the rest
        start_f = start_t * p // q
        win_f = (frames if stop_t == num_tokens else stop_t * p // q) - start_f
        known_f = done_t * p // q - start_f  # frames of this window generated already
        known_mask = np.zeros((batch, win_f), bool)
        known_mask[:, :known_f] = True
        motion = sample(params, config, tokens[:, start_t:stop_t], style_vec,
                        key if k == 0 else jax.random.fold_in(key, k), sample_steps=sample_steps, cfg_scale=cfg_scale,
                        temperature=temperature, known=out[:, start_f:start_f + win_f], known_mask=known_mask)
        out[:, start_f + known_f:start_f + win_f] = np.asarray(motion)[:, known_f:]
        done_t, k = stop_t, k + 1
    return out


@functools.partial(jax.jit, static_argnames=("config", "remat", "guidance"))
def _sample(params, tokens, style_vec, noise, temperature, ts, cfg_scale, known, known_mask, mask, chunked, config,
            remat, guidance):
    return generate_frames(
        params, config, tokens, style_vec, temperature * noise, ts, cfg_scale,
        known=known, known_mask=known_mask, mask=mask, chunked=chunked, remat=remat, guidance=guidance,
    )


def generate_frames(
    params: PyTree,
    config: TokTalkConfig,
    tokens: Float[Array, "batch tokens width"],
    style_vec: Float[Array, "batch vector"],
    noise: Float[Array, "batch frames param"],
    ts: Float[Array, " grid"],
    cfg_scale: Float[Array, ""],
    *,
    known: Float[Array, "batch frames param"] | None = None,
    known_mask: Bool[Array, "batch frames"] | None = None,
    mask: Bool[Array, "batch frames"] | None = None,
    chunked: Bool[Array, ""] | None = None,
    remat: bool = False,
    guidance: bool = True,
) -> Float[Array, "batch frames param"]:
    """The traced core of :func:`sample` and of the streaming engine (no validation).

    Args:
        params, config: the model.
        tokens: ``(B, Tt, speech_dim)`` at the base rate; interpolated to ``T = noise.shape[1]`` frames.
        style_vec: ``(B, style_vector_dim)``.
        noise: ``(B, T, param_dim)`` starting noise (in the flow's coordinates, see
            :func:`~jaxtalk.models.toktalk.model.to_flow_space`).
        ts: ``(N + 1,)`` time grid.
        cfg_scale: ``()`` guidance weight.
        known, known_mask: optional inpainting values ``(B, T, D)`` (raw units) and mask ``(B, T)``.
        mask: ``(B, T)`` real frames (None: all).
        chunked: ``()`` chunk attention flag (None: full attention).
        remat: checkpoint each Euler step.
        guidance: run the unconditional branch (static; False: ``cfg_scale`` ignored).

    Returns:
        ``(B, T, param_dim)`` in raw parameter units, zero on padded frames.
    """
    b, t, d = noise.shape
    known_raw = known
    if known is not None:
        known = to_flow_space(params, config, known, style_vec)
    frames_tokens = interpolate_tokens(tokens, config.token_rate, config.fps, t, config.token_alignment)
    mask = jnp.ones((b, t), bool) if mask is None else mask
    chunked = jnp.zeros((), bool) if chunked is None else chunked
    has_known = known is not None
    cond = Condition(
        tokens=frames_tokens,
        style=style_vec,
        known=known if has_known else jnp.zeros_like(noise),
        known_mask=(known_mask & mask) if has_known else jnp.zeros((b, t), bool),
        keep=jnp.ones((b,), noise.dtype),
        mask=mask,
        chunked=jnp.broadcast_to(chunked, (b,)),
    )
    x = sample_euler(
        sampler_model(config, params),
        noise,
        cond,
        ts,
        uncond=cond.unconditional() if guidance else None,
        cfg_scale=cfg_scale,
        known=known if has_known else None,
        known_mask=cond.known_mask[..., None] if has_known else None,
        sigma_min=config.sigma_min,
        remat=remat,
    )
    x = from_flow_space(params, config, x, style_vec)
    if has_known:
        # The round trip through flow coordinates is exact only up to rounding: paste the given frames.
        x = jnp.where(cond.known_mask[..., None], known_raw.astype(x.dtype), x)
    return x * mask[..., None].astype(x.dtype)
