"""Depth accuracy: AbsRel and delta1 (max(d/d*, d*/d) < 1.25) on the ground truth's valid pixels, optional median
scaling. A pixel the prediction leaves empty (no Gaussian rendered there: depth 0) is a failure, not left out."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor


def _valid(gt: Tensor, mask: Tensor | None) -> Tensor:
    v = (gt > 0) & torch.isfinite(gt)
    if mask is not None:
        v = v & mask.bool()
    return v


def depth_metrics(pred: Tensor, gt: Tensor, mask: Tensor | None = None,
                  align: Literal["none", "median"] = "none") -> dict[str, Tensor]:
    """AbsRel and delta1 per image.

    Args:
        pred, gt: ``[..., 1, H, W]`` z-depth in the same units (unless ``align="median"``).
        mask: ``[..., 1, H, W]`` validity of the ground truth (gt's shape), or None.
        align: ``"median"`` rescales each predicted image by ``median(gt) / median(pred)`` over the valid pixels
            it covers (for scale-ambiguous predictions).
    Returns:
        ``{"abs_rel": [M], "delta1": [M], "valid": [M] bool}`` over the ground truth's valid pixels (images with
        none: valid False, 0). A valid pixel with no positive, finite prediction scores AbsRel 1 and fails delta1.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"depth_metrics: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")
    if mask is not None and mask.shape != gt.shape:
        raise ValueError(f"depth_metrics: mask {tuple(mask.shape)} must have gt's shape {tuple(gt.shape)} "
                         "(one validity flag per ground-truth pixel; expand it first)")
    if align not in ("none", "median"):
        raise ValueError(f"depth_metrics: align must be 'none' or 'median', got {align!r}")
    h, w = pred.shape[-2:]
    p = pred.reshape(-1, h * w).float()
    g = gt.reshape(-1, h * w).float()
    v = _valid(g, None if mask is None else mask.reshape(-1, h * w))
    covered = v & (p > 0) & torch.isfinite(p)
    n = v.sum(-1)
    if align == "median":
        nan = torch.full_like(p, float("nan"))
        ratio = torch.where(covered, g, nan).nanmedian(-1).values / torch.where(covered, p, nan).nanmedian(-1).values
        p = p * torch.nan_to_num(ratio, nan=1.0)[:, None]
    safe_p = torch.where(covered, p, torch.zeros_like(p))  # a hole: depth 0
    safe_g = torch.where(v, g, torch.ones_like(g))
    rel = ((safe_p - safe_g).abs() / safe_g) * v
    thresh = torch.maximum(safe_p / safe_g, safe_g / safe_p.clamp_min(torch.finfo(p.dtype).tiny))
    d1 = ((thresh < 1.25) & covered).float()
    denom = n.clamp_min(1).float()
    return {"abs_rel": rel.sum(-1) / denom, "delta1": d1.sum(-1) / denom, "valid": n > 0}
