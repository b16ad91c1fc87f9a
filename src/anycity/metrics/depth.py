"""Depth accuracy: AbsRel and delta1 (max(d/d*, d*/d) < 1.25) on valid pixels, optional median scaling."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor


def _valid(pred: Tensor, gt: Tensor, mask: Tensor | None) -> Tensor:
    v = (gt > 0) & (pred > 0) & torch.isfinite(gt) & torch.isfinite(pred)
    if mask is not None:
        v = v & mask.bool()
    return v


def depth_metrics(pred: Tensor, gt: Tensor, mask: Tensor | None = None,
                  align: Literal["none", "median"] = "none") -> dict[str, Tensor]:
    """AbsRel and delta1 per image.

    Args:
        pred, gt: ``[..., 1, H, W]`` z-depth in the same units (unless ``align="median"``).
        mask: ``[..., 1, H, W]`` validity of the ground truth, or None.
        align: ``"median"`` rescales each predicted image by ``median(gt) / median(pred)`` over valid pixels
            (for scale-ambiguous predictions).
    Returns:
        ``{"abs_rel": [M], "delta1": [M], "valid": [M] bool}`` (images with no valid pixel: valid False, 0).
    """
    if pred.shape != gt.shape:
        raise ValueError(f"depth_metrics: pred {tuple(pred.shape)} and gt {tuple(gt.shape)} differ")
    if align not in ("none", "median"):
        raise ValueError(f"depth_metrics: align must be 'none' or 'median', got {align!r}")
    h, w = pred.shape[-2:]
    p = pred.reshape(-1, h * w).float()
    g = gt.reshape(-1, h * w).float()
    v = _valid(p, g, None if mask is None else mask.reshape(-1, h * w))
    n = v.sum(-1)
    if align == "median":
        nan = torch.full_like(p, float("nan"))
        ratio = torch.where(v, g, nan).nanmedian(-1).values / torch.where(v, p, nan).nanmedian(-1).values
        p = p * torch.nan_to_num(ratio, nan=1.0)[:, None]
    safe_p = torch.where(v, p, torch.ones_like(p))
    safe_g = torch.where(v, g, torch.ones_like(g))
    rel = ((safe_p - safe_g).abs() / safe_g) * v
    thresh = torch.maximum(safe_p / safe_g, safe_g / safe_p)
    d1 = ((thresh < 1.25) & v).float()
    denom = n.clamp_min(1).float()
    return {"abs_rel": rel.sum(-1) / denom, "delta1": d1.sum(-1) / denom, "valid": n > 0}
