"""Turn-by-turn streaming (Sec. 3.5) with a key/value cache of past turns.

The window holds the n previous turns and the current one (``context = n``, e.g. 0, 1, 3, 7; the
window of n + 1 turns must fit ``max_turns``). Past agent motion stays MASKED in the window (the
model's own outputs are never fed back), so a past turn's tokens are fixed once it has arrived.
While the window is not full (turn index t <= n), turn t sits at slot t and, under turn-causal
attention, the keys/values of slots < t cannot depend on it: they are cached per layer in a
fixed-size buffer, and turn t's step encodes only its own 110 tokens against that cache. Once the
window slides (t > n) every past turn moves to a new positional slot, so their keys/values are
rebuilt from the slid window (n turns, turn-causal) and the current turn runs against them as in a
filling turn (a constant n + 1 turns of work per step, minus the past turns' last-layer queries
whose outputs are never read). The bidirectional ablation always recomputes the whole window, and so
does the MAE-style encoder-decoder variant (``architecture="encoder_decoder"``): every turn runs its
encoder and decoder on the window with the unfilled slots hidden. That is exact, and it is the simpler
of the two correct ways: a second key/value cache for the decoder would only save work while the
window fills, since from then on the sliding window moves every past turn to a new positional slot
and a cache would be rebuilt from the n past turns at every step, about the n + 1 turns of work a
recomputation costs.

The state is an explicit pytree. :func:`stream_step` compiles two programs, filling and sliding,
and picks one on the host from the turn counter (under an outer ``jit`` the counter is abstract and
one program with a ``lax.cond`` is used instead). CFG stacks the conditional and the unconditional
window (user tokens -> fake token) along the batch axis; with ``guidance_drop="current_turn"`` (the
public code's choice) the unconditional rows drop the current turn's user tokens only and keep the
conditional rows' past turns.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.encoder import TimarEncoder
from jaxtalk.models.turns.streams import check_streams
from jaxtalk.checks import check_temperature
from jaxtalk.models.timar.sampling import MAR_TEMPERATURE, resolve_sampler, sample_frames, without_guidance
from jaxtalk.models.timar.tokens import turn_layout
from jaxtalk.masks import mask_to_bias
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Float, Int, PRNGKeyArray, Shaped, StreamLike

__all__ = ["StreamState", "init_stream", "stream_condition", "stream_step", "stream"]


class StreamState(NamedTuple):
    """Carried state of the streaming sampler (``S = 2B`` with guidance, else ``B``).

    Attributes:
        tokens: ``(S, n + 1, 4F + 10, width)`` embedded tokens of the window's turns (agent motion
            masked), slot order; unfilled slots are zeros.
        keys, values: per encoder layer, ``(S, n (4F + 10), heads, head_dim)`` cached keys/values
            of slots ``0..n-1`` (valid for slots < turn while the window has not slid; unused where
            the window is recomputed every turn: bidirectional attention, the encoder-decoder variant).
        turn: ``()`` int32, turns processed so far.
        rng: the stream's PRNG key, given once to :func:`init_stream`; turn ``i`` samples with
            ``jax.random.fold_in(rng, i)`` (the key policy of every jaxtalk stream).
    """

    tokens: Float[Array, "streams slots tokens width"]
    keys: tuple[Float[Array, "streams cache heads head_dim"], ...]
    values: tuple[Float[Array, "streams cache heads head_dim"], ...]
    turn: Int[Array, ""]
    rng: PRNGKeyArray


def _check_context(config: TimarConfig, context: int) -> int:
    if isinstance(context, bool) or not isinstance(context, (int, np.integer)) or context < 0:
        raise ValueError(f"context must be a non-negative integer number of turns, got {context!r}")
    if context + 1 > config.max_turns:
        raise ValueError(
            f"context n={context} needs a window of {context + 1} turns but the positional table has "
            f"max_turns={config.max_turns}"
        )
    return int(context)


def init_stream(
    config: TimarConfig, key: PRNGKeyArray, *, batch: int = 1, context: int, guidance: bool = True
) -> StreamState:
    """An empty stream.

    Args:
        config: model config.
        key: the stream's PRNG key (copied into the state, so the caller's key stays usable;
            :func:`stream_step` takes none).
        batch: B conversations streamed together.
        context: n previous turns kept in the window.
        guidance: keep the unconditional branch too (CFG).

    Returns:
        :class:`StreamState` at turn 0.

    Raises:
        ValueError: ``context`` negative or too long for ``max_turns``, ``batch < 1``.
    """
    n = _check_context(config, context)
    if isinstance(batch, bool) or not isinstance(batch, (int, np.integer)) or batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch!r}")
    s = 2 * batch if guidance else batch
    tpt = config.tokens_per_turn
    hd = config.width // config.num_heads
    # One distinct buffer per layer and per keys/values: the step donates (reuses) them in place.
    cache = lambda: jnp.zeros((s, n * tpt, config.num_heads, hd), jnp.float32)  # noqa: E731
    return StreamState(
        tokens=jnp.zeros((s, n + 1, tpt, config.width), jnp.float32),
        keys=tuple(cache() for _ in range(config.num_layers)),
        values=tuple(cache() for _ in range(config.num_layers)),
        turn=jnp.zeros((), jnp.int32),
        # A copy: stream_step donates the state, which must never delete the caller's own key.
        rng=jnp.array(key, copy=True),
    )


def _encoder_call(params: Any, config: TimarConfig, method: str, *args: Any, **kwargs: Any) -> Any:
    apply = compute_in(config.compute_dtype, TimarEncoder(config).apply)
    return apply({"params": params["encoder"]}, *args, method=getattr(TimarEncoder, method), **kwargs)


def _cached(config: TimarConfig) -> bool:
    """Whether past turns' keys/values are cached (turn-causal encoder-only); else the window is recomputed."""
    return config.attention == "turn_causal" and config.architecture == "encoder"


def _mode(config: TimarConfig, state: StreamState) -> str:
    """The branch of this turn, decided on the host when the turn counter is concrete.

    Two programs (filling the window / sliding it) chosen here run faster than one program with a
    ``lax.cond`` between them (XLA:CPU runs a conditional's branches as separate, less optimised
    computations); under an outer trace the counter is abstract and the ``lax.cond`` remains.
    """
    n = state.tokens.shape[1] - 1
    if not _cached(config) or n == 0 or isinstance(state.turn, jax.core.Tracer):
        return "auto"
    return "cached" if int(state.turn) <= n else "sliding"


def _condition(params, config, state, us, um, as_, guidance, mode="auto"):
    n = state.tokens.shape[1] - 1
    tpt = config.tokens_per_turn
    b = us.shape[0]
    add_turn = lambda x: x[:, None]  # noqa: E731  (B, F, D) -> (B, 1, F, D)
    us, um, as_ = add_turn(us), add_turn(um), add_turn(as_)
    drop = None
    if guidance:
        two = lambda x: jnp.concatenate([x, x], axis=0)  # noqa: E731
        us, um, as_ = two(us), two(um), two(as_)
        drop = jnp.concatenate([jnp.zeros((b,), bool), jnp.ones((b,), bool)])
    tok = _encoder_call(params, config, "embed", us, um, as_, None, None, drop)  # (S, 1, tpt, w)
    # What later turns see of this one: with guidance_drop="current_turn" the unconditional rows keep
    # the REAL user tokens of past turns (only the current turn's are dropped), so they store, and
    # cache the keys/values of, the conditional rows' tokens.
    per_turn = guidance and config.guidance_drop == "current_turn"
    keep_rows = (lambda x: jnp.concatenate([x[:b], x[:b]], axis=0)) if per_turn else (lambda x: x)  # noqa: E731
    tok_kept = keep_rows(tok)
    t = state.turn
    slot = jnp.minimum(t, n)
    written = jax.lax.dynamic_update_slice_in_dim(state.tokens, tok_kept, slot, axis=1)
    shifted = jnp.concatenate([state.tokens[:, 1:], tok_kept], axis=1)
    causal = config.attention == "turn_causal"
    layout = turn_layout(config.frames_per_turn)

    if not _cached(config) or n == 0:
        # Bidirectional: past turns attend to the current one, nothing can be cached; encoder-decoder:
        # recomputed (see the module docstring); n = 0: the window is the current turn alone.
        tokens = jnp.where(t > n, shifted, written)
        # The pass itself sees this turn's own tokens (the fake user tokens on unconditional rows).
        current = jax.lax.dynamic_update_slice_in_dim(tokens, tok, slot, axis=1) if per_turn else tokens
        static_mask = jnp.asarray(layout.attention_mask(n + 1, causal=causal))
        key_slot = jnp.asarray(np.repeat(np.arange(n + 1), tpt))
        visible = static_mask & (key_slot <= slot)[None, :]
        # Every agent frame is masked at inference, past ones included (outputs are never fed back).
        masked = jnp.ones(tokens.shape[:2] + (config.frames_per_turn,), bool)
        z = _encoder_call(params, config, "fuse", current, masked, visible)
        z = jax.lax.dynamic_index_in_dim(z, slot, axis=1, keepdims=False)
        return StreamState(tokens, state.keys, state.values, t + 1, state.rng), z

    def rebuild(_: Any) -> tuple[Any, Any]:
        # The window slid: every past turn moved to a new slot (new positional embedding), so their
        # keys/values are recomputed, turn-causally, from the n past turns now at slots 0..n-1. The
        # current turn then runs against them exactly as in a filling turn: only ITS queries pass
        # through the last layer (a full-window pass would also push the n past turns' queries
        # through it, for outputs nobody reads).
        past_mask = jnp.asarray(layout.attention_mask(n, causal=True))
        _, kvs = _encoder_call(params, config, "encode", shifted[:, :n], 0, mask_to_bias(past_mask), None, True)
        return tuple(k for k, _ in kvs), tuple(v for _, v in kvs)

    def keep(_: Any) -> tuple[Any, Any]:
        return state.keys, state.values

    if mode == "auto":
        tokens = jnp.where(t > n, shifted, written)
        keys, values = jax.lax.cond(t > n, rebuild, keep, None)
    elif mode == "sliding":
        tokens, (keys, values) = shifted, rebuild(None)
    else:
        tokens, (keys, values) = written, keep(None)

    cache_slot = jnp.asarray(np.repeat(np.arange(n), tpt))
    visible = jnp.concatenate([cache_slot < slot, jnp.ones((tpt,), bool)])
    feats, kvs = _encoder_call(
        params, config, "encode", tok, slot, mask_to_bias(visible)[None, :], tuple(zip(keys, values)), True
    )
    z = _encoder_call(params, config, "head_condition", feats, slot)[:, 0]
    # While filling (t < n) the newest turn's keys/values go to its slot. From t == n on, the cache is
    # never read again (later turns rebuild it from the slid window), so it is left as is.
    fill = t < n
    new_k = tuple(
        jnp.where(fill, jax.lax.dynamic_update_slice_in_dim(k_old, keep_rows(k_all[:, n * tpt:]), t * tpt, axis=1), k_old)
        for k_old, (k_all, _) in zip(state.keys, kvs)
    )
    new_v = tuple(
        jnp.where(fill, jax.lax.dynamic_update_slice_in_dim(v_old, keep_rows(v_all[:, n * tpt:]), t * tpt, axis=1), v_old)
        for v_old, (_, v_all) in zip(state.values, kvs)
    )
    return StreamState(tokens, new_k, new_v, t + 1, state.rng), z


@functools.partial(jax.jit, static_argnames=("config", "guidance", "mode"))
def _condition_jit(params, config, state, us, um, as_, guidance, mode):
    return _condition(params, config, state, us, um, as_, guidance, mode)


def _check_turn(config: TimarConfig, state: StreamState, us: Any, um: Any, as_: Any, guidance: bool) -> None:
    f = config.frames_per_turn
    for name, x in (("user_speech", us), ("user_motion", um), ("agent_speech", as_)):
        if np.ndim(x) != 3 or np.shape(x)[1] != f:
            raise ValueError(f"{name} of one turn must be (batch, {f}, dim), got shape {np.shape(x)}")
    check_streams(config, {"user_speech": us, "user_motion": um, "agent_speech": as_})
    s = state.tokens.shape[0]
    b = s // 2 if guidance else s
    if np.shape(us)[0] != b or (guidance and s % 2):
        raise ValueError(
            f"turn batch {np.shape(us)[0]} does not match the stream state (batch {b}, guidance={guidance}); "
            "create the state with init_stream(config, key, batch=..., context=..., guidance=...)"
        )


def stream_condition(
    params: dict[str, Any],
    config: TimarConfig,
    state: StreamState,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    *,
    guidance: bool = True,
) -> tuple[StreamState, Float[Array, "streams frames width"]]:
    """Push one turn into the stream and return its head conditions (no sampling).

    Args:
        params: model parameters.
        config: model config.
        state: current :class:`StreamState`.
        user_speech, agent_speech: ``(B, F, speech_dim)`` this turn's speech features.
        user_motion: ``(B, F, 56)`` this turn's user motion.
        guidance: must match the state (``init_stream(..., guidance=)``).

    Returns:
        ``(new_state, z)`` with ``z: (S, F, width)``: conditional rows first, then (with
        guidance) the unconditional rows.

    Raises:
        ValueError: a turn of the wrong length, mismatched streams, NaN, or a batch that does not
            match the state.
    """
    _check_turn(config, state, user_speech, user_motion, agent_speech, guidance)
    return _condition_jit(
        params, config, state, jnp.asarray(user_speech, jnp.float32), jnp.asarray(user_motion, jnp.float32),
        jnp.asarray(agent_speech, jnp.float32), bool(guidance), _mode(config, state),
    )


@functools.partial(
    jax.jit, static_argnames=("config", "sample_steps", "sampler", "guidance", "mode"), donate_argnums=(2,)
)
def _step(params, config, state, us, um, as_, cfg_scale, eta, temperature, sample_steps, sampler, guidance, mode,
          initial_noise=None, step_noise=None):
    key = jax.random.fold_in(state.rng, state.turn)  # before _condition advances the turn
    state, z = _condition(params, config, state, us, um, as_, guidance, mode)
    b = us.shape[0]
    z_c, z_u = (z[:b], z[b:]) if guidance else (z, None)
    x = sample_frames(params, config, z_c, z_u, key, cfg_scale=cfg_scale, sample_steps=sample_steps, sampler=sampler, eta=eta,
                      temperature=temperature, initial_noise=initial_noise, step_noise=step_noise)
    return state, x


def stream_step(
    params: dict[str, Any],
    config: TimarConfig,
    state: StreamState,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    *,
    cfg_scale: Shaped[Array, "..."] | float | None = None,
    sample_steps: int | None = None,
    sampler: str | None = None,
    eta: Float[Array, ""] | float = 0.0,
    temperature: Shaped[Array, "..."] | float | None = None,
    guidance: bool = True,
    initial_noise: StreamLike | None = None,
    step_noise: StreamLike | None = None,
) -> tuple[StreamState, Float[Array, "batch frames param_dim"]]:
    """One streaming turn: encode it against the window, sample the agent's motion for it.

    The state is donated (its buffers are reused): do not use ``state`` after the call.

    Args:
        params: model parameters.
        config: model config.
        state: current :class:`StreamState`.
        user_speech, agent_speech: ``(B, F, speech_dim)`` this turn's speech features.
        user_motion: ``(B, F, 56)`` this turn's user motion.
        cfg_scale: ``()`` guidance weight w, 0 = none (traced; default ``config.cfg_scale``).
        sample_steps: respaced diffusion steps (static; default ``config.sample_steps``).
        sampler: ``"ddpm"``, ``"ddim"`` or ``"mean"``; None: the config's (see
            :func:`~jaxtalk.models.timar.sampling.sample_frames`).
        eta: DDIM stochasticity (traced).
        temperature: MAR's sampling temperature (traced; see :func:`~jaxtalk.models.timar.sampling.sample_frames`;
            None: MAR's default, :data:`~jaxtalk.models.timar.sampling.MAR_TEMPERATURE`).
        guidance: must match the state.
        initial_noise, step_noise: explicit standard normal draws instead of the turn's key (see
            :func:`~jaxtalk.models.timar.sampling.sample_frames`; for reproducing another
            implementation's random stream).

    Returns:
        ``(new_state, motion)`` with ``motion: (B, F, 56)``.

    Raises:
        ValueError: as :func:`stream_condition`, plus an unknown sampler or bad step count.
    """
    _check_turn(config, state, user_speech, user_motion, agent_speech, guidance)
    sampler = resolve_sampler(config, sampler)
    sample_steps = config.sample_steps if sample_steps is None else sample_steps
    if isinstance(sample_steps, bool) or not isinstance(sample_steps, int) or not 1 <= sample_steps <= config.num_timesteps:
        raise ValueError(f"sample_steps must be an integer in [1, {config.num_timesteps}], got {sample_steps!r}")
    cfg = jnp.asarray(config.cfg_scale if cfg_scale is None else cfg_scale, jnp.float32)
    if cfg.ndim:
        raise ValueError(f"cfg_scale must be a scalar, got shape {cfg.shape}")
    return _step(
        params, config, state, jnp.asarray(user_speech, jnp.float32), jnp.asarray(user_motion, jnp.float32),
        jnp.asarray(agent_speech, jnp.float32), cfg, jnp.asarray(eta, jnp.float32),
        check_temperature(temperature, default=MAR_TEMPERATURE),
        sample_steps, sampler,
        bool(guidance), _mode(config, state),
        None if initial_noise is None else jnp.asarray(initial_noise, jnp.float32),
        None if step_noise is None else jnp.asarray(step_noise, jnp.float32),
    )


def stream(
    params: dict[str, Any],
    config: TimarConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    key: PRNGKeyArray,
    *,
    context: int,
    cfg_scale: Shaped[Array, "..."] | float | None = None,
    sample_steps: int | None = None,
    sampler: str | None = None,
    temperature: Shaped[Array, "..."] | float | None = None,
    guidance: bool = True,
) -> Float[Array, "batch frames param_dim"]:
    """Stream whole conversations turn by turn (any number of turns; the window slides).

    Turn ``i`` uses key ``jax.random.fold_in(key, i)``. This is the host driver of
    :func:`stream_step` (one dispatch per turn, as a live stream would be).

    Args:
        params: model parameters.
        config: model config.
        user_speech, agent_speech: ``(B, N F, speech_dim)``.
        user_motion: ``(B, N F, 56)``.
        key: PRNG key.
        context: n previous turns in the window.
        cfg_scale, sample_steps, sampler, temperature, guidance: see :func:`stream_step`.

    Returns:
        ``(B, N F, 56)`` agent motion.

    Raises:
        ValueError: bad streams or context.
    """
    turns = check_streams(config, {"user_speech": user_speech, "user_motion": user_motion, "agent_speech": agent_speech})
    f = config.frames_per_turn
    # A concrete weight of 0 needs no unconditional rows (as in sample); stream_step cannot decide
    # that itself, since its state was made with or without them.
    guidance = guidance and not without_guidance(config.cfg_scale if cfg_scale is None else cfg_scale)
    state = init_stream(config, key, batch=int(np.shape(user_speech)[0]), context=context, guidance=guidance)
    out = []
    for i in range(turns):  # host loop: one turn arrives at a time in a stream
        sl = slice(i * f, (i + 1) * f)
        state, x = stream_step(
            params, config, state, user_speech[:, sl], user_motion[:, sl], agent_speech[:, sl], cfg_scale=cfg_scale,
            sample_steps=sample_steps, sampler=sampler, temperature=temperature, guidance=guidance,
        )
        out.append(x)
    return jnp.concatenate(out, axis=1)
