"""TIMAR sampling: respaced DDIM/DDPM of every agent frame with the per-frame head, and CFG.

The encoder runs once (conditional and unconditional windows stacked as one batch); the diffusion
head then denoises all frames in parallel with :func:`jaxtalk.samplers.sample_ddim` /
:func:`~jaxtalk.samplers.sample_ddpm` (x0-prediction, ``sample_steps`` respaced steps of the 1000-step
schedule). Everything in the head that does not see the noisy frame is hoisted out of the step loop:
``Dense(z)`` once per frame and, since the respaced timesteps are known before the loop, every
adaLN modulation of every (step, frame) pair in one batched matmul per layer (2/3 of the head's
FLOPs, run on ``steps x frames`` rows instead of inside the loop on ``frames`` rows); the loop then
only runs the input projection, the K residual MLPs and the output layer on both CFG branches
stacked as one batch. Guidance follows the paper's Eq. (9): ``out_u + omega (out_c - out_u)``, i.e. the shared
sampler's ``w = omega - 1``; ``omega`` is a traced array, so a sweep over scales is a ``vmap`` of
:func:`sample` (the encoder, which does not depend on the scale, is not repeated) and never
recompiles.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.models.timar.config import SAMPLERS, TimarConfig
from jaxtalk.models.timar.head import (
    apply_head,
    apply_head_hoisted,
    apply_head_modulated,
    head_condition,
    head_modulations,
    time_embedding,
)
from jaxtalk.checks import check_temperature
from jaxtalk.models.turns.streams import check_streams, from_turns, to_turns
from jaxtalk.models.timar.model import encode_window
from jaxtalk.samplers import make_schedule, respace, sample_ddim, sample_ddpm
from jaxtalk.samplers.schedules import RespacedSchedule
from jaxtalk.types import Array, Float, PRNGKeyArray, Shaped, StreamLike

__all__ = [
    "without_guidance",
    "SAMPLERS",
    "MODULATION_TABLE_BYTES",
    "MAR_TEMPERATURE",
    "respaced_schedule",
    "resolve_sampler",
    "conditions",
    "sample_frames",
    "sample",
    "posterior_mean",
]

# Largest precomputed modulation table (bytes) before the sampler falls back to computing the
# modulations inside its loop: 100 steps x 2 x 25 frames of the 1024-wide paper head is 225 MB.
MODULATION_TABLE_BYTES = 512 * 2**20

# The sampling temperature when none is given: MAR's (and TIMAR's public evaluation's) 1, the
# trained noise scale. It is not a config field because the paper never sets another.
MAR_TEMPERATURE = 1.0


@functools.lru_cache(maxsize=32)
def respaced_schedule(schedule: str, num_timesteps: int, sample_steps: int) -> RespacedSchedule:
    """The float64 respaced tables (cached: built once per step count).

    Args:
        schedule: ``"cosine"`` or ``"linear"``.
        num_timesteps: training steps T.
        sample_steps: sampling steps N (1 <= N <= T).

    Returns:
        :class:`~jaxtalk.samplers.schedules.RespacedSchedule`.
    """
    return respace(make_schedule(schedule, num_timesteps), sample_steps)


@functools.lru_cache(maxsize=16)
def _head_fn(config: TimarConfig) -> Any:
    # One function object per config, so the samplers' jit cache is hit on every call.
    def head_fn(head_params: Any, x: Array, t: Array, cond: dict[str, Array]) -> Array:
        # cond["cz"] = Dense(z) was computed once before the loop (it does not depend on the step).
        return apply_head_hoisted(head_params, config, cond["cz"], x, t)

    return head_fn


@functools.lru_cache(maxsize=16)
def _modulated_head_fn(config: TimarConfig) -> Any:
    def head_fn(head_params: Any, step_times: Array, table: tuple[Array, ...], x: Array, t: Array,
                cond: dict[str, Array]) -> Array:
        # The sampler passes this step's ORIGINAL timestep, shared by every row: it selects the
        # step's slab of the precomputed table (exact: t is one of step_times). The table's rows
        # are ordered as guided_apply stacks its batch (conditional rows, then unconditional), so
        # ``cond`` itself is not needed here.
        j = jnp.argmin(jnp.abs(step_times - t[0]))
        return apply_head_modulated(head_params, config, x, tuple(m[j] for m in table))

    return head_fn


def _modulation_table(config, head_params, cz, step_times):
    """Modulations ``(N, R, *F, ...)`` of every step (timestep embedding + Dense(z), then each layer)."""
    temb = time_embedding(head_params, config, step_times)  # (N, W)
    c = cz[None] + temb.reshape(temb.shape[:1] + (1,) * (cz.ndim - 1) + temb.shape[1:])
    return head_modulations(head_params, config, c)


def conditions(
    params: dict[str, Any],
    config: TimarConfig,
    user_speech: Float[Array, "batch turns frames speech_dim"],
    user_motion: Float[Array, "batch turns frames param_dim"],
    agent_speech: Float[Array, "batch turns frames speech_dim"],
    *,
    guidance: bool = True,
) -> tuple[Float[Array, "batch turns frames width"], Float[Array, "batch turns frames width"] | None]:
    """Conditional (and unconditional) head conditions of a window, all agent frames masked.

    Args:
        params: model parameters.
        config: model config.
        user_speech, user_motion, agent_speech: ``(B, N, F, ...)`` turn-split streams.
        guidance: also compute the unconditional features (user tokens -> fake token: of the whole
            window, or with ``config.guidance_drop == "current_turn"`` of each frame's own turn only).

    Returns:
        ``(z_cond, z_uncond)``, each ``(B, N, F, width)``; ``z_uncond`` is None without guidance.
    """
    b, n = user_speech.shape[:2]
    if not guidance:
        return encode_window(params, config, user_speech, user_motion, agent_speech), None
    if config.guidance_drop == "current_turn" and n > 1:
        # Turn t's unconditional condition drops turn t's user tokens only (earlier turns keep theirs,
        # as a stream does): one window copy per turn t with that turn dropped, after the conditional
        # copy; copy t's turn-t features are kept.
        copies = lambda x: jnp.broadcast_to(x[None], (n + 1,) + x.shape).reshape((n + 1) * b, *x.shape[1:])  # noqa: E731
        drop = jnp.concatenate([jnp.zeros((1, n), bool), jnp.eye(n, dtype=bool)])  # (n + 1, n)
        drop = jnp.broadcast_to(drop[:, None], (n + 1, b, n)).reshape((n + 1) * b, n)
        z = encode_window(params, config, copies(user_speech), copies(user_motion), copies(agent_speech), None, None, drop)
        z = z.reshape((n + 1, b) + z.shape[1:])
        turns = jnp.arange(n)
        z_u = jnp.moveaxis(z[1 + turns, :, turns], 0, 1)  # (n, b, F, w) -> (b, n, F, w)
        return z[0], z_u
    two = lambda x: jnp.concatenate([x, x], axis=0)  # noqa: E731
    drop = jnp.concatenate([jnp.zeros((b,), bool), jnp.ones((b,), bool)])
    z = encode_window(params, config, two(user_speech), two(user_motion), two(agent_speech), None, None, drop)
    return z[:b], z[b:]


def sample_frames(
    params: dict[str, Any],
    config: TimarConfig,
    z_cond: Float[Array, "batch *frames width"],
    z_uncond: Float[Array, "batch *frames width"] | None,
    key: PRNGKeyArray,
    *,
    cfg_scale: Float[Array, ""] | float,
    sample_steps: int,
    sampler: str | None = None,
    eta: Float[Array, ""] | float = 0.0,
    temperature: Float[Array, ""] | float = 1.0,
    precompute: bool | None = None,
    # Loose annotations (Array or NumPy): the shape checks below raise a ValueError that names the problem.
    initial_noise: StreamLike | None = None,
    step_noise: StreamLike | None = None,
) -> Float[Array, "batch *frames param_dim"]:
    """Sample every frame's head parameters from its condition (jit-able building block).

    Args:
        params: model parameters.
        config: model config.
        z_cond: ``(B, *F, width)`` head conditions.
        z_uncond: unconditional conditions of the same shape, or None (no guidance).
        key: PRNG key (initial noise and, for DDPM / eta > 0, the step noise).
        cfg_scale: ``()`` the guidance weight w of :func:`jaxtalk.samplers.flow.guided_apply` (traced; the
            paper's omega is ``1 + w``); ignored without ``z_uncond``.
        sample_steps: respaced steps (static).
        sampler: ``"ddpm"``, ``"ddim"`` or ``"mean"`` (static; None: ``config.sampler``). ``"ddpm"``
            takes MAR's ancestral steps over the respaced schedule, with the learned variance when
            the config learns it (else the clipped posterior variance). ``"mean"`` evaluates the head once, at
            the last training timestep on the initial noise (which carries no information about
            x0 there), with guidance: the (guided) posterior mean ``E[x0 | condition]``, the point
            estimate for MSE-type scores (as :func:`posterior_mean`). A deterministic DDIM
            trajectory (temperature 0) is NOT that: after its first step it denoises the mean
            towards the training data, e.g. towards a training speaker's resting face.
        eta: ``()`` DDIM stochasticity (traced).
        temperature: ``()`` MAR's sampling temperature (traced). DDPM: the factor on every step's
            noise, as MAR's ``p_sample``; x_T stays standard normal. DDIM: the scale of x_T, its
            only randomness when ``eta = 0`` (the ``eta`` noise is not scaled). 1 samples the
            learned distribution in both; 0 gives DDPM's noise-free chain from a random x_T and
            DDIM's deterministic trajectory from x_T = 0.
        precompute: compute every step's adaLN modulations before the loop (static; None: when
            the table fits in :data:`MODULATION_TABLE_BYTES`). Both ways give the same samples up
            to float32 summation order.
        initial_noise: the standard normal x_T draw ``(B, *F, 56)`` to use instead of drawing it
            from ``key`` (temperature applies as to a drawn one).
        step_noise: ``(sample_steps, B, *F, 56)`` the standard normal draws of the DDPM steps in
            sampling order (noisiest first), used instead of drawing them from ``key``
            (``"ddpm"`` only). With both, the sampler is a deterministic function of the noises:
            this is the hook that reproduces another implementation's random stream (the public
            code's torch draws; ``experiments/timar_reference_parity.py``).

    Returns:
        ``(B, *F, 56)`` samples (the MLP head's prediction for the ``"mlp"`` ablation).

    Raises:
        ValueError: explicit noises of the wrong shape, or ``step_noise`` with a sampler other
            than ``"ddpm"``.
    """
    sampler = resolve_sampler(config, sampler)
    w = jnp.asarray(cfg_scale, jnp.float32)
    tau = jnp.asarray(temperature, jnp.float32)
    hp = params["head"]
    if config.head == "mlp":
        return _guided(lambda z: apply_head(hp, config, z), z_cond, z_uncond, w)
    k_noise, k_steps = jax.random.split(key)
    shape = z_cond.shape[:-1] + (config.param_dim,)
    if initial_noise is None:
        noise = jax.random.normal(k_noise, shape, jnp.float32)
    else:
        noise = jnp.asarray(initial_noise, jnp.float32)
        if noise.shape != shape:
            raise ValueError(f"initial_noise must have shape {shape}, got {noise.shape}")
    if step_noise is not None:
        if sampler != "ddpm":
            raise ValueError(f"step_noise is only used by the 'ddpm' sampler, got sampler {sampler!r}")
        step_noise = jnp.asarray(step_noise, jnp.float32)
        if step_noise.shape != (sample_steps,) + shape:
            raise ValueError(f"step_noise must have shape {(sample_steps,) + shape} (steps, *frames), got {step_noise.shape}")
    if sampler != "ddpm":
        noise = noise * tau
    if sampler == "mean":
        return _guided(lambda z: _head_at_last_timestep(config, hp, z, noise), z_cond, z_uncond, w)
    schedule = respaced_schedule(config.schedule, config.num_timesteps, sample_steps)
    # Hoisted out of the step loop: the head's projection of the condition (both CFG branches).
    cz = head_condition(hp, config, z_cond)
    cz_u = None if z_uncond is None else head_condition(hp, config, z_uncond)
    rows = cz if cz_u is None else jnp.concatenate([cz, cz_u], axis=0)  # guided_apply's batch order
    table_bytes = sample_steps * rows.size * (3 * config.head_blocks + 2) * rows.dtype.itemsize
    if precompute is None:
        precompute = table_bytes <= MODULATION_TABLE_BYTES
    if precompute:
        # The same float32 timesteps the sampler feeds the model (its tables are cast once, too).
        step_times = jnp.asarray(schedule.timesteps, jnp.float32)
        table = _modulation_table(config, hp, rows, step_times)
        model = jax.tree_util.Partial(_modulated_head_fn(config), hp, step_times, table)
    else:
        model = jax.tree_util.Partial(_head_fn(config), hp)
    kwargs = dict(
        uncond=None if cz_u is None else {"cz": cz_u},
        cfg_scale=w,
        prediction="x0",
        variance="learned_range" if config.learn_sigma else "fixed_small",
    )
    if sampler == "ddim":
        return sample_ddim(model, noise, {"cz": cz}, schedule, k_steps, eta=eta, **kwargs)
    return sample_ddpm(model, noise, {"cz": cz}, schedule, k_steps, temperature=tau, step_noise=step_noise, **kwargs)


def resolve_sampler(config: TimarConfig, sampler: str | None) -> str:
    """``sampler``, or the config's default when None.

    Raises:
        ValueError: a name not in :data:`~jaxtalk.models.timar.config.SAMPLERS`.
    """
    sampler = config.sampler if sampler is None else sampler
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; expected one of {SAMPLERS}")
    return sampler


def _guided(fn: Any, z_cond: Array, z_uncond: Array | None, w: Array) -> Array:
    """``fn(z_cond)``, or with guidance ``c + w (c - u)`` (the paper's Eq. 9 with omega = 1 + w) for
    ``u = fn(z_uncond)``."""
    out = fn(z_cond)
    if z_uncond is None:
        return out
    out_u = fn(z_uncond)
    return (1 + w) * out - w * out_u


def _head_at_last_timestep(config: TimarConfig, head_params: Any, z: Array, noise: Array) -> Array:
    """The head's x0 estimate at the last training timestep, where ``noise`` carries no information
    about x0: the posterior mean ``E[x0 | z]`` of an x0-predicting head."""
    t_last = jnp.full(noise.shape[:-1], config.num_timesteps - 1.0)
    return apply_head(head_params, config, z, noise, t_last)[..., : config.param_dim]


@functools.partial(jax.jit, static_argnames=("config", "sample_steps", "sampler", "guidance"))
def _sample(params, config, us, um, as_, key, cfg_scale, eta, temperature, sample_steps, sampler, guidance):
    f = config.frames_per_turn
    z_c, z_u = conditions(params, config, to_turns(us, f), to_turns(um, f), to_turns(as_, f), guidance=guidance)
    x = sample_frames(params, config, z_c, z_u, key, cfg_scale=cfg_scale, sample_steps=sample_steps, sampler=sampler, eta=eta,
                      temperature=temperature)
    return from_turns(x)


def sample(
    params: dict[str, Any],
    config: TimarConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    key: PRNGKeyArray,
    *,
    cfg_scale: Shaped[Array, "..."] | float | None = None,
    sample_steps: int | None = None,
    sampler: str | None = None,
    eta: Float[Array, ""] | float = 0.0,
    temperature: Shaped[Array, "..."] | float | None = None,
    guidance: bool = True,
) -> Float[Array, "batch frames param_dim"]:
    """Agent head motion for a whole window of N <= ``max_turns`` turns in one pass.

    Every agent frame is masked and the encoder is turn-causal, so turn t's output depends only on
    turns <= t: this equals streaming with a context of at least N - 1 turns (no sliding).

    Args:
        params: model parameters.
        config: model config.
        user_speech, agent_speech: ``(B, N F, speech_dim)`` per-frame speech features.
        user_motion: ``(B, N F, 56)`` the user's (normalised) head motion.
        key: PRNG key.
        cfg_scale: ``()`` guidance weight w, 0 = none (traced; default ``config.cfg_scale``).
        sample_steps: respaced diffusion steps (static; default ``config.sample_steps``).
        sampler: ``"ddpm"``, ``"ddim"`` or ``"mean"`` (the guided posterior mean); None: the
            config's (see :func:`sample_frames`).
        eta: DDIM stochasticity (traced).
        temperature: MAR's sampling temperature (traced; see :func:`sample_frames`; None: MAR's
            default, :data:`MAR_TEMPERATURE`).
        guidance: run the unconditional branch (False: conditional only, ``cfg_scale`` ignored). A
            concrete ``cfg_scale`` of 0 skips it too (:func:`without_guidance`).

    Returns:
        ``(B, N F, 56)`` sampled agent motion (in the training normalisation).

    Raises:
        ValueError: bad streams (lengths, shapes, NaN, more turns than ``max_turns``), an unknown
            sampler or a bad step count.
    """
    check_streams(
        config,
        {"user_speech": user_speech, "user_motion": user_motion, "agent_speech": agent_speech},
        max_turns=config.max_turns,
    )
    sampler = resolve_sampler(config, sampler)
    sample_steps = config.sample_steps if sample_steps is None else sample_steps
    if isinstance(sample_steps, bool) or not isinstance(sample_steps, int) or not 1 <= sample_steps <= config.num_timesteps:
        raise ValueError(f"sample_steps must be an integer in [1, {config.num_timesteps}], got {sample_steps!r}")
    cfg = jnp.asarray(config.cfg_scale if cfg_scale is None else cfg_scale, jnp.float32)
    if cfg.ndim:
        raise ValueError(f"cfg_scale must be a scalar (vmap over it for a sweep), got shape {cfg.shape}")
    guidance = guidance and not without_guidance(cfg)
    return _sample(
        params, config,
        jnp.asarray(user_speech, jnp.float32), jnp.asarray(user_motion, jnp.float32),
        jnp.asarray(agent_speech, jnp.float32), key, cfg, jnp.asarray(eta, jnp.float32),
        check_temperature(temperature, default=MAR_TEMPERATURE), sample_steps, sampler, bool(guidance),
    )


def without_guidance(cfg_scale: Any) -> bool:
    """Whether a guidance weight is a concrete 0 (the paper's omega = 1, the published evaluation's
    default): ``c + 0 (c - u)`` is ``c``, so the unconditional branch, half the encoder's batch and
    half the head's, can be skipped. A traced weight (a sweep under ``jit`` or ``vmap``) keeps it."""
    if isinstance(cfg_scale, jax.core.Tracer):
        return False
    return bool(np.all(np.asarray(cfg_scale) == 0))


@functools.partial(jax.jit, static_argnames=("config",))
def _posterior_mean(params, config, us, um, as_, key):
    f = config.frames_per_turn
    z, _ = conditions(params, config, to_turns(us, f), to_turns(um, f), to_turns(as_, f), guidance=False)
    if config.head == "mlp":
        return from_turns(apply_head(params["head"], config, z))
    noise = jax.random.normal(key, z.shape[:-1] + (config.param_dim,), jnp.float32)
    return from_turns(_head_at_last_timestep(config, params["head"], z, noise))


def posterior_mean(
    params: dict[str, Any],
    config: TimarConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    key: PRNGKeyArray,
) -> Float[Array, "batch frames param_dim"]:
    """The model's point estimate ``E[agent motion | context]`` of a window (no sampling).

    An x0-predicting head trained with the squared error returns, at the last training timestep
    (``x_T`` is pure noise and carries no information about x0), the posterior mean of x0 given its
    condition. This is the estimate to score with MSE: a SAMPLE of a correct model has about twice
    the conditional variance as its expected squared error, so on SynthTalk, where most of the
    variance is a per-speaker offset no audio reveals, samples lose to the mean pose on MSE while
    the posterior mean does not. The MLP-head ablation returns its prediction.

    Args:
        params: model parameters.
        config: model config.
        user_speech, agent_speech: ``(B, N F, speech_dim)``.
        user_motion: ``(B, N F, 56)``.
        key: PRNG key of the (irrelevant) noise input.

    Returns:
        ``(B, N F, 56)`` (training normalisation).

    Raises:
        ValueError: bad streams (see :func:`sample`).
    """
    check_streams(
        config,
        {"user_speech": user_speech, "user_motion": user_motion, "agent_speech": agent_speech},
        max_turns=config.max_turns,
    )
    return _posterior_mean(
        params, config, jnp.asarray(user_speech, jnp.float32), jnp.asarray(user_motion, jnp.float32),
        jnp.asarray(agent_speech, jnp.float32), key,
    )
