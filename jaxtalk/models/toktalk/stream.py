"""Streaming engine: chunk-by-chunk generation with an explicit carried state and a fixed window.

Each call receives the tokens of one chunk (``chunk_frames`` motion frames) and runs the Euler/CFG
sampler on a FIXED window of ``context_frames + chunk_frames`` frames: the bounded left context
(earlier tokens, padded at the start of the utterance and masked out) followed by the new chunk, with
the block-causal chunk mask. The last ``overlap_frames`` of already emitted output before the chunk
are known frames (inpainted at every step), so the new chunk continues the old one. The starting noise
of absolute frame ``f`` is ``buffer[f mod N]`` from a fixed buffer drawn once, so a frame regenerated
as left context sees the same noise as when it was first generated.

Because the window never grows, every chunk after the first reuses one compiled program and the
per-chunk cost does not depend on how long the utterance already is (the reference recomputes the
whole prefix for every chunk).
"""

from __future__ import annotations

import functools
from fractions import Fraction
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.model import check_finite, check_tokens
from jaxtalk.models.toktalk.sample import default_grid, generate_frames, resolve_style
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray

__all__ = ["StreamState", "init_stream", "stream_step", "stream", "tokens_per_chunk"]

PyTree = Any


class StreamState(NamedTuple):
    """Carried state of the streaming engine (a pytree; fixed shapes).

    Attributes:
        tokens: ``(B, Wt, token_dim)`` tokens of the current window (left context + last chunk).
        motion: ``(B, W, param_dim)`` emitted motion in the window (zeros where none yet).
        valid: ``(B, W)`` True on window frames that exist (False: padding before the utterance).
        noise: ``(B, N, param_dim)`` the fixed noise buffer; frame ``f`` uses row ``f mod N``.
        position: ``()`` absolute index of the first frame of the next chunk.
        step: ``()`` chunks generated so far.
    """

    tokens: Float[Array, "batch window_tokens token"]
    motion: Float[Array, "batch window param"]
    valid: Bool[Array, "batch window"]
    noise: Float[Array, "batch buffer param"]
    position: Int[Array, ""]
    step: Int[Array, ""]


def _whole(value: Fraction, what: str) -> int:
    if value.denominator != 1:
        raise ValueError(f"{what} is {float(value):g}, not a whole number of tokens")
    return int(value)


def tokens_per_chunk(config: TokTalkConfig, frames: int | None = None) -> int:
    """Tokens that cover ``frames`` (default ``chunk_frames``) motion frames at the base rate.

    Raises:
        ValueError: when the frames do not span a whole number of tokens (e.g. 5 frames at 12.5 Hz).
    """
    frames = config.chunk_frames if frames is None else frames
    rate = Fraction(str(float(config.token_rate))) / config.fps
    return _whole(frames * rate, f"{frames} frames at {config.token_rate} Hz tokens and {config.fps} fps")


def init_stream(
    config: TokTalkConfig,
    key: PRNGKeyArray,
    *,
    batch: int = 1,
    buffer_frames: int = 1000,
    dtype: Any = jnp.float32,
) -> StreamState:
    """Empty state before the first chunk, with the noise buffer drawn from ``key``.

    Args:
        config: model settings (chunk, context and overlap sizes).
        key: PRNG key of the noise buffer.
        batch: number of parallel streams.
        buffer_frames: rows of the noise buffer (reused cyclically; >= the window).
        dtype: floating dtype of the state.

    Returns:
        :class:`StreamState`.

    Raises:
        ValueError: chunk or context frames that do not span whole tokens, a buffer shorter than
            the window, a non-positive batch.
    """
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    w = config.window_frames
    if buffer_frames < w:
        raise ValueError(f"buffer_frames={buffer_frames} must be at least the window ({w} frames)")
    tokens_per_chunk(config)
    wt = tokens_per_chunk(config, w)
    state = StreamState(
        tokens=jnp.zeros((batch, wt, config.token_dim), dtype),
        motion=jnp.zeros((batch, w, config.param_dim), dtype),
        valid=jnp.zeros((batch, w), bool),
        noise=jax.random.normal(key, (batch, buffer_frames, config.param_dim), dtype),
        position=jnp.zeros((), jnp.int32),
        step=jnp.zeros((), jnp.int32),
    )
    # Commit the state to a device like the step's outputs are: an uncommitted first state gives the
    # jitted step a different cache key from every later one, so chunk 2 would compile again.
    return jax.device_put(state, jax.devices()[0])


def stream_step(
    params: PyTree,
    config: TokTalkConfig,
    state: StreamState,
    chunk_tokens: Float[Array, "batch chunk_tokens token"] | Float[np.ndarray, "batch chunk_tokens token"],
    style: Any,
    *,
    cfg_scale: Float[Array, ""] | float | None = None,
    ts: Any = None,
) -> tuple[StreamState, Float[Array, "batch chunk param"]]:
    """Generates the next chunk of motion from its tokens.

    Args:
        params: model parameters.
        config: model settings.
        state: the carried :class:`StreamState`.
        chunk_tokens: ``(B, tokens_per_chunk, token_dim)`` base-space tokens of the new chunk.
        style: ``(B, style_vector_dim)`` style vector or a ``(B, S, param_dim)`` reference clip (encoding a
            clip every chunk costs time: pass the vector).
        cfg_scale: guidance weight (traced; default ``config.cfg_scale``).
        ts: time grid (traced values; its length sets the step count; default the cosine grid).

    Returns:
        ``(new_state, motion)`` with ``motion`` ``(B, chunk_frames, param_dim)``.

    Raises:
        ValueError: tokens of the wrong width, count or batch; NaN/inf; bad style.
    """
    batch = state.motion.shape[0]
    ct = tokens_per_chunk(config)
    shape = tuple(np.shape(chunk_tokens))
    if len(shape) != 3 or shape[0] != batch or shape[1] != ct:
        raise ValueError(
            f"chunk_tokens must have shape ({batch}, {ct}, {config.token_dim}) (one chunk of "
            f"{config.chunk_frames} frames), got {shape}"
        )
    check_tokens(chunk_tokens, width=config.token_dim, rate=config.token_rate, fps=config.fps,
                 num_frames=config.chunk_frames, name="chunk tokens")
    style_vec = resolve_style(params, config, style, batch)
    ts = jnp.asarray(default_grid(config) if ts is None else ts, state.motion.dtype)
    check_finite("ts", ts)
    w = jnp.asarray(config.cfg_scale if cfg_scale is None else cfg_scale, state.motion.dtype)
    return _stream_step(params, state, jnp.asarray(chunk_tokens, state.tokens.dtype), style_vec, w, ts, config)


@functools.partial(jax.jit, static_argnames=("config",))
def _stream_step(params, state, chunk_tokens, style_vec, cfg_scale, ts, config):
    c, ctx = config.chunk_frames, config.context_frames
    w = config.window_frames
    batch = state.motion.shape[0]
    ct = chunk_tokens.shape[1]
    tokens = jnp.concatenate([state.tokens[:, ct:], chunk_tokens], axis=1)
    valid = jnp.concatenate([state.valid[:, c:], jnp.ones((batch, c), bool)], axis=1)
    motion = jnp.concatenate([state.motion[:, c:], jnp.zeros((batch, c, config.param_dim), state.motion.dtype)], axis=1)
    frames = jnp.arange(w)
    overlap = (frames >= ctx - config.overlap_frames) & (frames < ctx)
    known_mask = valid & overlap[None, :]
    n = state.noise.shape[1]
    rows = jnp.mod(state.position - ctx + frames, n)
    noise = jnp.take(state.noise, rows, axis=1)
    x = generate_frames(
        params, config, tokens, style_vec, noise, ts, cfg_scale,
        known=motion, known_mask=known_mask, mask=valid, chunked=jnp.ones((), bool),
    )
    out = x[:, ctx:]
    motion = jnp.concatenate([motion[:, :ctx], out], axis=1)
    new_state = StreamState(
        tokens=tokens, motion=motion, valid=valid, noise=state.noise,
        position=state.position + c, step=state.step + 1,
    )
    return new_state, out


def stream(
    params: PyTree,
    config: TokTalkConfig,
    tokens: Float[Array, "batch tokens token"] | Float[np.ndarray, "batch tokens token"],
    style: Any,
    key: PRNGKeyArray,
    *,
    cfg_scale: Float[Array, ""] | float | None = None,
    ts: Any = None,
    buffer_frames: int = 1000,
) -> Float[Array, "batch frames param"]:
    """Runs the streaming engine over a whole token sequence, chunk by chunk (as a live stream would).

    The last chunk is completed by repeating the last token and the output cropped back.

    Args:
        params, config: the model.
        tokens: ``(B, Tt, token_dim)`` base-space tokens.
        style: style vector or reference clip (encoded once).
        key: PRNG key of the noise buffer.
        cfg_scale, ts: see :func:`stream_step`.
        buffer_frames: noise buffer rows.

    Returns:
        ``(B, T, param_dim)`` with ``T`` the frames the tokens cover.

    Raises:
        ValueError: see :func:`stream_step`.
    """
    frames = check_tokens(tokens, width=config.token_dim, rate=config.token_rate, fps=config.fps)
    tokens = jnp.asarray(tokens)
    batch = tokens.shape[0]
    style_vec = resolve_style(params, config, style, batch)
    ct = tokens_per_chunk(config)
    num_chunks = -(-tokens.shape[1] // ct)
    pad = num_chunks * ct - tokens.shape[1]
    if pad:
        tokens = jnp.concatenate([tokens, jnp.repeat(tokens[:, -1:], pad, axis=1)], axis=1)
    state = init_stream(config, key, batch=batch, buffer_frames=buffer_frames, dtype=tokens.dtype)
    outs = []
    for i in range(num_chunks):  # one host call per chunk, exactly as chunks would arrive live
        state, out = stream_step(params, config, state, tokens[:, i * ct : (i + 1) * ct], style_vec,
                                 cfg_scale=cfg_scale, ts=ts)
        outs.append(out)
    return jnp.concatenate(outs, axis=1)[:, :frames]
