"""Stage 1 of rasterisation: 3D Gaussians -> 2D screen-space Gaussians per camera (EWA splatting).

Differentiable in plain PyTorch; shared by the torch backend and used as the reference for fused kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from anycity.geometry.rotations import quat_to_rotmat
from anycity.render.sh import C0, sh_basis

EPS2D = 0.3  # px² low-pass added to the 2D covariance diagonal (gsplat eps2d)
FOV_CLAMP = 0.3  # x/z, y/z clamped to the image extent plus this fraction of tan(fov/2) (gsplat, Inria 1.3x)
RADIUS_SIGMAS = 3.33  # footprint half-size per axis in standard deviations
RADIUS_MAX_KEPT = 2.0**30  # px; a footprint up to this size keeps its radius as computed
RADIUS_INT32_MAX = 2.0**31 - 128  # px; the largest float32 below 2^31, so the int32 cast cannot wrap
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


@dataclass
class Projected:
    """Screen-space Gaussians for C = B*V cameras (camera c = b*V + v) and the N Gaussians of scene b.

    Attributes:
        mean2d: ``[C, N, 2]`` pixel coordinates of the projected means.
        conic: ``[C, N, 3]`` (a, b, c): the upper triangle of the inverse 2D covariance.
        opacity: ``[C, N]``.
        features: ``[C, N, D]``: rgb (3), camera z (1), then the camera-frame normal (3) when asked.
        radius: ``[C, N, 2]`` int32 footprint half-size in pixels (x, y); one above 2^30 px is cut to what reaches
            the image's far edges (at most 2^31 - 128), which gives the same tiles.
        visible: ``[C, N]`` bool; False for culled or invalid Gaussians.
    """

    mean2d: Tensor
    conic: Tensor
    opacity: Tensor
    features: Tensor
    radius: Tensor
    visible: Tensor


def project_gaussians(means, quats, scales, opacities, sh, valid, w2c, K, width: int, height: int,
                      near: float, far: float, render_normals: bool) -> Projected:
    """Project B scenes of N Gaussians into V cameras each. Shapes as in ``anycity.render.api``."""
    B, N = means.shape[:2]
    V = w2c.shape[1]
    R, t = w2c[..., :3, :3], w2c[..., :3, 3]  # [B,V,3,3], [B,V,3]
    p = torch.einsum("bvij,bnj->bvni", R, means) + t[:, :, None]  # [B,V,N,3] camera-frame means
    x, y, z = p.unbind(-1)
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]  # [B,V,1]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]

    in_depth = (z > 0) & (z >= near) & (z <= far)
    zs = torch.where(in_depth, z, torch.ones_like(z))  # safe divisor: culled entries must not poison gradients
    half_tan_x, half_tan_y = FOV_CLAMP * 0.5 * width / fx, FOV_CLAMP * 0.5 * height / fy
    tx = zs * torch.minimum(torch.maximum(x / zs, -cx / fx - half_tan_x), (width - cx) / fx + half_tan_x)
    ty = zs * torch.minimum(torch.maximum(y / zs, -cy / fy - half_tan_y), (height - cy) / fy + half_tan_y)
    zero = torch.zeros_like(zs)
    j1 = torch.stack([fx / zs, zero, -fx * tx / (zs * zs)], -1)  # rows of the EWA Jacobian, [B,V,N,3]
    j2 = torch.stack([zero, fy / zs, -fy * ty / (zs * zs)], -1)
    M = quat_to_rotmat(quats) * scales[..., None, :]  # [B,N,3,3], Σ = M Mᵀ
    JR = torch.einsum("bvnrk,bvkj->bvnrj", torch.stack([j1, j2], -2), R)  # J W, [B,V,N,2,3]
    A = torch.einsum("bvnrk,bnkj->bvnrj", JR, M)  # [B,V,N,2,3]; Σ2D = A Aᵀ
    u1, u2 = A.unbind(-2)
    ca = (u1 * u1).sum(-1) + EPS2D
    cb = (u1 * u2).sum(-1)
    cc = (u2 * u2).sum(-1) + EPS2D
    # A 2D covariance past float32's range (a std of ~1e19 px) has no conic (inf/inf): cull it, kept out of the
    # maths so that neither the image nor any gradient becomes NaN.
    in_range = torch.isfinite(ca) & torch.isfinite(cc)
    ca, cc = torch.where(in_range, ca, torch.ones_like(ca)), torch.where(in_range, cc, torch.ones_like(cc))
    # ca cc - cb² by Lagrange's identity, |u1 x u2|² + the EPS2D terms: for a long thin footprint ca cc and cb² agree
    # in nearly every float32 digit (a 3000 px needle's alpha was off by 0.13), the cross product does not cancel
    keep = in_range[..., None]
    cross = torch.linalg.cross(torch.where(keep, u1, 0.0), torch.where(keep, u2, 0.0))
    det = cross.square().sum(-1) + EPS2D * (ca + cc) - EPS2D * EPS2D
    ok_det = in_range & (det > 0)
    det_s = torch.where(ok_det, det, torch.ones_like(det))
    conic = torch.stack([cc / det_s, -cb / det_s, ca / det_s], -1)
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)

    with torch.no_grad():
        radius = torch.ceil(RADIUS_SIGMAS * torch.stack([ca, cc], -1).clamp_min(0).sqrt())
        mx, my = mean2d.unbind(-1)
        rx, ry = radius.unbind(-1)
        on_image = (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
        # A Gaussian with opacity < 1/255 can never reach alpha >= 1/255: cull it (as gsplat's CUDA path does).
        visible = in_depth & ok_det & on_image & valid[:, None] & (opacities[:, None] >= ALPHA_MIN)
        # A huge (finite) scale would wrap in the int32 cast. A footprint only has to reach the image's far edges,
        # so clamp it there, never below RADIUS_MAX_KEPT: real footprints and every tile range stay as they were.
        reach = torch.ceil(torch.stack([torch.maximum(mx, width - mx), torch.maximum(my, height - my)], -1)) + 1
        radius = torch.minimum(radius, reach.clamp(RADIUS_MAX_KEPT, RADIUS_INT32_MAX))
        radius = torch.where(visible[..., None], radius, torch.zeros_like(radius)).to(torch.int32)

    features = [_colors(sh, means, w2c, R, t), z[..., None]]
    if render_normals:
        features.append(_normals(quats, scales, R, p))
    return Projected(
        mean2d=mean2d.flatten(0, 1),
        conic=conic.flatten(0, 1),
        opacity=opacities[:, None].expand(B, V, N).flatten(0, 1),
        features=torch.cat(features, -1).flatten(0, 1),
        radius=radius.flatten(0, 1),
        visible=visible.flatten(0, 1),
    )


def _colors(sh: Tensor, means: Tensor, w2c: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """SH -> ``[B,V,N,3]`` colours, viewed from each camera centre."""
    B, N, Kc = sh.shape[:3]
    V = w2c.shape[1]
    if Kc == 1:
        return (C0 * sh[:, None, :, 0] + 0.5).clamp_min(0).expand(B, V, N, 3)
    centers = -torch.einsum("bvji,bvj->bvi", R, t)  # -Rᵀ t
    dirs = means[:, None] - centers[:, :, None]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(dirs, int(math.isqrt(Kc)) - 1)  # [B,V,N,K]
    return (torch.einsum("bvnk,bnkc->bvnc", basis, sh) + 0.5).clamp_min(0)


def _normals(quats: Tensor, scales: Tensor, R: Tensor, p: Tensor) -> Tensor:
    """Axis of the smallest scale in the camera frame, flipped to face the camera: ``[B,V,N,3]``."""
    rot = quat_to_rotmat(quats)  # [B,N,3,3]
    axis = scales.detach().argmin(-1)  # [B,N]
    n_world = torch.gather(rot, 3, axis[..., None, None].expand(*axis.shape, 3, 1))[..., 0]
    n = torch.einsum("bvij,bnj->bvni", R, n_world)
    return torch.where((n * p).sum(-1, keepdim=True) > 0, -n, n)
