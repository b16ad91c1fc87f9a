"""Surface normals from z-depth by central differences of back-projected points."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from anycity.geometry.projection import unproject_depth_to_camera


def depth_to_normals(depth: Tensor, K: Tensor, eps: float = 1e-12) -> Tensor:
    """z-depth ``[..., 1, H, W]`` -> unit normals ``[..., 3, H, W]`` in the camera frame, facing the camera.

    Normal = normalise(dP/du x dP/dv) with central differences; the one-pixel border is zero (as gsplat's
    ``depth_to_normal``). Pixels whose neighbours have zero depth get unreliable normals: mask them upstream.
    """
    P = unproject_depth_to_camera(depth, K)  # [..., H, W, 3]
    dx = P[..., 1:-1, 2:, :] - P[..., 1:-1, :-2, :]
    dy = P[..., 2:, 1:-1, :] - P[..., :-2, 1:-1, :]
    n = torch.cross(dx, dy, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(eps)
    center = P[..., 1:-1, 1:-1, :]
    flip = (n * center).sum(-1, keepdim=True) > 0  # must point back towards the camera (origin)
    n = torch.where(flip, -n, n)
    n = F.pad(n.movedim(-1, -3), (1, 1, 1, 1))
    return n
