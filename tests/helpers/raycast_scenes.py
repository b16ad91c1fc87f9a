"""Analytic depth maps of tiny scenes (a ground plane z = 0 and axis-aligned boxes, world z up) for the
visibility and region tests: cameras by look-at, z-depth by ray-plane / ray-box intersection, 0 where a ray
hits nothing (sky)."""

from __future__ import annotations

import torch

from anycity.geometry import make_intrinsics, pixel_rays

H, W = 24, 32


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV world-to-camera ``[4, 4]`` (x right, y down, z forward) looking from ``eye`` at ``target``."""
    eye, target, up = (torch.as_tensor(x, dtype=torch.float32) for x in (eye, target, up))
    f = target - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, up)
    if r.norm() < 1e-6:  # looking along up: any perpendicular right axis will do
        r = torch.linalg.cross(f, torch.tensor([0.0, 1.0, 0.0]))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
    return w2c


def intrinsics(h=H, w=W, f=None) -> torch.Tensor:
    f = float(w) if f is None else f
    return make_intrinsics(f, f, w / 2, h / 2)


def render_depth(w2c, K, boxes=(), ground=True, h=H, w=W) -> torch.Tensor:
    """z-depth ``[..., 1, h, w]`` for cameras ``w2c [..., 4, 4]``, ``K [..., 3, 3]``.

    ``boxes``: iterable of ``(lo xyz, hi xyz)``; ``ground``: include the plane z = 0.
    """
    o, d = pixel_rays(K, w2c, h, w)  # [..., 3], [..., h, w, 3]
    o = o[..., None, None, :].expand_as(d)
    t = torch.full(d.shape[:-1], float("inf"))
    if ground:
        tg = -o[..., 2] / d[..., 2]
        t = torch.where((d[..., 2] < 0) & (tg > 0), torch.minimum(t, tg), t)
    for lo, hi in boxes:
        lo, hi = torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)
        with torch.no_grad():
            inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
            t0, t1 = (lo - o) * inv, (hi - o) * inv
            tn = torch.minimum(t0, t1).amax(-1)
            tf = torch.maximum(t0, t1).amin(-1)
        hit = (tn <= tf) & (tn > 0)
        t = torch.where(hit, torch.minimum(t, tn), t)
    fwd = w2c[..., 2, :3]  # camera z axis in world
    z = t * (d * fwd[..., None, None, :]).sum(-1)
    z = torch.where(torch.isfinite(z), z, torch.zeros_like(z))
    return z[..., None, :, :]
