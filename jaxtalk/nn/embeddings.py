"""Sinusoidal embeddings of diffusion/flow times (and positions) and the timestep MLP.

Two conventions meet in jaxtalk:

* CosyVoice / Matcha-TTS (TokTalk's decoder): ``[sin, cos]`` of ``1000 * t`` for ``t`` in [0, 1],
  width 320, frequencies ``exp(-log(10000) * i / (half - 1))`` -> ``freq_shift=1``.
* DiT / MAR (TIMAR's diffusion head): ``[cos, sin]`` of integer steps, width 256, frequencies
  ``exp(-log(10000) * i / half)`` -> ``freq_shift=0``.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.types import Array, Float, Shaped

__all__ = ["sinusoidal_embedding", "TimestepEmbedding"]

Dtype = Any
Initializer = Any
Order = Literal["sin_cos", "cos_sin"]


def sinusoidal_embedding(
    t: Shaped[Array, "*batch"] | float | int,
    dim: int,
    *,
    order: Order = "sin_cos",
    scale: float | Float[Array, ""] = 1.0,
    max_period: float = 10000.0,
    freq_shift: float = 0.0,
) -> Float[Array, "*batch {dim}"]:
    """Sinusoidal features of scalar times or positions.

    With ``half = dim // 2`` and ``f_i = exp(-log(max_period) * i / (half - freq_shift))`` for
    ``i = 0..half-1``, the embedding of ``t`` is ``[sin(scale t f), cos(scale t f)]``
    (``order="sin_cos"``) or ``[cos(...), sin(...)]`` (``"cos_sin"``), followed by one zero when
    ``dim`` is odd.

    Args:
        t: times or positions, any shape (integers are converted to float).
        dim: embedding width (static).
        order: ``"sin_cos"`` (CosyVoice) or ``"cos_sin"`` (DiT/MAR).
        scale: multiplies ``t`` before the sinusoids (CosyVoice: 1000); may be a traced scalar.
        max_period: the longest period, ``2 pi max_period`` in units of ``scale * t``.
        freq_shift: 0 (DiT/MAR, diffusers ``downscale_freq_shift=0``) or 1 (CosyVoice/Matcha).

    Returns:
        ``(*batch, dim)`` float32 (float64 when ``t`` is float64).

    Raises:
        ValueError: on ``dim < 2``, an unknown ``order``, a non-positive ``max_period``, or a
            ``freq_shift`` that leaves no positive denominator.
    """
    half = dim // 2
    if dim < 2:
        raise ValueError(f"sinusoidal_embedding needs dim >= 2, got {dim}")
    if order not in ("sin_cos", "cos_sin"):
        raise ValueError(f"order must be 'sin_cos' or 'cos_sin', got {order!r}")
    if not max_period > 0:
        raise ValueError(f"max_period must be positive, got {max_period}")
    if not half - freq_shift > 0:
        raise ValueError(f"freq_shift {freq_shift} must be below dim // 2 = {half}")
    t = jnp.asarray(t)
    dtype = t.dtype if jnp.issubdtype(t.dtype, jnp.floating) else jnp.float32
    dtype = jnp.promote_types(dtype, jnp.float32)
    freqs = jnp.exp(
        jnp.arange(half, dtype=dtype) * jnp.asarray(-math.log(max_period) / (half - freq_shift), dtype)
    )
    scale = jnp.asarray(scale, dtype)
    if scale.ndim:
        raise ValueError(f"scale must be a scalar, got shape {scale.shape}")
    args = (t.astype(dtype) * scale)[..., None] * freqs.reshape((1,) * t.ndim + (half,))
    sin, cos = jnp.sin(args), jnp.cos(args)
    parts = [sin, cos] if order == "sin_cos" else [cos, sin]
    if dim % 2:
        parts.append(jnp.zeros(args.shape[:-1] + (1,), dtype))
    return jnp.concatenate(parts, axis=-1)


class TimestepEmbedding(nn.Module):
    """Sinusoid -> Dense(hidden) -> SiLU -> Dense(features): the time conditioning of both decoders.

    CosyVoice: ``TimestepEmbedding(1024, frequency_dim=320, order="sin_cos", scale=1000.0,
    freq_shift=1.0)``. MAR: ``TimestepEmbedding(width, frequency_dim=256, order="cos_sin")``.

    Attributes:
        features: output width.
        hidden_features: hidden width; ``None`` = ``features``.
        frequency_dim: width of the sinusoidal features.
        order, scale, max_period, freq_shift: see :func:`sinusoidal_embedding`.
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: kernel initialiser.
    """

    features: int
    hidden_features: int | None = None
    frequency_dim: int = 256
    order: Order = "cos_sin"
    scale: float = 1.0
    max_period: float = 10000.0
    freq_shift: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    @nn.compact
    def __call__(self, t: Shaped[Array, "*batch"]) -> Float[Array, "*batch {self.features}"]:
        """Embeds times ``t``.

        Args:
            t: times or integer steps, any shape.

        Returns:
            ``(*batch, features)``.
        """
        emb = sinusoidal_embedding(
            t,
            self.frequency_dim,
            order=self.order,
            scale=self.scale,
            max_period=self.max_period,
            freq_shift=self.freq_shift,
        )
        dense = lambda width, name: nn.Dense(  # noqa: E731
            width,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name=name,
        )
        h = jax.nn.silu(dense(self.hidden_features or self.features, "hidden")(emb))
        return dense(self.features, "out")(h)
