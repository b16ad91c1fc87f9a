"""Lightning callbacks: freezing, previews, loss-term progress, prediction export, non-finite step skipping, SLURM
time-limit checkpoints between steps."""

from anycity.callbacks.export import PredictionExport
from anycity.callbacks.freeze import FreezeModules, freeze_by_patterns
from anycity.callbacks.nonfinite import NonFiniteGuard
from anycity.callbacks.previews import ImagePreviews, depth_to_rgb, preview_grid
from anycity.callbacks.progress import LossProgressBar
from anycity.callbacks.requeue import RequeueAtSafePoint

__all__ = ["PredictionExport", "FreezeModules", "freeze_by_patterns", "NonFiniteGuard", "ImagePreviews",
           "depth_to_rgb", "preview_grid", "LossProgressBar", "RequeueAtSafePoint"]
