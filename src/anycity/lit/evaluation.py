"""Evaluation helpers: map ground-truth cameras into the predicted frame (Sim(3) fit of the context cameras)
and accumulate PSNR / SSIM / depth metrics with torchmetrics (DDP-safe)."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torchmetrics import MeanMetric
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from anycity.geometry import camera_centers, umeyama

AlignMode = Literal["sim3", "none"]


def _frame_points(w2c: Tensor) -> Tensor:
    """``[B, V, 4, 4]`` -> ``[B, 4V, 3]``: camera centres plus points one spread-length along each camera axis,
    so that rotation and scale are determined even for nearly collinear trajectories."""
    c = camera_centers(w2c)  # [B, V, 3]
    spread = (c - c.mean(1, keepdim=True)).norm(dim=-1).mean(1).clamp_min(1e-3)  # [B]
    axes = w2c[..., :3, :3]  # rows = camera axes in world coordinates
    pts = c[:, :, None, :] + spread[:, None, None, None] * axes  # [B, V, 3, 3]
    return torch.cat([c[:, :, None, :], pts], dim=2).flatten(1, 2)


def fit_gt_to_pred(pred_w2c: Tensor, gt_w2c: Tensor, mode: AlignMode = "sim3") -> tuple[Tensor, Tensor, Tensor]:
    """Similarity ``p_pred = s R p_gt + t`` between the ground-truth and predicted context frames.

    Args:
        pred_w2c, gt_w2c: ``[B, V, 4, 4]`` the same context views, predicted and ground truth.
        mode: ``"sim3"`` (Umeyama fit; identity when V == 1) or ``"none"`` (identity: both frames put the first
            context camera at the origin with the same scale convention).
    Returns:
        ``s [B]``, ``R [B, 3, 3]``, ``t [B, 3]`` (float32, no gradient).
    """
    b = pred_w2c.shape[0]
    eye = torch.eye(3, device=pred_w2c.device).expand(b, 3, 3)
    ident = (torch.ones(b, device=pred_w2c.device), eye, torch.zeros(b, 3, device=pred_w2c.device))
    if mode == "none" or pred_w2c.shape[1] < 2:
        return ident
    if mode != "sim3":
        raise ValueError(f"eval_align: expected 'sim3' or 'none', got {mode!r}")
    with torch.no_grad(), torch.autocast(pred_w2c.device.type, enabled=False):
        s, R, t = umeyama(_frame_points(gt_w2c.float()), _frame_points(pred_w2c.float()))
    ok = torch.isfinite(s) & (s > 0) & torch.isfinite(R).flatten(1).all(1) & torch.isfinite(t).all(1)
    s = torch.where(ok, s, ident[0])
    R = torch.where(ok[:, None, None], R, ident[1])
    t = torch.where(ok[:, None], t, ident[2])
    return s, R, t


def cameras_in_pred_frame(gt_w2c: Tensor, s: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Ground-truth ``w2c [B, T, 4, 4]`` -> the same cameras in the predicted frame (rigid, predicted units).

    A point at camera depth z (ground-truth units) has depth ``s * z`` in the returned cameras.
    """
    Rc, tc = gt_w2c[..., :3, :3].float(), gt_w2c[..., :3, 3].float()
    Rn = Rc @ R.transpose(-1, -2)[:, None]
    tn = s[:, None, None] * tc - (Rn @ t[:, None, :, None])[..., 0]
    out = torch.zeros_like(gt_w2c, dtype=torch.float32)
    out[..., :3, :3], out[..., :3, 3], out[..., 3, 3] = Rn, tn, 1.0
    return out


class EvalMetrics(nn.Module):
    """Per-image PSNR / SSIM (torchmetrics) and per-image AbsRel / delta1 means, for named variants (plus PSNR of
    the ``baseline`` and ``nearest`` view references).

    ``update(variant, pred, target)`` takes ``[M, 3, H, W]`` images; ``update_depth(variant, abs_rel, delta1)``
    takes per-image values. ``items()`` yields ``(name, metric)`` pairs ready for ``LightningModule.log``.
    """

    def __init__(self, variants: tuple[str, ...]) -> None:
        super().__init__()
        self.variants = variants
        m: dict[str, nn.Module] = {}
        for v in (*variants, "baseline", "nearest"):
            m[f"psnr_{v}"] = PeakSignalNoiseRatio(data_range=1.0, dim=(1, 2, 3), reduction="elementwise_mean")
        for v in variants:
            m[f"ssim_{v}"] = StructuralSimilarityIndexMeasure(data_range=1.0)
            m[f"abs_rel_{v}"] = MeanMetric()
            m[f"delta1_{v}"] = MeanMetric()
        self.metrics = nn.ModuleDict(m)

    def update(self, variant: str, pred: Tensor, target: Tensor) -> None:
        p, t = pred.float().clamp(0, 1), target.float()
        self.metrics[f"psnr_{variant}"].update(p, t)
        if f"ssim_{variant}" in self.metrics:
            self.metrics[f"ssim_{variant}"].update(p, t)

    def update_depth(self, variant: str, abs_rel: Tensor, delta1: Tensor, valid: Tensor) -> None:
        if bool(valid.any()):
            self.metrics[f"abs_rel_{variant}"].update(abs_rel[valid])
            self.metrics[f"delta1_{variant}"].update(delta1[valid])

    def items(self):
        return self.metrics.items()
