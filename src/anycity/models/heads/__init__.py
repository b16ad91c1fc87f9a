"""Prediction heads: camera (pose encoding), DPT depth, DPT Gaussian parameters."""

from anycity.models.heads.camera_head import CameraHead
from anycity.models.heads.dpt import DepthHead, DPTHead
from anycity.models.heads.gaussian_head import GaussianHead, raw_gaussian_channels

__all__ = ["CameraHead", "DPTHead", "DepthHead", "GaussianHead", "raw_gaussian_channels"]
