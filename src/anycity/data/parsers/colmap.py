"""COLMAP sparse models (text and binary). PINHOLE and SIMPLE_PINHOLE cameras are kept; SIMPLE_RADIAL (COLMAP's
default), RADIAL, OPENCV and FULL_OPENCV images are undistorted to a pinhole camera while converting
(``base.undistort``); fisheye, thin-prism and FOV models are refused, naming the model (undistort them with COLMAP
first). Photos in ``images/`` the model did
not register are named in a warning and left out.

Layout: ``SCENE/images/*`` and ``SCENE/sparse/0/{cameras,images,points3D}.{bin,txt}`` (or ``SCENE/sparse/``);
``--src`` may also be a folder of such scenes. Poses are world-to-camera with wxyz quaternions and OpenCV axes,
so the world frame is kept as is (``world_from_source = I``, units "sfm", metres unknown).
"""

from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from anycity.data.parsers.base import ParsedScene, ParsedView, require, rigid
from anycity.data.photos import PHOTO_SUFFIXES
from anycity.geometry import quat_to_rotmat

# model id -> (name, number of params)
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
          5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
          9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16)}
_BY_NAME = {name: (i, n) for i, (name, n) in MODELS.items()}


@dataclass
class ColmapModel:
    cameras: dict[int, tuple[str, int, int, np.ndarray]]  # id -> (model, width, height, params)
    images: dict[int, dict]  # id -> {qvec, tvec, camera_id, name, xys [n, 2], point3D_ids [n]}
    points: dict[int, np.ndarray]  # id -> xyz


def _read(f, fmt: str):
    fmt = "<" + fmt
    return struct.unpack(fmt, f.read(struct.calcsize(fmt)))


def _read_bin(d: Path) -> ColmapModel:
    cams, imgs, pts = {}, {}, {}
    with open(d / "cameras.bin", "rb") as f:
        for _ in range(_read(f, "Q")[0]):
            cid, mid, w, h = _read(f, "iiQQ")
            if mid not in MODELS:
                raise ValueError(f"{d / 'cameras.bin'}: unknown camera model id {mid}; the file is corrupt")
            cams[cid] = (MODELS[mid][0], w, h, np.array(_read(f, "d" * MODELS[mid][1])))
    with open(d / "images.bin", "rb") as f:
        for _ in range(_read(f, "Q")[0]):
            iid, *qt, cid = _read(f, "idddddddi")
            name = b""
            while (c := f.read(1)) != b"\x00":
                if not c:
                    raise ValueError(f"{d / 'images.bin'}: truncated image name; the file is corrupt")
                name += c
            n2d = _read(f, "Q")[0]
            obs = np.frombuffer(f.read(24 * n2d), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
            imgs[iid] = {"qvec": np.array(qt[:4]), "tvec": np.array(qt[4:]), "camera_id": cid,
                         "name": name.decode(), "xys": np.stack([obs["x"], obs["y"]], 1), "point3D_ids": obs["id"]}
    if (d / "points3D.bin").exists():
        with open(d / "points3D.bin", "rb") as f:
            for _ in range(_read(f, "Q")[0]):
                pid, x, y, z, _r, _g, _b, _err, n = _read(f, "QdddBBBdQ")
                f.read(8 * n)
                pts[pid] = np.array([x, y, z])
    return ColmapModel(cams, imgs, pts)


def _lines(p: Path) -> list[str]:
    """The lines of ``p``, stripped (an indented ``#`` is a comment too, as COLMAP reads it)."""
    return [ln.strip() for ln in p.read_text().splitlines()]


def _data(lines: list[str]) -> list[str]:
    return [ln for ln in lines if ln and not ln.startswith("#")]


def _camera(ln: str, path: Path) -> tuple[int, tuple[str, int, int, np.ndarray]]:
    """One ``cameras.txt`` line -> ``(id, (model, width, height, params))``, refused when its parameter count does
    not fit the model (a short distortion vector would be undistorted wrongly, or make OpenCV assert)."""
    e = ln.split()
    cid, model, params = int(e[0]), e[1], e[4:]
    if model in _BY_NAME and len(params) != _BY_NAME[model][1]:  # an unknown model is refused by name later
        raise ValueError(f"{path}: camera {cid} ({model}) has {len(params)} parameters, {model} takes "
                         f"{_BY_NAME[model][1]}; fix the line or re-export the model")
    return cid, (model, int(e[2]), int(e[3]), np.array([float(x) for x in params]))


def _image_blocks(lines: list[str]) -> list[tuple[str, str]]:
    """``(image line, POINTS2D line)`` pairs of ``images.txt``, found as COLMAP's ReadImagesText finds them: blank
    and comment lines are skipped before an image line only, and the line after it is its POINTS2D (maybe
    empty). A last image line with no line after it (a writer that trims the end) has no points."""
    blocks, rest = [], iter(lines)
    for ln in rest:
        if ln and not ln.startswith("#"):
            blocks.append((ln, next(rest, "")))
    return blocks


def _read_txt(d: Path) -> ColmapModel:
    imgs, pts = {}, {}
    cams = dict(_camera(ln, d / "cameras.txt") for ln in _data(_lines(d / "cameras.txt")))
    for ln, points in _image_blocks(_lines(d / "images.txt")):
        e = ln.split()
        obs = np.array([float(x) for x in points.split()]).reshape(-1, 3)
        imgs[int(e[0])] = {"qvec": np.array([float(x) for x in e[1:5]]), "tvec": np.array([float(x) for x in e[5:8]]),
                           "camera_id": int(e[8]), "name": " ".join(e[9:]), "xys": obs[:, :2],
                           "point3D_ids": obs[:, 2].astype(np.int64)}
    if (d / "points3D.txt").exists():
        for ln in _data(_lines(d / "points3D.txt")):
            e = ln.split()
            pts[int(e[0])] = np.array([float(x) for x in e[1:4]])
    return ColmapModel(cams, imgs, pts)


def model_dir(scene: Path) -> Path:
    for d in (scene / "sparse" / "0", scene / "sparse", scene):
        if (d / "cameras.bin").exists() or (d / "cameras.txt").exists():
            return d
    raise FileNotFoundError(f"{scene}: no COLMAP model (cameras.bin or cameras.txt in sparse/0, sparse or the "
                            "folder itself); point --src at a COLMAP scene")


def read_model(scene: str | Path) -> ColmapModel:
    """Read the sparse model of a COLMAP scene folder (binary preferred, else text)."""
    d = model_dir(Path(scene))
    if (d / "cameras.bin").exists():
        require(d / "images.bin", "COLMAP images.bin beside cameras.bin")
        return _read_bin(d)
    require(d / "images.txt", "COLMAP images.txt beside cameras.txt")
    return _read_txt(d)


_NOT_READ = {"OPENCV_FISHEYE": "a fisheye lens", "SIMPLE_RADIAL_FISHEYE": "a fisheye lens",
             "RADIAL_FISHEYE": "a fisheye lens", "FOV": "the FOV (arctan) lens model",
             "THIN_PRISM_FISHEYE": "a thin-prism fisheye lens",
             "RAD_TAN_THIN_PRISM_FISHEYE": "a thin-prism fisheye lens"}  # model -> why it is refused


def intrinsics(model: str, params: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``K [3, 3]`` and OpenCV distortion of a COLMAP camera: ``(k1, k2, p1, p2)``, or FULL_OPENCV's rational
    ``(k1, k2, p1, p2, k3, k4, k5, k6)`` (OpenCV's order too); None for a pinhole model."""
    p = np.asarray(params, float)
    if model in ("PINHOLE", "OPENCV", "FULL_OPENCV"):
        fx, fy, cx, cy = p[:4]
    elif model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1:3]
    else:
        kind = _NOT_READ.get(model, "not a COLMAP model this reader knows")
        raise ValueError(f"{where}: camera model {model} ({kind}) is not read here; undistort first (colmap "
                         "image_undistorter or pycolmap.undistort_images) so the model is PINHOLE")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], float)
    if model == "SIMPLE_RADIAL":
        return K, np.array([p[3], 0, 0, 0])
    if model == "RADIAL":
        return K, np.array([p[3], p[4], 0, 0])
    return K, {"OPENCV": p[4:8], "FULL_OPENCV": p[4:12]}.get(model)


def w2c_of(image: dict) -> np.ndarray:
    R = quat_to_rotmat(torch.as_tensor(image["qvec"], dtype=torch.float64)).numpy()
    return rigid(R, image["tvec"])


def parse(src: str | Path) -> list[ParsedScene]:
    """One ParsedScene per COLMAP scene under ``src`` (views sorted by image name, the llffhold order)."""
    src = require(Path(src), "a COLMAP scene folder")
    try:
        scenes = [src] if model_dir(src) else []
    except FileNotFoundError:
        scenes = sorted(p for p in src.iterdir() if p.is_dir() and any((p / s).exists() for s in ("sparse",)))
        if not scenes:
            raise
    out = []
    for sc in scenes:
        m = read_model(sc)
        where = str(model_dir(sc))
        if model_dir(sc) == sc and not (sc / "images").is_dir():  # --src SCENE/sparse/0
            root = next((q for q in list(sc.parents)[:2] if (q / "images").is_dir()), None)
            if root is not None:
                raise FileNotFoundError(f"{sc} is the scene's COLMAP model folder; pass --src the scene folder that "
                                        f"holds images/ and sparse/: {root}")
        _warn_unregistered(sc / "images", {img["name"] for img in m.images.values()})
        views = []
        for img in sorted(m.images.values(), key=lambda x: x["name"]):
            model, w, h, params = m.cameras[img["camera_id"]]
            K, dist = intrinsics(model, params, where)
            views.append(ParsedView(name=img["name"], image_path=sc / "images" / img["name"], w2c=w2c_of(img),
                                    K=K, width=w, height=h, dist=dist))
        out.append(ParsedScene(name=sc.name, views=views, source="colmap", units="sfm", metres_per_unit=None,
                               extra={"model": where}))
    return out


def _warn_unregistered(images: Path, registered: set[str]) -> None:
    """Warn, naming a few, when ``images`` holds photos the model did not register: they are left out, and the
    llffhold split counts the registered views only."""
    if not images.is_dir():
        return
    left = sorted(p.relative_to(images).as_posix() for p in images.rglob("*")
                  if p.suffix.lower() in PHOTO_SUFFIXES and p.relative_to(images).as_posix() not in registered)
    if left:
        warnings.warn(f"{images}: {len(left)} image(s) are not in the COLMAP model (not registered) and are left "
                      f"out: {', '.join(left[:3])}{', ...' if len(left) > 3 else ''}", stacklevel=2)
