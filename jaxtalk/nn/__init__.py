"""Shared Flax Linen layers that every jaxtalk model builds on.

Sequences are ``(*batch, time, channels)`` (channels last); leading batch axes are optional wherever
that makes sense. Every layer takes ``dtype`` (computation) and ``param_dtype`` (parameters), so a
model can run in bfloat16 with float32 parameters.

* :mod:`~jaxtalk.nn.attention`: multi-head attention with an additive bias and a key/value cache.
* :mod:`~jaxtalk.nn.transformer`: pre-LN encoder and decoder (cross-attention) blocks.
* :mod:`~jaxtalk.nn.embeddings`: sinusoidal time/position embeddings and the timestep MLP.
* :mod:`~jaxtalk.nn.adaln`: adaLN residual MLP blocks and the final adaLN layer (MAR).
* :mod:`~jaxtalk.nn.conv`: 1-D conv blocks of CosyVoice's U-Net decoder, masked and causal.
* :mod:`~jaxtalk.nn.graph`: graph convolution on small fixed graphs.
* :mod:`~jaxtalk.nn.mlp`: a plain MLP.
"""

from __future__ import annotations

from jaxtalk.nn.adaln import AdaLNFinalLayer, AdaLNResBlock, adaln_modulation, modulate
from jaxtalk.nn.attention import (
    Bias,
    MultiHeadAttention,
    dot_product_attention,
)
from jaxtalk.nn.conv import (
    Conv1d,
    Conv1dBlock,
    Downsample1D,
    MaskedGroupNorm,
    ResnetBlock1D,
    Upsample1D,
    downsample_mask,
    masked_group_norm,
    upsample_mask,
)
from jaxtalk.nn.embeddings import TimestepEmbedding, sinusoidal_embedding
from jaxtalk.nn.graph import GraphConv, normalized_adjacency
from jaxtalk.nn.mlp import MLP, gelu_exact
from jaxtalk.nn.transformer import DecoderBlock, FeedForward, TransformerBlock

__all__ = [
    "Bias",
    "dot_product_attention",
    "MultiHeadAttention",
    "FeedForward",
    "TransformerBlock",
    "DecoderBlock",
    "sinusoidal_embedding",
    "TimestepEmbedding",
    "modulate",
    "adaln_modulation",
    "AdaLNResBlock",
    "AdaLNFinalLayer",
    "masked_group_norm",
    "downsample_mask",
    "upsample_mask",
    "Conv1d",
    "MaskedGroupNorm",
    "Conv1dBlock",
    "ResnetBlock1D",
    "Downsample1D",
    "Upsample1D",
    "normalized_adjacency",
    "GraphConv",
    "MLP",
    "gelu_exact",
]
