"""Style encoder (MSMD-style): a reference motion clip -> a Gaussian over style vectors.

Two k3 convolutions to ``style_hidden`` (ELU, LayerNorm, dropout), a sinusoidal positional encoding
that differs per frame (the reference adds one constant vector to every frame by mistake), one
transformer encoder layer, a k3 convolution to ``2 * style_dim``, and a masked mean over time giving
``(mu, logvar)``. Trained jointly with the decoder with a small KL weight; inference uses ``mu``.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.masks import mask_to_bias, padding_mask
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.nn import Conv1d, TransformerBlock, sinusoidal_embedding
from jaxtalk.types import Array, Bool, Float

__all__ = ["StyleEncoder", "kl_divergence"]


def kl_divergence(
    mu: Float[Array, "batch style"], logvar: Float[Array, "batch style"]
) -> Float[Array, ""]:
    """``KL(N(mu, exp(logvar)) || N(0, I))`` summed over style dimensions, averaged over the batch.

    Args:
        mu: ``(B, S)`` means.
        logvar: ``(B, S)`` log-variances.

    Returns:
        Scalar KL divergence (nats).
    """
    kl = 0.5 * jnp.sum(jnp.square(mu) + jnp.exp(logvar) - 1.0 - logvar, axis=-1)
    return jnp.mean(kl)


class StyleEncoder(nn.Module):
    """Reference clip ``(B, S, param_dim)`` -> ``(mu, logvar)``, each ``(B, style_dim)``.

    Attributes:
        config: static model settings.
    """

    config: TokTalkConfig

    @nn.compact
    def __call__(
        self,
        clip: Float[Array, "batch frames param"],
        mask: Bool[Array, "batch frames"] | None = None,
        deterministic: bool = True,
    ) -> tuple[Float[Array, "batch style"], Float[Array, "batch style"]]:
        """Encodes a reference clip.

        Args:
            clip: ``(B, S, param_dim)`` reference motion.
            mask: ``(B, S)`` True on real frames (None: all real).
            deterministic: disables dropout.

        Returns:
            ``(mu, logvar)``, each ``(B, style_dim)``.
        """
        cfg = self.config
        if mask is None:
            mask = jnp.ones(clip.shape[:2], dtype=bool)
        maskf = mask.astype(clip.dtype)[..., None]
        h = clip * maskf
        for i in range(2):
            h = Conv1d(cfg.style_hidden, 3, name=f"conv_{i}")(h * maskf)
            h = nn.LayerNorm(name=f"norm_{i}")(jax.nn.elu(h))
            h = nn.Dropout(cfg.dropout)(h, deterministic=deterministic)
        positions = jnp.arange(clip.shape[1], dtype=h.dtype)
        h = h + sinusoidal_embedding(positions, cfg.style_hidden).astype(h.dtype)[None]
        bias = mask_to_bias(padding_mask(mask), jnp.float32)
        h = TransformerBlock(
            num_heads=cfg.style_heads,
            head_dim=cfg.style_hidden // cfg.style_heads,
            dropout_rate=cfg.dropout,
            name="transformer",
        )(h, bias=bias, deterministic=deterministic)
        h = Conv1d(2 * cfg.style_dim, 3, name="conv_out")(h * maskf)
        count = jnp.maximum(jnp.sum(maskf, axis=1), 1.0)
        pooled = jnp.sum(h * maskf, axis=1) / count
        mu, logvar = jnp.split(pooled, 2, axis=-1)
        return mu, logvar
