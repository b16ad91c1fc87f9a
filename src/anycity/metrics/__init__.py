"""Evaluation metrics: image quality (PSNR/SSIM via torchmetrics), depth accuracy (AbsRel, delta1) and relative
camera pose errors (RRE, RTE, AUC@30)."""

from anycity.metrics.depth import depth_metrics
from anycity.metrics.image import mean_colour_baseline, nearest_view_reference, psnr, ssim
from anycity.metrics.pose import pose_auc, relative_pose_errors

__all__ = ["depth_metrics", "mean_colour_baseline", "nearest_view_reference", "pose_auc", "psnr",
           "relative_pose_errors", "ssim"]
