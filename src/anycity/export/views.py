"""Where ``anycity predict`` saves each view's images: ``<scene folder>/<kind>/NNN.png``, ``kind`` being ``inputs``
(the context image the camera belongs to, at the cameras' size) or ``renders``, ``NNN`` the view's index."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image
from torch import Tensor

from anycity.atomic import atomic_open


def view_png(folder: str | Path, kind: str, view: int) -> Path:
    """``folder/kind/NNN.png`` for view index ``view``."""
    return Path(folder) / kind / f"{view:03d}.png"


def save_view_pngs(folder: str | Path, kind: str, images: Tensor, views: Sequence[int]) -> None:
    """Write ``images[j]`` (``[V, 3, H, W]``, in [0, 1]) as the 8-bit PNG ``view_png(folder, kind, views[j])``,
    each through :func:`anycity.atomic.atomic_open`: a killed run leaves no truncated PNG for the viewer to read."""
    if len(views) != len(images):
        raise ValueError(f"{len(images)} images for {len(views)} view indices")
    (Path(folder) / kind).mkdir(parents=True, exist_ok=True)
    for v, img in zip(views, images, strict=True):
        arr = (img.float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        with atomic_open(view_png(folder, kind, v)) as f:
            Image.fromarray(arr).save(f, format="PNG")
