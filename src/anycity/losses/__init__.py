"""Training losses. Every function returns a dict of named terms plus ``"total"`` (its weighted sum)."""

from anycity.losses.camera import camera_loss
from anycity.losses.depth import align_scale_shift, depth_z_loss, ray_anchor_loss
from anycity.losses.distill import d2s_loss, preservation_loss
from anycity.losses.normal import normal_loss, structure_weight
from anycity.losses.photometric import rgb_loss
from anycity.losses.regularizers import regularizer_loss

__all__ = [
    "camera_loss", "align_scale_shift", "depth_z_loss", "ray_anchor_loss", "d2s_loss", "preservation_loss",
    "normal_loss", "structure_weight", "rgb_loss", "regularizer_loss",
]
