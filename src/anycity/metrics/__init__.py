"""Evaluation metrics: image quality (PSNR via torchmetrics, SSIM as skimage's default), depth accuracy (AbsRel,
delta1) and relative camera pose errors (RRE, RTE, AUC@30), and the observed / weak region diagnostic with
region-masked metrics."""

from anycity.metrics.depth import depth_metrics
from anycity.metrics.image import mean_colour_baseline, nearest_view_reference, psnr, ssim
from anycity.metrics.pose import pose_auc, relative_pose_errors
from anycity.metrics.regions import RegionMetric, lpips_or_none, masked_lpips, masked_psnr, masked_ssim, region_masks

__all__ = ["depth_metrics", "mean_colour_baseline", "nearest_view_reference", "pose_auc", "psnr",
           "relative_pose_errors", "ssim", "RegionMetric", "lpips_or_none", "masked_lpips", "masked_psnr",
           "masked_ssim", "region_masks"]
