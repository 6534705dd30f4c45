"""Multi-head dot-product attention with an additive bias and key/value caching.

Masks enter every attention layer of jaxtalk as an ADDITIVE bias: ``0`` where a query may see a key,
a large finite negative number where it may not. Static boolean masks (chunk, band, turn-causal,
padding) are built in NumPy and turned into a bias once with the one helper,
:func:`jaxtalk.masks.mask_to_bias`.

Incremental decoding: :class:`MultiHeadAttention` can return the keys/values it attended to
(``return_kv=True``) and accept them back as ``kv_cache`` on the next call, where they are prepended
to the keys/values of the new inputs. A model that processes turns (TIMAR) or chunks (TokTalk
streaming) therefore computes each prefix's keys/values once. For cross-attention to a fixed memory,
:meth:`MultiHeadAttention.project_kv` computes the memory's keys/values once and
:meth:`MultiHeadAttention.attend` reuses them.
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.nn.precision import matmul_layer
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = [
    "Bias",
    "dot_product_attention",
    "MultiHeadAttention",
]

Dtype = Any
Initializer = Any
# Biases are often static NumPy constants built from masks; both kinds are accepted.
Bias = Float[Array, "..."] | Float[np.ndarray, "..."]


def _expand_bias(bias: Array | np.ndarray, target: tuple[int, ...]) -> Array | np.ndarray:
    """Prepends unit axes so ``bias`` has the logits' rank (rank promotion is an error here)."""
    if bias.ndim > len(target):
        raise ValueError(
            f"attention bias has shape {bias.shape}, more axes than the logits {target} "
            "(batch..., heads, q_len, k_len)"
        )
    bias = bias.reshape((1,) * (len(target) - bias.ndim) + bias.shape)
    try:
        broadcast = jnp.broadcast_shapes(bias.shape, target)
    except ValueError:
        broadcast = None
    if broadcast != target:
        raise ValueError(
            f"attention bias of shape {bias.shape} does not broadcast to the logits shape {target} "
            "(batch..., heads, q_len, k_len)"
        )
    return bias


def dot_product_attention(
    query: Float[Array, "*batch q_len heads head_dim"],
    key: Float[Array, "*batch k_len heads head_dim"],
    value: Float[Array, "*batch k_len heads v_dim"],
    bias: Bias | None = None,
    *,
    dropout_rate: float = 0.0,
    dropout_rng: PRNGKeyArray | None = None,
) -> Float[Array, "*batch q_len heads v_dim"]:
    """Scaled dot-product attention, softmax(q k^T / sqrt(d) + bias) v, over any leading batch axes.

    Logits and softmax are computed in float32 whatever the input dtype (bfloat16 logits lose the
    small differences that matter after a large blocking bias); the weights are cast back to the
    value dtype for the second product. A written-out version rather than
    ``jax.nn.dot_product_attention`` because jaxtalk needs any number of batch axes and dropout on the
    attention weights.

    Args:
        query: queries, ``(*batch, q_len, heads, head_dim)``.
        key: keys, ``(*batch, k_len, heads, head_dim)``.
        value: values, ``(*batch, k_len, heads, v_dim)``.
        bias: additive bias broadcastable to ``(*batch, heads, q_len, k_len)`` (leading axes may be
            omitted, e.g. ``(q_len, k_len)``); 0 = visible, :func:`jaxtalk.masks.mask_to_bias`'s
            blocked value = hidden.
        dropout_rate: probability of dropping an attention weight (inverted dropout).
        dropout_rng: PRNG key, required when ``dropout_rate > 0``.

    Returns:
        ``(*batch, q_len, heads, v_dim)`` in the value dtype.

    Raises:
        ValueError: on mismatched batch/head axes, a bias that does not broadcast, or dropout without
            a key.
    """
    if query.shape[:-3] != key.shape[:-3] or key.shape[:-1] != value.shape[:-1]:
        raise ValueError(
            f"attention shapes disagree: query {query.shape}, key {key.shape}, value {value.shape} "
            "(expected (*batch, q_len, heads, d), (*batch, k_len, heads, d), (*batch, k_len, heads, dv))"
        )
    if query.shape[-2:] != key.shape[-2:]:
        raise ValueError(
            f"query heads/head_dim {query.shape[-2:]} differ from key heads/head_dim {key.shape[-2:]}"
        )
    scale = 1.0 / math.sqrt(query.shape[-1])
    logits = jnp.einsum(
        "...qhd,...khd->...hqk", query, key, preferred_element_type=jnp.float32
    ) * jnp.float32(scale)
    if bias is not None:
        logits = logits + _expand_bias(bias, logits.shape).astype(jnp.float32)
    weights = jax.nn.softmax(logits, axis=-1)
    if dropout_rate > 0.0:
        if dropout_rng is None:
            raise ValueError("dropout_rate > 0 needs a dropout_rng")
        keep = jax.random.bernoulli(dropout_rng, 1.0 - dropout_rate, weights.shape)
        weights = jnp.where(keep, weights / (1.0 - dropout_rate), 0.0)
    return jnp.einsum("...hqk,...khd->...qhd", weights.astype(value.dtype), value)


@matmul_layer
class _MergeHeads(nn.Module):
    """Output projection ``(*batch, len, heads, head_dim) -> (*batch, len, features)``.

    Its width defaults to the query width, which is only known at call time, so the parameters are
    created here lazily instead of in :meth:`MultiHeadAttention.setup`.
    """

    features: int | None
    use_bias: bool
    dtype: Dtype | None
    param_dtype: Dtype
    kernel_init: Initializer

    @nn.compact
    def __call__(self, x: Array, default_features: int) -> Array:
        features = self.features or default_features
        heads, head_dim = x.shape[-2:]
        # Kernel laid out (heads, head_dim, out): variance scaling then sees fan_in = heads * head_dim.
        kernel = self.param("kernel", self.kernel_init, (heads, head_dim, features), self.param_dtype)
        bias = (
            self.param("bias", nn.initializers.zeros_init(), (features,), self.param_dtype)
            if self.use_bias
            else None
        )
        x, kernel, bias = nn.dtypes.promote_dtype(x, kernel, bias, dtype=self.dtype)
        # One (heads * head_dim) -> features matmul: the einsum over two contracted axes is the same sum, but
        # ONNX converters lower it by broadcasting the kernel over every batch and frame, which made the
        # exported stream far slower than XLA's (docs/onnx.md).
        y = x.reshape(*x.shape[:-2], heads * head_dim) @ kernel.reshape(heads * head_dim, features)
        if bias is not None:
            y = y + bias.reshape((1,) * (y.ndim - 1) + bias.shape)
        return y


class MultiHeadAttention(nn.Module):
    """Multi-head attention with an additive bias, self or cross, with key/value caching.

    Parameters: ``query``/``key``/``value`` projections ``features -> (heads, head_dim)`` (bias
    optional: CosyVoice's decoder uses none) and an ``out`` projection ``(heads, head_dim) ->
    out_features``. ``num_heads * head_dim`` need not equal the model width (CosyVoice: 8 x 64 heads
    on 256 channels).

    Attributes:
        num_heads: number of heads.
        head_dim: width of each head's queries/keys/values.
        out_features: output width; ``None`` = the query width.
        qkv_bias: whether the q/k/v projections have a bias.
        out_bias: whether the output projection has a bias.
        dropout_rate: dropout on attention weights (active when ``deterministic=False``; needs the
            ``"dropout"`` RNG stream).
        dtype: computation dtype (``None``: inferred from inputs and parameters).
        param_dtype: parameter dtype.
        kernel_init: initialiser of every projection kernel.
    """

    num_heads: int
    head_dim: int
    out_features: int | None = None
    qkv_bias: bool = True
    out_bias: bool = True
    dropout_rate: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    def setup(self) -> None:
        if self.num_heads < 1 or self.head_dim < 1:
            raise ValueError(
                f"num_heads and head_dim must be positive, got {self.num_heads} and {self.head_dim}"
            )

        def projection() -> nn.DenseGeneral:
            return nn.DenseGeneral(
                features=(self.num_heads, self.head_dim),
                use_bias=self.qkv_bias,
                dtype=self.dtype,
                param_dtype=self.param_dtype,
                kernel_init=self.kernel_init,
            )

        self.query = projection()
        self.key = projection()
        self.value = projection()
        self.out = _MergeHeads(
            features=self.out_features,
            use_bias=self.out_bias,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
        )

    def project_kv(
        self, inputs_kv: Float[Array, "*batch k_len kv_features"]
    ) -> tuple[
        Float[Array, "*batch k_len heads head_dim"], Float[Array, "*batch k_len heads head_dim"]
    ]:
        """Keys and values of ``inputs_kv``, to cache a prefix or a cross-attention memory.

        Args:
            inputs_kv: ``(*batch, k_len, kv_features)``.

        Returns:
            ``(keys, values)``, each ``(*batch, k_len, num_heads, head_dim)``.
        """
        return self.key(inputs_kv), self.value(inputs_kv)

    def attend(
        self,
        inputs_q: Float[Array, "*batch q_len features"],
        keys: Float[Array, "*batch k_len heads head_dim"],
        values: Float[Array, "*batch k_len heads head_dim"],
        *,
        bias: Bias | None = None,
        deterministic: bool = True,
    ) -> Float[Array, "*batch q_len out_features"]:
        """Attends from ``inputs_q`` to already projected keys/values (see :meth:`project_kv`).

        Args:
            inputs_q: ``(*batch, q_len, features)``.
            keys: ``(*batch, k_len, num_heads, head_dim)``.
            values: ``(*batch, k_len, num_heads, head_dim)``.
            bias: additive bias broadcastable to ``(*batch, num_heads, q_len, k_len)``.
            deterministic: disables attention dropout.

        Returns:
            ``(*batch, q_len, out_features)``.

        Raises:
            ValueError: if the keys/values do not have ``(num_heads, head_dim)`` trailing axes or
                their batch axes differ from the queries', or the bias does not broadcast.
        """
        expected = (self.num_heads, self.head_dim)
        if keys.shape[-2:] != expected or values.shape[-2:] != expected:
            raise ValueError(
                f"keys {keys.shape} / values {values.shape} must end in (num_heads, head_dim) = "
                f"{expected}"
            )
        query = self.query(inputs_q)
        use_dropout = not deterministic and self.dropout_rate > 0.0
        y = dot_product_attention(
            query,
            keys.astype(query.dtype),
            values.astype(query.dtype),
            bias,
            dropout_rate=self.dropout_rate if use_dropout else 0.0,
            dropout_rng=self.make_rng("dropout") if use_dropout else None,
        )
        return self.out(y, inputs_q.shape[-1])

    def __call__(
        self,
        inputs_q: Float[Array, "*batch q_len features"],
        inputs_kv: Float[Array, "*batch kv_len kv_features"] | None = None,
        *,
        bias: Bias | None = None,
        kv_cache: tuple[
            Float[Array, "*batch cache_len heads head_dim"],
            Float[Array, "*batch cache_len heads head_dim"],
        ]
        | None = None,
        return_kv: bool = False,
        deterministic: bool = True,
    ) -> (
        Float[Array, "*batch q_len out_features"]
        | tuple[
            Float[Array, "*batch q_len out_features"],
            tuple[Float[Array, "*batch k_len heads head_dim"], Float[Array, "*batch k_len heads head_dim"]],
        ]
    ):
        """Self-attention (``inputs_kv=None``) or cross-attention, optionally continuing a cache.

        Keys/values are those of ``kv_cache`` (if given) followed by those of ``inputs_kv`` (or of
        ``inputs_q`` for self-attention), so the bias's key axis has length ``cache_len + kv_len``.
        With a causal or block-causal bias, running a sequence in pieces while carrying the cache
        gives the same outputs as one pass over the whole sequence.

        Args:
            inputs_q: ``(*batch, q_len, features)``.
            inputs_kv: ``(*batch, kv_len, kv_features)``; ``None`` for self-attention.
            bias: additive bias broadcastable to ``(*batch, num_heads, q_len, cache_len + kv_len)``.
            kv_cache: ``(keys, values)`` of earlier positions, each
                ``(*batch, cache_len, num_heads, head_dim)``, as returned with ``return_kv=True``.
            return_kv: also return the keys/values attended to (cache + new), for the next call.
            deterministic: disables attention dropout.

        Returns:
            ``(*batch, q_len, out_features)``; with ``return_kv`` a pair ``(output, (keys, values))``
            whose keys/values are ``(*batch, cache_len + kv_len, num_heads, head_dim)``.

        Raises:
            ValueError: if the cache's batch/head axes do not match the new keys, or the bias does not
                broadcast.
        """
        keys, values = self.project_kv(inputs_q if inputs_kv is None else inputs_kv)
        if kv_cache is not None:
            cache_k, cache_v = kv_cache
            if cache_k.shape != cache_v.shape or (
                cache_k.shape[:-3] + cache_k.shape[-2:] != keys.shape[:-3] + keys.shape[-2:]
            ):
                raise ValueError(
                    f"kv_cache shapes {cache_k.shape} / {cache_v.shape} do not extend the new keys "
                    f"{keys.shape} (expected (*batch, cache_len, num_heads, head_dim))"
                )
            keys = jnp.concatenate([cache_k.astype(keys.dtype), keys], axis=-3)
            values = jnp.concatenate([cache_v.astype(values.dtype), values], axis=-3)
        out = self.attend(inputs_q, keys, values, bias=bias, deterministic=deterministic)
        return (out, (keys, values)) if return_kv else out
