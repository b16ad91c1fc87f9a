"""Which views see a world point: in frame, in front of the camera, and not occluded (a depth test).

The depth test compares the point's camera z with the view's z-depth map at the projected pixel. The reference
depth is the **minimum of the 2x2 pixel neighbourhood** around the projected position (the four bilinear taps),
not a bilinear blend: at a depth discontinuity a blend of a near and a far surface can lie behind an occluded
point and wrongly let it through, while the minimum keeps any point behind the nearer surface hidden. The
pixel holding the projection (nearest pixel) must have valid depth; invalid taps around it are ignored.
Points on the far side of an edge within one pixel of it are thereby called hidden, a conservative choice.
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry.projection import project_points

# Points per chunk times views: bounds the [B, V, chunk, 4] temporaries (64 views x 200k points -> 4 chunks).
_CHUNK_ELEMS = 2**22


def _check(points: Tensor, depth: Tensor, w2c: Tensor, K: Tensor, valid: Tensor | None) -> None:
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"visible_views: points must be [B, N, 3], got {tuple(points.shape)}")
    if depth.dim() != 5 or depth.shape[2] != 1:
        raise ValueError(f"visible_views: depth must be [B, V, 1, H, W] z-depth, got {tuple(depth.shape)}")
    b, v = depth.shape[:2]
    if w2c.shape != (b, v, 4, 4) or K.shape != (b, v, 3, 3) or points.shape[0] != b:
        raise ValueError(f"visible_views: expected w2c [{b}, {v}, 4, 4], K [{b}, {v}, 3, 3] and points [{b}, N, 3] "
                         f"for depth {tuple(depth.shape)}, got {tuple(w2c.shape)}, {tuple(K.shape)}, "
                         f"{tuple(points.shape)}")
    if valid is not None and valid.shape != depth.shape:
        raise ValueError(f"visible_views: valid must match depth {tuple(depth.shape)}, got {tuple(valid.shape)}")


def visible_views(points: Tensor, depth: Tensor, w2c: Tensor, K: Tensor, *, depth_tol: float = 0.05,
                  valid: Tensor | None = None) -> Tensor:
    """Per-view visibility of world points.

    Args:
        points: ``[B, N, 3]`` world points.
        depth: ``[B, V, 1, H, W]`` z-depth of each view (same units as the points); <= 0 or non-finite = no depth.
        w2c: ``[B, V, 4, 4]`` world-to-camera (OpenCV).
        K: ``[B, V, 3, 3]`` intrinsics in pixels of the depth maps (pixel centres at +0.5).
        depth_tol: relative tolerance: visible when ``z_point <= depth_ref * (1 + depth_tol)``.
        valid: optional ``[B, V, 1, H, W]`` bool; False pixels count as having no depth.
    Returns:
        ``[B, V, N]`` bool: the point projects inside view v's frame, lies in front of the camera, the pixel it
        lands in has valid depth and it passes the depth test against the 2x2-neighbourhood minimum depth.
        Non-finite points are visible nowhere.
    """
    _check(points, depth, w2c, K, valid)
    b, v, _, h, w = depth.shape
    d = depth[:, :, 0].float()
    ok = torch.isfinite(d) & (d > 0)
    if valid is not None:
        ok = ok & valid[:, :, 0].bool()
    # Invalid pixels never occlude (they hold no surface): +inf for the neighbourhood minimum.
    d_ref = torch.where(ok, d, torch.full_like(d, float("inf"))).reshape(b, v, h * w)
    ok_flat = ok.reshape(b, v, h * w)
    pts = points.float()
    w2c, K = w2c.float(), K.float()
    n = pts.shape[1]
    chunk = max(1, _CHUNK_ELEMS // max(1, b * v * 4))
    out = []
    for s in range(0, n, chunk):
        p = pts[:, None, s:s + chunk].expand(-1, v, -1, -1)  # [B, V, n, 3]
        uv, z = project_points(p, w2c, K)  # [B, V, n, 2], [B, V, n]
        u, vv = uv[..., 0], uv[..., 1]
        inside = (z > 0) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h) & torch.isfinite(p).all(-1)
        u = torch.where(inside, u, torch.zeros_like(u))
        vv = torch.where(inside, vv, torch.zeros_like(vv))
        # Nearest pixel (must hold depth) and the 2x2 bilinear taps around the position (pixel centres at +0.5).
        ni = (vv.floor().long().clamp(0, h - 1) * w + u.floor().long().clamp(0, w - 1))
        x0 = (u - 0.5).floor().long()
        y0 = (vv - 0.5).floor().long()
        taps = []
        for dy in (0, 1):
            for dx in (0, 1):
                taps.append((y0 + dy).clamp(0, h - 1) * w + (x0 + dx).clamp(0, w - 1))
        idx = torch.stack(taps, dim=-1).reshape(b, v, -1)  # [B, V, n*4]
        ref = torch.gather(d_ref, 2, idx).reshape(*u.shape, 4).amin(-1)
        has = torch.gather(ok_flat, 2, ni)
        out.append(inside & has & (z <= ref * (1.0 + depth_tol)))
    if not out:
        return torch.zeros(b, v, 0, dtype=torch.bool, device=depth.device)
    return torch.cat(out, dim=-1)


def count_visible(points: Tensor, depth: Tensor, w2c: Tensor, K: Tensor, *, depth_tol: float = 0.05,
                  valid: Tensor | None = None) -> Tensor:
    """Number of views that see each point: ``[B, N]`` int64 (see :func:`visible_views`)."""
    return visible_views(points, depth, w2c, K, depth_tol=depth_tol, valid=valid).sum(dim=1)
