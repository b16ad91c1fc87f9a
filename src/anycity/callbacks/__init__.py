"""Lightning callbacks: freezing, LoRA injection, previews, loss-term progress, prediction export."""

from anycity.callbacks.export import PredictionExport
from anycity.callbacks.freeze import FreezeModules, freeze_by_patterns
from anycity.callbacks.lora import LoRAInjection, inject_lora
from anycity.callbacks.previews import ImagePreviews, depth_to_rgb, preview_grid
from anycity.callbacks.progress import LossProgressBar

__all__ = ["PredictionExport", "FreezeModules", "freeze_by_patterns", "LoRAInjection", "inject_lora", "ImagePreviews",
           "depth_to_rgb", "preview_grid", "LossProgressBar"]
