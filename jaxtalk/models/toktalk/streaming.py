"""Streaming engine: chunk-by-chunk generation with an explicit carried state and a fixed window.

Each call receives the tokens of one chunk (``chunk_frames`` motion frames) and runs the Euler/CFG
sampler on a FIXED window of ``context_frames + chunk_frames`` frames: the bounded left context
(earlier tokens, padded at the start of the utterance and masked out) followed by the new chunk, with
the block-causal chunk mask. The last ``overlap_frames`` of already emitted output before the chunk
are known frames (inpainted at every step), so the new chunk continues the old one. The starting noise
of absolute frame ``f`` is a fixed function of the stream's key and ``f``
(:func:`~jaxtalk.models.toktalk.noise.frame_noise`), so a frame regenerated as left context sees the
same noise as when it was first generated, and the noise never repeats however long the stream runs.

Because the window never grows, every chunk after the first reuses one compiled program and the
per-chunk cost does not depend on how long the utterance already is (the reference recomputes the
whole prefix for every chunk).

Only the causal model streams (``config.causal``): its decoder's receptive field ends at the last frame
of the current chunk and its token alignment reads no later token, so a chunk generated live is the
computation it was trained on. Source-space tokens (another audio LLM) stream through the causal
adaptation layer first: each chunk's source tokens are resampled to the base rate by time overlap and
adapted against a carried buffer of the last :func:`~jaxtalk.models.toktalk.adapter.receptive_field`
base-rate inputs, with positions continuing across chunks, which gives exactly the offline adapter's
output (:func:`~jaxtalk.models.toktalk.model.adapt_tokens`).
"""

from __future__ import annotations

import functools
from fractions import Fraction
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite, check_temperature
from jaxtalk.audio.framerate import default_num_frames
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.adapter import receptive_field
from jaxtalk.models.toktalk.model import (
    adapter_apply,
    adapter_source_dim,
    check_tokens,
    frames_for_tokens,
    source_to_base_rate,
)
from jaxtalk.models.toktalk.noise import frame_noise
from jaxtalk.models.toktalk.sampling import default_grid, generate_frames, resolve_style
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray

__all__ = [
    "StreamState",
    "AdapterState",
    "init_stream",
    "stream_step",
    "stream",
    "tokens_per_chunk",
    "source_tokens_per_chunk",
    "overlap_window_mask",
    "stream_noise",
    "advance_window",
]

PyTree = Any


class AdapterState(NamedTuple):
    """Carried state of the streaming adaptation layer.

    Attributes:
        inputs: ``(B, R, src_dim)`` the last ``R = receptive_field(config)`` source tokens at the base
            rate (zeros before the utterance).
        valid: ``(B, R)`` True on buffer rows that exist.
        position: ``()`` absolute base-token index of the next chunk's first token.
    """

    inputs: Float[Array, "batch past src"]
    valid: Bool[Array, "batch past"]
    position: Int[Array, ""]


class StreamState(NamedTuple):
    """Carried state of the streaming engine (a pytree; fixed shapes).

    Attributes:
        tokens: ``(B, Wt, speech_dim)`` tokens of the current window (left context + last chunk).
        motion: ``(B, W, param_dim)`` emitted motion in the window (zeros where none yet).
        valid: ``(B, W)`` True on window frames that exist (False: padding before the utterance).
        noise_key: the key of the starting noise (:func:`stream_noise`).
        position: ``()`` absolute index of the first frame of the next chunk.
        step: ``()`` chunks generated so far.
        adapter: the adaptation layer's state when the stream takes source-space tokens, else None.
    """

    tokens: Float[Array, "batch window_tokens token"]
    motion: Float[Array, "batch window param"]
    valid: Bool[Array, "batch window"]
    noise_key: PRNGKeyArray
    position: Int[Array, ""]
    step: Int[Array, ""]
    adapter: AdapterState | None = None


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


def source_tokens_per_chunk(config: TokTalkConfig, src_rate: float | int) -> int:
    """Source tokens at ``src_rate`` that cover one chunk (25 Hz, 10-frame chunks: 10).

    Raises:
        ValueError: when a chunk does not span a whole number of source tokens.
    """
    rate = Fraction(str(float(src_rate))) / config.fps
    return _whole(config.chunk_frames * rate, f"{config.chunk_frames} frames at {src_rate} Hz source tokens")


def overlap_window_mask(config: TokTalkConfig) -> np.ndarray:
    """``(window_frames,)`` True on the window rows inpainted as known frames: the last
    ``overlap_frames`` frames of left context before the new chunk (only where they exist)."""
    frames = np.arange(config.window_frames)
    ctx = config.context_frames
    return (frames >= ctx - config.overlap_frames) & (frames < ctx)


def stream_noise(
    config: TokTalkConfig, key: PRNGKeyArray, frames: int, *, batch: int = 1, first_frame: int = 0,
    dtype: Any = jnp.float32,
) -> Float[Array, "batch frames param"]:
    """The starting noise a stream made with ``init_stream(config, key, batch=batch)`` uses for absolute
    frames ``first_frame .. first_frame + frames - 1``: pass it to ``sample(..., noise=...)`` to
    reproduce a stream offline."""
    return frame_noise(key, first_frame, frames, batch, config.param_dim, config.noise_frames, dtype)


def _require_causal(config: TokTalkConfig) -> None:
    if not config.causal:
        raise ValueError(
            "this TokTalk config is the offline model (causal=False): its decoder's convolutions and "
            "group norm and its token interpolation read frames after the current chunk, which a live "
            "stream does not have yet. Stream a causal model (TokTalkConfig(causal=True), the default) "
            "or use sample() for whole utterances."
        )


def init_stream(
    config: TokTalkConfig,
    key: PRNGKeyArray,
    *,
    batch: int = 1,
    dtype: Any = jnp.float32,
    source_dim: int | None = None,
) -> StreamState:
    """Empty state before the first chunk; ``key`` fixes the starting noise of every frame.

    Args:
        config: model settings (chunk, context and overlap sizes).
        key: PRNG key of the starting noise (:func:`stream_noise`).
        batch: number of parallel streams.
        dtype: floating dtype of the state.
        source_dim: width of source-space tokens to stream through the adaptation layer (None: the
            stream takes base-space tokens).

    Returns:
        :class:`StreamState`.

    Raises:
        ValueError: the offline (non-causal) model, chunk or context frames that do not span whole
            tokens, a non-positive batch or source width.
    """
    _require_causal(config)
    if source_dim is not None and (isinstance(source_dim, bool) or int(source_dim) < 1):
        raise ValueError(f"source_dim must be a positive integer, got {source_dim!r}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    w = config.window_frames
    tokens_per_chunk(config)
    wt = tokens_per_chunk(config, w)
    state = StreamState(
        tokens=jnp.zeros((batch, wt, config.speech_dim), dtype),
        motion=jnp.zeros((batch, w, config.param_dim), dtype),
        valid=jnp.zeros((batch, w), bool),
        noise_key=key,
        position=jnp.zeros((), jnp.int32),
        step=jnp.zeros((), jnp.int32),
        adapter=None if source_dim is None else AdapterState(
            inputs=jnp.zeros((batch, receptive_field(config), int(source_dim)), dtype),
            valid=jnp.zeros((batch, receptive_field(config)), bool),
            position=jnp.zeros((), jnp.int32),
        ),
    )
    # Commit the state to a device like the step's outputs are: an uncommitted first state gives the
    # jitted step a different cache key from every later one, so chunk 2 would compile again.
    return jax.device_put(state, jax.local_devices()[0])  # this process's own: jax.devices()[0] may be another's


def stream_step(
    params: PyTree,
    config: TokTalkConfig,
    state: StreamState,
    chunk_tokens: Float[Array, "batch chunk_tokens token"] | Float[np.ndarray, "batch chunk_tokens token"],
    style: Any,
    *,
    cfg_scale: Float[Array, ""] | float | None = None,
    sample_steps: int | None = None,
    ts: Any = None,
    src_rate: float | int | None = None,
    temperature: Float[Array, ""] | float | None = None,
) -> tuple[StreamState, Float[Array, "batch chunk param"]]:
    """Generates the next chunk of motion from its tokens.

    Args:
        params: model parameters.
        config: model settings.
        state: the carried :class:`StreamState`.
        chunk_tokens: ``(B, tokens_per_chunk, speech_dim)`` base-space tokens of the new chunk, or, for a
            state made with ``source_dim``, ``(B, source_tokens_per_chunk, source_dim)`` source-space
            tokens at ``src_rate`` (adapted on the way in).
        style: ``(B, style_vector_dim)`` style vector or a ``(B, S, param_dim)`` reference clip (encoding a
            clip every chunk costs time: pass the vector).
        cfg_scale: guidance weight w, 0 = none (traced; default ``config.cfg_scale``).
        sample_steps: Euler steps on the cosine grid (default ``config.sample_steps``; static).
        ts: an explicit time grid instead (traced values; its length sets the step count).
        src_rate: the source tokens' rate in Hz (required with a source-token state, static).
        temperature: scale of the starting noise (traced; default ``config.temperature``).

    Returns:
        ``(new_state, motion)`` with ``motion`` ``(B, chunk_frames, param_dim)``.

    Raises:
        ValueError: the offline model; tokens of the wrong width, count or batch; NaN/inf; bad style;
            a source-token state without ``src_rate`` or without an adapter in ``params``.
    """
    _require_causal(config)
    batch = state.motion.shape[0]
    if state.adapter is None:
        if src_rate is not None:
            raise ValueError("src_rate given but the stream takes base tokens: init_stream(..., source_dim=...)")
        ct, width, rate, name = tokens_per_chunk(config), config.speech_dim, config.token_rate, "chunk tokens"
    else:
        if src_rate is None:
            raise ValueError("this stream takes source-space tokens: pass their rate, src_rate=...")
        width, trained = int(state.adapter.inputs.shape[2]), adapter_source_dim(params)
        if trained != width:
            raise ValueError(f"the stream was made for {width}-d source tokens but the adapter in params "
                             f"takes {trained}-d ones")
        ct, rate, name = source_tokens_per_chunk(config, src_rate), src_rate, "source chunk tokens"
        src_rate = float(src_rate)
    shape = tuple(np.shape(chunk_tokens))
    if len(shape) != 3 or shape[0] != batch or shape[1] != ct:
        raise ValueError(
            f"{name} must have shape ({batch}, {ct}, {width}) (one chunk of "
            f"{config.chunk_frames} frames), got {shape}"
        )
    check_tokens(chunk_tokens, width=width, rate=rate, fps=config.fps, num_frames=config.chunk_frames, name=name)
    style_vec = resolve_style(params, config, style, batch)
    ts = jnp.asarray(default_grid(config, sample_steps) if ts is None else ts, state.motion.dtype)
    check_finite(ts, "ts")
    w = jnp.asarray(config.cfg_scale if cfg_scale is None else cfg_scale, state.motion.dtype)
    tau = check_temperature(temperature, state.motion.dtype, default=config.temperature)
    return _stream_step(params, state, jnp.asarray(chunk_tokens, state.tokens.dtype), style_vec, w, tau, ts, config,
                        src_rate)


def _adapter_step(params, config, state: AdapterState, chunk_src, src_rate):
    """One chunk through the causal adapter against the carried buffer (see the module docstring)."""
    base = source_to_base_rate(chunk_src, src_rate, config)
    r, ct = state.inputs.shape[1], base.shape[1]
    window = jnp.concatenate([state.inputs, base], axis=1)
    valid = jnp.concatenate([state.valid, jnp.ones(base.shape[:2], bool)], axis=1)
    positions = state.position - r + jnp.arange(r + ct)
    out = adapter_apply(params, config, window, mask=valid, positions=positions)[:, r:]
    keep = window.shape[1] - r
    return AdapterState(window[:, keep:], valid[:, keep:], state.position + ct), out


def advance_window(
    params: PyTree,
    config: TokTalkConfig,
    tokens: Float[Array, "batch window_tokens token"],
    motion: Float[Array, "batch window param"],
    valid: Bool[Array, "batch window"],
    chunk_tokens: Float[Array, "batch chunk_tokens token"],
    style_vec: Float[Array, "batch vector"],
    noise: Float[Array, "batch window param"],
    cfg_scale: Float[Array, ""],
    ts: Float[Array, " grid"],
) -> tuple[Float[Array, "batch window_tokens token"], Float[Array, "batch window param"], Bool[Array, "batch window"],
           Float[Array, "batch chunk param"]]:
    """One chunk of the streaming engine on explicit arrays (traced, no checks): the window moves on by
    one chunk, the new chunk is sampled from ``noise`` (the starting noise of the moved window's frames,
    already scaled by the temperature) with the overlap inpainted, and is returned with the new window.

    :func:`stream_step` and the portable export (:mod:`jaxtalk.models.toktalk.portable`) both run this.

    Args:
        params, config: the model.
        tokens, motion, valid: the window before the chunk (:class:`StreamState`'s fields).
        chunk_tokens: ``(B, tokens_per_chunk, speech_dim)`` base-space tokens of the new chunk.
        style_vec: ``(B, style_vector_dim)``.
        noise: ``(B, window_frames, param_dim)`` starting noise of the moved window.
        cfg_scale: ``()`` guidance weight w.
        ts: ``(N + 1,)`` time grid.

    Returns:
        ``(tokens, motion, valid, chunk)``: the moved window and the chunk's ``(B, chunk_frames, param_dim)``.
    """
    c, ctx = config.chunk_frames, config.context_frames
    batch = motion.shape[0]
    ct = chunk_tokens.shape[1]
    tokens = jnp.concatenate([tokens[:, ct:], chunk_tokens], axis=1)
    valid = jnp.concatenate([valid[:, c:], jnp.ones((batch, c), bool)], axis=1)
    motion = jnp.concatenate([motion[:, c:], jnp.zeros((batch, c, config.param_dim), motion.dtype)], axis=1)
    known_mask = valid & overlap_window_mask(config)[None, :]
    x = generate_frames(
        params, config, tokens, style_vec, noise, ts, cfg_scale,
        known=motion, known_mask=known_mask, mask=valid, chunked=jnp.ones((), bool),
    )
    out = x[:, ctx:]
    return tokens, jnp.concatenate([motion[:, :ctx], out], axis=1), valid, out


@functools.partial(jax.jit, static_argnames=("config", "src_rate"))
def _stream_step(params, state, chunk_tokens, style_vec, cfg_scale, temperature, ts, config, src_rate):
    adapter = state.adapter
    if adapter is not None:
        adapter, chunk_tokens = _adapter_step(params, config, adapter, chunk_tokens, src_rate)
    batch = state.motion.shape[0]
    noise = temperature * frame_noise(state.noise_key, state.position - config.context_frames, config.window_frames,
                                      batch, config.param_dim, config.noise_frames, state.motion.dtype)
    tokens, motion, valid, out = advance_window(params, config, state.tokens, state.motion, state.valid, chunk_tokens,
                                                style_vec, noise, cfg_scale, ts)
    new_state = StreamState(
        tokens=tokens, motion=motion, valid=valid, noise_key=state.noise_key,
        position=state.position + config.chunk_frames, step=state.step + 1, adapter=adapter,
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
    sample_steps: int | None = None,
    ts: Any = None,
    src_rate: float | int | None = None,
    temperature: Float[Array, ""] | float | None = None,
) -> Float[Array, "batch frames param"]:
    """Runs the streaming engine over a whole token sequence, chunk by chunk (as a live stream would).

    The last chunk is completed by repeating the last token and the output cropped back.

    Args:
        params, config: the model.
        tokens: ``(B, Tt, speech_dim)`` base-space tokens, or with ``src_rate`` ``(B, Ts, src_dim)``
            source-space tokens, adapted chunk by chunk by the streaming adaptation layer.
        style: style vector or reference clip (encoded once).
        key: PRNG key of the starting noise (:func:`stream_noise`).
        cfg_scale, sample_steps, ts, temperature: see :func:`stream_step`.
        src_rate: the rate of source-space ``tokens`` (None: base-space tokens).

    Returns:
        ``(B, T, param_dim)`` with ``T`` the frames the tokens cover (for source tokens, the frames
        their base-rate resampling covers, as offline ``sample(adapt_tokens(...))``).

    Raises:
        ValueError: see :func:`stream_step`.
    """
    _require_causal(config)
    source_dim = None
    if src_rate is None:
        frames = check_tokens(tokens, width=config.speech_dim, rate=config.token_rate, fps=config.fps)
        ct = tokens_per_chunk(config)
    else:
        source_dim = adapter_source_dim(params)
        check_tokens(tokens, width=source_dim, rate=src_rate, fps=config.fps, name="source tokens")
        base = default_num_frames(int(np.shape(tokens)[1]), src_rate, config.token_rate)
        frames = frames_for_tokens(base, config.token_rate, config.fps)
        ct = source_tokens_per_chunk(config, src_rate)
    if isinstance(tokens, jax.core.Tracer):
        xp = jnp
    else:
        # Chunks are cut on the host: slices of a device array queue behind the previous chunk's step,
        # and the next step's input checks would wait for them, so the host could never run ahead
        # of the device (a compile per clip length, too).
        xp, tokens = np, np.asarray(tokens)
        tokens = tokens.astype(jax.dtypes.canonicalize_dtype(tokens.dtype), copy=False)
    batch = tokens.shape[0]
    style_vec = resolve_style(params, config, style, batch)
    num_chunks = -(-tokens.shape[1] // ct)
    pad = num_chunks * ct - tokens.shape[1]
    if pad:
        tokens = xp.concatenate([tokens, xp.repeat(tokens[:, -1:], pad, axis=1)], axis=1)
    state = init_stream(config, key, batch=batch, dtype=tokens.dtype,
                        source_dim=source_dim)
    outs = []
    for i in range(num_chunks):  # one host call per chunk, exactly as chunks would arrive live
        state, out = stream_step(params, config, state, tokens[:, i * ct : (i + 1) * ct], style_vec,
                                 cfg_scale=cfg_scale, sample_steps=sample_steps, ts=ts, src_rate=src_rate,
                                 temperature=temperature)
        outs.append(out)
    return jnp.concatenate(outs, axis=1)[:, :frames]
