"""Alternating-attention aggregator (VGGT): per-frame and global self-attention over all views' tokens.

Tokens per frame: ``[camera (1), registers (R), patches (P)]``. The camera and register tokens have two
learned slots: slot 0 for the first frame (the world frame), slot 1 shared by all other frames. Then
``depth`` pairs of blocks run in the order frame_i (tokens ``[B*V, T, C]``), global_i (``[B, V*T, C]``);
after each pair the two outputs are concatenated on channels, giving ``depth`` tensors ``[B, V, T, 2C]``.
Parameter names and shapes match VGGT's checkpoint under ``aggregator.``.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.utils.checkpoint import checkpoint

from anycity.models.layers import Block, PatchEmbed, RoPE2D, build_vit, patch_positions

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _first_and_rest(token: Tensor, b: int, v: int) -> Tensor:
    """``[1, 2, X, C]`` learned slots -> ``[B*V, X, C]``: slot 0 for frame 0, slot 1 for frames 1..V-1."""
    first = token[:, :1].expand(b, 1, *token.shape[2:])
    rest = token[:, 1:].expand(b, v - 1, *token.shape[2:])
    return torch.cat([first, rest], dim=1).reshape(b * v, *token.shape[2:])


class Aggregator(nn.Module):
    """``images [B, V, 3, H, W]`` in [0, 1] -> list of ``depth`` tensors ``[B, V, T, 2C]`` (None where not kept).

    Args:
        patch_embed: ``"conv"`` (a plain stride-p conv, honours ``embed_dim``) or a DINOv2 ViT name
            (``"dinov2_vitl14_reg"`` for VGGT-1B; its width must equal ``embed_dim``).
        img_size: the ViT's native square size (its position-embedding grid); unused by ``"conv"``.
    """

    def __init__(self, img_size: int = 518, patch_size: int = 14, embed_dim: int = 1024, depth: int = 24,
                 num_heads: int = 16, mlp_ratio: float = 4.0, num_register_tokens: int = 4,
                 patch_embed: str = "dinov2_vitl14_reg", qk_norm: bool = True, rope_freq: float = 100.0,
                 init_values: float = 0.01):
        super().__init__()
        if patch_embed == "conv":
            self.patch_embed = PatchEmbed(patch_size, embed_dim)
        else:
            self.patch_embed = build_vit(patch_embed, img_size, patch_size, num_register_tokens)
            if self.patch_embed.embed_dim != embed_dim:
                raise ValueError(f"patch_embed {patch_embed!r} has width {self.patch_embed.embed_dim}, but "
                                 f"embed_dim={embed_dim}; set embed_dim to match")
        self.rope = RoPE2D(rope_freq) if rope_freq > 0 else None

        def make_blocks() -> nn.ModuleList:
            return nn.ModuleList(Block(embed_dim, num_heads, mlp_ratio, init_values=init_values, qk_norm=qk_norm,
                                       rope=self.rope) for _ in range(depth))

        self.frame_blocks, self.global_blocks = make_blocks(), make_blocks()
        self.camera_token = nn.Parameter(torch.randn(1, 2, 1, embed_dim) * 1e-6)
        self.register_token = nn.Parameter(torch.randn(1, 2, num_register_tokens, embed_dim) * 1e-6)
        self.patch_start_idx = 1 + num_register_tokens
        self.depth, self.patch_size, self.embed_dim = depth, patch_size, embed_dim
        self.register_buffer("_resnet_mean", torch.tensor(IMAGENET_MEAN).view(1, 1, 3, 1, 1), persistent=False)
        self.register_buffer("_resnet_std", torch.tensor(IMAGENET_STD).view(1, 1, 3, 1, 1), persistent=False)
        self.gradient_checkpointing = False

    def _run(self, block: nn.Module, x: Tensor, pos: Tensor) -> Tensor:
        if self.gradient_checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(block, x, pos, use_reentrant=False)
        return block(x, pos=pos)

    def forward(self, images: Tensor, keep: set[int] | None = None) -> list[Tensor | None]:
        """``keep``: layer indices to return (None = all); the others are None to save memory."""
        b, v, _, h, w = images.shape
        x = ((images - self._resnet_mean) / self._resnet_std).reshape(b * v, 3, h, w)
        patches = self.patch_embed(x)
        tokens = torch.cat([_first_and_rest(self.camera_token, b, v), _first_and_rest(self.register_token, b, v),
                            patches], dim=1)
        t, c = tokens.shape[1:]
        gh, gw = h // self.patch_size, w // self.patch_size
        pos = patch_positions(b * v, gh, gw, self.patch_start_idx, images.device)
        pos_global = pos.reshape(b, v * t, 2)
        out: list[Tensor | None] = []
        for i in range(self.depth):
            tokens = self._run(self.frame_blocks[i], tokens.reshape(b * v, t, c), pos)
            frame_out = tokens.reshape(b, v, t, c)
            tokens = self._run(self.global_blocks[i], tokens.reshape(b, v * t, c), pos_global)
            keep_i = keep is None or i in keep
            out.append(torch.cat([frame_out, tokens.reshape(b, v, t, c)], dim=-1) if keep_i else None)
        return out
