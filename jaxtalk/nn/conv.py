"""1-D convolution blocks over ``(*batch, time, channels)`` sequences with padding masks.

The pieces of CosyVoice's flow-matching U-Net decoder (which TokTalk adapts): ``Conv1d``,
``Conv1dBlock`` (conv -> norm -> Mish, masked), ``ResnetBlock1D`` (two blocks, the time embedding
added between them, 1x1-conv residual), ``Downsample1D`` and ``Upsample1D``. Every layer has a causal
variant (left padding ``k - 1``; output frame ``t`` depends only on input frames ``<= t``), used by
the streaming decoder.

Masks are ``(*batch, time)``, True/1 on real frames. Padded frames are zeroed before every
convolution, and the group norm takes its statistics over real frames only, so the outputs on real
frames do not depend on how much padding follows them. (CosyVoice's ``GroupNorm`` counts padded
frames in its statistics; jaxtalk deliberately does not.)

Lengths: ``Downsample1D`` maps ``T -> ceil(T / 2)`` (7 -> 4, 8 -> 4) and ``Upsample1D`` maps
``T -> 2 T``, so a down/up round trip on an odd length gives ``T + 1`` frames: crop to the skip
connection's length, as CosyVoice does.
"""

from __future__ import annotations

from typing import Any, Literal

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, Shaped

__all__ = [
    "masked_group_norm",
    "downsample_mask",
    "upsample_mask",
    "Conv1d",
    "MaskedGroupNorm",
    "Conv1dBlock",
    "ResnetBlock1D",
    "Downsample1D",
    "Upsample1D",
]

Dtype = Any
Initializer = Any
# Padding masks may come straight from the NumPy data pipeline.
Mask = Shaped[Array, "*batch time"] | Shaped[np.ndarray, "*batch time"]


def _frame_weights(mask: Array | np.ndarray | None, x: Array) -> Array | None:
    """``(*batch, time, 1)`` 0/1 weights in ``x``'s dtype, checked against ``x``'s leading axes."""
    if mask is None:
        return None
    if mask.shape != x.shape[:-1]:
        raise ValueError(
            f"mask shape {mask.shape} does not match the input's (*batch, time) = {x.shape[:-1]}"
        )
    return jnp.asarray(mask).astype(x.dtype)[..., None]


def _apply_mask(x: Array, mask: Array | np.ndarray | None) -> Array:
    weights = _frame_weights(mask, x)
    return x if weights is None else x * weights


def masked_group_norm(
    x: Float[Array, "*batch time channels"],
    mask: Mask | None = None,
    *,
    num_groups: int = 8,
    epsilon: float = 1e-5,
) -> Float[Array, "*batch time channels"]:
    """Group normalisation over (time, channels-in-group), statistics over real frames only.

    Without affine parameters (see :class:`MaskedGroupNorm`). Statistics are computed in float32
    (two-pass variance). A sequence with no real frame gets zero mean and unit variance instead of
    NaN.

    Args:
        x: ``(*batch, time, channels)``.
        mask: ``(*batch, time)``, nonzero on real frames; ``None`` = all real.
        num_groups: channel groups (must divide ``channels``).
        epsilon: added to the variance.

    Returns:
        ``(*batch, time, channels)`` in ``x``'s dtype; padded frames hold normalised garbage (mask
        them afterwards).

    Raises:
        ValueError: if ``num_groups`` does not divide the channels or the mask shape is wrong.
    """
    channels = x.shape[-1]
    if num_groups < 1 or channels % num_groups:
        raise ValueError(f"num_groups {num_groups} does not divide the {channels} channels")
    xf = x.astype(jnp.promote_types(x.dtype, jnp.float32))
    grouped = xf.reshape(x.shape[:-1] + (num_groups, channels // num_groups))
    weights = _frame_weights(mask, xf)
    weights = (
        jnp.ones(grouped.shape[:-3] + (grouped.shape[-3], 1, 1), xf.dtype)
        if weights is None
        else weights[..., None]
    )
    axes = (-3, -1)
    count = jnp.sum(weights, axis=axes, keepdims=True) * (channels // num_groups)
    count = jnp.maximum(count, 1.0)
    mean = jnp.sum(grouped * weights, axis=axes, keepdims=True) / count
    centred = grouped - mean
    var = jnp.sum(jnp.square(centred) * weights, axis=axes, keepdims=True) / count
    normed = centred * jax.lax.rsqrt(var + epsilon)
    return normed.reshape(x.shape).astype(x.dtype)


def downsample_mask(mask: Mask) -> Shaped[Array, "*batch down_time"]:
    """The mask of a :class:`Downsample1D` output: frame ``i`` is real iff input frame ``2 i`` is.

    Args:
        mask: ``(*batch, time)``.

    Returns:
        ``(*batch, ceil(time / 2))``.
    """
    return jnp.asarray(mask)[..., ::2]


def upsample_mask(mask: Mask) -> Shaped[Array, "*batch up_time"]:
    """The mask of an :class:`Upsample1D` output: each frame's flag repeated twice.

    Args:
        mask: ``(*batch, time)``.

    Returns:
        ``(*batch, 2 * time)``.
    """
    return jnp.repeat(mask, 2, axis=-1)


class Conv1d(nn.Module):
    """1-D convolution over the time axis, ``same``-length or causal, any leading batch axes.

    Non-causal padding is ``((k - 1) // 2, k // 2)`` (odd ``k``: ``k // 2`` both sides, as in
    PyTorch's ``padding=k // 2``); causal padding is ``(k - 1, 0)``. With ``strides=s`` the output
    has ``ceil(T / s)`` frames.

    Attributes:
        features: output channels.
        kernel_size: taps.
        strides: stride over time.
        causal: left padding only.
        use_bias: conv bias.
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: kernel initialiser.
    """

    features: int
    kernel_size: int = 3
    strides: int = 1
    causal: bool = False
    use_bias: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch time channels"]
    ) -> Float[Array, "*batch out_time {self.features}"]:
        """Convolves ``x``.

        Args:
            x: ``(*batch, time, channels)``.

        Returns:
            ``(*batch, ceil(time / strides), features)``.

        Raises:
            ValueError: on a non-positive kernel size or stride, or an empty time axis.
        """
        k, s = self.kernel_size, self.strides
        if k < 1 or s < 1:
            raise ValueError(f"kernel_size and strides must be positive, got {k} and {s}")
        if x.shape[-2] < 1:
            raise ValueError(f"Conv1d got an empty time axis: input shape {x.shape}")
        # Total padding k - 1 gives floor((T - 1) / s) + 1 = ceil(T / s) output frames.
        pad = (k - 1, 0) if self.causal else ((k - 1) // 2, k // 2)
        return nn.Conv(
            self.features,
            (k,),
            strides=(s,),
            padding=(pad,),
            use_bias=self.use_bias,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="conv",
        )(x)


class MaskedGroupNorm(nn.Module):
    """:func:`masked_group_norm` with a learnable per-channel scale and bias.

    Attributes:
        num_groups: channel groups (8 in CosyVoice).
        epsilon: variance epsilon (1e-5, PyTorch's default).
        use_scale, use_bias: learnable affine.
        dtype: output dtype (``None``: the input's); param_dtype: parameter dtype.
    """

    num_groups: int = 8
    epsilon: float = 1e-5
    use_scale: bool = True
    use_bias: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch time channels"], mask: Mask | None = None
    ) -> Float[Array, "*batch time channels"]:
        """Normalises ``x`` (see :func:`masked_group_norm`) and applies the affine.

        Args:
            x: ``(*batch, time, channels)``.
            mask: ``(*batch, time)``; ``None`` = all frames real.

        Returns:
            ``(*batch, time, channels)``.
        """
        dtype = x.dtype if self.dtype is None else self.dtype
        y = masked_group_norm(x, mask, num_groups=self.num_groups, epsilon=self.epsilon).astype(dtype)
        channels = x.shape[-1]
        # Explicit reshape to the input's rank: implicit rank promotion is an error in jaxtalk.
        as_row = lambda p: p.astype(dtype).reshape((1,) * (x.ndim - 1) + (channels,))  # noqa: E731
        if self.use_scale:
            y = y * as_row(self.param("scale", nn.initializers.ones_init(), (channels,), self.param_dtype))
        if self.use_bias:
            y = y + as_row(self.param("bias", nn.initializers.zeros_init(), (channels,), self.param_dtype))
        return y


class Conv1dBlock(nn.Module):
    """``Mish(Norm(Conv(x * mask))) * mask``, CosyVoice's ``Block1D`` / ``CausalBlock1D``.

    The norm is a masked group norm for the offline block; the causal block uses a per-frame
    LayerNorm (as CosyVoice2 does), because group statistics over time would let future frames
    change past outputs.

    Attributes:
        features: output channels.
        kernel_size: conv taps (3).
        causal: causal conv and per-frame norm.
        norm: ``"group"`` or ``"layer"``; ``None`` = ``"layer"`` if causal else ``"group"``.
        num_groups: groups of the group norm.
        dtype: computation dtype; param_dtype: parameter dtype.
    """

    features: int
    kernel_size: int = 3
    causal: bool = False
    norm: Literal["group", "layer"] | None = None
    num_groups: int = 8
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch time channels"], mask: Mask | None = None
    ) -> Float[Array, "*batch time {self.features}"]:
        """Applies the block.

        Args:
            x: ``(*batch, time, channels)``.
            mask: ``(*batch, time)``; ``None`` = all frames real.

        Returns:
            ``(*batch, time, features)``, zero on padded frames.

        Raises:
            ValueError: on a causal block with a group norm (it would leak the future), an unknown
                norm, or a wrong mask shape.
        """
        norm = self.norm or ("layer" if self.causal else "group")
        if norm not in ("group", "layer"):
            raise ValueError(f"norm must be 'group' or 'layer', got {norm!r}")
        if self.causal and norm == "group":
            raise ValueError(
                "a causal Conv1dBlock cannot use a group norm: its statistics over time would make "
                "past outputs depend on future frames; use norm='layer'"
            )
        h = Conv1d(
            self.features,
            self.kernel_size,
            causal=self.causal,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="conv",
        )(_apply_mask(x, mask))
        if norm == "group":
            h = MaskedGroupNorm(
                self.num_groups, dtype=self.dtype, param_dtype=self.param_dtype, name="norm"
            )(h, mask)
        else:
            h = nn.LayerNorm(
                epsilon=1e-5, dtype=self.dtype, param_dtype=self.param_dtype, name="norm"
            )(h)
        return _apply_mask(jax.nn.mish(h), mask)


class ResnetBlock1D(nn.Module):
    """CosyVoice's ``ResnetBlock1D``: block1 -> + Dense(Mish(time_emb)) -> block2, 1x1-conv residual.

    The time embedding enters the decoder only here, added to every frame between the two blocks.

    Attributes:
        features: output channels.
        kernel_size: conv taps of both blocks.
        causal: causal blocks (per-frame LayerNorm).
        norm: see :class:`Conv1dBlock`.
        num_groups: group-norm groups.
        dtype: computation dtype; param_dtype: parameter dtype.
    """

    features: int
    kernel_size: int = 3
    causal: bool = False
    norm: Literal["group", "layer"] | None = None
    num_groups: int = 8
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "*batch time channels"],
        mask: Mask | None,
        time_emb: Float[Array, "*batch time_features"],
    ) -> Float[Array, "*batch time {self.features}"]:
        """Applies the block.

        Args:
            x: ``(*batch, time, channels)``.
            mask: ``(*batch, time)``; ``None`` = all frames real.
            time_emb: ``(*batch, time_features)``, one vector per sequence.

        Returns:
            ``(*batch, time, features)``; padded frames hold only the residual of zeroed input
            (the conv bias).
        """
        block = lambda name: Conv1dBlock(  # noqa: E731
            self.features,
            self.kernel_size,
            causal=self.causal,
            norm=self.norm,
            num_groups=self.num_groups,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name=name,
        )
        h = block("block1")(x, mask)
        t = nn.Dense(
            self.features, dtype=self.dtype, param_dtype=self.param_dtype, name="time_proj"
        )(jax.nn.mish(time_emb))
        h = h + t[..., None, :]
        h = block("block2")(h, mask)
        residual = Conv1d(
            self.features, 1, dtype=self.dtype, param_dtype=self.param_dtype, name="residual"
        )(_apply_mask(x, mask))
        return h + residual


class Downsample1D(nn.Module):
    """Stride-2 convolution (k=3, padding 1; causal: left padding 2): ``T -> ceil(T / 2)``.

    Output frame ``i`` covers input frames ``2i-1..2i+1`` (causal: ``2i-2..2i``).

    Attributes:
        features: output channels; ``None`` = input channels.
        causal: left padding only.
        dtype: computation dtype; param_dtype: parameter dtype.
    """

    features: int | None = None
    causal: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch time channels"], mask: Mask | None = None
    ) -> Float[Array, "*batch down_time out_channels"]:
        """Downsamples ``x`` by 2 in time.

        Args:
            x: ``(*batch, time, channels)``.
            mask: ``(*batch, time)``: padded input frames are zeroed and the output is multiplied
                by :func:`downsample_mask`; ``None`` = all real.

        Returns:
            ``(*batch, ceil(time / 2), features)``.
        """
        y = Conv1d(
            self.features or x.shape[-1],
            3,
            strides=2,
            causal=self.causal,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="conv",
        )(_apply_mask(x, mask))
        return y if mask is None else _apply_mask(y, downsample_mask(mask))


class Upsample1D(nn.Module):
    """Stride-2 transposed convolution (k=4): ``T -> 2 T``.

    Offline: PyTorch's ``ConvTranspose1d(k=4, stride=2, padding=1)`` (output frame ``o`` mixes input
    frames ``(o-1)//2`` and ``(o+1)//2``, one of them in the future). Causal: the same transposed conv
    cropped on the right instead, so output frames ``2m`` and ``2m+1`` mix input frames ``m-1`` and
    ``m`` only.

    Attributes:
        features: output channels; ``None`` = input channels.
        causal: causal crop.
        dtype: computation dtype; param_dtype: parameter dtype.
    """

    features: int | None = None
    causal: bool = False
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch time channels"], mask: Mask | None = None
    ) -> Float[Array, "*batch up_time out_channels"]:
        """Upsamples ``x`` by 2 in time.

        Args:
            x: ``(*batch, time, channels)``.
            mask: ``(*batch, time)``: padded input frames are zeroed and the output is multiplied
                by :func:`upsample_mask`; ``None`` = all real.

        Returns:
            ``(*batch, 2 * time, features)``.

        Raises:
            ValueError: on an empty time axis.
        """
        length = x.shape[-2]
        if length < 1:
            raise ValueError(f"Upsample1D got an empty time axis: input shape {x.shape}")
        # 'VALID' transposed conv: (T - 1) * 2 + 4 = 2T + 2 frames; frame 2m + j gets input m via tap j.
        full = nn.ConvTranspose(
            self.features or x.shape[-1],
            (4,),
            strides=(2,),
            padding="VALID",
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="conv",
        )(_apply_mask(x, mask))
        start = 0 if self.causal else 1
        y = full[..., start : start + 2 * length, :]
        return y if mask is None else _apply_mask(y, upsample_mask(mask))
