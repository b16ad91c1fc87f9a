"""2D rotary position embedding (VGGT's ``RotaryPositionEmbedding2D``, base frequency 100).

The head dim is split in halves: the first half is rotated by the token's row (y), the second by its
column (x). Within a half, rotate-half style with ``inv_freq = base^(-2i/d)``. Patch positions are integer
grid coordinates + 1; special tokens (camera, registers) sit at (0, 0).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn


def patch_positions(batch: int, grid_h: int, grid_w: int, num_special: int, device=None) -> Tensor:
    """``[batch, num_special + grid_h*grid_w, 2]`` long (y, x) positions, specials at 0, patches at +1."""
    ys, xs = torch.meshgrid(torch.arange(grid_h, device=device), torch.arange(grid_w, device=device), indexing="ij")
    pos = torch.stack([ys.reshape(-1), xs.reshape(-1)], dim=-1) + 1
    pos = torch.cat([pos.new_zeros(num_special, 2), pos], dim=0)
    return pos[None].expand(batch, -1, -1)


class RoPE2D(nn.Module):
    """Applies 2D RoPE to ``[B, heads, N, head_dim]`` given positions ``[B, N, 2]`` (y, x)."""

    def __init__(self, base: float = 100.0):
        super().__init__()
        self.base = float(base)

    def _rotate_1d(self, x: Tensor, pos: Tensor) -> Tensor:
        d = x.shape[-1]
        inv_freq = 1.0 / self.base ** (torch.arange(0, d, 2, device=x.device).float() / d)
        # angles (up to ~grid size radians) and their cos/sin in float32 at least, cast to x's dtype afterwards: a
        # bfloat16 angle of 30 rad is off by up to 0.06 rad. float32 and float64 inputs compute as before.
        angles = pos.to(inv_freq.dtype)[..., None] * inv_freq  # [B, N, d/2]
        angles = angles.to(torch.promote_types(angles.dtype, x.dtype))
        angles = torch.cat([angles, angles], dim=-1)[:, None]  # [B, 1, N, d]
        cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
        x1, x2 = x.chunk(2, dim=-1)
        return x * cos + torch.cat([-x2, x1], dim=-1) * sin

    def forward(self, x: Tensor, pos: Tensor) -> Tensor:
        if x.shape[-1] % 4:
            raise ValueError(f"RoPE2D: head_dim must be divisible by 4, got {x.shape[-1]}")
        y_half, x_half = x.chunk(2, dim=-1)
        return torch.cat([self._rotate_1d(y_half, pos[..., 0]), self._rotate_1d(x_half, pos[..., 1])], dim=-1)
