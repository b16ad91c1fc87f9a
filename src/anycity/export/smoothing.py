"""Mip-Splatting's 3D smoothing filter, baked into exported scales and opacities.

Most predicted Gaussians are far below a pixel; our renderer shows them only through its 0.3 px² 2-D low-pass
(:data:`anycity.render.projection.EPS2D`). Viewers with a smaller or no low-pass drop them and show holes. The
3-D filter gives each Gaussian a minimum size from the highest sampling rate at which an input camera saw it:
``Σ' = Σ + (variance_px / ν²) I`` with ``ν = f / z`` (pixels per world unit), and scales the opacity by
``sqrt(det Σ / det Σ')`` so the integrated density is kept.
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.structures import Gaussians

VARIANCE_PX = 0.2  # Mip-Splatting's 3D filter variance in pixels² of the input cameras


def sampling_rate(means: Tensor, w2c: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """``[B, N]`` highest ``f / z`` (pixels per world unit) over the cameras that see each centre in frame; for a
    centre no camera frames, the highest over the cameras it is in front of; 0 when behind all of them.
    ``means [B, N, 3]``, ``w2c [B, V, 4, 4]``, ``K [B, V, 3, 3]`` for ``width x height`` images."""
    p = torch.einsum("bvij,bnj->bvni", w2c[..., :3, :3], means) + w2c[..., None, :3, 3]
    z = p[..., 2]
    front = z > 1e-6
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[..., 0, 0, None] * p[..., 0] / zs + K[..., 0, 2, None]
    v = K[..., 1, 1, None] * p[..., 1] / zs + K[..., 1, 2, None]
    inside = front & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    nu = torch.maximum(K[..., 0, 0, None], K[..., 1, 1, None]) / zs  # [B, V, N]
    zero = torch.zeros_like(nu)
    best = torch.where(inside, nu, zero).amax(1)
    return torch.where(best > 0, best, torch.where(front, nu, zero).amax(1))


def smooth_3d(g: Gaussians, w2c: Tensor, K: Tensor, width: int, height: int,
              variance_px: float = VARIANCE_PX) -> Gaussians:
    """``g`` with the 3-D filter baked in (a new object; Gaussians no camera sees in front are kept as is)."""
    nu = sampling_rate(g.means.float(), w2c.float(), K.float(), width, height)
    filt = torch.where(nu > 0, variance_px / nu.clamp_min(1e-12) ** 2, torch.zeros_like(nu))  # [B, N] world²
    var = g.scales.float() ** 2
    new_var = var + filt[..., None]
    gain = torch.sqrt(var.prod(-1) / new_var.prod(-1))
    return Gaussians(means=g.means, quats=g.quats, scales=new_var.sqrt().to(g.scales.dtype),
                     opacities=(g.opacities * gain.to(g.opacities.dtype)), sh=g.sh, valid=g.valid)
