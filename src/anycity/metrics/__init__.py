"""Evaluation metrics: image quality (PSNR/SSIM via torchmetrics) and depth accuracy (AbsRel, delta1)."""

from anycity.metrics.depth import depth_metrics
from anycity.metrics.image import mean_colour_baseline, nearest_view_reference, psnr, ssim

__all__ = ["depth_metrics", "mean_colour_baseline", "nearest_view_reference", "psnr", "ssim"]
