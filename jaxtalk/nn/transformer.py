"""Pre-LayerNorm transformer blocks: encoder (self-attention + FF) and decoder (+ cross-attention).

Each sub-layer is ``x + Dropout(F(LayerNorm(x)))``. Attention masks are additive biases (see
:mod:`jaxtalk.nn.attention`). The self-attention of both blocks can carry a key/value cache, so a
stack of blocks can decode turn by turn or chunk by chunk: the cache of a block holds the keys/values
of the layer-normalised inputs it has already seen.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from jaxtalk.nn.attention import Bias, MultiHeadAttention
from jaxtalk.nn.mlp import MLP, gelu_exact
from jaxtalk.types import Array, Float

__all__ = ["FeedForward", "TransformerBlock", "DecoderBlock"]

Dtype = Any
Initializer = Any
# Keys/values of earlier positions, and the cache returned after a call (earlier + new positions).
KVCache = tuple[
    Float[Array, "*batch cache_len heads head_dim"], Float[Array, "*batch cache_len heads head_dim"]
]
UpdatedKVCache = tuple[
    Float[Array, "*batch total_len heads head_dim"], Float[Array, "*batch total_len heads head_dim"]
]


class FeedForward(nn.Module):
    """Position-wise feed-forward ``Dense(ratio * width) -> activation -> Dropout -> Dense(width)``.

    Attributes:
        mlp_ratio: hidden width as a multiple of the input width (4 in every paper here).
        out_features: output width; ``None`` = input width.
        activation: hidden activation (exact GELU by default, as in PyTorch/CosyVoice).
        dropout_rate: dropout after the hidden activation.
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: kernel initialiser.
    """

    mlp_ratio: float = 4.0
    out_features: int | None = None
    activation: Callable[[Array], Array] = gelu_exact
    dropout_rate: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch features"], *, deterministic: bool = True
    ) -> Float[Array, "*batch out_features"]:
        """Applies the feed-forward to every position.

        Args:
            x: ``(*batch, features)``.
            deterministic: disables dropout.

        Returns:
            ``(*batch, out_features)``.

        Raises:
            ValueError: if ``mlp_ratio`` gives a hidden width below 1.
        """
        width = x.shape[-1]
        hidden = int(round(self.mlp_ratio * width))
        if hidden < 1:
            raise ValueError(f"mlp_ratio {self.mlp_ratio} gives hidden width {hidden} for width {width}")
        return MLP(
            (hidden, self.out_features or width),
            activation=self.activation,
            dropout_rate=self.dropout_rate,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="mlp",
        )(x, deterministic=deterministic)


class _AttentionSublayer(nn.Module):
    """``x + Dropout(Attention(LayerNorm(x), memory))``; self-attention when ``memory`` is None."""

    num_heads: int
    head_dim: int
    qkv_bias: bool
    dropout_rate: float
    attention_dropout_rate: float
    layer_norm_epsilon: float
    dtype: Dtype | None
    param_dtype: Dtype
    kernel_init: Initializer

    @nn.compact
    def __call__(
        self,
        x: Array,
        memory: Array | None,
        bias: Array | None,
        kv_cache: KVCache | None,
        return_kv: bool,
        deterministic: bool,
    ) -> Array | tuple[Array, UpdatedKVCache]:
        h = nn.LayerNorm(
            epsilon=self.layer_norm_epsilon,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="norm",
        )(x)
        result = MultiHeadAttention(
            num_heads=self.num_heads,
            head_dim=self.head_dim,
            qkv_bias=self.qkv_bias,
            dropout_rate=self.attention_dropout_rate,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="attention",
        )(
            h,
            memory,
            bias=bias,
            kv_cache=kv_cache,
            return_kv=return_kv,
            deterministic=deterministic,
        )
        y, cache = result if return_kv else (result, None)
        x = x + nn.Dropout(self.dropout_rate)(y, deterministic=deterministic)
        return (x, cache) if return_kv else x


class _FeedForwardSublayer(nn.Module):
    """``x + Dropout(FeedForward(LayerNorm(x)))``."""

    mlp_ratio: float
    activation: Callable[[Array], Array]
    dropout_rate: float
    layer_norm_epsilon: float
    dtype: Dtype | None
    param_dtype: Dtype
    kernel_init: Initializer

    @nn.compact
    def __call__(self, x: Array, deterministic: bool) -> Array:
        h = nn.LayerNorm(
            epsilon=self.layer_norm_epsilon,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="norm",
        )(x)
        y = FeedForward(
            mlp_ratio=self.mlp_ratio,
            activation=self.activation,
            dropout_rate=self.dropout_rate,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="feed_forward",
        )(h, deterministic=deterministic)
        return x + nn.Dropout(self.dropout_rate)(y, deterministic=deterministic)


class TransformerBlock(nn.Module):
    """Pre-LN encoder block: self-attention then feed-forward, each with a residual.

    Attributes:
        num_heads: attention heads.
        head_dim: width per head (``num_heads * head_dim`` need not equal the model width).
        mlp_ratio: feed-forward hidden width / model width.
        qkv_bias: whether q/k/v projections have biases (CosyVoice: no).
        dropout_rate: dropout on each residual branch and inside the feed-forward.
        attention_dropout_rate: dropout on attention weights.
        layer_norm_epsilon: LayerNorm epsilon (1e-5, PyTorch's default).
        activation: feed-forward activation (exact GELU).
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: kernel initialiser.
    """

    num_heads: int
    head_dim: int
    mlp_ratio: float = 4.0
    qkv_bias: bool = True
    dropout_rate: float = 0.0
    attention_dropout_rate: float = 0.0
    layer_norm_epsilon: float = 1e-5
    activation: Callable[[Array], Array] = gelu_exact
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    def _attention(self, name: str) -> _AttentionSublayer:
        return _AttentionSublayer(
            num_heads=self.num_heads,
            head_dim=self.head_dim,
            qkv_bias=self.qkv_bias,
            dropout_rate=self.dropout_rate,
            attention_dropout_rate=self.attention_dropout_rate,
            layer_norm_epsilon=self.layer_norm_epsilon,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name=name,
        )

    def _feed_forward(self) -> _FeedForwardSublayer:
        return _FeedForwardSublayer(
            mlp_ratio=self.mlp_ratio,
            activation=self.activation,
            dropout_rate=self.dropout_rate,
            layer_norm_epsilon=self.layer_norm_epsilon,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="feed_forward",
        )

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "*batch time features"],
        *,
        bias: Bias | None = None,
        kv_cache: KVCache | None = None,
        return_kv: bool = False,
        deterministic: bool = True,
    ) -> (
        Float[Array, "*batch time features"]
        | tuple[Float[Array, "*batch time features"], UpdatedKVCache]
    ):
        """Applies the block.

        Args:
            x: ``(*batch, time, features)``.
            bias: self-attention bias broadcastable to ``(*batch, heads, time, cache_len + time)``.
            kv_cache: self-attention keys/values of earlier positions (from ``return_kv=True``).
            return_kv: also return the self-attention keys/values (cache + new).
            deterministic: disables dropout.

        Returns:
            ``(*batch, time, features)``; with ``return_kv`` also the updated ``(keys, values)``.
        """
        result = self._attention("self_attention")(
            x, None, bias, kv_cache, return_kv, deterministic
        )
        x, cache = result if return_kv else (result, None)
        x = self._feed_forward()(x, deterministic)
        return (x, cache) if return_kv else x


class DecoderBlock(TransformerBlock):
    """Pre-LN decoder block: self-attention, cross-attention to a memory, feed-forward.

    FreeTalk's audio-to-sparse (ATS) denoiser: motion tokens attend to themselves (band bias) and to
    the audio features (cross bias). Same attributes as :class:`TransformerBlock`; the
    cross-attention uses the same heads. The memory is not normalised here (it is an encoder output
    or a projected feature track).
    """

    @nn.compact
    def __call__(  # type: ignore[override]
        self,
        x: Float[Array, "*batch time features"],
        memory: Float[Array, "*batch mem_len mem_features"],
        *,
        self_bias: Bias | None = None,
        cross_bias: Bias | None = None,
        kv_cache: KVCache | None = None,
        return_kv: bool = False,
        deterministic: bool = True,
    ) -> (
        Float[Array, "*batch time features"]
        | tuple[Float[Array, "*batch time features"], UpdatedKVCache]
    ):
        """Applies the block.

        Args:
            x: ``(*batch, time, features)``.
            memory: ``(*batch, mem_len, mem_features)`` attended to by the cross-attention.
            self_bias: broadcastable to ``(*batch, heads, time, cache_len + time)``.
            cross_bias: broadcastable to ``(*batch, heads, time, mem_len)``.
            kv_cache: self-attention keys/values of earlier positions.
            return_kv: also return the self-attention keys/values (cache + new).
            deterministic: disables dropout.

        Returns:
            ``(*batch, time, features)``; with ``return_kv`` also the updated ``(keys, values)``.
        """
        result = self._attention("self_attention")(
            x, None, self_bias, kv_cache, return_kv, deterministic
        )
        x, cache = result if return_kv else (result, None)
        x = self._attention("cross_attention")(x, memory, cross_bias, None, False, deterministic)
        x = self._feed_forward()(x, deterministic)
        return (x, cache) if return_kv else x
