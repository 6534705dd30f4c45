"""TIMAR's per-frame heads: the lightweight adaLN diffusion head and the MLP-head ablation.

Both are written for ONE frame (no frame or batch axis) and applied to any number of leading axes by
:func:`apply_head`, which nests ``jax.vmap`` (one set of parameters shared by every frame). The
diffusion head follows MAR's ``SimpleMLPAdaLN``: the noisy frame is projected to ``d_m``, the
condition is ``c = TimestepEmbedding(t) + Dense(z)``, then K residual adaLN blocks and a final adaLN
layer, with every modulation and the output layer zero-initialised (the head predicts 0 at init).
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.nn import MLP, AdaLNFinalLayer, AdaLNResBlock, TimestepEmbedding, adaln_modulation
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = [
    "DiffusionHead",
    "MLPHead",
    "init_head",
    "apply_head",
    "head_condition",
    "apply_head_hoisted",
    "time_embedding",
    "head_modulations",
    "apply_head_modulated",
]


class DiffusionHead(nn.Module):
    """adaLN residual MLP denoiser of one frame: ``(x_t, t, z) -> x0`` (and variance channels).

    The condition ``c = TimestepEmbedding(t) + Dense(z)`` is split into its two parts so that a
    sampler can compute ``Dense(z)`` once per frame (it does not change between diffusion steps)
    and the timestep embedding once per step (every frame of a step shares ``t``):
    :meth:`embed_condition`, :meth:`embed_time`, :meth:`denoise`. :meth:`denoise` also accepts the
    adaLN modulations of every layer precomputed (:func:`head_modulations`): they depend on
    ``(t, z)`` only, never on the noisy frame, so a sampler with a known timestep sequence computes
    all of them in one large matmul before its loop.

    Attributes:
        width: hidden width d_m.
        blocks: residual adaLN blocks K.
        out_dim: output width (56, or 112 with a learned variance).
    """

    width: int
    blocks: int
    out_dim: int

    def setup(self) -> None:
        self.time_embed = TimestepEmbedding(self.width, frequency_dim=256, order="cos_sin")
        self.cond_embed = nn.Dense(self.width)
        self.input_proj = nn.Dense(self.width)
        self.res_blocks = [AdaLNResBlock() for _ in range(self.blocks)]  # K is a static handful
        self.final = AdaLNFinalLayer(self.out_dim)

    def embed_condition(self, z: Float[Array, " cond_dim"]) -> Float[Array, " width"]:
        """``Dense(z)``: the step-independent part of the condition."""
        return self.cond_embed(z)

    def embed_time(self, t: Float[Array, ""]) -> Float[Array, " width"]:
        """The timestep embedding (frame-independent within a sampling step)."""
        return self.time_embed(t)

    def denoise(
        self,
        x: Float[Array, " param_dim"],
        c: Float[Array, " width"] | None = None,
        modulations: tuple[Float[Array, " _mod"], ...] | None = None,
    ) -> Float[Array, " out_dim"]:
        """Residual adaLN blocks on the projected noisy frame, modulated by ``c`` (or by the
        precomputed per-layer ``modulations`` of :func:`head_modulations`: K blocks, then the final)."""
        mods = (None,) * (self.blocks + 1) if modulations is None else modulations
        h = self.input_proj(x)
        for block, m in zip(self.res_blocks, mods[:-1]):
            h = block(h, c, modulation=m)
        return self.final(h, c, modulation=mods[-1])

    def __call__(
        self, x: Float[Array, " param_dim"], t: Float[Array, ""], z: Float[Array, " cond_dim"]
    ) -> Float[Array, " out_dim"]:
        """Denoise one frame.

        Args:
            x: ``(param_dim,)`` noisy head parameters x_t.
            t: ``()`` training timestep (0..T-1, as a float).
            z: ``(cond_dim,)`` encoder feature of this frame plus the head's positional embedding.

        Returns:
            ``(out_dim,)`` x0 estimate (first ``param_dim``) and, if learned, the variance values.
        """
        return self.denoise(x, self.embed_time(t) + self.embed_condition(z))


class MLPHead(nn.Module):
    """Direct regression of one frame from its feature (Table 2's "w/ MLP head").

    Attributes:
        width: hidden width.
        out_dim: output width (56).
    """

    width: int
    out_dim: int

    @nn.compact
    def __call__(self, z: Float[Array, " cond_dim"]) -> Float[Array, " out_dim"]:
        """Predict one frame.

        Args:
            z: ``(cond_dim,)`` encoder feature plus positional embedding.

        Returns:
            ``(out_dim,)`` head parameters.
        """
        return MLP((self.width, self.width, self.out_dim), activation=jax.nn.silu, name="mlp")(z)


def _module(config: TimarConfig) -> nn.Module:
    if config.head == "diffusion":
        return DiffusionHead(config.head_width, config.head_blocks, config.head_out_dim)
    return MLPHead(config.head_width, config.param_dim)


def init_head(config: TimarConfig, key: PRNGKeyArray) -> dict[str, Any]:
    """Initialise the head's parameters (one frame's worth; shared by all frames).

    Args:
        config: model config (``head`` selects the module).
        key: PRNG key.

    Returns:
        The head's parameter pytree.
    """
    z = jnp.zeros((config.width,), jnp.float32)
    if config.head == "diffusion":
        x = jnp.zeros((config.param_dim,), jnp.float32)
        return _module(config).init(key, x, jnp.zeros((), jnp.float32), z)["params"]
    return _module(config).init(key, z)["params"]


def apply_head(
    params: dict[str, Any],
    config: TimarConfig,
    z: Float[Array, "*frames cond_dim"],
    x: Float[Array, "*frames param_dim"] | None = None,
    t: Float[Array, "*frames"] | None = None,
) -> Float[Array, "*frames out_dim"]:
    """Apply the one-frame head to every frame: ``jax.vmap`` nested over all leading axes.

    Args:
        params: head parameters (:func:`init_head`).
        config: model config.
        z: ``(*F, cond_dim)`` conditioning features.
        x: ``(*F, param_dim)`` noisy frames (diffusion head only).
        t: ``(*F,)`` timesteps (diffusion head only).

    Returns:
        ``(*F, out_dim)`` per-frame outputs.

    Raises:
        ValueError: if the diffusion head is missing ``x``/``t`` or the leading axes disagree.
    """
    module = _module(config)
    apply = compute_in(config.compute_dtype, module.apply)
    lead = z.shape[:-1]
    if config.head == "diffusion":
        if x is None or t is None:
            raise ValueError("the diffusion head needs the noisy frames x and timesteps t")
        if x.shape[:-1] != lead or t.shape != lead:
            raise ValueError(f"leading axes disagree: z {z.shape}, x {x.shape}, t {t.shape}")

        def one(xi: Array, ti: Array, zi: Array) -> Array:
            return apply({"params": params}, xi, ti, zi)

        fn = one
        for _ in lead:
            fn = jax.vmap(fn)
        return fn(x, t.astype(x.dtype), z)

    def one_mlp(zi: Array) -> Array:
        return apply({"params": params}, zi)

    fn = one_mlp
    for _ in lead:
        fn = jax.vmap(fn)
    return fn(z)


def _nest_vmap(fn: Any, depth: int) -> Any:
    for _ in range(depth):
        fn = jax.vmap(fn)
    return fn


def head_condition(
    params: dict[str, Any], config: TimarConfig, z: Float[Array, "*frames cond_dim"]
) -> Float[Array, "*frames head_width"]:
    """``Dense(z)`` of every frame: the diffusion head's step-independent condition (hoisted).

    Args:
        params: head parameters.
        config: model config (diffusion head).
        z: ``(*F, cond_dim)`` conditioning features.

    Returns:
        ``(*F, head_width)``.
    """
    module = _module(config)
    apply = compute_in(config.compute_dtype, module.apply)
    one = lambda zi: apply({"params": params}, zi, method=DiffusionHead.embed_condition)  # noqa: E731
    return _nest_vmap(one, z.ndim - 1)(z)


def apply_head_hoisted(
    params: dict[str, Any],
    config: TimarConfig,
    cz: Float[Array, "batch *frames head_width"],
    x: Float[Array, "batch *frames param_dim"],
    t: Float[Array, " batch"],
) -> Float[Array, "batch *frames out_dim"]:
    """The diffusion head with one timestep per batch row and a precomputed ``Dense(z)``.

    Equal to :func:`apply_head` with ``t`` broadcast over the frames, but the timestep MLP runs once
    per row instead of once per frame and ``Dense(z)`` is not recomputed (sampling loops call this
    every step with the same ``cz``).

    Args:
        params: head parameters.
        config: model config (diffusion head).
        cz: ``(B, *F, head_width)`` from :func:`head_condition`.
        x: ``(B, *F, param_dim)`` noisy frames.
        t: ``(B,)`` timesteps.

    Returns:
        ``(B, *F, out_dim)``.
    """
    module = _module(config)
    apply = compute_in(config.compute_dtype, module.apply)
    temb = jax.vmap(lambda ti: apply({"params": params}, ti, method=DiffusionHead.embed_time))(t.astype(x.dtype))
    c = cz + temb.reshape(temb.shape[:1] + (1,) * (cz.ndim - 2) + temb.shape[1:])
    one = lambda xi, ci: apply({"params": params}, xi, ci, method=DiffusionHead.denoise)  # noqa: E731
    return _nest_vmap(one, x.ndim - 1)(x, c)


def time_embedding(
    params: dict[str, Any], config: TimarConfig, t: Float[Array, "*steps"]
) -> Float[Array, "*steps head_width"]:
    """The diffusion head's timestep embedding of any array of timesteps.

    Args:
        params: head parameters.
        config: model config (diffusion head).
        t: ``(*S,)`` training timesteps (as floats).

    Returns:
        ``(*S, head_width)``.
    """
    module = _module(config)
    apply = compute_in(config.compute_dtype, module.apply)
    one = lambda ti: apply({"params": params}, ti, method=DiffusionHead.embed_time)  # noqa: E731
    return _nest_vmap(one, t.ndim)(t)


def head_modulations(
    params: dict[str, Any], config: TimarConfig, c: Float[Array, "*rows head_width"]
) -> tuple[Float[Array, "*rows _mod"], ...]:
    """Every adaLN modulation of the head for conditions ``c = TimestepEmbedding(t) + Dense(z)``.

    The modulation linears hold 2/3 of the head's FLOPs (3K + 2 outputs of width d_m per frame
    against 2K for the MLPs) and see only the condition, never the noisy frame: a sampler whose
    timesteps are fixed in advance evaluates them for every (step, frame) pair here, as K + 1
    matmuls of ``steps x frames`` rows instead of ``steps x (K + 1)`` small ones inside its loop.

    Args:
        params: head parameters.
        config: model config (diffusion head).
        c: ``(*R, head_width)`` conditions (any leading axes, e.g. ``(steps, batch, frames)``).

    Returns:
        K arrays ``(*R, 3 head_width)`` (shift, scale, gate of each residual block) and one
        ``(*R, 2 head_width)`` (shift, scale of the final layer), as :meth:`DiffusionHead.denoise`
        takes them.
    """
    names = [f"res_blocks_{i}" for i in range(config.head_blocks)] + ["final"]
    return tuple(adaln_modulation(params[name]["modulation"], c) for name in names)


def apply_head_modulated(
    params: dict[str, Any],
    config: TimarConfig,
    x: Float[Array, "*frames param_dim"],
    modulations: tuple[Float[Array, "*frames _mod"], ...],
) -> Float[Array, "*frames out_dim"]:
    """The diffusion head on noisy frames whose adaLN modulations are precomputed.

    Equal to :func:`apply_head` when ``modulations = head_modulations(params, config, c)`` with
    ``c = TimestepEmbedding(t) + Dense(z)`` of the same frames.

    Args:
        params: head parameters.
        config: model config (diffusion head).
        x: ``(*F, param_dim)`` noisy frames.
        modulations: :func:`head_modulations` of the frames' conditions, each ``(*F, ...)``.

    Returns:
        ``(*F, out_dim)``.

    Raises:
        ValueError: if the number of modulations is not ``head_blocks + 1``.
    """
    if len(modulations) != config.head_blocks + 1:
        raise ValueError(f"expected {config.head_blocks + 1} modulations (K blocks + final), got {len(modulations)}")
    module = _module(config)
    apply = compute_in(config.compute_dtype, module.apply)

    def one(xi: Array, mods: tuple[Array, ...]) -> Array:
        return apply({"params": params}, xi, None, mods, method=DiffusionHead.denoise)

    return _nest_vmap(one, x.ndim - 1)(x, tuple(modulations))
