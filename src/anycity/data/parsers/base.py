"""What every converter produces (:class:`ParsedScene`) and how parsed scenes become shards.

Each parser re-expresses its source in OpenCV world-to-camera poses and pixel intrinsics, and records the
similarity it applied to the source world (``world_from_source``, scale included) and the output units.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import SPLITS, ShardSetWriter, split_scenes

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # c2w_cv = c2w_gl @ GL_TO_CV


@dataclass
class ParsedView:
    """One source view: image file, OpenCV ``w2c [4, 4]``, ``K [3, 3]`` for an image of width x height pixels."""

    name: str
    image_path: Path
    w2c: np.ndarray
    K: np.ndarray
    width: int
    height: int
    depth: Callable[[], np.ndarray] | None = None  # -> [H, W] z-depth in the scene's output units, 0 invalid
    dist: np.ndarray | None = None  # OpenCV lens distortion (k1, k2, p1, p2[, k3]) of K; undistorted when loaded


@dataclass
class ParsedScene:
    name: str
    views: list[ParsedView]
    source: str
    units: str
    metres_per_unit: float | None = None
    world_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    split: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def require(path: Path, what: str) -> Path:
    """Raise FileNotFoundError naming the missing file and what it should be."""
    if not path.exists():
        raise FileNotFoundError(f"{path}: not found; expected {what}")
    return path


def safe_key(*parts: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "-", "_".join(p for p in parts if p)).strip("-") or "scene"


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def c2w_gl_to_w2c(c2w_gl: np.ndarray) -> np.ndarray:
    """OpenGL/NeRF camera-to-world ``[4, 4]`` (or 3x4) -> OpenCV world-to-camera."""
    c2w = np.eye(4)
    c2w[: c2w_gl.shape[0]] = c2w_gl
    return np.linalg.inv(c2w @ GL_TO_CV)


_HALF = np.array([[1.0, 0, -0.5], [0, 1, -0.5], [0, 0, 1]])  # K with +0.5 pixel centres -> OpenCV's integer ones


def undistort(img: np.ndarray, depth: np.ndarray | None, K: np.ndarray,
              dist: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Resample ``img [H, W, 3]`` (bilinear) and ``depth [H, W]`` (nearest; z-depth is unchanged, the camera does
    not rotate) from the camera ``K`` with OpenCV distortion ``dist`` to a pinhole camera of the same size, which
    OpenCV's ``getOptimalNewCameraMatrix`` picks so every pixel sees the source (alpha 0: the borders are cropped, as
    LaCT's DL3DV step does). Returns ``(img, depth, K_new)``. K uses pixel centres at +0.5, OpenCV integers."""
    h, w = img.shape[:2]
    K_cv = _HALF @ K
    new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, dist, (w, h), 0, (w, h))
    mx, my = cv2.initUndistortRectifyMap(K_cv, dist, None, new_cv, (w, h), cv2.CV_32FC1)
    img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if depth is not None:  # nearest rounds each map coordinate to the closest pixel (integer centres, as mx, my)
        depth = cv2.remap(depth.astype(np.float32), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
    return img, depth, np.linalg.inv(_HALF) @ new_cv


def _load_view(v: ParsedView, max_side: int | None) -> ViewRecord:
    raw = require(v.image_path, f"the image of view {v.name}").read_bytes()
    # The stored pixels, which the cameras describe (COLMAP ignores the EXIF orientation); the shards are decoded so.
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ValueError(f"{v.image_path}: not a readable image; replace or remove the file")
    h, w = img.shape[:2]
    K = np.asarray(v.K, np.float64).copy()
    if (w, h) != (v.width, v.height):  # camera given for another resolution of the same image
        if abs(w * v.height - h * v.width) > v.width + v.height:  # more than a pixel of rounding on either axis
            raise ValueError(f"{v.image_path}: the image is {w}x{h} but its camera is for {v.width}x{v.height}, "
                             "another aspect ratio (rotated or cropped since?); give the image the camera describes")
        K[0] *= w / v.width
        K[1] *= h / v.height
    depth = v.depth() if v.depth is not None else None
    distorted = v.dist is not None and bool(np.any(np.asarray(v.dist) != 0))
    if distorted:
        if depth is not None and depth.shape[:2] != (h, w):
            depth = cv2.resize(depth.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST_EXACT)
        img, depth, K = undistort(img, depth, K, np.asarray(v.dist, np.float64))
    ext = v.image_path.suffix.lower().lstrip(".")
    ext = "jpg" if ext in ("jpg", "jpeg") else "png"
    s = min(1.0, max_side / max(h, w)) if max_side else 1.0
    if s < 1.0:
        nw, nh = round(w * s), round(h * s)
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        K[0] *= nw / w
        K[1] *= nh / h
        if depth is not None:
            depth = cv2.resize(depth, (nw, nh), interpolation=cv2.INTER_NEAREST_EXACT)
        w, h = nw, nh
        image: np.ndarray | bytes = img[..., ::-1]
    else:
        stored = not distorted and v.image_path.suffix.lower() in (".jpg", ".jpeg", ".png")
        image = raw if stored else img[..., ::-1]  # the file's own bytes when its pixels are kept as they are
    if depth is not None and depth.shape[:2] != (h, w):
        depth = cv2.resize(depth.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST_EXACT)
    mask = None if depth is None else (depth > 0) & np.isfinite(depth)
    if depth is not None:
        depth = np.where(mask, depth, 0).astype(np.float32)
    return ViewRecord(name=v.name, image=image, w2c=v.w2c, K=K, width=w, height=h, depth=depth, mask=mask, ext=ext)


def to_records(scene: ParsedScene, max_views: int = 64, max_side: int | None = None) -> Iterator[SceneRecord]:
    """Cut a scene into samples of at most ``max_views`` consecutive views and load their images."""
    n = len(scene.views)
    if n == 0:
        raise ValueError(f"scene {scene.name}: no views found; check the source layout")
    chunks = max(1, -(-n // max_views))
    for c in range(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        key = safe_key(scene.source, scene.name) + (f"_w{c:03d}" if chunks > 1 else "")
        yield SceneRecord(key=key, views=[_load_view(v, max_side) for v in scene.views[a:b]], source=scene.source,
                          units=scene.units, metres_per_unit=scene.metres_per_unit,
                          world_from_source=scene.world_from_source,
                          extra={**scene.extra, "scene": scene.name, "window": [a, b]},
                          scene=safe_key(scene.source, scene.name), first_index=a, scene_views=n)


def write_scenes(scenes: list[ParsedScene], out: str | Path, split: str = "auto", max_views: int = 64,
                 max_side: int | None = None, seed: int = 0, maxcount: int = 16,
                 overwrite: bool = False) -> dict:
    """Write parsed scenes as shards. ``split``: auto (dataset split, else 8:1:1 by scene) or train|val|test."""
    if split not in ("auto", *SPLITS):
        raise ValueError(f"split: expected auto, train, val or test, got {split!r}")
    auto = split_scenes(len(scenes), seed)
    with ShardSetWriter(out, maxcount=maxcount, depth_dtype="float32", overwrite=overwrite) as w:
        for i, sc in enumerate(scenes):
            sp = split if split != "auto" else (sc.split or auto[i])
            for rec in to_records(sc, max_views, max_side):
                w.write(rec, sp)
    return w.close()
