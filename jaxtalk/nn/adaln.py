"""adaLN (adaptive LayerNorm) residual MLP blocks, MAR's ``SimpleMLPAdaLN`` pieces.

A condition vector ``c`` produces per-feature ``(shift, scale, gate)`` through ``Dense(SiLU(c))``.
That Dense is zero-initialised, so at initialisation every residual block is the identity and the
final layer outputs zeros: the diffusion head starts as a predictor of 0, which is what keeps early
training stable.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.nn.mlp import MLP
from jaxtalk.types import Array, Float

__all__ = ["modulate", "adaln_modulation", "AdaLNResBlock", "AdaLNFinalLayer"]

Dtype = Any
Initializer = Any


def modulate(
    x: Float[Array, "*batch features"],
    shift: Float[Array, "*batch features"],
    scale: Float[Array, "*batch features"],
) -> Float[Array, "*batch features"]:
    """``x * (1 + scale) + shift`` (adaLN modulation; the ``1 +`` makes zero modulation neutral).

    Args:
        x: ``(*batch, features)``.
        shift: same shape as ``x``.
        scale: same shape as ``x``.

    Returns:
        ``(*batch, features)``.
    """
    return x * (1 + scale) + shift


def adaln_modulation(
    params: dict[str, Any], c: Float[Array, "*batch cond_features"]
) -> Float[Array, "*batch modulation_features"]:
    """The modulation ``Dense(SiLU(c))`` of an adaLN layer, from that layer's ``"modulation"`` params.

    Lets a caller compute the modulations of many conditions in one batched matmul ahead of time
    (e.g. every (diffusion step, frame) pair of a sampler, whose timesteps are known in advance) and
    feed them to :class:`AdaLNResBlock` / :class:`AdaLNFinalLayer` through ``modulation=``.

    Args:
        params: ``{"kernel": (cond_features, chunks * features), "bias": (chunks * features,)}``,
            i.e. ``layer_params["modulation"]``.
        c: ``(*batch, cond_features)`` conditions.

    Returns:
        ``(*batch, chunks * features)``: ``(shift, scale, gate)`` (res block) or ``(shift, scale)``
        (final layer) concatenated on the last axis.

    Raises:
        ValueError: if ``c``'s width does not match the kernel.
    """
    kernel, bias = params["kernel"], params["bias"]
    if c.shape[-1] != kernel.shape[0]:
        raise ValueError(f"condition width {c.shape[-1]} does not match the modulation kernel {kernel.shape}")
    out = jax.nn.silu(c) @ kernel
    return out + jnp.reshape(bias, (1,) * (out.ndim - 1) + (-1,))  # explicit rank (no promotion)


def _split_modulation(modulation: Array, features: int, chunks: int) -> list[Array]:
    if modulation.shape[-1] != chunks * features:
        raise ValueError(
            f"modulation must have {chunks} x {features} = {chunks * features} features, got {modulation.shape}"
        )
    return jnp.split(modulation, chunks, axis=-1)


def _modulation(
    c: Array | None,
    modulation: Array | None,
    features: int,
    chunks: int,
    dtype: Dtype | None,
    param_dtype: Dtype,
) -> list[Array]:
    """``chunks`` zero-initialised ``(*batch, features)`` maps of ``SiLU(c)`` (or of a precomputed one)."""
    if (c is None) == (modulation is None):
        raise ValueError("pass exactly one of the condition c and a precomputed modulation")
    if modulation is not None:
        return _split_modulation(modulation, features, chunks)
    params = nn.Dense(
        chunks * features,
        dtype=dtype,
        param_dtype=param_dtype,
        kernel_init=nn.initializers.zeros_init(),
        bias_init=nn.initializers.zeros_init(),
        name="modulation",
    )(jax.nn.silu(c))
    return jnp.split(params, chunks, axis=-1)


class AdaLNResBlock(nn.Module):
    """``x + gate * MLP(LayerNorm(x) * (1 + scale) + shift)`` with ``(shift, scale, gate)`` from ``c``.

    The MLP is ``Dense(width * mlp_ratio) -> SiLU -> Dense(width)`` (MAR: ratio 1). The modulation
    Dense is zero-initialised, so the block is the identity at initialisation.

    Attributes:
        mlp_ratio: MLP hidden width / input width.
        activation: MLP activation (SiLU in MAR).
        layer_norm_epsilon: LayerNorm epsilon (1e-6 in MAR).
        use_layer_norm_affine: learnable LayerNorm scale/bias (MAR's block has them).
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: MLP kernel initialiser.
    """

    mlp_ratio: float = 1.0
    activation: Callable[[Array], Array] = jax.nn.silu
    layer_norm_epsilon: float = 1e-6
    use_layer_norm_affine: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.xavier_uniform()

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "*batch features"],
        c: Float[Array, "*batch cond_features"] | None = None,
        *,
        modulation: Float[Array, "*batch modulation_features"] | None = None,
    ) -> Float[Array, "*batch features"]:
        """Applies the block.

        Args:
            x: ``(*batch, features)``.
            c: condition ``(*batch, cond_features)`` with the same leading axes as ``x``.
            modulation: instead of ``c``, a precomputed ``(*batch, 3 features)``
                :func:`adaln_modulation` of this block's ``"modulation"`` params.

        Returns:
            ``(*batch, features)``.

        Raises:
            ValueError: if ``mlp_ratio`` gives a hidden width below 1, if not exactly one of ``c``
                and ``modulation`` is given, or ``modulation`` has the wrong width.
        """
        width = x.shape[-1]
        hidden = int(round(self.mlp_ratio * width))
        if hidden < 1:
            raise ValueError(f"mlp_ratio {self.mlp_ratio} gives hidden width {hidden} for width {width}")
        shift, scale, gate = _modulation(c, modulation, width, 3, self.dtype, self.param_dtype)
        h = nn.LayerNorm(
            epsilon=self.layer_norm_epsilon,
            use_scale=self.use_layer_norm_affine,
            use_bias=self.use_layer_norm_affine,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="norm",
        )(x)
        h = MLP(
            (hidden, width),
            activation=self.activation,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="mlp",
        )(modulate(h, shift, scale))
        return x + gate * h


class AdaLNFinalLayer(nn.Module):
    """``Dense(out)(LayerNorm(x) * (1 + scale) + shift)``, output and modulation zero-initialised.

    The LayerNorm has no learnable affine (as in MAR/DiT); the layer outputs zeros at init.

    Attributes:
        out_features: output width.
        layer_norm_epsilon: LayerNorm epsilon (1e-6).
        dtype: computation dtype; param_dtype: parameter dtype.
    """

    out_features: int
    layer_norm_epsilon: float = 1e-6
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "*batch features"],
        c: Float[Array, "*batch cond_features"] | None = None,
        *,
        modulation: Float[Array, "*batch modulation_features"] | None = None,
    ) -> Float[Array, "*batch {self.out_features}"]:
        """Applies the layer.

        Args:
            x: ``(*batch, features)``.
            c: condition ``(*batch, cond_features)``.
            modulation: instead of ``c``, a precomputed ``(*batch, 2 features)``
                :func:`adaln_modulation` of this layer's ``"modulation"`` params.

        Returns:
            ``(*batch, out_features)``.

        Raises:
            ValueError: if not exactly one of ``c`` and ``modulation`` is given, or ``modulation``
                has the wrong width.
        """
        shift, scale = _modulation(c, modulation, x.shape[-1], 2, self.dtype, self.param_dtype)
        h = nn.LayerNorm(
            epsilon=self.layer_norm_epsilon,
            use_scale=False,
            use_bias=False,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="norm",
        )(x)
        return nn.Dense(
            self.out_features,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=nn.initializers.zeros_init(),
            bias_init=nn.initializers.zeros_init(),
            name="out",
        )(modulate(h, shift, scale))
