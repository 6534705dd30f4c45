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
from jaxtalk.nn import MLP, AdaLNFinalLayer, AdaLNResBlock, TimestepEmbedding
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = ["DiffusionHead", "MLPHead", "init_head", "apply_head"]


class DiffusionHead(nn.Module):
    """adaLN residual MLP denoiser of one frame: ``(x_t, t, z) -> x0`` (and variance channels).

    Attributes:
        width: hidden width d_m.
        blocks: residual adaLN blocks K.
        out_dim: output width (56, or 112 with a learned variance).
    """

    width: int
    blocks: int
    out_dim: int

    @nn.compact
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
        c = TimestepEmbedding(self.width, frequency_dim=256, order="cos_sin", name="time_embed")(t)
        c = c + nn.Dense(self.width, name="cond_embed")(z)
        h = nn.Dense(self.width, name="input_proj")(x)
        for k in range(self.blocks):  # K is a static handful of layers
            h = AdaLNResBlock(name=f"block_{k}")(h, c)
        return AdaLNFinalLayer(self.out_dim, name="final")(h, c)


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
    config: TimarConfig,
    params: dict[str, Any],
    z: Float[Array, "*frames cond_dim"],
    x: Float[Array, "*frames param_dim"] | None = None,
    t: Float[Array, "*frames"] | None = None,
) -> Float[Array, "*frames out_dim"]:
    """Apply the one-frame head to every frame: ``jax.vmap`` nested over all leading axes.

    Args:
        config: model config.
        params: head parameters (:func:`init_head`).
        z: ``(*F, cond_dim)`` conditioning features.
        x: ``(*F, param_dim)`` noisy frames (diffusion head only).
        t: ``(*F,)`` timesteps (diffusion head only).

    Returns:
        ``(*F, out_dim)`` per-frame outputs.

    Raises:
        ValueError: if the diffusion head is missing ``x``/``t`` or the leading axes disagree.
    """
    module = _module(config)
    lead = z.shape[:-1]
    if config.head == "diffusion":
        if x is None or t is None:
            raise ValueError("the diffusion head needs the noisy frames x and timesteps t")
        if x.shape[:-1] != lead or t.shape != lead:
            raise ValueError(f"leading axes disagree: z {z.shape}, x {x.shape}, t {t.shape}")

        def one(xi: Array, ti: Array, zi: Array) -> Array:
            return module.apply({"params": params}, xi, ti, zi)

        fn = one
        for _ in lead:
            fn = jax.vmap(fn)
        return fn(x, t.astype(x.dtype), z)

    def one_mlp(zi: Array) -> Array:
        return module.apply({"params": params}, zi)

    fn = one_mlp
    for _ in lead:
        fn = jax.vmap(fn)
    return fn(z)
