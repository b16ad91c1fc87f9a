"""DINOv2-style ViT with register tokens, used as the 1B aggregator's patch embedding.

Only the normalised patch tokens are returned (``x_norm_patchtokens``): ``[N, 3, H, W] -> [N, (H/p)(W/p), C]``.
The learned position embedding (for a ``img_size/p`` square grid plus cls) is bicubic-interpolated with
antialiasing to other grids, exactly as DINOv2 with ``interpolate_offset=0``. Parameter names follow VGGT's
checkpoint (``cls_token``, ``pos_embed``, ``register_tokens``, ``mask_token``, ``patch_embed.proj``,
``blocks.N``, ``norm``). No pretrained weights are loaded here; they come from a VGGT/AnySplat checkpoint.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anycity.models.layers.block import Block
from anycity.models.layers.patch_embed import PatchEmbed

VIT_SIZES = {  # name -> (embed_dim, depth, num_heads)
    "dinov2_vits14_reg": (384, 12, 6),
    "dinov2_vitb14_reg": (768, 12, 12),
    "dinov2_vitl14_reg": (1024, 24, 16),
}


class DinoViT(nn.Module):
    def __init__(self, img_size: int = 518, patch_size: int = 14, embed_dim: int = 1024, depth: int = 24,
                 num_heads: int = 16, mlp_ratio: float = 4.0, num_register_tokens: int = 4,
                 init_values: float = 1.0):
        super().__init__()
        self.patch_size, self.embed_dim = patch_size, embed_dim
        self.patch_embed = PatchEmbed(patch_size, embed_dim)
        grid = img_size // patch_size
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, grid * grid + 1, embed_dim))
        self.register_tokens = nn.Parameter(torch.zeros(1, num_register_tokens, embed_dim))
        self.num_register_tokens = num_register_tokens
        self.blocks = nn.ModuleList(
            Block(embed_dim, num_heads, mlp_ratio, init_values=init_values, norm_eps=1e-6) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        self.mask_token = nn.Parameter(torch.zeros(1, embed_dim), requires_grad=False)  # unused, kept for the key
        self.gradient_checkpointing = False
        self._init_weights()

    def _init_weights(self) -> None:
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        nn.init.normal_(self.register_tokens, std=1e-6)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)

    def _pos_embed(self, grid_h: int, grid_w: int, dtype: torch.dtype) -> Tensor:
        n = self.pos_embed.shape[1] - 1
        m = math.isqrt(n)
        if grid_h * grid_w == n and grid_h == grid_w:
            return self.pos_embed
        pe = self.pos_embed.float()
        patch = pe[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        patch = F.interpolate(patch, size=(grid_h, grid_w), mode="bicubic", antialias=True)
        patch = patch.permute(0, 2, 3, 1).reshape(1, grid_h * grid_w, -1)
        return torch.cat([pe[:, :1], patch], dim=1).to(dtype)

    def forward(self, x: Tensor) -> Tensor:
        n, _, h, w = x.shape
        tokens = self.patch_embed(x)
        tokens = torch.cat([self.cls_token.expand(n, -1, -1), tokens], dim=1)
        tokens = tokens + self._pos_embed(h // self.patch_size, w // self.patch_size, tokens.dtype)
        tokens = torch.cat([tokens[:, :1], self.register_tokens.expand(n, -1, -1), tokens[:, 1:]], dim=1)
        for blk in self.blocks:
            if self.gradient_checkpointing and self.training and torch.is_grad_enabled():
                tokens = torch.utils.checkpoint.checkpoint(blk, tokens, use_reentrant=False)
            else:
                tokens = blk(tokens)
        return self.norm(tokens)[:, 1 + self.num_register_tokens:]


def build_vit(name: str, img_size: int, patch_size: int, num_register_tokens: int) -> DinoViT:
    if name not in VIT_SIZES:
        raise ValueError(f"patch_embed: expected 'conv' or one of {sorted(VIT_SIZES)}, got {name!r}")
    dim, depth, heads = VIT_SIZES[name]
    return DinoViT(img_size, patch_size, dim, depth, heads, num_register_tokens=num_register_tokens)
