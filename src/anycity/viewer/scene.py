"""A predicted scene as the viewer and the video renderer need it: Gaussians, provenance columns, cameras and
input thumbnails, loaded from a predict folder or a ``scene.ply``."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from anycity.export.cli import camera_tensors, load_scene
from anycity.export.ply import load_ply_extras
from anycity.export.views import view_png
from anycity.structures import Gaussians

SH_C0 = 0.28209479177387814
GREY = np.array([0.5, 0.5, 0.5])  # an unknown value in :func:`ramp`


@dataclass
class ViewScene:
    """``gaussians`` (one scene); ``extras`` per-Gaussian columns (``obs_views``, ``completion``) ``{name: [N]}``;
    ``w2c [V, 4, 4]``, ``K [V, 3, 3]`` float64 or None; ``width``, ``height`` of the input images; ``thumbs``: the
    input images ``[h, w, 3]`` uint8 (empty when predict saved none); ``folder``: where renders are saved."""

    gaussians: Gaussians
    extras: dict[str, np.ndarray]
    w2c: torch.Tensor | None
    K: torch.Tensor | None
    width: int
    height: int
    folder: Path
    thumbs: list[np.ndarray] = field(default_factory=list)


def load_view_scene(path: str | Path, thumb_side: int = 128, thumbs: bool = True) -> ViewScene:
    """The scene at ``path`` (a predict folder or a ``scene.ply``); one line for a scene with no Gaussians.
    ``thumbs=False`` skips the input thumbnails (render-video never shows them)."""
    path = Path(path)
    g, cams = load_scene(path)
    folder = path if path.is_dir() else path.parent
    ply = folder / "scene.ply" if path.is_dir() else path
    if g.num_gaussians == 0:
        raise ValueError(f"{ply}: 0 Gaussians (predict writes only valid, finite ones and this scene had none); "
                         "nothing to view, re-run predict with a checkpoint that gives finite Gaussians")
    extras = load_ply_extras(ply)
    if cams is None:
        return ViewScene(g, extras, None, None, 0, 0, folder)
    w2c, K, w, h, names = camera_tensors(cams)
    return ViewScene(g, extras, w2c, K, w, h, folder, load_thumbs(folder, len(names), thumb_side) if thumbs else [])


def load_thumbs(folder: Path, views: int, side: int = 128) -> list[np.ndarray]:
    """``[h, w, 3]`` uint8 thumbnails (longest side ``side``) of ``folder/inputs/NNN.png`` for each of ``views``
    views, or none at all when one is missing or unreadable (a damaged copy, or one too large for Pillow, warns once;
    the splats still show)."""
    thumbs = []
    for i in range(views):
        f = view_png(folder, "inputs", i)
        if not f.is_file():
            return []
        try:
            with Image.open(f) as im:
                im = im.convert("RGB")
        # PIL's errors for a truncated or damaged PNG, and for one whose header claims a decompression bomb's size
        except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
            warnings.warn(f"{f}: unreadable input image ({e}); the viewer shows no camera thumbnails for this scene "
                          "(copy the predict folder again or re-run predict to get them)", stacklevel=2)
            return []
        im.thumbnail((side, side))
        thumbs.append(np.asarray(im))
    return thumbs


def splat_arrays(g: Gaussians) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(centres [N, 3], covariances [N, 3, 3], rgb [N, 3] in [0, 1], opacity [N, 1])`` as viser takes them."""
    from anycity.geometry import quat_to_rotmat

    R = quat_to_rotmat(g.quats[0].float())
    cov = R @ torch.diag_embed(g.scales[0].float() ** 2) @ R.transpose(-1, -2)
    rgb = (0.5 + SH_C0 * g.sh[0, :, 0, :].float()).clamp(0, 1)
    return (g.means[0].float().numpy(), cov.numpy(), rgb.numpy(), g.opacities[0, :, None].float().numpy())


def ramp(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] -> ``[N, 3]`` colours from blue (0) through white to red (1); NaN (unknown, e.g. the
    completion of a voxel-merged prediction) is grey, not the colour of 0."""
    unknown = np.isnan(x)[:, None]
    x = np.clip(np.nan_to_num(x, nan=0.0), 0, 1)[:, None]
    blue, white, red = np.array([0.15, 0.3, 0.9]), np.ones(3), np.array([0.9, 0.15, 0.1])
    col = np.where(x < 0.5, blue + (white - blue) * 2 * x, white + (red - white) * (2 * x - 1))
    return np.where(unknown, GREY, col)
