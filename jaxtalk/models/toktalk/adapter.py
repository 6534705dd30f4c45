"""Adaptation layer: another audio LLM's token embeddings -> the base token embedding space.

The source stream is first time-interpolated to the base token rate (outside this module, see
:func:`jaxtalk.models.toktalk.model.adapt_tokens`); then a 1-D convolution to ``adapter_width``, a
sinusoidal positional embedding, ``adapter_layers`` pre-LN transformer encoder blocks and a final
LayerNorm + Dense map it to ``token_dim``. Trained in stage 2 with the base model frozen.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from jaxtalk.masks import mask_to_bias, padding_mask
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.nn import Conv1d, TransformerBlock, sinusoidal_embedding
from jaxtalk.types import Array, Bool, Float

__all__ = ["Adapter"]


class Adapter(nn.Module):
    """``(B, Tt, src_dim)`` source embeddings at the base rate -> ``(B, Tt, token_dim)``.

    Attributes:
        config: static model settings.
    """

    config: TokTalkConfig

    @nn.compact
    def __call__(
        self,
        src: Float[Array, "batch tokens src"],
        mask: Bool[Array, "batch tokens"] | None = None,
        deterministic: bool = True,
    ) -> Float[Array, "batch tokens token"]:
        """Maps source embeddings onto the base embedding space.

        Args:
            src: ``(B, Tt, src_dim)`` source embeddings, already at the base token rate.
            mask: ``(B, Tt)`` True on real tokens (None: all real).
            deterministic: disables dropout.

        Returns:
            ``(B, Tt, token_dim)``.
        """
        cfg = self.config
        if mask is None:
            mask = jnp.ones(src.shape[:2], dtype=bool)
        maskf = mask.astype(src.dtype)[..., None]
        h = Conv1d(cfg.adapter_width, cfg.adapter_kernel, name="conv")(src * maskf)
        positions = jnp.arange(src.shape[1], dtype=h.dtype)
        h = h + sinusoidal_embedding(positions, cfg.adapter_width).astype(h.dtype)[None]
        bias = mask_to_bias(padding_mask(mask), jnp.float32)
        for i in range(cfg.adapter_layers):
            h = TransformerBlock(
                num_heads=cfg.adapter_heads,
                head_dim=cfg.adapter_width // cfg.adapter_heads,
                dropout_rate=cfg.dropout,
                name=f"transformer_{i}",
            )(h, bias=bias, deterministic=deterministic)
        h = nn.LayerNorm(name="norm")(h)
        return nn.Dense(cfg.token_dim, name="out")(h) * maskf
