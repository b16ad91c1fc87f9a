"""Pre-norm transformer block with LayerScale (VGGT/DINOv2 ``Block``).

``x + ls1(attn(norm1(x), pos))`` then ``x + ls2(mlp(norm2(x)))``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from anycity.models.layers.attention import Attention
from anycity.models.layers.mlp import Mlp
from anycity.models.layers.rope import RoPE2D


class LayerScale(nn.Module):
    """Per-channel learnable scale ``gamma`` (init ``init_values``)."""

    def __init__(self, dim: int, init_values: float = 1e-5):
        super().__init__()
        self.gamma = nn.Parameter(init_values * torch.ones(dim))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


class Block(nn.Module):
    """``[B, N, C] -> [B, N, C]``; ``init_values`` None/0 disables LayerScale; ``norm_eps``: every LayerNorm's eps
    (norm1, norm2 and the qk-norm; VGGT's aggregator blocks 1e-5, DINOv2's 1e-6)."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0, qkv_bias: bool = True,
                 proj_bias: bool = True, ffn_bias: bool = True, init_values: float | None = None,
                 qk_norm: bool = False, rope: RoPE2D | None = None, norm_eps: float = 1e-5):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn = Attention(dim, num_heads, qkv_bias=qkv_bias, proj_bias=proj_bias, qk_norm=qk_norm, rope=rope,
                              norm_eps=norm_eps)
        self.ls1 = LayerScale(dim, init_values) if init_values else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio), bias=ffn_bias)
        self.ls2 = LayerScale(dim, init_values) if init_values else nn.Identity()

    def forward(self, x: Tensor, pos: Tensor | None = None) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), pos=pos))
        return x + self.ls2(self.mlp(self.norm2(x)))
