"""DPT dense head (VGGT ``DPTHead``) over aggregator layers; the depth head is a DPT with exp depth.

For each of 4 layers: patch tokens -> LayerNorm -> grid -> 1x1 ``projects`` -> UV sin-cos embedding ->
``resize_layers`` (x4, x2, x1, /2 of the patch grid) -> RefineNet fusion (``scratch``) -> ``output_conv1`` ->
bilinear resize to the image -> embedding again -> ``output_conv2``. Frames are decoded in chunks.
Names and shapes follow VGGT's checkpoint.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from anycity.models.heads.activations import activate_dense


def uv_embedding(h: int, w: int, channels: int, aspect: float, dtype: torch.dtype, device) -> Tensor:
    """``[channels, h, w]`` sin-cos embedding of an aspect-aware UV grid (VGGT ``create_uv_grid`` + omega_0=100)."""
    diag = (aspect ** 2 + 1.0) ** 0.5
    sx, sy = aspect / diag, 1.0 / diag
    xs = torch.linspace(-sx * (w - 1) / w, sx * (w - 1) / w, w, dtype=dtype, device=device)
    ys = torch.linspace(-sy * (h - 1) / h, sy * (h - 1) / h, h, dtype=dtype, device=device)
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1).reshape(-1, 2).double()
    d = channels // 2
    omega = 1.0 / 100.0 ** (torch.arange(d // 2, dtype=torch.float64, device=device) / (d / 2.0))

    def sincos(p: Tensor) -> Tensor:
        ang = p[:, None] * omega
        return torch.cat([ang.sin(), ang.cos()], dim=1)

    emb = torch.cat([sincos(grid[:, 0]), sincos(grid[:, 1])], dim=-1).float()
    return emb.reshape(h, w, channels).permute(2, 0, 1)


class ResidualConvUnit(nn.Module):
    """``relu(x) + conv2(relu(conv1(relu(x))))``: VGGT's in-place ReLU makes the skip carry relu(x)."""

    def __init__(self, features: int):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(x)
        return self.conv2(F.relu(self.conv1(x))) + x


class FusionBlock(nn.Module):
    """RefineNet fusion: (skip + RCU1(lateral)) -> RCU2 -> bilinear resize -> 1x1 ``out_conv``."""

    def __init__(self, features: int, has_residual: bool = True):
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        if has_residual:
            self.resConfUnit1 = ResidualConvUnit(features)
        self.has_residual = has_residual
        self.resConfUnit2 = ResidualConvUnit(features)

    def forward(self, x: Tensor, lateral: Tensor | None = None, size=None) -> Tensor:
        if self.has_residual:
            x = x + self.resConfUnit1(lateral)
        x = self.resConfUnit2(x)
        size = size if size is not None else (x.shape[-2] * 2, x.shape[-1] * 2)
        return self.out_conv(F.interpolate(x, size=size, mode="bilinear", align_corners=True))


class DPTHead(nn.Module):
    """Tokens of 4 aggregator layers ``[B, V, T, dim_in]`` -> raw map ``[B, V, output_dim, H, W]``.

    Args:
        features: RefineNet width (256 in VGGT); ``output_conv1`` halves it.
        out_channels: widths of the four projected layers ([256, 512, 1024, 1024] in VGGT).
        layers: aggregator layer indices read ([4, 11, 17, 23] in VGGT).
        hidden: width of ``output_conv2`` (32 in VGGT).
    """

    def __init__(self, dim_in: int, patch_size: int = 14, output_dim: int = 2, features: int = 256,
                 out_channels: tuple[int, ...] = (256, 512, 1024, 1024), layers: tuple[int, ...] = (4, 11, 17, 23),
                 hidden: int = 32, frames_chunk_size: int = 8):
        super().__init__()
        self.patch_size, self.layers, self.frames_chunk_size = patch_size, tuple(layers), frames_chunk_size
        self.norm = nn.LayerNorm(dim_in)
        self.projects = nn.ModuleList(nn.Conv2d(dim_in, oc, 1) for oc in out_channels)
        c = out_channels
        self.resize_layers = nn.ModuleList([
            nn.ConvTranspose2d(c[0], c[0], kernel_size=4, stride=4),
            nn.ConvTranspose2d(c[1], c[1], kernel_size=2, stride=2),
            nn.Identity(), nn.Conv2d(c[3], c[3], kernel_size=3, stride=2, padding=1)])
        self.scratch = nn.Module()
        for i, oc in enumerate(c, start=1):
            setattr(self.scratch, f"layer{i}_rn", nn.Conv2d(oc, features, 3, padding=1, bias=False))
        for i in (1, 2, 3):
            setattr(self.scratch, f"refinenet{i}", FusionBlock(features))
        self.scratch.refinenet4 = FusionBlock(features, has_residual=False)
        self.scratch.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        self.scratch.output_conv2 = nn.Sequential(nn.Conv2d(features // 2, hidden, 3, padding=1), nn.ReLU(),
                                                  nn.Conv2d(hidden, output_dim, 1))

    def _add_pos(self, x: Tensor, aspect: float) -> Tensor:
        return x + 0.1 * uv_embedding(x.shape[-2], x.shape[-1], x.shape[1], aspect, x.dtype, x.device)

    def features(self, tokens_list: list[Tensor | None], images: Tensor, patch_start_idx: int,
                 delta: list[Tensor] | None = None) -> Tensor:
        """Fused features at image resolution ``[B*V, features/2, H, W]`` (before ``output_conv2``)."""
        b, v, _, h, w = images.shape
        gh, gw = h // self.patch_size, w // self.patch_size
        maps = []
        for i, layer in enumerate(self.layers):
            x = tokens_list[layer][:, :, patch_start_idx:]
            if delta is not None:
                x = x + delta[i]
            x = self.norm(x.reshape(b * v, gh * gw, -1))
            x = x.transpose(1, 2).reshape(b * v, -1, gh, gw)
            x = self._add_pos(self.projects[i](x), w / h)
            maps.append(self.resize_layers[i](x))
        s = self.scratch
        l1, l2, l3, l4 = (getattr(s, f"layer{i}_rn")(m) for i, m in enumerate(maps, start=1))
        out = s.refinenet4(l4, size=l3.shape[-2:])
        out = s.refinenet3(out, l3, size=l2.shape[-2:])
        out = s.refinenet2(out, l2, size=l1.shape[-2:])
        out = s.output_conv1(s.refinenet1(out, l1))
        return out

    def decode(self, feats: Tensor, images: Tensor) -> Tensor:
        """``features()`` output -> raw ``[B*V, output_dim, H, W]``."""
        h, w = images.shape[-2:]
        p = self.patch_size
        out = F.interpolate(feats, size=(h // p * p, w // p * p), mode="bilinear", align_corners=True)
        return self.scratch.output_conv2(self._add_pos(out, w / h))

    def forward(self, tokens_list: list[Tensor | None], images: Tensor, patch_start_idx: int,
                delta: list[Tensor] | None = None) -> Tensor:
        b, v = images.shape[:2]
        chunk = self.frames_chunk_size or v
        outs = []
        for s in range(0, v, chunk):
            sl = slice(s, min(s + chunk, v))
            toks = [None if t is None else t[:, sl] for t in tokens_list]
            d = None if delta is None else [x[:, sl] for x in delta]
            imgs = images[:, sl]
            outs.append(self.decode(self.features(toks, imgs, patch_start_idx, d), imgs).unflatten(0, (b, -1)))
        return torch.cat(outs, dim=1)


class DepthHead(DPTHead):
    """DPT with ``exp`` depth and ``1 + exp`` confidence: returns ``depth, conf`` each ``[B, V, 1, H, W]``."""

    def __init__(self, dim_in: int, **kwargs):
        super().__init__(dim_in, output_dim=2, **kwargs)

    def forward(self, tokens_list, images, patch_start_idx, delta=None) -> tuple[Tensor, Tensor]:
        raw = super().forward(tokens_list, images, patch_start_idx, delta)
        depth, conf = activate_dense(raw.flatten(0, 1), "exp", "expp1")
        b, v = raw.shape[:2]
        return depth.permute(0, 3, 1, 2).unflatten(0, (b, v)), conf[:, None].unflatten(0, (b, v))
