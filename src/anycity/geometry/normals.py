"""Surface normals from z-depth by central differences of back-projected points."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from anycity.geometry.projection import unproject_depth_to_camera


def depth_to_normals(depth: Tensor, K: Tensor, eps: float = 1e-12) -> Tensor:
    """z-depth ``[..., 1, H, W]`` -> unit normals ``[..., 3, H, W]`` in the camera frame, facing the camera.

    Normal = normalise(dP/du x dP/dv) with central differences; the one-pixel border is zero (as gsplat's
    ``depth_to_normal``). A pixel is also zero where it or any of its 4 neighbours has no depth (``<= 0`` or
    non-finite: rendered depth is 0 where alpha is 0, e.g. sky beyond a roof edge), the rule of
    ``anycity.data.pipeline._normals_from_depth``; such pixels get no gradient either.
    """
    z = depth[..., 0, :, :]
    ok = (z > 0) & torch.isfinite(z)  # [..., H, W]
    # a missing depth (0, NaN, inf) would give its neighbours wrong normals and NaN gradients: stand 1 in for it
    depth = torch.where(ok[..., None, :, :], depth, torch.ones_like(depth))
    P = unproject_depth_to_camera(depth, K)  # [..., H, W, 3]
    dx = P[..., 1:-1, 2:, :] - P[..., 1:-1, :-2, :]
    dy = P[..., 2:, 1:-1, :] - P[..., :-2, 1:-1, :]
    n = torch.cross(dx, dy, dim=-1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(eps)
    center = P[..., 1:-1, 1:-1, :]
    flip = (n * center).sum(-1, keepdim=True) > 0  # must point back towards the camera (origin)
    n = torch.where(flip, -n, n)
    inner = (ok[..., 1:-1, 1:-1] & ok[..., :-2, 1:-1] & ok[..., 2:, 1:-1] & ok[..., 1:-1, :-2]
             & ok[..., 1:-1, 2:])  # the pixel and its 4 neighbours have depth
    n = torch.where(inner[..., None], n, torch.zeros_like(n))
    n = F.pad(n.movedim(-1, -3), (1, 1, 1, 1))
    return n
