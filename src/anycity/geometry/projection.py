"""Projection of world points into pixels and unprojection of depth maps (OpenCV, pixel centres +0.5)."""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry.cameras import w2c_to_c2w


def transform_points(T: Tensor, points: Tensor) -> Tensor:
    """Apply ``[..., 4, 4]`` transforms to ``[..., N, 3]`` points."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def project_points(points: Tensor, w2c: Tensor, K: Tensor, eps: float = 1e-8) -> tuple[Tensor, Tensor]:
    """World points ``[..., N, 3]`` -> pixel coordinates ``[..., N, 2]`` and camera z ``[..., N]``.

    ``w2c [..., 4, 4]`` and ``K [..., 3, 3]`` broadcast over the leading dims. Pixel (u, v) = (0.5, 0.5) is the
    centre of the top-left pixel. Points with z <= eps get a clamped divisor; mask them by ``z > 0``.
    """
    cam = transform_points(w2c, points)
    z = cam[..., 2]
    uvw = cam @ K.transpose(-1, -2)
    uv = uvw[..., :2] / uvw[..., 2:].clamp_min(eps)
    return uv, z


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> Tensor:
    """``[H, W, 2]`` pixel-centre coordinates (u, v) = (j + 0.5, i + 0.5). In float16/bfloat16 the centres of wide
    images are not representable (bfloat16: 4.5 px off at u = 1500.5); the unprojections build it in float32."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype) + 0.5,
        torch.arange(width, device=device, dtype=dtype) + 0.5,
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def _work_dtype(*tensors: Tensor) -> tuple[torch.dtype, torch.dtype]:
    """(dtype the inputs promote to, that dtype raised to at least float32 for the arithmetic)."""
    out = tensors[0].dtype
    for t in tensors[1:]:
        out = torch.promote_types(out, t.dtype)
    return out, torch.promote_types(out, torch.float32)


def unproject_depth_to_camera(depth: Tensor, K: Tensor) -> Tensor:
    """z-depth ``[..., 1, H, W]`` and ``K [..., 3, 3]`` -> camera-frame points ``[..., H, W, 3]``.

    Computed in float32 at least (pixel centres of half-precision grids are off by pixels); returned in the dtype
    ``depth`` and ``K`` promote to."""
    out, work = _work_dtype(depth, K)
    depth, K = depth.to(work), K.to(work)
    h, w = depth.shape[-2:]
    uv = pixel_grid(h, w, device=depth.device, dtype=work)
    fx, fy = K[..., 0, 0, None, None], K[..., 1, 1, None, None]
    cx, cy = K[..., 0, 2, None, None], K[..., 1, 2, None, None]
    z = depth[..., 0, :, :]
    x = (uv[..., 0] - cx) / fx * z
    y = (uv[..., 1] - cy) / fy * z
    return torch.stack([x, y, z], dim=-1).to(out)


def unproject_depth(depth: Tensor, K: Tensor, w2c: Tensor) -> Tensor:
    """z-depth ``[..., 1, H, W]`` -> world points ``[..., H, W, 3]`` given ``K`` and ``w2c [..., 4, 4]``.

    Computed in float32 at least; returned in the dtype ``depth``, ``K`` and ``w2c`` promote to."""
    out, work = _work_dtype(depth, K, w2c)
    cam = unproject_depth_to_camera(depth.to(work), K.to(work))
    c2w = w2c_to_c2w(w2c.to(work))
    R, t = c2w[..., :3, :3], c2w[..., :3, 3]
    return (torch.einsum("...ij,...hwj->...hwi", R, cam) + t[..., None, None, :]).to(out)


def pixel_rays(K: Tensor, w2c: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Ray origins ``[..., 3]`` and unit world directions ``[..., H, W, 3]`` through pixel centres.

    Computed in float32 at least; returned in the dtype ``K`` and ``w2c`` promote to."""
    out, work = _work_dtype(K, w2c)
    K, w2c = K.to(work), w2c.to(work)
    ones = torch.ones(*K.shape[:-2], 1, height, width, dtype=work, device=K.device)
    cam = unproject_depth_to_camera(ones, K)
    c2w = w2c_to_c2w(w2c)
    d = torch.einsum("...ij,...hwj->...hwi", c2w[..., :3, :3], cam)
    return c2w[..., :3, 3].to(out), (d / d.norm(dim=-1, keepdim=True)).to(out)
