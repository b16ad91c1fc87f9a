"""Multi-head self-attention with optional qk-LayerNorm and 2D RoPE (VGGT ``Attention``), and a cross-attention."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from anycity.models.layers.rope import RoPE2D


class Attention(nn.Module):
    """``[B, N, C] -> [B, N, C]``; parameter names ``qkv``, ``q_norm``, ``k_norm``, ``proj`` as in VGGT."""

    def __init__(self, dim: int, num_heads: int = 8, qkv_bias: bool = True, proj_bias: bool = True,
                 qk_norm: bool = False, rope: RoPE2D | None = None, norm_eps: float = 1e-5):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"Attention: dim {dim} must be divisible by num_heads {num_heads}")
        self.num_heads = num_heads
        self.head_dim = dim // num_heads
        self.qkv = nn.Linear(dim, dim * 3, bias=qkv_bias)
        self.q_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.k_norm = nn.LayerNorm(self.head_dim, eps=norm_eps) if qk_norm else nn.Identity()
        self.proj = nn.Linear(dim, dim, bias=proj_bias)
        self.rope = rope

    def forward(self, x: Tensor, pos: Tensor | None = None) -> Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(x).reshape(b, n, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4).unbind(0)
        q, k = self.q_norm(q), self.k_norm(k)
        if self.rope is not None and pos is not None:
            q, k = self.rope(q, pos), self.rope(k, pos)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(b, n, c))


class CrossAttention(nn.Module):
    """Queries ``[B, Nq, Cq]`` attend to a context ``[B, Nk, Ck]``; output ``[B, Nq, out_dim]``.

    Pre-norms both inputs, qk-LayerNorm per head. ``out_dim`` defaults to ``dim`` (the inner width).
    """

    def __init__(self, query_dim: int, context_dim: int, dim: int, num_heads: int, out_dim: int | None = None):
        super().__init__()
        if dim % num_heads:
            raise ValueError(f"CrossAttention: dim {dim} must be divisible by num_heads {num_heads}")
        self.num_heads, self.head_dim = num_heads, dim // num_heads
        self.norm_q, self.norm_kv = nn.LayerNorm(query_dim), nn.LayerNorm(context_dim)
        self.to_q = nn.Linear(query_dim, dim)
        self.to_kv = nn.Linear(context_dim, 2 * dim)
        self.q_norm, self.k_norm = nn.LayerNorm(self.head_dim), nn.LayerNorm(self.head_dim)
        self.proj = nn.Linear(dim, out_dim or dim)

    def forward(self, x: Tensor, context: Tensor) -> Tensor:
        b, nq, _ = x.shape
        nk = context.shape[1]
        q = self.to_q(self.norm_q(x)).reshape(b, nq, self.num_heads, self.head_dim).transpose(1, 2)
        k, v = self.to_kv(self.norm_kv(context)).reshape(b, nk, 2, self.num_heads, self.head_dim).permute(
            2, 0, 3, 1, 4).unbind(0)
        out = F.scaled_dot_product_attention(self.q_norm(q), self.k_norm(k), v)
        return self.proj(out.transpose(1, 2).reshape(b, nq, -1))
