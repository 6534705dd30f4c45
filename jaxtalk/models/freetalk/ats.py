"""ATS (Audio-To-Sparse): FreeTalk's emotion-conditioned landmark-displacement diffusion transformer.

The denoiser ``f(x_l, l, A, e, i) -> x0`` works on landmark displacement sequences
``x = (Delta L_t)_t`` of shape ``(T, 3 N)`` (N = 68). Inputs and audio memory are projected to the
model width with learned positional tables (equation 6); the diffusion-step embedding and the
emotion x intensity embedding are added to the target tokens; each pre-LN decoder block applies
self-attention over the motion frames, then cross-attention to the audio memory under the static
band-diagonal mask ``|i - p_j| <= r`` (equations 9-10, read as a hard band: NOTES.md), then a
feed-forward; a final LayerNorm and a linear head predict x0 (equation 11).

Training: DDPM with the linear schedule (1000 steps), x0 prediction, the motion loss with velocity
and acceleration weights 0.3 / 0.1. Sampling: DDIM over any number of respaced steps through
:func:`jaxtalk.samplers.sample_ddim`, one compiled program per (shapes, step count); DDIM ``eta``
and the emotion intensity are traced.

Units: public functions take and return displacements in metres; the network sees them multiplied
by ``config.displacement_scale``.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.masks import band_mask, combine, mask_to_bias
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.models.freetalk.emotions import check_intensity, emotion_ids
from jaxtalk.models.freetalk.loss import motion_loss
from jaxtalk.nn import DecoderBlock, TimestepEmbedding
from jaxtalk.nn.precision import compute_in
from jaxtalk.samplers import make_schedule, respace, sample_ddim
from jaxtalk.types import Array, Bool, Float, Int, PRNGKeyArray

__all__ = [
    "ATSCondition",
    "ATSDenoiser",
    "init_params",
    "make_condition",
    "ats_denoise",
    "loss",
    "make_loss_fn",
    "sample",
    "cross_attention_mask",
]

PyTree = Any


class ATSCondition(NamedTuple):
    """What the denoiser is conditioned on; every leaf has the batch as its leading axis.

    Attributes:
        audio: ``(B, Ta, speech_dim)`` audio features (``Ta = T * audio_frames_per_frame``).
        emotion: ``(B,)`` int32 emotion ids (see :data:`~jaxtalk.models.freetalk.emotions.EMOTIONS`).
        intensity: ``(B,)`` float32 intensities in ``[1, num_intensities]``.
        mask: ``(B, T)`` True on real motion frames.
        audio_mask: ``(B, Ta)`` True on real audio frames.
    """

    audio: Float[Array, "batch audio_frames speech_dim"]
    emotion: Int[Array, " batch"]
    intensity: Float[Array, " batch"]
    mask: Bool[Array, "batch frames"]
    audio_mask: Bool[Array, "batch audio_frames"]


def cross_attention_mask(config: ATSConfig, num_frames: int, num_audio_frames: int) -> Bool[np.ndarray, "q k"]:
    """The static band-diagonal cross-attention mask (True = motion frame i may see audio frame j).

    Args:
        config: ATS configuration (``band_radius``, ``audio_frames_per_frame``).
        num_frames: T motion frames.
        num_audio_frames: Ta audio frames.

    Returns:
        ``(T, Ta)`` bool NumPy array.
    """
    return band_mask(num_frames, num_audio_frames, config.band_radius, config.audio_frames_per_frame)


class _AffectEmbedding(nn.Module):
    """``g_c(e, i) = A_e + (i / I) B_e``: an emotion embedding plus an intensity-scaled emotion direction.

    Every (emotion, intensity) cell shares its emotion's two vectors, so the embedding is learned
    from all clips of an emotion whatever their intensity (a per-cell lookup would see a handful of
    clips per cell on a small corpus, and none at all for cells the corpus happens to lack). The
    embedding is affine in the intensity, so a traced float moves smoothly between the discrete
    levels (clipped to ``[1, num_intensities]``) and reaches cells the corpus lacks; the transformer
    downstream stays free to respond to it non-linearly.
    """

    config: ATSConfig

    @nn.compact
    def __call__(self, emotion: Array, intensity: Array) -> Array:
        cfg = self.config
        init = nn.initializers.normal(1.0)
        base = self.param("emotion", init, (cfg.num_emotions, cfg.width))
        direction = self.param("intensity_direction", init, (cfg.num_emotions, cfg.width))
        # Clipped to the trained range, as make_condition enforces at the API boundary (a traced value
        # inside someone else's jit, e.g. an intensity inversion, cannot be checked there).
        level = jnp.clip(intensity.astype(jnp.float32), 1.0, float(cfg.num_intensities))
        scale = (level / cfg.num_intensities)[:, None]
        return base[emotion] + scale * direction[emotion]


class ATSDenoiser(nn.Module):
    """The transformer-decoder denoiser: ``(x_l, l, condition) -> x0`` in model units.

    Attributes:
        config: static :class:`ATSConfig`.
    """

    config: ATSConfig

    def setup(self) -> None:
        cfg = self.config
        init = nn.initializers.normal(0.02)
        self.input_proj = nn.Dense(cfg.width, name="input_proj")
        self.audio_norm = nn.LayerNorm(name="audio_norm")
        self.audio_proj = nn.Dense(cfg.width, name="audio_proj")
        self.target_pos = self.param("target_pos", init, (cfg.max_frames, cfg.width))
        self.memory_pos = self.param("memory_pos", init, (cfg.max_audio_frames, cfg.width))
        self.time_embed = TimestepEmbedding(cfg.width, frequency_dim=cfg.time_frequency_dim, order="cos_sin")
        self.affect = _AffectEmbedding(cfg)
        self.blocks = [
            DecoderBlock(
                num_heads=cfg.num_heads,
                head_dim=cfg.head_dim,
                mlp_ratio=cfg.ff_dim / cfg.width,
                dropout_rate=cfg.dropout,
                name=f"block_{i}",
            )
            for i in range(cfg.num_layers)
        ]
        self.out_norm = nn.LayerNorm(name="out_norm")
        self.head = nn.Dense(cfg.motion_dim, name="head")

    def encode_memory(self, audio: Array) -> Array:
        """``A_hat = W_h H + P_mem`` (computed once per clip, reused at every diffusion step).

        The LayerNorm makes the projection indifferent to the audio features' units (log-mel or
        HuBERT) without dataset statistics.
        """
        ta = audio.shape[1]
        return self.audio_proj(self.audio_norm(audio)) + self.memory_pos[None, :ta]

    def __call__(
        self,
        x: Array,
        t: Array,
        memory: Array,
        cond: ATSCondition,
        deterministic: bool = True,
    ) -> Array:
        cfg = self.config
        b, frames, _ = x.shape
        z = self.input_proj(x) + self.target_pos[None, :frames]
        z = z + (self.time_embed(t) + self.affect(cond.emotion, cond.intensity))[:, None, :]
        self_bias = mask_to_bias(combine(np.ones((frames, frames), bool), cond.mask))
        band = jnp.asarray(cross_attention_mask(cfg, frames, memory.shape[1]))
        cross_ok = band[None, None] & cond.audio_mask[:, None, None, :]
        cross_bias = mask_to_bias(cross_ok)
        for block in self.blocks:
            z = block(z, memory, self_bias=self_bias, cross_bias=cross_bias, deterministic=deterministic)
        return self.head(self.out_norm(z))


# ------------------------------------------------------------------------------------------------
# Parameters, conditions and the denoiser as pure functions
# ------------------------------------------------------------------------------------------------


def _dummy(config: ATSConfig, frames: int) -> tuple[Array, Array, ATSCondition]:
    ta = max(1, int(round(frames * config.audio_frames_per_frame)))
    cond = ATSCondition(
        audio=jnp.zeros((1, ta, config.speech_dim)),
        emotion=jnp.zeros((1,), jnp.int32),
        intensity=jnp.ones((1,)),
        mask=jnp.ones((1, frames), bool),
        audio_mask=jnp.ones((1, ta), bool),
    )
    return jnp.zeros((1, frames, config.motion_dim)), jnp.zeros((1,)), cond


def init_params(config: ATSConfig, key: PRNGKeyArray) -> PyTree:
    """Initial ATS parameters.

    Args:
        config: static configuration.
        key: PRNG key.

    Returns:
        The ``{"params": ...}`` variables of :class:`ATSDenoiser`.
    """
    return _init(config, key)


@functools.partial(jax.jit, static_argnames="config")
def _init(config: ATSConfig, key: PRNGKeyArray) -> PyTree:
    # Module level with a static config: compiled once per configuration, not once per call.
    x, t, cond = _dummy(config, 4)

    def both(m: ATSDenoiser) -> Array:
        return m(x, t, m.encode_memory(cond.audio), cond)

    return nn.init(both, ATSDenoiser(config))(key)


def make_condition(
    config: ATSConfig,
    audio: Float[Array, "batch audio_frames speech_dim"] | Float[np.ndarray, "batch audio_frames speech_dim"],
    emotion: Any,
    intensity: Any = 1.0,
    *,
    mask: Bool[Array, "batch frames"] | Bool[np.ndarray, "batch frames"] | None = None,
    audio_mask: Bool[Array, "batch audio_frames"] | Bool[np.ndarray, "batch audio_frames"] | None = None,
    num_frames: int | None = None,
) -> ATSCondition:
    """Validate and assemble an :class:`ATSCondition` (the API boundary of ATS).

    Args:
        config: ATS configuration.
        audio: ``(B, Ta, speech_dim)`` features.
        emotion: emotion names, or ids, one per example (a single name broadcasts to the batch).
        intensity: scalar or ``(B,)`` intensities in ``[1, num_intensities]``.
        mask: ``(B, T)`` real motion frames (default all).
        audio_mask: ``(B, Ta)`` real audio frames (default all).
        num_frames: T when ``mask`` is not given (default ``round(Ta / audio_frames_per_frame)``).

    Returns:
        The condition.

    Raises:
        ValueError: wrong audio width or rank, NaN/inf audio, unknown emotion, intensity out of range,
            masks of the wrong shape, or T beyond ``config.max_frames``.
    """
    if audio.ndim != 3 or audio.shape[-1] != config.speech_dim:
        raise ValueError(f"audio features must have shape (batch, frames, {config.speech_dim}), got {audio.shape}")
    b, ta, _ = audio.shape
    if ta == 0:
        raise ValueError("audio features are empty (0 frames)")
    if ta > config.max_audio_frames:
        raise ValueError(f"{ta} audio frames exceed config.max_audio_frames={config.max_audio_frames}")
    if not isinstance(audio, jax.core.Tracer) and not bool(np.all(np.isfinite(np.asarray(audio)))):
        raise ValueError("audio features contain NaN or inf")
    ids = emotion_ids(emotion, config.emotions)
    if ids.shape[0] == 1 and b > 1:
        ids = np.repeat(ids, b)
    if ids.shape != (b,):
        raise ValueError(f"need one emotion per example ({b}), got {ids.shape[0]}")
    inten = check_intensity(intensity, config.num_intensities, b)
    if mask is None:
        frames = int(round(ta / config.audio_frames_per_frame)) if num_frames is None else int(num_frames)
        mask = np.ones((b, frames), bool)
    if mask.ndim != 2 or mask.shape[0] != b or mask.dtype != bool:
        raise ValueError(f"mask must be a bool array of shape ({b}, frames), got {mask.dtype} {mask.shape}")
    if not 1 <= mask.shape[1] <= config.max_frames:
        raise ValueError(f"motion length {mask.shape[1]} must lie in [1, config.max_frames={config.max_frames}]")
    if audio_mask is None:
        audio_mask = np.ones((b, ta), bool)
    if audio_mask.shape != (b, ta) or audio_mask.dtype != bool:
        raise ValueError(f"audio_mask must be a bool array of shape ({b}, {ta}), got {audio_mask.dtype} {audio_mask.shape}")
    return ATSCondition(
        audio=jnp.asarray(audio, jnp.float32),
        emotion=jnp.asarray(ids),
        intensity=jnp.asarray(inten, jnp.float32),
        mask=jnp.asarray(mask),
        audio_mask=jnp.asarray(audio_mask),
    )


def _denoise(params: PyTree, config: ATSConfig, x: Array, t: Array, cond: ATSCondition,
             deterministic: bool = True, rngs: dict | None = None) -> Array:
    model = ATSDenoiser(config)

    def run(m: ATSDenoiser, x: Array, t: Array, cond: ATSCondition) -> Array:
        return m(x, t, m.encode_memory(cond.audio), cond, deterministic)

    return compute_in(config.compute_dtype, nn.apply(run, model))(params, x, t, cond, rngs=rngs)


@functools.partial(jax.jit, static_argnames="config")
def ats_denoise(
    params: PyTree,
    config: ATSConfig,
    x: Float[Array, "batch frames motion"],
    t: Float[Array, " batch"],
    cond: ATSCondition,
) -> Float[Array, "batch frames motion"]:
    """One denoiser evaluation ``x0_hat = f(x_t, t, A, e, i)`` in model units (jitted).

    Args:
        params: ATS variables.
        config: static configuration.
        x: ``(B, T, 3N)`` noisy displacements (model units).
        t: ``(B,)`` diffusion steps in ``[0, num_timesteps)``.
        cond: from :func:`make_condition`.

    Returns:
        ``(B, T, 3N)`` predicted clean displacements (model units).
    """
    return _denoise(params, config, x, t, cond)


# ------------------------------------------------------------------------------------------------
# Training loss
# ------------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=8)
def _alphas_cumprod(num_timesteps: int) -> np.ndarray:
    return make_schedule("linear", num_timesteps).alphas_cumprod


def loss(
    params: PyTree,
    config: ATSConfig,
    batch: dict[str, Any],
    key: PRNGKeyArray,
    *,
    deterministic: bool = False,
) -> tuple[Float[Array, ""], dict[str, Float[Array, ""]]]:
    """DDPM x0-prediction loss: noise the clean sequence at a uniform step and score the prediction.

    Args:
        params: ATS variables.
        config: static configuration.
        batch: ``"displacements"`` ``(B, T, N, 3)`` metres, ``"audio"`` ``(B, Ta, speech_dim)``,
            ``"emotion"`` ``(B,)`` int, ``"intensity"`` ``(B,)`` float, optional ``"mask"`` ``(B, T)``
            and ``"audio_mask"`` ``(B, Ta)`` bool.
        key: PRNG key (step, noise, dropout).
        deterministic: disable dropout.

    Returns:
        ``(loss, metrics)`` with the position / velocity / acceleration terms (model units).
    """
    disp = jnp.asarray(batch["displacements"], jnp.float32)
    b, frames = disp.shape[:2]
    x0 = disp.reshape(b, frames, -1) * config.displacement_scale
    mask = jnp.asarray(batch["mask"], bool) if "mask" in batch else jnp.ones((b, frames), bool)
    audio = jnp.asarray(batch["audio"], jnp.float32)
    audio_mask = (
        jnp.asarray(batch["audio_mask"], bool) if "audio_mask" in batch else jnp.ones(audio.shape[:2], bool)
    )
    cond = ATSCondition(
        audio=audio,
        emotion=jnp.asarray(batch["emotion"], jnp.int32),
        intensity=jnp.asarray(batch["intensity"], jnp.float32),
        mask=mask,
        audio_mask=audio_mask,
    )
    k_t, k_eps, k_drop = jax.random.split(key, 3)
    steps = jax.random.randint(k_t, (b,), 0, config.num_timesteps)
    abar = jnp.asarray(_alphas_cumprod(config.num_timesteps), jnp.float32)[steps][:, None, None]
    eps = jax.random.normal(k_eps, x0.shape)
    xt = jnp.sqrt(abar) * x0 + jnp.sqrt(1.0 - abar) * eps
    pred = _denoise(params, config, xt, steps.astype(jnp.float32), cond, deterministic, {"dropout": k_drop})
    n = config.num_landmarks
    return motion_loss(
        pred.reshape(b, frames, n, 3),
        x0.reshape(b, frames, n, 3),
        mask,
        velocity_weight=config.velocity_weight,
        acceleration_weight=config.acceleration_weight,
    )


def make_loss_fn(config: ATSConfig):
    """``loss_fn(params, batch, key) -> (loss, metrics)`` for :func:`jaxtalk.train.train`.

    Args:
        config: static configuration.

    Returns:
        The loss function with ``config`` bound.
    """
    return functools.partial(_bound_loss, config)


def _bound_loss(config: ATSConfig, params: PyTree, batch: dict[str, Any], key: PRNGKeyArray):
    return loss(params, config, batch, key)


# ------------------------------------------------------------------------------------------------
# DDIM sampling
# ------------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=16)
def _respaced(num_timesteps: int, sample_steps: int):
    return respace(make_schedule("linear", num_timesteps), sample_steps)


def _apply_denoiser(config: ATSConfig, params: PyTree, x: Array, t: Array, cond: tuple[Array, ATSCondition]) -> Array:
    memory, rest = cond
    run = nn.apply(lambda m, x, t, memory, rest: m(x, t, memory, rest), ATSDenoiser(config))
    return compute_in(config.compute_dtype, run)(params, x, t, memory, rest)


@functools.partial(jax.jit, static_argnames=("config", "sample_steps", "remat"))
def _sample(params, config: ATSConfig, cond: ATSCondition, key, eta, noise, sample_steps: int, remat: bool):
    b, frames = cond.mask.shape
    # The audio memory does not depend on the diffusion step: encode it once, outside the scan.
    memory = compute_in(config.compute_dtype, nn.apply(lambda m, audio: m.encode_memory(audio), ATSDenoiser(config)))(
        params, cond.audio)
    # A Partial (a pytree) rather than a closure, so the parameters are traced leaves of the scan
    # (differentiable, e.g. by jaxtalk.models.freetalk.inversion) and not baked-in constants.
    apply_fn = jax.tree_util.Partial(functools.partial(_apply_denoiser, config), params)
    k_noise, k_steps = jax.random.split(key)
    if noise is None:
        noise = jax.random.normal(k_noise, (b, frames, config.motion_dim))
    x0 = sample_ddim(
        apply_fn, noise, (memory, cond), _respaced(config.num_timesteps, sample_steps), k_steps,
        eta=eta, prediction="x0", remat=remat,
    )
    return x0.reshape(b, frames, config.num_landmarks, 3) / config.displacement_scale


def sample(
    params: PyTree,
    config: ATSConfig,
    cond: ATSCondition,
    key: PRNGKeyArray | None,
    *,
    sample_steps: int | None = None,
    eta: Float[Array, ""] | float = 0.0,
    noise: Float[Array, "batch frames motion"] | Float[np.ndarray, "batch frames motion"] | None = None,
    remat: bool = False,
) -> Float[Array, "batch frames landmarks 3"]:
    """Generate landmark displacement sequences with DDIM (one jitted program per shape and step count).

    Static: ``config``, ``sample_steps``, ``remat``, whether ``noise`` is given, and the shapes in
    ``cond``. Traced: ``params``, ``eta``, ``noise``, the emotion ids and intensities, the audio and
    masks (so an intensity or eta sweep never recompiles, and the output is differentiable in all
    of them).

    Args:
        params: ATS variables.
        config: static configuration.
        cond: from :func:`make_condition`.
        key: PRNG key: the starting noise is drawn from ``split(key)[0]`` unless ``noise`` is given;
            with ``eta > 0`` the per-step noise comes from ``split(key)[1]``. May be None when
            ``noise`` is given and ``eta = 0`` (deterministic DDIM).
        sample_steps: DDIM steps (default ``config.sample_steps``; any count in
            ``[1, num_timesteps]``).
        eta: DDIM stochasticity (0 = deterministic).
        noise: ``(B, T, 3N)`` explicit starting noise in model units (e.g. held fixed while an input
            is optimised through the sampler); default: drawn from ``key``.
        remat: ``jax.checkpoint`` each DDIM step (memory of a reverse pass through the sampler).

    Returns:
        ``(B, T, N, 3)`` displacements in metres (relative to the neutral landmarks), i.e. model
        units / ``displacement_scale``.

    Raises:
        ValueError: a bad step count, a non-scalar / non-finite eta, noise of the wrong shape or with
            NaN/inf, or no key where one is needed.
    """
    steps = config.sample_steps if sample_steps is None else sample_steps
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 1 <= steps <= config.num_timesteps:
        raise ValueError(f"sample_steps must be an integer in [1, {config.num_timesteps}], got {sample_steps!r}")
    if np.ndim(eta) != 0:
        raise ValueError(f"eta must be a scalar, got shape {np.shape(eta)}")
    # Inspect the value as given: inside someone else's jit even a Python float becomes a tracer
    # once converted.
    concrete_eta = not isinstance(eta, jax.core.Tracer)
    if concrete_eta and not np.isfinite(float(np.asarray(eta))):
        raise ValueError(f"eta must be finite, got {eta!r}")
    eta_arr = jnp.asarray(eta, jnp.float32)
    if noise is not None:
        shape = (*cond.mask.shape, config.motion_dim)
        if tuple(np.shape(noise)) != shape:
            raise ValueError(f"noise must have shape {shape} (batch, frames, 3N), got {tuple(np.shape(noise))}")
        if not isinstance(noise, jax.core.Tracer) and not bool(np.all(np.isfinite(np.asarray(noise)))):
            raise ValueError("noise contains NaN or inf")
        noise = jnp.asarray(noise)
    if key is None:
        if noise is None:
            raise ValueError("sample needs a key to draw the starting noise (or an explicit noise=)")
        if not concrete_eta or float(np.asarray(eta)) != 0.0:
            raise ValueError("sample needs a key for eta > 0 (the per-step noise); got key=None")
        # Deterministic DDIM never reads its step keys: any fixed key gives the same program.
        key = jax.random.key(0)
    return _sample(params, config, cond, key, eta_arr, noise, int(steps), bool(remat))
