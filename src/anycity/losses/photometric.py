"""Photometric loss ``L_rgb``: MSE plus an optional (1 - SSIM) term between renders and ground truth."""

from __future__ import annotations

from torch import Tensor
from torchmetrics.functional.image import structural_similarity_index_measure


def _flat(x: Tensor) -> Tensor:
    """``[..., C, H, W]`` -> ``[M, C, H, W]``."""
    return x.reshape(-1, *x.shape[-3:])


def rgb_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None, ssim_weight: float = 0.0) -> dict[str, Tensor]:
    """Photometric terms between rendered and ground-truth images.

    Args:
        pred, target: ``[..., 3, H, W]`` in [0, 1] (leading dims are typically ``B, V``).
        mask: ``[..., 1, H, W]`` weights or bool, or None (all pixels). Applies to the MSE only.
        ssim_weight: weight of ``1 - SSIM`` (0 switches it off and skips the computation).
    Returns:
        ``{"mse": ..., "ssim": ...}`` (the SSIM term only when ``ssim_weight > 0``) and ``"total"``,
        the weighted sum ``mse + ssim_weight * (1 - SSIM)``.
    """
    if pred.shape != target.shape:
        raise ValueError(f"rgb_loss: pred and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    err = (pred - target).square()
    if mask is None:
        mse = err.mean()
    else:
        w = mask.to(err.dtype).expand_as(err)
        mse = (err * w).sum() / w.sum().clamp_min(1.0)
    out = {"mse": mse}
    total = mse
    if ssim_weight > 0:
        ssim = structural_similarity_index_measure(_flat(pred).float(), _flat(target).float(), data_range=1.0)
        out["ssim"] = 1.0 - ssim
        total = total + ssim_weight * out["ssim"]
    out["total"] = total
    return out
