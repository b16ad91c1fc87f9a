"""Thin adapter over ``gsplat.rasterization`` (CUDA), imported lazily; same outputs as the torch backend.

One call per scene (``[N, ...]`` Gaussians, ``[V, 4, 4]`` cameras), which works across gsplat 1.x. Gradients
reach the Gaussians, ``w2c`` and the background, not ``K`` (refused). Differences from our semantics that
remain: gsplat 1.5.x caps α at 0.999 (≥ 1.6 uses 0.99, as we do) and uses an opacity-aware footprint on CUDA;
both only change pixels near saturation or the footprint edge.
"""

from __future__ import annotations

import torch

from anycity.render.projection import EPS2D, _normals


def _gsplat():
    try:
        import gsplat
    except ImportError as e:  # pragma: no cover - exercised only without gsplat
        raise ImportError("gsplat is not installed; pip install 'anycity[gsplat]' on a CUDA machine") from e
    return gsplat


def kernels_available() -> bool:
    """Whether the installed gsplat has its CUDA kernels. gsplat 1.x loads them lazily: without a prebuilt wheel for
    this torch and CUDA, and without nvcc to build them, ``import gsplat`` works and sets ``_C = None``, and every
    render then fails with "'NoneType' object has no attribute ...". Another gsplat layout: assumed present. May
    build the kernels (minutes, the first time)."""
    try:
        from gsplat.cuda._backend import _C
    except ImportError:
        return True
    return _C is not None


def render_gsplat(means, quats, scales, opacities, sh, valid, w2c, K, width, height, background, near, far,
                  render_normals):
    """Backend entry point (contract in ``anycity.render.api``). gsplat's projection returns no gradient for
    ``Ks``: a ``K`` that requires grad is refused rather than silently left without one."""
    if torch.is_grad_enabled() and K.requires_grad:
        raise ValueError("backend='gsplat': K requires grad, but gsplat gives intrinsics no gradient; pass "
                         "K.detach(), or use backend='torch' for intrinsics gradients")
    if means.device.type != "cuda":
        raise ValueError(f"backend='gsplat' needs CUDA tensors, got {means.device}; use backend='torch' or 'cpu'")
    gsplat = _gsplat()
    B = means.shape[0]
    sh_degree = int(round(sh.shape[2] ** 0.5)) - 1
    opacities = torch.where(valid, opacities, torch.zeros_like(opacities))
    common = dict(width=width, height=height, near_plane=near, far_plane=far, eps2d=EPS2D, packed=False,
                  rasterize_mode="classic")
    rgbs, depths, alphas, normals = [], [], [], []
    for b in range(B):
        colors, alpha, _ = gsplat.rasterization(
            means[b], quats[b], scales[b], opacities[b], sh[b], w2c[b], K[b], sh_degree=sh_degree,
            render_mode="RGB+ED", **common)
        rgbs.append(colors[..., :3])
        depths.append(colors[..., 3:4])
        alphas.append(alpha)
        if render_normals:
            p = torch.einsum("vij,nj->vni", w2c[b, :, :3, :3], means[b]) + w2c[b, :, None, :3, 3]
            n = _normals(quats[b:b + 1], scales[b:b + 1], w2c[b:b + 1, :, :3, :3], p[None])[0]  # [V, N, 3]
            nor, _, _ = gsplat.rasterization(means[b], quats[b], scales[b], opacities[b], n, w2c[b], K[b],
                                             render_mode="RGB", **common)
            normals.append(nor)
    to_bv = lambda xs: torch.stack(xs).permute(0, 1, 4, 2, 3)  # [B,V,H,W,C] -> [B,V,C,H,W]  # noqa: E731
    alpha = to_bv(alphas)
    rgb = to_bv(rgbs) + (1 - alpha) * background[..., None, None]
    depth = to_bv(depths)
    depth = torch.where(alpha > 0, depth, torch.zeros_like(depth))
    return rgb, depth, alpha, (to_bv(normals) if render_normals else None)
