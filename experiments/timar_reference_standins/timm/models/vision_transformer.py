"""A minimal stand-in for timm's ViT ``Block`` (timm 1.0.x, ``timm/models/vision_transformer.py``).

Why: timm imports torchvision, and with the CPU torch 2.13.0 on this machine the index's
torchvision does not load ("operator torchvision::nms does not exist"). The public TIMAR code only
uses ``Block(dim, num_heads, mlp_ratio, qkv_bias=True, norm_layer=..., proj_drop=..., attn_drop=...)``
and ``block(x, attn_mask=mask)``; this file re-states timm's definition for exactly that use, with
timm's parameter names (so a state dict of either loads into the other):

* ``norm1``, ``attn.qkv`` (fused, ``Linear(dim, 3 dim, bias=qkv_bias)``, output reshaped to
  ``(3, heads, head_dim)``), ``attn.proj``, ``norm2``, ``mlp.fc1`` -> exact GELU -> ``mlp.fc2``;
* ``x = x + attn(norm1(x)); x = x + mlp(norm2(x))`` (pre-LN; no layer scale, no drop path at
  timm's defaults ``init_values=None, drop_path=0``);
* attention by ``F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)`` (timm's fused path),
  scale ``head_dim ** -0.5``.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn
import torch.nn.functional as F


class Mlp(nn.Module):
    """timm's ``Mlp``: fc1 -> act -> drop -> fc2 -> drop."""

    def __init__(self, in_features: int, hidden_features: int, act_layer=nn.GELU, drop: float = 0.0) -> None:
        super().__init__()
        self.fc1 = nn.Linear(in_features, hidden_features)
        self.act = act_layer()
        self.drop1 = nn.Dropout(drop)
        self.fc2 = nn.Linear(hidden_features, in_features)
        self.drop2 = nn.Dropout(drop)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop2(self.fc2(self.drop1(self.act(self.fc1(x)))))


class Attention(nn.Module):
    """timm's ``Attention`` (fused qkv, no q/k norm)."""

    def __init__(self, dim: int, num_heads: int = 8, qkv_bias: bool = False, attn_drop: float = 0.0,
                 proj_drop: float = 0.0) -> None:
        super().__init__()
        assert dim % num_heads == 0, "dim should be divisible by num_heads"
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.attn_drop = nn.Dropout(attn_drop)
        self.proj = nn.Linear(dim, dim)
        self.proj_drop = nn.Dropout(proj_drop)

    def forward(self, x: torch.Tensor, attn_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
        B, N, C = x.shape
        qkv = self.qkv(x).reshape(B, N, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        x = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask,
                                           dropout_p=self.attn_drop.p if self.training else 0.0)
        x = x.transpose(1, 2).reshape(B, N, C)
        return self.proj_drop(self.proj(x))


class Block(nn.Module):
    """timm's pre-LN ViT ``Block`` at ``init_values=None, drop_path=0``."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, qkv_bias: bool = False,
                 proj_drop: float = 0.0, attn_drop: float = 0.0, act_layer=nn.GELU, norm_layer=nn.LayerNorm) -> None:
        super().__init__()
        self.norm1 = norm_layer(dim)
        self.attn = Attention(dim, num_heads=num_heads, qkv_bias=qkv_bias, attn_drop=attn_drop, proj_drop=proj_drop)
        self.norm2 = norm_layer(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), act_layer=act_layer, drop=proj_drop)

    def forward(self, x: torch.Tensor, attn_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), attn_mask=attn_mask)
        x = x + self.mlp(self.norm2(x))
        return x
