"""nerfstudio ``transforms.json`` (also DL3DV): OpenGL camera-to-world -> OpenCV world-to-camera.

The poses stay in the json's world frame (``world_from_source = I``); the file's own ``applied_transform`` /
``applied_scale`` (nerfstudio's COLMAP -> json map) are kept in ``extra``. ``OPENCV`` cameras with ``k1 k2 k3 p1
p2`` are undistorted to a pinhole camera while converting (``base.undistort``); fisheye and 360 (equirectangular)
cameras are refused.

A frame whose ``file_path`` (``images/x.png``) is missing is read from nerfstudio's downscaled folders, the largest
found of ``images_2``, ``images_4``, ``images_8``: DL3DV's 960P release ships ``images_4`` only, beside a json
written for the full resolution. ``--src`` is the folder holding ``transforms.json`` (DL3DV: ``SCENE/nerfstudio``),
or the file; a folder named ``nerfstudio`` (or ``images`` and the like) takes its parent's name as the scene's.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from anycity.data.imagecheck import read_image
from anycity.data.parsers.base import ParsedScene, ParsedView, c2w_gl_to_w2c, require
from anycity.data.photos import GENERIC_FOLDERS, folder_scene_name

_DIST = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
_PINHOLE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
_FISHEYE = ("OPENCV_FISHEYE", "FISHEYE624")
# nerfstudio's spherical camera types: a whole sphere (or half) per image, which no pinhole camera describes
_PANORAMA = ("EQUIRECTANGULAR", "OMNIDIRECTIONALSTEREO_L", "OMNIDIRECTIONALSTEREO_R", "VR180_L", "VR180_R")
_GENERIC = GENERIC_FOLDERS | {"nerfstudio"}  # folder names that say nothing of the scene (DL3DV: HASH/nerfstudio)


def _refuse_lens(model: str, k4: float, where: str) -> None:
    """Raise naming the camera unless it is a pinhole or OpenCV (k1 k2 p1 p2 k3) one, which can be undistorted."""
    if model.upper() in _PANORAMA:
        raise ValueError(f"{where}: camera model {model} (360 equirectangular images) is not read here; these images "
                         "cannot be converted, cut perspective crops from them (e.g. ns-process-data images "
                         "--camera-type equirectangular) and convert those")
    if abs(k4) > 1e-9 or model not in _PINHOLE:
        kind = ("k4: a fisheye lens" if model in _PINHOLE else "a fisheye lens" if model in _FISHEYE
                else "not a camera model this reader knows")
        raise ValueError(f"{where}: camera model {model} ({kind}) is not read here; undistort the images first (e.g. "
                         "colmap image_undistorter) and write a PINHOLE transforms.json")


def _intrinsics(d: dict, where: str) -> tuple[np.ndarray, int, int, np.ndarray | None]:
    """``(K, w, h, dist)``: OpenCV distortion ``(k1, k2, p1, p2, k3)``, None when every term is 0."""
    try:
        fx, fy = float(d["fl_x"]), float(d.get("fl_y", d["fl_x"]))
        w, h = int(d["w"]), int(d["h"])
    except KeyError as e:
        raise ValueError(f"{where}: missing intrinsics key {e}; transforms.json needs fl_x, w, h (top level or "
                         "per frame)") from e
    _refuse_lens(str(d.get("camera_model", "OPENCV")), float(d.get("k4", 0.0)), where)
    dist = np.array([float(d.get(k, 0.0)) for k in _DIST])
    cx, cy = float(d.get("cx", w / 2)), float(d.get("cy", h / 2))
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), w, h, dist if np.any(dist != 0) else None


def _image_path(root: Path, file_path: str) -> Path:
    """``root / file_path``, else the same name in the largest of nerfstudio's downscaled folders present."""
    p = root / file_path
    if p.exists() or p.parent == root:
        return p
    for n in (2, 4, 8):
        q = p.parent.with_name(f"{p.parent.name}_{n}") / p.name
        if q.exists():
            return q
    return p  # missing: named when the view is loaded


def parse(src: str | Path) -> list[ParsedScene]:
    src = Path(src)
    path = src if src.suffix == ".json" else src / "transforms.json"
    root = path.parent
    meta = json.loads(require(path, "a nerfstudio transforms.json").read_text())
    scale = float(meta.get("depth_unit_scale_factor", 1e-3))
    views = []
    # In file-name order, as nerfstudio's own dataparser reads them: ns-process-data writes COLMAP's image-id order,
    # and the trajectory order is what the llffhold split and the nearest-context-view choice read.
    frames = sorted(enumerate(meta.get("frames", [])), key=lambda f: str(f[1].get("file_path", "")))
    for i, fr in frames:
        where = f"{path} frame {i}"
        K, w, h, dist = _intrinsics({**meta, **fr}, where)
        if "transform_matrix" not in fr or "file_path" not in fr:
            raise ValueError(f"{where}: missing 'transform_matrix' or 'file_path'")
        depth = None
        if fr.get("depth_file_path"):
            dp = root / fr["depth_file_path"]

            def depth(dp=dp):
                raw = read_image(require(dp, "a 16-bit depth png"), cv2.IMREAD_UNCHANGED)
                if raw is None or raw.ndim != 2:
                    raise ValueError(f"{dp}: not a one-channel depth png; re-export it, or drop its depth_file_path")
                return raw.astype(np.float32) * scale
        c2w = np.asarray(fr["transform_matrix"], float)
        views.append(ParsedView(name=Path(fr["file_path"]).name, image_path=_image_path(root, fr["file_path"]),
                                w2c=c2w_gl_to_w2c(c2w), K=K, width=w, height=h, depth=depth, dist=dist))
    extra = {k: meta[k] for k in ("applied_transform", "applied_scale") if k in meta}
    return [ParsedScene(name=folder_scene_name(root, _GENERIC), views=views, source="nerfstudio", units="nerfstudio",
                        metres_per_unit=None, extra=extra)]
