"""Normal loss ``L_normal``: structure-adaptive normal consistency plus a flatness prior.

``L = mean_px[ w * Huber(1 - n_surf . n_gs) ] + lambda_flat * mean_px[ w * s_min ]``, where ``n_surf`` comes from
the rendered depth by central differences, ``n_gs`` is the rendered (alpha-blended) Gaussian normal, ``s_min`` the
smallest scale of the pixel's own (pixel-aligned) Gaussian and ``w = valid * exp(-|grad I|)``: the structure
weight relaxes both terms at image edges, where depth discontinuities live, and ``valid`` drops sky and other
pixels without a defined normal from both.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from kornia.filters import spatial_gradient
from torch import Tensor

from anycity.geometry import depth_to_normals


def structure_weight(image: Tensor, alpha: float = 1.0) -> Tensor:
    """``[..., 3, H, W]`` -> ``[..., 1, H, W]`` weights ``exp(-alpha * |grad I|)`` (grey-level Sobel gradient)."""
    lead = image.shape[:-3]
    grey = image.reshape(-1, *image.shape[-3:]).mean(-3, keepdim=True)
    g = spatial_gradient(grey, mode="sobel", order=1)  # [M, 1, 2, H, W]
    mag = g.square().sum(2).sqrt()
    return torch.exp(-alpha * mag).reshape(*lead, 1, *image.shape[-2:])


def normal_loss(
    depth: Tensor,
    normal: Tensor,
    K: Tensor,
    image: Tensor | None = None,
    alpha: Tensor | None = None,
    scales: Tensor | None = None,
    flat_weight: float = 0.0,
    huber_delta: float = 0.1,
    edge_alpha: float = 1.0,
    scales_valid: Tensor | None = None,
    mask: Tensor | None = None,
) -> dict[str, Tensor]:
    """Normal consistency between depth-derived and Gaussian-derived normals.

    Args:
        depth: ``[B, V, 1, H, W]`` rendered z-depth; normal: ``[B, V, 3, H, W]`` rendered Gaussian normals
            (camera frame, facing the camera, not necessarily unit length).
        K: ``[B, V, 3, 3]`` intrinsics of the renders.
        image: ``[B, V, 3, H, W]`` guide image for the structure weight, or None (weight 1).
        alpha: ``[B, V, 1, H, W]`` rendered opacity; pixels with alpha < 0.5 are ignored. None = all. Pixels
            whose depth-derived normal is undefined (the border, a pixel with a 4-neighbour of depth <= 0) and
            pixels whose Gaussian normal is zero are ignored too.
        scales: ``[B, N, 3]`` Gaussian scales for the flatness prior (smallest scale, scene units), or None.
            Pixel-aligned Gaussians (``N = V*H*W`` in (view, row, column) order, ``scales_valid`` None) take their
            pixel's weight ``w`` of the normal term; others (a voxel merge: no pixel) the plain mean.
        scales_valid: ``[B, N]`` bool, the Gaussians that exist (a voxel merge pads with invalid ones), or None (all).
        mask: ``[B, V, 1, H, W]`` bool/float validity of the pixels (0 = sky / invalid), or None (all valid).
    Returns:
        ``{"normal", "flat", "total"}``.
    """
    # zero on the 1-pixel border and where a pixel or a 4-neighbour has no depth (alpha 0): excluded below
    n_surf = depth_to_normals(depth.float(), K.float())
    n_gs = F.normalize(normal.float(), dim=-3, eps=1e-8)
    cos = (n_surf * n_gs).sum(-3, keepdim=True)
    valid = (n_surf.abs().sum(-3, keepdim=True) > 0) & (normal.abs().sum(-3, keepdim=True) > 0) & (depth > 0)
    if alpha is not None:
        valid = valid & (alpha > 0.5)
    if mask is not None:
        valid = valid & mask.bool()
    w = valid.float()
    if image is not None:
        w = w * structure_weight(image.float(), edge_alpha)
    per_px = F.huber_loss(1.0 - cos, torch.zeros_like(cos), reduction="none", delta=huber_delta)
    term = (per_px * w).sum() / valid.float().sum().clamp_min(1.0)
    flat = term.new_zeros(()) if scales is None else flatness(scales, w, valid, scales_valid)
    return {"normal": term, "flat": flat, "total": term + flat_weight * flat}


def flatness(scales: Tensor, w: Tensor, valid: Tensor, scales_valid: Tensor | None = None) -> Tensor:
    """The flatness prior: smallest Gaussian scale (scene units), averaged like the normal term.

    Args:
        scales: ``[B, N, 3]``; w, valid: ``[B, V, 1, H, W]`` the normal term's pixel weights and validity.
        scales_valid: ``[B, N]`` bool or None, see :func:`normal_loss`.
    Returns:
        Scalar: ``sum(w * s_min) / sum(valid)`` over pixel-aligned Gaussians (``N = V*H*W``, no ``scales_valid``),
        else the mean ``s_min`` of the existing Gaussians.
    """
    s_min = scales.float().min(-1).values  # [B, N]
    b = s_min.shape[0]
    if scales_valid is None and s_min.shape[1] == w[0].numel():
        return (s_min * w.reshape(b, -1)).sum() / valid.float().sum().clamp_min(1.0)
    if scales_valid is None:
        return s_min.mean()
    return s_min[scales_valid].sum() / scales_valid.sum().clamp_min(1)
