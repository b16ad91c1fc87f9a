"""Gaussian parameter head (AnySplat ``VGGT_DPT_GS_Head``): a DPT plus an image-feature merger.

The fused DPT features are resized to the full image, the merger's features of the raw [0, 1] image
(7x7 conv + ReLU) are added, then the UV embedding and ``output_conv2`` give raw per-pixel channels
``[B, V, C_raw, H, W]`` with the layout of :data:`anycity.models.gaussians` (opacity logit, 3 scale,
4 quaternion xyzw, 3*K SH, merge confidence). No activation here. Names follow AnySplat's
``gaussian_param_head`` (we call it ``gaussian_head``). ``delta`` (Stage II) is added to the patch tokens
of each read layer before the head's LayerNorm.

Beyond AnySplat, a separate zero-initialised 1x1 conv ``offset_conv`` reads the input of ``output_conv2`` (before
its ReLU, so a dead hidden layer cannot cut it off) and predicts a per-pixel centre offset ``[B, V, 3, H, W]``
(camera frame, in units of the pixel's depth; see :func:`anycity.models.gaussians.pixel_centres`). It is a new key
(AnySplat and VGGT checkpoints still load key for key, reporting only it as missing) and starts at exactly 0, so
centres start on their pixel rays at the depth.

``hidden_slope`` > 0 makes the hidden activation of ``output_conv2`` a leaky ReLU (no parameters, same keys). The
tiny quickstart model trained from scratch otherwise kills that layer: every unit negative on every pixel, so
opacity, scale, rotation and colour residual become constants that no Stage II residual can change.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anycity.models.heads.dpt import DPTHead


def raw_gaussian_channels(sh_degree: int) -> int:
    """Opacity 1 + scale 3 + quaternion 4 + SH 3*(d+1)^2 + confidence 1."""
    return 1 + 3 + 4 + 3 * (sh_degree + 1) ** 2 + 1


class GaussianHead(DPTHead):
    def __init__(self, dim_in: int, sh_degree: int = 4, features: int = 256, hidden: int | None = None,
                 hidden_slope: float = 0.0, **kwargs):
        output_dim = raw_gaussian_channels(sh_degree)
        merged = features // 2
        hidden = hidden or (merged if output_dim > 50 else 32)  # AnySplat: 128 for SH degree 4, else 32
        super().__init__(dim_in, output_dim=output_dim, features=features, hidden=hidden, **kwargs)
        self.sh_degree = sh_degree
        self.input_merger = nn.Sequential(nn.Conv2d(3, merged, 7, 1, 3), nn.ReLU())
        if hidden_slope > 0:
            self.scratch.output_conv2[1] = nn.LeakyReLU(hidden_slope)
        # skip_init: no draw from the RNG, so every other module's random init is what it was without this conv
        self.offset_conv = nn.utils.skip_init(nn.Conv2d, merged, 3, 1)
        nn.init.zeros_(self.offset_conv.weight)
        nn.init.zeros_(self.offset_conv.bias)

    def init_sh_residual(self, gain: float = 0.01) -> None:
        """Random init for ``color_mode="pixel"``: shrink the SH outputs of the last conv so the head starts as a
        near-zero residual on the pixel colours (AnySplat's full-colour head is left as it is otherwise)."""
        last = self.scratch.output_conv2[-1]
        k = (self.sh_degree + 1) ** 2
        with torch.no_grad():
            last.weight[8:8 + 3 * k].mul_(gain)
            last.bias[8:8 + 3 * k].zero_()

    def decode(self, feats: Tensor, images: Tensor) -> Tensor:
        """-> ``[B*V, C_raw + 3, H, W]``: the raw Gaussian channels, then the 3 offset channels."""
        h, w = images.shape[-2:]
        out = F.interpolate(feats, size=(h, w), mode="bilinear", align_corners=True)
        out = out + self.input_merger(images.flatten(0, 1))
        out = self._add_pos(out, w / h)
        return torch.cat([self.scratch.output_conv2(out), self.offset_conv(out)], dim=1)

    def forward(self, tokens_list, images, patch_start_idx, delta=None) -> tuple[Tensor, Tensor]:
        """-> ``raw [B, V, C_raw, H, W]`` (layout of :mod:`anycity.models.gaussians`) and ``offset [B, V, 3, H, W]``."""
        out = super().forward(tokens_list, images, patch_start_idx, delta)
        return out[:, :, :-3], out[:, :, -3:]
