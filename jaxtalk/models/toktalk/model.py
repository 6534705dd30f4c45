"""TokTalk as pure functions: parameter init, the conditioning pytree, the velocity, style and adapter.

Parameters are a plain dict ``{"decoder": ..., "style": ..., "adapter": ...}`` (the adapter only
after stage 2 or when asked for); every function takes ``(params, config, ...)`` with ``config`` a
static frozen dataclass.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite
from jaxtalk.audio.framerate import area_weights, default_num_frames, interpolation_plan
from jaxtalk.data.standardize import identity_standardizer, standardize, unstandardize
from jaxtalk.models.toktalk.adapter import Adapter
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.decoder import Decoder
from jaxtalk.models.toktalk.style import StyleEncoder
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Bool, Float, PRNGKeyArray

__all__ = [
    "Condition",
    "init_params",
    "interpolate_tokens",
    "frames_for_tokens",
    "velocity",
    "encode_style",
    "adapt_tokens",
    "adapter_apply",
    "adapter_source_dim",
    "source_to_base_rate",
    "check_tokens",
    "preconditioning",
    "style_vector",
    "anchor_pose",
    "join_style",
    "to_flow_space",
    "from_flow_space",
    "fit_flow_scale",
]

PyTree = Any


class Condition(NamedTuple):
    """Everything the decoder is conditioned on; every leaf has the batch as its leading axis.

    Attributes:
        tokens: ``(B, T, speech_dim)`` token embeddings at the motion frame rate.
        style: ``(B, style_vector_dim)`` style vectors.
        known: ``(B, T, param_dim)`` known frames (values elsewhere ignored).
        known_mask: ``(B, T)`` True on known frames.
        keep: ``(B,)`` 1 = conditional, 0 = unconditional (CFG / condition dropout).
        mask: ``(B, T)`` True on real frames.
        chunked: ``(B,)`` True for block-causal chunk attention, False for full attention.
    """

    tokens: Float[Array, "batch frames token"]
    style: Float[Array, "batch style"]
    known: Float[Array, "batch frames param"]
    known_mask: Bool[Array, "batch frames"]
    keep: Float[Array, " batch"]
    mask: Bool[Array, "batch frames"]
    chunked: Bool[Array, " batch"]

    def unconditional(self) -> Condition:
        """The same condition with tokens, style and known frames dropped (``keep = 0``)."""
        return self._replace(keep=jnp.zeros_like(self.keep))


def frames_for_tokens(num_tokens: int, token_rate: float | int, fps: int) -> int:
    """Motion frames covered by ``num_tokens`` tokens at ``token_rate`` (``round(n * fps / rate)``)."""
    return default_num_frames(int(num_tokens), token_rate, fps)


def check_tokens(
    tokens: Any, *, width: int, rate: float | int, fps: int, num_frames: int | None = None, name: str = "tokens"
) -> int:
    """Validates a ``(B, Tt, width)`` token batch and returns the number of motion frames it covers.

    Args:
        tokens: token embeddings (array or tracer).
        width: expected embedding width.
        rate: the stream's token rate (Hz).
        fps: motion frame rate.
        num_frames: if given, the number of frames the caller expects; must match the rate.
        name: the argument's name for messages.

    Returns:
        Number of motion frames ``T``.

    Raises:
        ValueError: wrong rank or width, NaN/inf, empty, or a token count that does not cover
            ``num_frames`` frames at ``rate`` (the stream has another rate than configured).
    """
    shape = tuple(np.shape(tokens))
    if len(shape) != 3:
        raise ValueError(f"{name} must have shape (batch, tokens, {width}), got {shape}")
    if shape[2] != width:
        raise ValueError(f"{name} have width {shape[2]}, expected {width} (speech_dim of this stream)")
    if shape[0] == 0 or shape[1] == 0:
        raise ValueError(f"{name} are empty: shape {shape}")
    check_finite(tokens, name)
    frames = frames_for_tokens(shape[1], rate, fps)
    if num_frames is not None and frames != num_frames:
        raise ValueError(
            f"{shape[1]} {name} at {rate} Hz cover {frames} frames at {fps} fps, but {num_frames} frames "
            f"were expected: is the token rate wrong (expected {rate} Hz, i.e. "
            f"{num_frames * rate / fps:g} tokens)?"
        )
    return frames


def interpolate_tokens(
    tokens: Float[Array, "batch tokens width"],
    src_rate: float | int,
    dst_rate: float | int,
    num_frames: int,
    mode: str = "previous",
) -> Float[Array, "batch frames width"]:
    """Token embeddings at another rate (exact rational positions).

    Args:
        tokens: ``(B, Tt, W)``.
        src_rate: its rate (Hz).
        dst_rate: wanted rate (Hz).
        num_frames: output length (static).
        mode: ``"previous"`` (each frame takes the latest token starting at or before it: no future
            token, the streaming model's alignment) or ``"linear"`` (blends the next token: offline);
            see :attr:`TokTalkConfig.token_alignment`.

    Returns:
        ``(B, num_frames, W)``; frames past the last token hold it.
    """
    lo, hi, w = interpolation_plan(tokens.shape[1], src_rate, dst_rate, num_frames, mode)
    if mode == "previous":
        return tokens[:, lo]
    w = jnp.asarray(w, tokens.dtype)[None, :, None]
    return tokens[:, lo] * (1 - w) + tokens[:, hi] * w


def init_params(
    config: TokTalkConfig, key: PRNGKeyArray, *, adapter_src_dim: int | None = None
) -> dict[str, PyTree]:
    """Fresh parameters of the decoder and style encoder (and an adapter for ``adapter_src_dim``).

    Args:
        config: model settings.
        key: PRNG key.
        adapter_src_dim: width of the source token space to adapt from (None: no adapter).

    Returns:
        ``{"decoder": ..., "style": ..., "norm": ...}`` plus ``"adapter"`` when requested. ``norm`` is
        the motion standardiser (``{"mean", "std"}``) and the flow's per-channel scale
        (``"flow_scale"``), identity here; :func:`jaxtalk.models.toktalk.recipe.train` fits them on the training motion (see
        :func:`fit_flow_scale`): the decoder and the style encoder work on standardised motion, every
        public input and output is in raw parameter units.
    """
    # One jitted program: op-by-op initialisation dispatches (and compiles) every primitive.
    params = _init_params(key, config, adapter_src_dim)
    params["norm"] = {k: jnp.asarray(v) for k, v in identity_standardizer(config.param_dim).items()}
    params["norm"]["flow_scale"] = jnp.ones((config.param_dim,), jnp.float32)
    return params


@functools.partial(jax.jit, static_argnames=("config", "adapter_src_dim"))
def _init_params(key: PRNGKeyArray, config: TokTalkConfig, adapter_src_dim: int | None) -> dict[str, PyTree]:
    k_dec, k_sty, k_ad = jax.random.split(key, 3)
    b, t = 1, 2 * config.chunk_frames
    z = jnp.zeros((b, t, config.param_dim))
    cond = Condition(
        tokens=jnp.zeros((b, t, config.speech_dim)),
        style=jnp.zeros((b, config.style_vector_dim)),
        known=z,
        known_mask=jnp.zeros((b, t), bool),
        keep=jnp.ones((b,)),
        mask=jnp.ones((b, t), bool),
        chunked=jnp.zeros((b,), bool),
    )
    params = {
        "decoder": Decoder(config).init(k_dec, z, jnp.zeros((b,)), *cond)["params"],
        "style": StyleEncoder(config).init(k_sty, jnp.zeros((b, config.style_frames, config.param_dim)))[
            "params"
        ],
    }
    if adapter_src_dim is not None:
        params["adapter"] = _init_adapter(k_ad, config, adapter_src_dim)
    return params


def init_adapter(config: TokTalkConfig, key: PRNGKeyArray, src_dim: int) -> PyTree:
    """Fresh adapter parameters for a source token space of width ``src_dim``."""
    return _init_adapter(key, config, int(src_dim))


@functools.partial(jax.jit, static_argnames=("config", "src_dim"))
def _init_adapter(key: PRNGKeyArray, config: TokTalkConfig, src_dim: int) -> PyTree:
    return Adapter(config).init(key, jnp.zeros((1, 8, src_dim)))["params"]


def velocity(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    x: Float[Array, "batch frames param"],
    t: Float[Array, " batch"],
    cond: Condition,
    *,
    dropout_key: PRNGKeyArray | None = None,
) -> Float[Array, "batch frames param"]:
    """The decoder's velocity prediction (``dropout_key`` given = training mode).

    Args:
        params: model parameters (uses ``params["decoder"]``).
        config: model settings.
        x: ``(B, T, param_dim)`` noisy motion.
        t: ``(B,)`` flow times.
        cond: :class:`Condition`.
        dropout_key: PRNG key for dropout; None = deterministic.

    Returns:
        ``(B, T, param_dim)``.
    """
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    if config.style_anchor and not config.anchor_input:  # the anchor centres the flow; the decoder sees the latent
        cond = cond._replace(style=cond.style.at[:, config.style_dim :].set(0.0))
    if not config.latent_input:  # the decoder sees no learned style latent
        cond = cond._replace(style=cond.style.at[:, : config.style_dim].set(0.0))
    if not config.precondition:
        return compute_in(config.compute_dtype, Decoder(config).apply)(
            {"params": params["decoder"]}, x, t, *cond, deterministic=dropout_key is None, rngs=rngs
        )
    c_skip, c_out, c_in = preconditioning(t, config.sigma_min)
    col = lambda c: c[:, None, None].astype(x.dtype)  # noqa: E731  (B,) -> (B, 1, 1)
    f = compute_in(config.compute_dtype, Decoder(config).apply)(
        {"params": params["decoder"]}, x * col(c_in), t, *cond, deterministic=dropout_key is None, rngs=rngs
    )
    return col(c_skip) * x + col(c_out) * f


def preconditioning(
    t: Float[Array, " batch"], sigma_min: float | int = 0.0
) -> tuple[Float[Array, " batch"], Float[Array, " batch"], Float[Array, " batch"]]:
    """Skip, output and input scales that make the decoder learn a unit-variance residual.

    On the path ``x_t = a z + t x1`` with ``a = 1 - (1 - sigma_min) t`` and standardised data
    (unit variance, like the noise), the best LINEAR predictor of the target ``u = x1 - (1 -
    sigma_min) z`` from ``x_t`` is ``c_skip x_t`` with ``c_skip = (t - (1 - sigma_min) a) / (a^2 +
    t^2)``, and its residual has standard deviation ``c_out = sqrt(1 + (1 - sigma_min)^2 - c_skip^2
    (a^2 + t^2))``. So ``v = c_skip x_t + c_out F(c_in x_t, ...)`` with ``c_in = 1 / sqrt(a^2 + t^2)``
    (a unit-variance input) leaves the network a unit-scale residual to learn instead of the
    near-identity map of the noise (EDM's preconditioning, Karras et al. 2022, for this path). For
    Gaussian data ``F = 0`` is already exact, so the decoder starts from the right answer's linear part.

    Args:
        t: ``(B,)`` flow times.
        sigma_min: minimum noise of the path.

    Returns:
        ``(c_skip, c_out, c_in)``, each ``(B,)``.
    """
    k = 1.0 - sigma_min
    a = 1.0 - k * t
    var = a * a + t * t
    c_skip = (t - k * a) / var
    c_out = jnp.sqrt(jnp.maximum(1.0 + k * k - c_skip * c_skip * var, 1e-12))
    return c_skip, c_out, jax.lax.rsqrt(var)


def _sampler_velocity(config: TokTalkConfig, params: PyTree, x: Array, t: Array, cond: Condition) -> Array:
    return velocity(params, config, x, t, cond)


def sampler_model(config: TokTalkConfig, params: dict[str, PyTree]) -> jax.tree_util.Partial:
    """``apply_fn(x, t, cond)`` for :mod:`jaxtalk.samplers.flow`, with ``params`` as traced leaves."""
    return jax.tree_util.Partial(functools.partial(_sampler_velocity, config), params)


def style_distribution(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    clip: Float[Array, "batch frames param"],
    mask: Bool[Array, "batch frames"] | None = None,
    *,
    dropout_key: PRNGKeyArray | None = None,
) -> tuple[Float[Array, "batch style"], Float[Array, "batch style"]]:
    """``(mu, logvar)`` of the style encoder's latent for raw-unit reference clips (jit-friendly).

    The latent is ``style_dim`` wide; the full style vector (:func:`style_vector`) appends the anchor.
    """
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    if "norm" in params:
        clip = standardize(params["norm"], clip)
    return compute_in(config.compute_dtype, StyleEncoder(config).apply)(
        {"params": params["style"]}, clip, mask, deterministic=dropout_key is None, rngs=rngs
    )


def anchor_pose(
    params: dict[str, PyTree],
    clip: Float[Array, "batch frames param"],
    mask: Bool[Array, "batch frames"] | None = None,
) -> Float[Array, "batch param"]:
    """The reference clip's (masked) mean pose in standardised units: the style vector's anchor part."""
    if "norm" in params:
        clip = standardize(params["norm"], clip)
    if mask is None:
        return jnp.mean(clip, axis=1)
    w = mask.astype(clip.dtype)[..., None]
    return jnp.sum(clip * w, axis=1) / jnp.maximum(jnp.sum(w, axis=1), 1.0)


def join_style(
    config: TokTalkConfig, latent: Float[Array, "batch style"], anchor: Float[Array, "batch param"]
) -> Float[Array, "batch vector"]:
    """``[latent | anchor]`` with ``style_anchor``, else the latent alone (``style_vector_dim`` wide)."""
    return jnp.concatenate([latent, anchor], axis=-1) if config.style_anchor else latent


def style_vector(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    clip: Float[Array, "batch frames param"],
    mask: Bool[Array, "batch frames"] | None = None,
) -> Float[Array, "batch vector"]:
    """The full style vector of raw-unit reference clips: encoder mean (+ anchor pose); no validation."""
    return join_style(config, style_distribution(params, config, clip, mask)[0], anchor_pose(params, clip, mask))


def _anchor_of(config: TokTalkConfig, style_vec: Array) -> Array | None:
    return style_vec[:, config.style_dim :] if config.style_anchor else None


def to_flow_space(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    motion: Float[Array, "batch frames param"],
    style_vec: Float[Array, "batch vector"],
) -> Float[Array, "batch frames param"]:
    """Raw motion -> the coordinates the flow runs in: standardised, minus the style's anchor pose,
    divided by ``norm["flow_scale"]`` (the per-channel RMS of that residual on the training data)."""
    norm = params.get("norm", {})
    x = standardize(norm, motion) if norm else motion
    anchor = _anchor_of(config, style_vec)
    if anchor is not None:
        x = x - anchor[:, None, :].astype(x.dtype)
    if "flow_scale" in norm:
        x = x / jax.lax.stop_gradient(jnp.asarray(norm["flow_scale"], x.dtype))[None, None, :]
    return x


def from_flow_space(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    x: Float[Array, "batch frames param"],
    style_vec: Float[Array, "batch vector"],
) -> Float[Array, "batch frames param"]:
    """Inverse of :func:`to_flow_space`."""
    norm = params.get("norm", {})
    if "flow_scale" in norm:
        x = x * jax.lax.stop_gradient(jnp.asarray(norm["flow_scale"], x.dtype))[None, None, :]
    anchor = _anchor_of(config, style_vec)
    if anchor is not None:
        x = x + anchor[:, None, :].astype(x.dtype)
    return unstandardize(norm, x) if norm else x


def fit_flow_scale(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    motion: Float[np.ndarray, "n frames param"],
    mask: Bool[np.ndarray, "n frames"],
    style: Float[np.ndarray, "n style_frames param"],
    floor: float = 0.05,
    *,
    style_mask: Bool[np.ndarray, "n style_frames"] | None = None,
) -> Float[np.ndarray, " param"]:
    """Per-channel RMS of the anchored, standardised training motion (floored), for ``norm["flow_scale"]``.

    Anchoring removes most of a channel's spread when it is a speaker constant (SynthTalk's resting
    expression channels keep ~0.3 of their standard deviation): rescaling gives the flow unit-spread
    data in every channel again, which the preconditioning's skip (derived for unit variance) and the
    unit noise assume.

    Args:
        params: parameters with the fitted ``norm`` (``mean``, ``std``).
        config: model settings.
        motion, mask, style: training windows (:class:`~jaxtalk.models.toktalk.recipe.TokTalkWindows`).
        floor: smallest scale (a channel that never moves is not blown up).
        style_mask: True on the style clips' real frames (None: all real).

    Returns:
        ``(param_dim,)`` float32.
    """
    # The model's own standardisation and anchor (what to_flow_space subtracts), not a re-derivation.
    z = np.asarray(standardize(params["norm"], jnp.asarray(motion, jnp.float32)), np.float64)
    if config.style_anchor:
        smask = None if style_mask is None else jnp.asarray(style_mask, bool)
        z = z - np.asarray(anchor_pose(params, jnp.asarray(style, jnp.float32), smask), np.float64)[:, None, :]
    z = z[np.asarray(mask, bool)]
    if z.shape[0] == 0:
        raise ValueError("fit_flow_scale needs at least one real frame")
    return np.maximum(np.sqrt(np.mean(z * z, axis=0)), floor).astype(np.float32)


def check_style_clip(clip: Any, config: TokTalkConfig) -> None:
    """Validates a ``(B, S, param_dim)`` reference clip.

    Raises:
        ValueError: wrong rank or width, shorter than ``style_min_frames``, NaN/inf.
    """
    shape = tuple(np.shape(clip))
    if len(shape) != 3 or shape[2] != config.param_dim or shape[0] == 0:
        raise ValueError(f"style clip must have shape (batch, frames, {config.param_dim}), got {shape}")
    if shape[1] < config.style_min_frames:
        raise ValueError(
            f"style clip has {shape[1]} frames, shorter than the minimum style_min_frames="
            f"{config.style_min_frames}"
        )
    check_finite(clip, "style clip")


def encode_style(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    clip: Float[Array, "batch frames param"] | Float[np.ndarray, "batch frames param"],
    mask: Bool[Array, "batch frames"] | Bool[np.ndarray, "batch frames"] | None = None,
) -> Float[Array, "batch vector"]:
    """The style vector of reference motion clips: the encoder's mean, then (``style_anchor``) the
    clip's mean pose in standardised units.

    Args:
        params: model parameters.
        config: model settings.
        clip: ``(B, S, param_dim)`` reference motion, ``S >= style_min_frames``.
        mask: ``(B, S)`` True on real frames (None: all real).

    Returns:
        ``(B, style_vector_dim)``.

    Raises:
        ValueError: bad clip shape, too short, NaN/inf.
    """
    check_style_clip(clip, config)
    return _encode_style(params, jnp.asarray(clip), None if mask is None else jnp.asarray(mask), config)


@functools.partial(jax.jit, static_argnames=("config",))
def _encode_style(params: PyTree, clip: Array, mask: Array | None, config: TokTalkConfig) -> Array:
    return style_vector(params, config, clip, mask)


def source_to_base_rate(
    src: Float[Array, "batch src_tokens src"], src_rate: float | int, config: TokTalkConfig
) -> Float[Array, "batch tokens src"]:
    """Resamples a source token stream to the base token rate by time overlap (no token dropped).

    Base token ``j`` is the overlap-weighted mean of the source tokens inside its span (25 -> 12.5 Hz:
    the mean of each pair); see :func:`jaxtalk.audio.framerate.area_weights`. A base token reads no
    source token from a later span, so streaming chunk by chunk gives the same result.
    """
    num = default_num_frames(src.shape[1], src_rate, config.token_rate)
    w = area_weights(src.shape[1], src_rate, config.token_rate, num)
    return jnp.einsum("ji,bid->bjd", jnp.asarray(w, src.dtype), src)


def adapter_apply(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    at_base: Float[Array, "batch tokens src"],
    *,
    mask: Bool[Array, "batch tokens"] | None = None,
    positions: Array | None = None,
    dropout_key: PRNGKeyArray | None = None,
) -> Float[Array, "batch tokens token"]:
    """The adapter network on source tokens already at the base rate (no validation; jit-friendly)."""
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    return compute_in(config.compute_dtype, Adapter(config).apply)(
        {"params": params["adapter"]}, at_base, mask, deterministic=dropout_key is None, positions=positions,
        rngs=rngs,
    )


def adapter_forward(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    src: Float[Array, "batch src_tokens src"],
    src_rate: float | int,
    *,
    positions: Array | None = None,
    dropout_key: PRNGKeyArray | None = None,
) -> Float[Array, "batch tokens token"]:
    """Source tokens -> base-space tokens at the base rate (no validation; jit-friendly); ``positions``:
    the base tokens' absolute positions (None: ``0 .. Tt-1``)."""
    return adapter_apply(params, config, source_to_base_rate(src, src_rate, config), positions=positions,
                         dropout_key=dropout_key)


def adapter_source_dim(params: dict[str, PyTree]) -> int:
    """Width of the source token space ``params["adapter"]`` was built for.

    Raises:
        ValueError: no adapter in ``params``.
    """
    if "adapter" not in params:
        raise ValueError("params has no 'adapter' entry: train stage 2 (toktalk.recipe.train_adapter) first")
    return int(params["adapter"]["conv"]["conv"]["kernel"].shape[1])


def adapt_tokens(
    params: dict[str, PyTree],
    config: TokTalkConfig,
    src: Float[Array, "batch src_tokens src"] | Float[np.ndarray, "batch src_tokens src"],
    src_rate: float | int,
) -> Float[Array, "batch tokens token"]:
    """Maps another token space onto the base one (resampled to the base rate by time overlap first).

    Args:
        params: model parameters with an ``"adapter"`` entry (stage 2).
        config: model settings.
        src: ``(B, Ts, src_dim)`` source token embeddings.
        src_rate: their rate in Hz.

    Returns:
        ``(B, Tt, speech_dim)`` base-space embeddings at ``config.token_rate``.

    Raises:
        ValueError: no adapter in ``params``, a source width the adapter was not trained for,
            bad shapes, NaN/inf.
    """
    src_dim = adapter_source_dim(params)  # raises without an adapter
    check_tokens(src, width=src_dim, rate=src_rate, fps=config.fps, name="source tokens")
    return _adapt(params, jnp.asarray(src), float(src_rate), config)


@functools.partial(jax.jit, static_argnames=("src_rate", "config"))
def _adapt(params: PyTree, src: Array, src_rate: float, config: TokTalkConfig) -> Array:
    return adapter_forward(params, config, src, src_rate)
