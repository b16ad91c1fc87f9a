"""Depth losses ``L_depth = L_z + L_xy``.

``L_z``: scale-and-shift aligned log-inverse depth L1 plus multi-scale gradient matching (MiDaS style) on
valid pixels. ``L_xy``: ray anchoring (the paper's appendix), the masked mean L1, in pixels, between each
Gaussian centre's reprojection in its supervision camera and its source pixel. Centres leave their rays only
through the Gaussian head's centre offsets, which this term keeps from drifting sideways.
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry import pixel_grid, transform_points


def align_scale_shift(pred: Tensor, target: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Least-squares ``s, t`` per image minimising ``sum mask * (s * pred + t - target)^2``.

    Args:
        pred, target: ``[M, H, W]``; mask: ``[M, H, W]`` float weights (0/1).
    Returns:
        ``s, t`` each ``[M]`` (``s = 1, t = 0`` where fewer than 2 valid pixels or no variance). ``s >= 0``: where
        the fit is negative (an inverted map) the alignment is shift-only, ``s = 1`` and ``t`` its least-squares
        shift, so the residual still depends on (and its gradient corrects) the prediction. A constant target
        (valid pixels), whose fit's sign is rounding noise, keeps ``s = max(fit, 0)``: about 0, and ``t`` that
        constant.
    """
    w = mask
    n = w.sum((-1, -2))
    sp, st = (w * pred).sum((-1, -2)), (w * target).sum((-1, -2))
    # centred moments (two passes): raw ones cancel in float32 when pred's spread is small against its mean (a
    # log-depth of mean 3 and spread 0.01 fitted s = 140 for 100)
    mp, mt = sp / n.clamp_min(1), st / n.clamp_min(1)
    dp = (pred - mp[:, None, None]) * w
    var, cov = (dp * dp).sum((-1, -2)), (dp * (target - mt[:, None, None])).sum((-1, -2))
    det = n * var  # n spp - sp^2
    ok = (n >= 2) & (det.abs() > 1e-12 * n.clamp_min(1) ** 2)
    safe = torch.where(ok, var, torch.ones_like(var))
    s = torch.where(ok, cov / safe, torch.ones_like(det))
    # a negative fit falls back to s = 1, not to the best constant s = 0, whose residual (so its gradient) does not
    # depend on pred; a constant target keeps s = 0 (its fit's sign is rounding noise). Value and gradient stay
    # exact where s >= 0. t below is computed from this s
    lo, hi = torch.where(w > 0, target, torch.inf), torch.where(w > 0, target, -torch.inf)
    varied = lo.amin((-1, -2)) < hi.amax((-1, -2))
    s = torch.where((s < 0) & varied, torch.ones_like(s), s.clamp_min(0.0))
    t = torch.where(ok, (st - s * sp) / n.clamp_min(1), torch.zeros_like(det))
    return s, t


def _gradient_matching(residual: Tensor, mask: Tensor, scales: int) -> Tensor:
    """MiDaS-style gradient-matching term on ``[M, H, W]`` residuals, averaged over ``scales`` dyadic levels.

    Each level is the mean absolute residual difference over the valid neighbour pairs (MiDaS divides the sum by the
    number of valid pixels and sums the levels): a level's weight does not grow with how many pairs it keeps.
    """
    total = residual.new_zeros(())
    for k in range(scales):
        if k > 0:
            residual = residual[:, ::2, ::2]
            mask = mask[:, ::2, ::2]
        mx = mask[:, :, 1:] * mask[:, :, :-1]
        my = mask[:, 1:, :] * mask[:, :-1, :]
        gx = (residual[:, :, 1:] - residual[:, :, :-1]).abs() * mx
        gy = (residual[:, 1:, :] - residual[:, :-1, :]).abs() * my
        total = total + (gx.sum() + gy.sum()) / (mx.sum() + my.sum()).clamp_min(1.0)
    return total / max(scales, 1)


def depth_z_loss(
    pred_depth: Tensor,
    gt_depth: Tensor,
    mask: Tensor | None = None,
    confidence: Tensor | None = None,
    conf_threshold: float | None = None,
    grad_weight: float = 0.5,
    grad_scales: int = 4,
    align: bool = True,
    eps: float = 1e-6,
) -> dict[str, Tensor]:
    """Scale-and-shift aligned log-inverse depth L1 + gradient matching.

    Both depths go to ``u = log(1 / z)``; the prediction is aligned per image by least squares
    (``s * u_pred + t``), so any ``pred = c * gt^k`` with ``k > 0`` gives zero loss; an inverted map (``k < 0``,
    a negative least-squares ``s``) is aligned by shift only (``s = 1``), so it scores > 0 with a gradient towards
    the ground truth. Invalid pixels (mask 0, ground truth <= 0 or not finite, prediction <= 0, or confidence below
    ``conf_threshold``) are ignored, whatever values they hold.

    Args:
        pred_depth, gt_depth: ``[..., 1, H, W]`` z-depth (> 0 where valid).
        mask: ``[..., 1, H, W]`` bool/float validity of the ground truth, or None.
        confidence: ``[..., 1, H, W]`` predicted confidence, used only with ``conf_threshold``.
        grad_weight: weight of the gradient-matching term.
        align: False skips the alignment (``s = 1, t = 0``): an absolute log-depth L1 for predictions that live
            in the ground truth's normalised frame.
    Returns:
        ``{"depth_l1", "depth_grad", "total"}``.
    """
    if pred_depth.shape != gt_depth.shape:
        raise ValueError(f"depth_z_loss: pred {tuple(pred_depth.shape)} and gt {tuple(gt_depth.shape)} differ")
    h, w = pred_depth.shape[-2:]
    p = pred_depth.reshape(-1, h, w).float()
    g = gt_depth.reshape(-1, h, w).float()
    valid = (g > eps) & torch.isfinite(g) & (p > eps)
    if mask is not None:
        valid = valid & mask.reshape(-1, h, w).bool()
    if confidence is not None and conf_threshold is not None:
        valid = valid & (confidence.reshape(-1, h, w) >= conf_threshold)
    m = valid.float()
    # invalid pixels read 1 (u = 0) before the log: a masked inf/NaN would otherwise reach the sums as 0 * inf = NaN
    # (and its gradient as NaN); valid pixels are untouched
    up = -torch.log(torch.where(valid, p, 1.0).clamp_min(eps))
    ug = -torch.log(torch.where(valid, g, 1.0).clamp_min(eps))
    if align:
        s, t = align_scale_shift(up, ug, m)
    else:
        s, t = torch.ones_like(m[:, 0, 0]), torch.zeros_like(m[:, 0, 0])
    residual = (s[:, None, None] * up + t[:, None, None] - ug) * m
    l1 = residual.abs().sum() / m.sum().clamp_min(1.0)
    grad = _gradient_matching(residual, m, grad_scales) if grad_weight > 0 else residual.new_zeros(())
    return {"depth_l1": l1, "depth_grad": grad, "total": l1 + grad_weight * grad}


def ray_anchor_loss(pixel_means: Tensor, w2c: Tensor, K: Tensor, mask: Tensor | None = None,
                    eps: float = 1e-2) -> Tensor:
    """Ray anchoring ``L_xy`` of pixel-aligned Gaussian centres (the paper's definition).

    Each centre is projected into its supervision camera (the source view it was decoded from) and compared with
    its source pixel centre ``(u + 0.5, v + 0.5)``: L1 over the two pixel coordinates, averaged over the masked
    pixels. A centre nearer than ``eps`` (the renderer's near plane, in the frame's units), or behind the camera,
    is reprojected as if at depth ``eps`` and also costs its depth deficit ``eps - z`` times the focal length: the
    loss and its gradient stay bounded and continuous there (a threshold of 1e-6 made a wall of 1e8 gradients just
    in front of it and almost none just behind).

    Args:
        pixel_means: ``[B, V, H, W, 3]`` world centres, one per source pixel.
        w2c: ``[B, V, 4, 4]`` and K ``[B, V, 3, 3]`` of the supervision (source) views.
        mask: ``[B, V, 1, H, W]`` pixels to include (e.g. valid ground-truth depth), or None.
    Returns:
        Scalar: mean L1 reprojection error in pixels.
    """
    b, v, h, w, _ = pixel_means.shape
    cam = transform_points(w2c.float(), pixel_means.float().reshape(b, v, h * w, 3))  # [B, V, HW, 3]
    z = cam[..., 2]
    Kf = K.float()
    focal = torch.stack([Kf[..., 0, 0], Kf[..., 1, 1]], -1)[..., None, :]  # [B, V, 1, 2]
    uv = cam[..., :2] / z.clamp_min(eps)[..., None] * focal + Kf[..., None, :2, 2]
    ref = pixel_grid(h, w, device=cam.device).reshape(1, 1, h * w, 2)
    err = (uv - ref).abs().sum(-1) + (eps - z).clamp_min(0) * focal.mean(-1)
    if mask is None:
        return err.mean()
    m = mask.reshape(b, v, h * w).to(err.dtype)
    return (err * m).sum() / m.sum().clamp_min(1.0)
