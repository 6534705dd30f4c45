"""Adaptation layer: another audio LLM's token embeddings -> the base token embedding space.

The source stream is first resampled to the base token rate by time overlap (outside this module, see
:func:`jaxtalk.models.toktalk.model.adapter_forward`: every source token counts, none is dropped); then
a 1-D convolution to ``adapter_width``, a sinusoidal positional embedding, ``adapter_layers`` pre-LN
transformer encoder blocks and a final LayerNorm + Dense map it to ``speech_dim``. Trained in stage 2
with the base model frozen.

With ``config.causal`` (the streaming model) the convolution is causal and each attention query sees
only itself and the ``adapter_context - 1`` tokens before it, so token ``i``'s output depends on the
inputs ``i - receptive_field(config) .. i`` alone and the streaming adapter
(:mod:`jaxtalk.models.toktalk.streaming`) reproduces the offline one from a fixed-size buffer of past
inputs. Positions are absolute (``positions``), so a stream's positions continue across chunks; stage-2
training places its windows at random starts up to ``adapter_max_position`` so those positions are trained.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp

from jaxtalk.masks import chunk_mask, combine, mask_to_bias, padding_mask
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.nn import Conv1d, TransformerBlock, sinusoidal_embedding
from jaxtalk.types import Array, Bool, Float, Int

__all__ = ["Adapter", "receptive_field"]


def receptive_field(config: TokTalkConfig) -> int:
    """Past base-rate tokens a causal adapter output depends on (beyond its own token).

    The convolution reaches ``adapter_kernel - 1`` tokens back and each of the ``adapter_layers``
    attention layers ``adapter_context - 1`` more.
    """
    return config.adapter_layers * (config.adapter_context - 1) + config.adapter_kernel - 1


class Adapter(nn.Module):
    """``(B, Tt, src_dim)`` source embeddings at the base rate -> ``(B, Tt, speech_dim)``.

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
        positions: Int[Array, " tokens"] | None = None,
    ) -> Float[Array, "batch tokens token"]:
        """Maps source embeddings onto the base embedding space.

        Args:
            src: ``(B, Tt, src_dim)`` source embeddings, already at the base token rate.
            mask: ``(B, Tt)`` True on real tokens (None: all real). Padded tokens read as zeros to
                the convolution and are never attended to.
            deterministic: disables dropout.
            positions: ``(Tt,)`` absolute token positions (None: ``0 .. Tt-1``).

        Returns:
            ``(B, Tt, speech_dim)``, zero on padded tokens.
        """
        cfg = self.config
        t = src.shape[1]
        if mask is None:
            mask = jnp.ones(src.shape[:2], dtype=bool)
        maskf = mask.astype(src.dtype)[..., None]
        h = Conv1d(cfg.adapter_width, cfg.adapter_kernel, causal=cfg.causal, name="conv")(src * maskf)
        if positions is None:
            positions = jnp.arange(t)
        h = h + sinusoidal_embedding(jnp.asarray(positions, h.dtype), cfg.adapter_width).astype(h.dtype)[None]
        if cfg.causal:
            # chunk_mask with 1-token chunks and adapter_context - 1 chunks of left context: query i
            # sees keys i - adapter_context + 1 .. i.
            allowed = combine(chunk_mask(t, 1, left_chunks=cfg.adapter_context - 1), mask)
        else:
            allowed = padding_mask(mask)
        bias = mask_to_bias(allowed, jnp.float32)
        for i in range(cfg.adapter_layers):
            h = TransformerBlock(
                num_heads=cfg.adapter_heads,
                head_dim=cfg.adapter_width // cfg.adapter_heads,
                dropout_rate=cfg.dropout,
                name=f"transformer_{i}",
            )(h, bias=bias, deterministic=deterministic)
        h = nn.LayerNorm(name="norm")(h)
        return nn.Dense(cfg.speech_dim, name="out")(h) * maskf
