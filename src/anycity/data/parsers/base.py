"""What every converter produces (:class:`ParsedScene`) and how parsed scenes become shards.

Each parser re-expresses its source in OpenCV world-to-camera poses and pixel intrinsics, and records the
similarity it applied to the source world (``world_from_source``, scale included) and the output units.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from anycity.data.imagecheck import check_jpeg_complete
from anycity.data.photos import JPEG_SUFFIXES
from anycity.data.schema import SceneRecord, ViewRecord, encode_image
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
    dist: np.ndarray | None = None  # OpenCV distortion of K, (k1, k2, p1, p2[, k3[, k4, k5, k6]]); undone on load


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
MAX_FOCAL_CHANGE = 10.0  # undistorting a real lens changes the focal well inside this (a wide drone lens: 0.9x)


def undistort(img: np.ndarray, depth: np.ndarray | None, K: np.ndarray, dist: np.ndarray,
              where: str = "image") -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Resample ``img [H, W, 3]`` (bilinear) and ``depth [H, W]`` (nearest; z-depth is unchanged, the camera does
    not rotate) from the camera ``K`` with OpenCV distortion ``dist`` to a pinhole camera of the same size, which
    OpenCV's ``getOptimalNewCameraMatrix`` picks so every pixel sees the source (alpha 0: the borders are cropped, as
    LaCT's DL3DV step does). Returns ``(img, depth, K_new)``. K uses pixel centres at +0.5, OpenCV integers.

    Lens terms no lens has (non-finite; the focal changing over ``MAX_FOCAL_CHANGE`` times; most pixels taken from
    outside the image) are refused in one line naming ``where`` (the view's file)."""
    h, w = img.shape[:2]
    K_cv = _HALF @ K
    bad = f"{where}: lens terms {np.asarray(dist).tolist()} are not a lens"
    if not np.all(np.isfinite(dist)):
        raise ValueError(f"{bad} (not finite); {_FIX_LENS}")
    try:
        new_cv, _ = cv2.getOptimalNewCameraMatrix(K_cv, dist, (w, h), 0, (w, h))
        _check_focal(K_cv, new_cv, bad)
        mx, my = cv2.initUndistortRectifyMap(K_cv, dist, None, new_cv, (w, h), cv2.CV_32FC1)
    except cv2.error as e:
        raise ValueError(f"{bad}: OpenCV cannot undistort with them ({' '.join(str(e).split())[-120:]}); "
                         f"{_FIX_LENS}") from None
    _check_maps(mx, my, bad)
    img = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if depth is not None:  # nearest rounds each map coordinate to the closest pixel (integer centres, as mx, my)
        depth = cv2.remap(depth.astype(np.float32), mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0)
    return img, depth, np.linalg.inv(_HALF) @ new_cv


_FIX_LENS = "check the camera file's distortion parameters, or re-export it"


def _check_focal(K_cv: np.ndarray, new_cv: np.ndarray, bad: str) -> None:
    """Refuse a non-finite pinhole ``new_cv [3, 3]``, or one whose focal is over ``MAX_FOCAL_CHANGE`` times
    ``K_cv``'s either way (NaN lens terms gave fx 4.6e-38 and a black image; k1 = 1e30 gave fx 1.2e31)."""
    f_old, f_new = np.diag(K_cv)[:2], np.diag(new_cv)[:2]
    with np.errstate(over="ignore", invalid="ignore"):  # an overflowing ratio is refused below, not warned about
        change = f_new / f_old
    if not (np.isfinite(new_cv).all() and ((1 / MAX_FOCAL_CHANGE < change) & (change < MAX_FOCAL_CHANGE)).all()):
        raise ValueError(f"{bad}: undistorting them takes the focal from {f_old[0]:.4g}, {f_old[1]:.4g} px to "
                         f"{f_new[0]:.4g}, {f_new[1]:.4g} px, over {MAX_FOCAL_CHANGE:g}x; {_FIX_LENS}")


def _check_maps(mx: np.ndarray, my: np.ndarray, bad: str) -> None:
    """Refuse undistortion maps ``[H, W]`` (source x, y of each output pixel, integer centres) that take most
    pixels from outside the source image: alpha 0 promises none do (k1 = -1e30 kept K and replicated the border)."""
    h, w = mx.shape
    outside = 1 - np.mean((mx >= -1) & (mx <= w) & (my >= -1) & (my <= h))  # NaN counts as outside
    if outside > 0.5:
        raise ValueError(f"{bad}: undistorting them takes {outside:.0%} of the pixels from outside the image; "
                         f"{_FIX_LENS}")


def _decode(v: ParsedView) -> tuple[bytes, np.ndarray]:
    """The file's bytes and its stored pixels ``[H, W, 3]`` uint8 BGR, or one line naming the file."""
    path = require(v.image_path, f"the image of view {v.name}")
    if path.is_dir():  # an empty image name in the camera file names the images folder itself
        raise ValueError(f"{path}: a folder, not the image of view {v.name!r}; the camera file's image name is "
                         "damaged (re-export the model)")
    check_jpeg_complete(path)  # OpenCV 4.x decodes a cut JPEG without a word, the missing rows grey
    raw = path.read_bytes()
    # The stored pixels, which the cameras describe (COLMAP ignores the EXIF orientation); the shards are decoded so.
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if img is None:
        raise ValueError(f"{v.image_path}: not a readable image; replace or remove the file")
    return raw, img


def _camera_for(v: ParsedView, w: int, h: int) -> np.ndarray:
    """``K [3, 3]`` of ``v`` for its image as stored, ``w`` x ``h`` pixels (a camera given for another resolution
    of the same image is rescaled; another aspect ratio is refused)."""
    K = np.asarray(v.K, np.float64).copy()
    if (w, h) != (v.width, v.height):
        if abs(w * v.height - h * v.width) > v.width + v.height:  # more than a pixel of rounding on either axis
            raise ValueError(f"{v.image_path}: the image is {w}x{h} but its camera is for {v.width}x{v.height}, "
                             "another aspect ratio (rotated or cropped since?); give the image the camera describes")
        K[0] *= w / v.width
        K[1] *= h / v.height
    return K


def _resize_depth(depth: np.ndarray, w: int, h: int) -> np.ndarray:
    """``depth [h', w']`` -> ``[h, w]``: the source pixel under each target pixel's centre."""
    if depth.shape[:2] == (h, w):
        return depth
    return cv2.resize(depth.astype(np.float32), (w, h), interpolation=cv2.INTER_NEAREST_EXACT)


def _load_view(v: ParsedView, max_side: int | None) -> ViewRecord:
    """Read, undistort and downscale one view. The image comes back encoded (jpg/png bytes: the file's own when
    its pixels are kept as they are), so a sample of 64 views of 12 MP holds a few MB per view, not 36-48 MB."""
    raw, img = _decode(v)
    h, w = img.shape[:2]
    K = _camera_for(v, w, h)
    depth = v.depth() if v.depth is not None else None
    distorted = v.dist is not None and bool(np.any(np.asarray(v.dist) != 0))
    if distorted:
        if depth is not None:
            depth = _resize_depth(depth, w, h)
        img, depth, K = undistort(img, depth, K, np.asarray(v.dist, np.float64), f"{v.image_path} (view {v.name})")
    ext = "jpg" if v.image_path.suffix.lower() in JPEG_SUFFIXES else "png"
    s = min(1.0, max_side / max(h, w)) if max_side else 1.0
    resized = s < 1.0
    if resized:
        nw, nh = max(1, round(w * s)), max(1, round(h * s))
        img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        K[0] *= nw / w
        K[1] *= nh / h
        w, h = nw, nh
    kept = not distorted and not resized and v.image_path.suffix.lower() in (*JPEG_SUFFIXES, ".png")
    image = raw if kept else encode_image(img[..., ::-1], ext)
    mask = None
    if depth is not None:
        depth = _resize_depth(depth, w, h)
        mask = (depth > 0) & np.isfinite(depth)
        depth = np.where(mask, depth, 0).astype(np.float32)
    return ViewRecord(name=v.name, image=image, w2c=v.w2c, K=K, width=w, height=h, depth=depth, mask=mask, ext=ext)


def to_records(scene: ParsedScene, max_views: int = 64, max_side: int | None = None,
               key: str | None = None) -> Iterator[SceneRecord]:
    """Cut a scene into samples of at most ``max_views`` consecutive views and load their images. ``key``: the
    scene's sample-key stem (default ``safe_key(source, name)``; :func:`write_scenes` gives each scene its own)."""
    n = len(scene.views)
    if n == 0:
        raise ValueError(f"scene {scene.name}: no views found; check the source layout")
    key = key or safe_key(scene.source, scene.name)
    chunks = max(1, -(-n // max_views))
    for c in range(chunks):
        a, b = c * n // chunks, (c + 1) * n // chunks
        yield SceneRecord(key=key + (f"_w{c:03d}" if chunks > 1 else ""),
                          views=[_load_view(v, max_side) for v in scene.views[a:b]], source=scene.source,
                          units=scene.units, metres_per_unit=scene.metres_per_unit,
                          world_from_source=scene.world_from_source,
                          extra={**scene.extra, "scene": scene.name, "window": [a, b]},
                          scene=key, first_index=a, scene_views=n)


def scene_keys(scenes: list[ParsedScene]) -> list[str]:
    """One distinct sample-key stem per scene: ``safe_key(source, name)``, plus 8 hex digits of the name's SHA-1
    where sanitising changed it ('東京' and '大阪' both sanitise to 'colmap_'; 'block 1' to 'block-1'), plus ``-2``,
    ``-3``, ... for a name that occurs again."""
    keys: list[str] = []
    for sc in scenes:
        key = safe_key(sc.source, sc.name)
        if key != f"{sc.source}_{sc.name}":
            key += "-" + hashlib.sha1(sc.name.encode("utf-8", "surrogatepass")).hexdigest()[:8]
        stem, n, taken = key, 1, set(keys)
        while key in taken:
            n += 1
            key = f"{stem}-{n}"
        keys.append(key)
    return keys


def write_scenes(scenes: list[ParsedScene], out: str | Path, split: str = "auto", max_views: int = 64,
                 max_side: int | None = None, seed: int = 0, maxcount: int = 16,
                 overwrite: bool = False) -> dict:
    """Write parsed scenes as shards. ``split``: auto (dataset split, else 8:1:1 by scene) or train|val|test."""
    if split not in ("auto", *SPLITS):
        raise ValueError(f"split: expected auto, train, val or test, got {split!r}")
    auto = split_scenes(len(scenes), seed)
    with ShardSetWriter(out, maxcount=maxcount, depth_dtype="float32", overwrite=overwrite) as w:
        for i, (sc, key) in enumerate(zip(scenes, scene_keys(scenes))):
            sp = split if split != "auto" else (sc.split or auto[i])
            for rec in to_records(sc, max_views, max_side, key):
                w.write(rec, sp)
    return w.close()
