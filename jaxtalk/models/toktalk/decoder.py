"""TokTalk's flow-matching decoder: CosyVoice's 1-D U-Net transformer over 25 fps motion.

Input per frame (channels last) is the concatenation of the noisy motion ``x``, the projected token
embedding ``mu``, the projected style vector broadcast over time, the known-frames track (zeros
elsewhere) and its 0/1 indicator (CosyVoice has no indicator; without it a known frame whose value is
0 would be indistinguishable from "unknown"). Condition dropout for classifier-free guidance zeroes
``mu``, the style and the known track together through the per-example ``keep`` flag, so the
unconditional branch is the same call with ``keep = 0``.

Layout (``design/REFERENCE_NOTES.md``): down stage 1 = ResNet block + transformer blocks + stride-2
downsample; down stage 2 = ResNet block + transformer blocks + k3 conv; ``num_mid_blocks`` middle
stages; two up stages on the skip concatenation (the first ends in a stride-2 transposed conv, the
output cropped to the skip's length); final conv block + 1x1 conv, times the padding mask. The time
embedding enters only through the ResNet blocks. Attention sees an additive bias built from the full
or the block-causal chunk mask (``chunk_frames`` at full rate, ``chunk_frames / 2`` after the
downsampling) combined with padding; the choice is a per-example traced flag, so one compiled program
serves training batches of both kinds and both inference modes.
"""

from __future__ import annotations

import flax.linen as nn
import jax.numpy as jnp
import numpy as np

from jaxtalk.masks import chunk_mask, combine, mask_to_bias
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.nn import (
    Conv1d,
    Conv1dBlock,
    Downsample1D,
    ResnetBlock1D,
    TimestepEmbedding,
    TransformerBlock,
    Upsample1D,
    downsample_mask,
)
from jaxtalk.types import Array, Bool, Float

__all__ = ["Decoder", "attention_bias"]


def attention_bias(
    valid: Bool[Array, "batch frames"],
    chunked: Bool[Array, " batch"],
    chunk_frames: int,
) -> Float[Array, "batch 1 frames frames"]:
    """Additive self-attention bias: the full or the block-causal chunk mask, AND padding.

    Args:
        valid: ``(B, T)`` True on real frames.
        chunked: ``(B,)`` per example, True for the chunk mask, False for the full mask.
        chunk_frames: frames per chunk at this resolution (static).

    Returns:
        ``(B, 1, T, T)`` float32 bias: 0 where a query may attend, a large negative number elsewhere.
    """
    t = valid.shape[1]
    full = combine(np.ones((t, t), dtype=bool), valid)
    chunk = combine(chunk_mask(t, chunk_frames), valid)
    # A boolean select as logic: the same values, and ONNX runtimes have no Where for booleans.
    pick = chunked[:, None, None, None]
    allowed = (pick & chunk) | (~pick & full)
    return mask_to_bias(allowed, jnp.float32)


class _Stage(nn.Module):
    """ResNet block (time embedding) followed by ``transformer_blocks`` transformer blocks."""

    config: TokTalkConfig

    @nn.compact
    def __call__(self, h: Array, mask: Array, temb: Array, bias: Array, deterministic: bool) -> Array:
        cfg = self.config
        h = ResnetBlock1D(cfg.width, causal=cfg.causal, num_groups=cfg.num_groups, name="resnet")(
            h, mask, temb
        )
        for i in range(cfg.transformer_blocks):
            h = TransformerBlock(
                num_heads=cfg.num_heads,
                head_dim=cfg.head_dim,
                mlp_ratio=cfg.mlp_ratio,
                qkv_bias=False,
                dropout_rate=cfg.dropout,
                name=f"transformer_{i}",
            )(h, bias=bias, deterministic=deterministic)
        return h


class Decoder(nn.Module):
    """The velocity model ``v_theta(x_t, t | tokens, style, known frames)`` (see the module docstring).

    Attributes:
        config: static model settings.
    """

    config: TokTalkConfig

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "batch frames param"],
        t: Float[Array, " batch"],
        tokens: Float[Array, "batch frames token"],
        style: Float[Array, "batch style"],
        known: Float[Array, "batch frames param"],
        known_mask: Bool[Array, "batch frames"],
        keep: Float[Array, " batch"] | Bool[Array, " batch"],
        mask: Bool[Array, "batch frames"],
        chunked: Bool[Array, " batch"],
        deterministic: bool = True,
    ) -> Float[Array, "batch frames param"]:
        """Predicts the flow velocity for every frame.

        Args:
            x: ``(B, T, param_dim)`` noisy motion at time ``t``.
            t: ``(B,)`` flow times in [0, 1].
            tokens: ``(B, T, speech_dim)`` token embeddings already at the motion frame rate.
            style: ``(B, style_vector_dim)`` style vectors.
            known: ``(B, T, param_dim)`` known frames (values elsewhere are ignored).
            known_mask: ``(B, T)`` True on known frames.
            keep: ``(B,)`` 1 to condition, 0 to drop tokens, style and known frames (CFG).
            mask: ``(B, T)`` True on real (unpadded) frames.
            chunked: ``(B,)`` True for the block-causal chunk mask, False for full attention.
            deterministic: disables dropout.

        Returns:
            ``(B, T, param_dim)`` velocity, zero on padded frames.
        """
        cfg = self.config
        dtype = x.dtype
        maskf = mask.astype(dtype)
        keepf = jnp.asarray(keep).astype(dtype)[:, None, None]
        flag = known_mask.astype(dtype)[..., None] * keepf
        mu = nn.Dense(cfg.param_dim, name="token_proj")(tokens) * keepf
        spk = nn.Dense(cfg.param_dim, name="style_proj")(style)[:, None, :] * keepf
        spk = jnp.broadcast_to(spk, x.shape[:2] + (cfg.param_dim,))
        h = jnp.concatenate([x, mu, spk, known * flag, flag], axis=-1)

        temb = TimestepEmbedding(
            cfg.time_embed_dim,
            frequency_dim=cfg.time_frequency_dim,
            order="sin_cos",
            scale=1000.0,
            freq_shift=1.0,
            name="time_embedding",
        )(t)

        full_len = x.shape[1]
        mask_half = downsample_mask(mask)
        bias_full = attention_bias(mask, chunked, cfg.chunk_frames)
        bias_half = attention_bias(mask_half, chunked, cfg.chunk_frames // 2)
        mask_half_f = mask_half.astype(dtype)

        # Down stage 1 (full rate) then the stride-2 downsample.
        h = _Stage(cfg, name="down_0")(h, maskf, temb, bias_full, deterministic)
        skip_full = h
        h = Downsample1D(cfg.width, causal=cfg.causal, name="downsample")(h, maskf)
        # Down stage 2 (half rate), ending in a plain k3 conv as in the reference.
        h = _Stage(cfg, name="down_1")(h, mask_half_f, temb, bias_half, deterministic)
        skip_half = h
        h = Conv1d(cfg.width, 3, causal=cfg.causal, name="down_1_conv")(h * mask_half_f[..., None])
        for i in range(cfg.num_mid_blocks):
            h = _Stage(cfg, name=f"mid_{i}")(h, mask_half_f, temb, bias_half, deterministic)
        # Up stages on [x | skip]; the transposed conv doubles the half length (crop to the skip).
        h = jnp.concatenate([h[:, : skip_half.shape[1]], skip_half], axis=-1)
        h = _Stage(cfg, name="up_0")(h, mask_half_f, temb, bias_half, deterministic)
        h = Upsample1D(cfg.width, causal=cfg.causal, name="upsample")(h, mask_half_f)
        h = jnp.concatenate([h[:, :full_len], skip_full], axis=-1)
        h = _Stage(cfg, name="up_1")(h, maskf, temb, bias_full, deterministic)
        h = Conv1d(cfg.width, 3, causal=cfg.causal, name="up_1_conv")(h * maskf[..., None])
        h = Conv1dBlock(cfg.width, causal=cfg.causal, num_groups=cfg.num_groups, name="final_block")(
            h, maskf
        )
        out = Conv1d(cfg.param_dim, 1, name="final_proj")(h * maskf[..., None])
        return out * maskf[..., None]
