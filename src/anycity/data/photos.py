"""A folder of one scene's own photos (no poses) -> the network's input, for ``anycity predict``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from anycity.data.imagecheck import check_image_file
from anycity.data.views import resize_view

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
MAX_VIEWS = 64


def load_photo_folder(folder: str | Path, size: tuple[int, int], mode: str = "crop", patch: int = 14) -> dict:
    """Read every ``.jpg``/``.jpeg``/``.png`` in ``folder`` (sorted by name, EXIF orientation applied) and resize it
    like the training data.

    Args:
        folder: one scene's photos, 2..64 of them.
        size: ``(H, W)`` of :func:`anycity.data.views.resize_view` (``mode="keep"`` keeps each aspect ratio at
            about H*W pixels, so every photo of the folder must share it).
        mode, patch: see :func:`anycity.data.views.resize_view`.
    Returns:
        ``{"images": [V, 3, H, W] float32 in [0, 1], "scene": folder name, "names": file names}``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"predict_images: {folder} is not a folder; pass a folder holding one scene's photos")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not 2 <= len(files) <= MAX_VIEWS:
        raise ValueError(f"predict_images: {folder} holds {len(files)} photos ({'/'.join(PHOTO_SUFFIXES)}); the "
                         f"network takes 2..{MAX_VIEWS} views of one scene, so add or remove photos")
    images = []
    for f in files:
        check_image_file(f)  # decompression bombs and truncated JPEGs are refused before decoding
        bgr = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"predict_images: cannot decode {f}; re-save it as JPEG or PNG, or remove it")
        h, w = bgr.shape[:2]
        K = np.array([[max(h, w), 0, w / 2], [0, max(h, w), h / 2], [0, 0, 1]], np.float64)  # unused placeholder
        rgb, *_ = resize_view(np.ascontiguousarray(bgr[..., ::-1]), K, tuple(size), mode, patch)
        images.append(torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255)
    shapes = {tuple(im.shape) for im in images}
    if len(shapes) > 1:
        raise ValueError(f"predict_images: the photos of {folder} resize to different sizes {sorted(shapes)} "
                         "(resize_mode 'keep' with mixed aspect ratios); use resize_mode 'crop' or crop them alike")
    return {"images": torch.stack(images), "scene": folder.name, "names": [f.name for f in files]}
