"""Which views see a point: projection into each view's frame plus a depth test against that view's depth map.

Used by the region diagnostic (:mod:`anycity.metrics.regions`) and for per-Gaussian provenance (how many context views
observe a Gaussian).
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry.projection import transform_points

CHUNK = 65536  # points per step: 64 views x 64k points x a few floats stays well under a GB


def visible_views(points: Tensor, depth: Tensor, w2c: Tensor, K: Tensor, *, depth_tol: float = 0.05,
                  valid: Tensor | None = None) -> Tensor:
    """``[B, V, N]`` bool: view v sees point n.

    A view sees a point when the point projects inside its frame, in front of the camera, onto a pixel with valid
    depth ``d``, and is not behind that surface: ``z <= d * (1 + depth_tol)``. The depth is read at the pixel the
    point falls in (pixel centres at +0.5, so pixel ``floor(u), floor(v)``), with no interpolation: a point just
    behind a depth edge reads the nearer surface and stays occluded.

    Args:
        points: ``[B, N, 3]`` world points.
        depth: ``[B, V, 1, H, W]`` z-depth of each view (<= 0 or non-finite = no surface, e.g. sky).
        w2c: ``[B, V, 4, 4]``; K: ``[B, V, 3, 3]`` in pixels of ``depth``.
        depth_tol: relative tolerance of the depth test.
        valid: ``[B, V, 1, H, W]`` bool, pixels whose depth may be used, or None.
    """
    b, v, _, h, w = depth.shape
    d = depth.float().reshape(b, v, h * w)
    ok = torch.isfinite(d) & (d > 0)
    if valid is not None:
        ok = ok & valid.reshape(b, v, h * w).bool()
    d = torch.where(ok, d, torch.zeros_like(d))
    out = []
    for s in range(0, points.shape[1], CHUNK):
        pts = points[:, None, s:s + CHUNK].float().expand(b, v, -1, 3)
        cam = transform_points(w2c.float(), pts)  # [B, V, n, 3]
        z = cam[..., 2]
        uvw = cam @ K.float().transpose(-1, -2)
        u = uvw[..., 0] / z.clamp_min(1e-9)
        vv = uvw[..., 1] / z.clamp_min(1e-9)
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (vv >= 0) & (vv < h) & torch.isfinite(u) & torch.isfinite(vv)
        idx = (vv.floor().clamp(0, h - 1) * w + u.floor().clamp(0, w - 1)).long()
        surf = torch.gather(d, 2, idx)
        out.append(inside & (surf > 0) & (z <= surf * (1 + depth_tol)))
    return torch.cat(out, dim=2) if out else torch.zeros(b, v, 0, dtype=torch.bool, device=depth.device)


def count_visible(points: Tensor, depth: Tensor, w2c: Tensor, K: Tensor, *, depth_tol: float = 0.05,
                  valid: Tensor | None = None) -> Tensor:
    """``[B, N]`` int: how many views see each point (:func:`visible_views`)."""
    return visible_views(points, depth, w2c, K, depth_tol=depth_tol, valid=valid).sum(1)
