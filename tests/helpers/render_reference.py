"""A slow, dense, obviously-correct Gaussian rasteriser: every Gaussian at every pixel, one Gaussian at a time.

It spells out gsplat's semantics (see ``anycity.render.api.render``) with no tiling, no sorting tricks and no
chunking, so the fast backends can be checked against it, forward and backward (autograd in float64).
Fine for N <= ~2k Gaussians at <= 64x64 pixels.
"""

from __future__ import annotations

import torch

from anycity.geometry import quat_to_rotmat
from anycity.render.sh import eval_sh
from anycity.structures import Gaussians, RenderOutput


def _render_one(g: Gaussians, b: int, w2c, K, width, height, background, near, far, render_normals):
    R, t = w2c[:3, :3], w2c[:3, 3]
    means = g.means[b]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    Rg = quat_to_rotmat(g.quats[b])
    M = Rg * g.scales[b][:, None, :]
    cov_cam = R @ (M @ M.transpose(-1, -2)) @ R.T
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    lim_x_pos = (width - cx) / fx + 0.3 * (0.5 * width / fx)
    lim_x_neg = cx / fx + 0.3 * (0.5 * width / fx)
    lim_y_pos = (height - cy) / fy + 0.3 * (0.5 * height / fy)
    lim_y_neg = cy / fy + 0.3 * (0.5 * height / fy)
    zs = torch.where(z.abs() > 1e-12, z, torch.ones_like(z))
    tx = zs * torch.clamp(x / zs, -lim_x_neg, lim_x_pos)
    ty = zs * torch.clamp(y / zs, -lim_y_neg, lim_y_pos)
    zero = torch.zeros_like(z)
    J = torch.stack([
        torch.stack([fx / zs, zero, -fx * tx / zs**2], -1),
        torch.stack([zero, fy / zs, -fy * ty / zs**2], -1),
    ], -2)
    cov2d = J @ cov_cam @ J.transpose(-1, -2) + 0.3 * torch.eye(2, dtype=means.dtype)
    a, bb, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - bb * bb
    mx, my = fx * x / zs + cx, fy * y / zs + cy
    visible = (z >= near) & (z <= far) & (det > 0)
    if g.valid is not None:
        visible &= g.valid[b]
    view_dirs = means - (-R.T @ t)  # from the camera centre to each mean
    colors = eval_sh(g.sh[b], view_dirs / view_dirs.norm(dim=-1, keepdim=True))
    if render_normals:
        axis = g.scales[b].argmin(-1)
        n_world = torch.gather(Rg, 2, axis[:, None, None].expand(-1, 3, 1))[..., 0]
        n = n_world @ R.T
        n = torch.where(((n * p).sum(-1, keepdim=True) > 0), -n, n)
    v, u = torch.meshgrid(torch.arange(height, dtype=means.dtype) + 0.5, torch.arange(width, dtype=means.dtype) + 0.5,
                          indexing="ij")
    T = torch.ones(height, width, dtype=means.dtype)
    done = torch.zeros(height, width, dtype=torch.bool)
    rgb = torch.zeros(height, width, 3, dtype=means.dtype)
    dep = torch.zeros(height, width, dtype=means.dtype)
    nor = torch.zeros(height, width, 3, dtype=means.dtype)
    order = torch.argsort(z.detach(), stable=True)
    for i in order.tolist():
        if not bool(visible[i]):
            continue
        ia, ib, ic = c[i] / det[i], -bb[i] / det[i], a[i] / det[i]
        dx, dy = mx[i] - u, my[i] - v
        sigma = 0.5 * (ia * dx * dx + ic * dy * dy) + ib * dx * dy
        alpha = torch.clamp(g.opacities[b, i] * torch.exp(-sigma), max=0.99)
        skip = (sigma < 0) | (alpha < 1.0 / 255.0) | done
        next_T = T * (1 - alpha)
        stop = (next_T <= 1e-4) & ~skip
        use = ~skip & ~stop
        w = torch.where(use, alpha * T, torch.zeros_like(T))
        rgb = rgb + w[..., None] * colors[i]
        dep = dep + w * z[i]
        if render_normals:
            nor = nor + w[..., None] * n[i]
        T = torch.where(use, next_T, T)
        done = done | stop
    alpha_img = 1 - T
    rgb = rgb + T[..., None] * background
    depth = dep / alpha_img.clamp_min(1e-10)
    return rgb.permute(2, 0, 1), depth[None], alpha_img[None], (nor.permute(2, 0, 1) if render_normals else None)


def render_reference(gaussians: Gaussians, w2c, K, width: int, height: int, *, background=None, near=0.01,
                     far=1e10, render_normals=False) -> RenderOutput:
    """Same signature and outputs as ``anycity.render.render``; slow."""
    B, V = w2c.shape[:2]
    dtype = gaussians.means.dtype
    bg = torch.zeros(B, V, 3, dtype=dtype) if background is None else torch.as_tensor(background, dtype=dtype)
    bg = bg.expand(B, V, 3)
    outs = [[_render_one(gaussians, b, w2c[b, v], K[b, v], width, height, bg[b, v], near, far, render_normals)
             for v in range(V)] for b in range(B)]
    stack = lambda k: torch.stack([torch.stack([o[k] for o in row]) for row in outs])  # noqa: E731
    return RenderOutput(rgb=stack(0), depth=stack(1), alpha=stack(2), normal=stack(3) if render_normals else None)
