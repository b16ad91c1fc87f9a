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
        # cos/sin tables per positions tensor: one module serves every block, for q and k, so the tables of one
        # forward were rebuilt 2 x 2 x depth times (3 to 7 % of a tiny Stage I step on CPU); bitwise the same
        self._tables: dict[tuple, tuple[Tensor, ...]] = {}

    def _angles(self, pos: Tensor, d: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """``(cos, sin)`` ``[B, 1, N, d]`` of the angles of one coordinate's positions ``pos [B, N]``."""
        inv_freq = 1.0 / self.base ** (torch.arange(0, d, 2, device=pos.device).float() / d)
        # angles (up to ~grid size radians) and their cos/sin in float32 at least, cast to x's dtype afterwards: a
        # bfloat16 angle of 30 rad is off by up to 0.06 rad. float32 and float64 inputs compute as before.
        angles = pos.to(inv_freq.dtype)[..., None] * inv_freq  # [B, N, d/2]
        angles = angles.to(torch.promote_types(angles.dtype, dtype))
        angles = torch.cat([angles, angles], dim=-1)[:, None]  # [B, 1, N, d]
        return angles.cos().to(dtype), angles.sin().to(dtype)

    def _tables_of(self, pos: Tensor, d: int, dtype: torch.dtype) -> tuple[Tensor, ...]:
        """``(cos_y, sin_y, cos_x, sin_x)`` for positions ``pos [B, N, 2]`` and halves of width ``d``, kept while
        ``pos`` is the same unchanged tensor (its identity and version; the entry holds it, so the id is not reused
        meanwhile): the aggregator passes one positions tensor to every frame block and one to every global block."""
        key = (id(pos), pos._version, d, dtype, pos.device)
        hit = self._tables.get(key)
        if hit is not None and hit[0] is pos:
            return hit[1:]
        tables = (*self._angles(pos[..., 0], d, dtype), *self._angles(pos[..., 1], d, dtype))
        if len(self._tables) >= 4:  # a forward uses two positions tensors (frame, global)
            self._tables.clear()
        self._tables[key] = (pos, *tables)
        return tables

    @staticmethod
    def _rotate_1d(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
        x1, x2 = x.chunk(2, dim=-1)
        return x * cos + torch.cat([-x2, x1], dim=-1) * sin

    def forward(self, x: Tensor, pos: Tensor) -> Tensor:
        if x.shape[-1] % 4:
            raise ValueError(f"RoPE2D: head_dim must be divisible by 4, got {x.shape[-1]}")
        cos_y, sin_y, cos_x, sin_x = self._tables_of(pos, x.shape[-1] // 2, x.dtype)
        y_half, x_half = x.chunk(2, dim=-1)
        return torch.cat([self._rotate_1d(y_half, cos_y, sin_y), self._rotate_1d(x_half, cos_x, sin_x)], dim=-1)
