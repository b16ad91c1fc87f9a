"""COLMAP sparse models (text and binary). PINHOLE and SIMPLE_PINHOLE cameras are kept; SIMPLE_RADIAL (COLMAP's
default), RADIAL, OPENCV and FULL_OPENCV images are undistorted to a pinhole camera while converting
(``base.undistort``); fisheye, thin-prism and FOV models are refused, naming the model (undistort them with COLMAP
first). Photos in ``images/`` the model did
not register are named in a warning and left out.

Layout: ``SCENE/images/*`` and ``SCENE/sparse/N/{cameras,images,points3D}.{bin,txt}`` (or ``SCENE/sparse/``). A
scene with several models (the mapper's ``sparse/0``, ``sparse/1``, ... of disconnected parts, or a merged
``sparse/`` beside them) is refused, naming them; ``--src SCENE/sparse/N`` converts that one model, with the
scene's ``images/`` and name. ``--src`` may also be a folder of scenes (a sub-folder without a model is skipped with
a warning). Poses are world-to-camera with wxyz quaternions and OpenCV axes, so the world frame is kept as is
(``world_from_source = I``, units "sfm", metres unknown). Converting reads neither the 2D observations nor the 3D
points (``read_model(points=False)``): a city model holds millions.
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
    # id -> {qvec, tvec, camera_id, name, xys [n, 2], point3D_ids [n]}; xys and point3D_ids are empty (n = 0) when
    # read with points=False
    images: dict[int, dict]
    points: dict[int, np.ndarray]  # id -> xyz; empty when read with points=False


def _read(f, fmt: str):
    fmt = "<" + fmt
    return struct.unpack(fmt, f.read(struct.calcsize(fmt)))


def _no_observations() -> dict:
    return {"xys": np.zeros((0, 2)), "point3D_ids": np.zeros(0, np.int64)}


def _observations(f, keep: bool) -> dict:
    """The next image's 2D observations in ``images.bin``, or none (passed over, not read) unless ``keep``."""
    n2d = _read(f, "Q")[0]
    if not keep:
        f.seek(24 * n2d, 1)
        return _no_observations()
    obs = np.frombuffer(f.read(24 * n2d), dtype=[("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
    return {"xys": np.stack([obs["x"], obs["y"]], 1), "point3D_ids": obs["id"]}


def _read_bin(d: Path, points: bool = True) -> ColmapModel:
    cams, imgs, pts = {}, {}, {}
    with open(d / "cameras.bin", "rb") as f:
        for _ in range(_read(f, "Q")[0]):
            cid, mid, w, h = _read(f, "iiQQ")
            if mid not in MODELS:  # COLMAP 4.x added ids 12+; their parameter counts are not known here
                raise ValueError(f"{d / 'cameras.bin'}: camera model id {mid} is not one this reader knows (a newer "
                                 "COLMAP's lens model, or a damaged file); undistort first (colmap image_undistorter) "
                                 "so the model is PINHOLE, or export the model as text to see its name")
            cams[cid] = (MODELS[mid][0], w, h, np.array(_read(f, "d" * MODELS[mid][1])))
    with open(d / "images.bin", "rb") as f:
        for _ in range(_read(f, "Q")[0]):
            iid, *qt, cid = _read(f, "idddddddi")
            name = b""
            while (c := f.read(1)) != b"\x00":
                if not c:
                    raise ValueError(f"{d / 'images.bin'}: truncated image name; the file is corrupt")
                name += c
            imgs[iid] = {"qvec": np.array(qt[:4]), "tvec": np.array(qt[4:]), "camera_id": cid,
                         "name": name.decode(), **_observations(f, points)}
    if points and (d / "points3D.bin").exists():
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


def _read_txt(d: Path, points: bool = True) -> ColmapModel:
    imgs, pts = {}, {}
    cams = dict(_camera(ln, d / "cameras.txt") for ln in _data(_lines(d / "cameras.txt")))
    for ln, points2d in _image_blocks(_lines(d / "images.txt")):
        e = ln.split()
        obs = _no_observations()
        if points:
            xyi = np.array([float(x) for x in points2d.split()]).reshape(-1, 3)
            obs = {"xys": xyi[:, :2], "point3D_ids": xyi[:, 2].astype(np.int64)}
        imgs[int(e[0])] = {"qvec": np.array([float(x) for x in e[1:5]]), "tvec": np.array([float(x) for x in e[5:8]]),
                           "camera_id": int(e[8]), "name": " ".join(e[9:]), **obs}
    if points and (d / "points3D.txt").exists():
        for ln in _data(_lines(d / "points3D.txt")):
            e = ln.split()
            pts[int(e[0])] = np.array([float(x) for x in e[1:4]])
    return ColmapModel(cams, imgs, pts)


def _has_model(d: Path) -> bool:
    return (d / "cameras.bin").exists() or (d / "cameras.txt").exists()


def _models(scene: Path) -> list[Path]:
    """The COLMAP models of a scene: ``sparse/`` itself (where model_merger or a 3DGS script writes one) and
    ``sparse/<N>/`` (the mapper's, one per disconnected part), in that order."""
    sparse = scene / "sparse"
    subs = sorted((p for p in sparse.iterdir() if p.is_dir() and p.name.isdigit()),
                  key=lambda p: int(p.name)) if sparse.is_dir() else []
    return [d for d in (sparse, *subs) if _has_model(d)]


def _image_count(d: Path) -> str:
    """How many images the model at ``d`` holds, read cheaply: images.bin's leading count, or the image lines of
    images.txt; "?" when its images file is missing or short."""
    if (d / "cameras.bin").exists():
        if not (d / "images.bin").exists():
            return "?"
        with open(d / "images.bin", "rb") as f:
            head = f.read(8)
        return str(struct.unpack("<Q", head)[0]) if len(head) == 8 else "?"
    return str(len(_image_blocks(_lines(d / "images.txt")))) if (d / "images.txt").exists() else "?"


def model_dir(scene: Path) -> Path:
    """The folder of the scene's one COLMAP model: ``sparse/<N>/``, ``sparse/``, or ``scene`` itself (a model
    folder). Several models are refused: reading one left the others' images out as "not registered"."""
    models = _models(scene)
    if len(models) > 1:
        listed = ", ".join(f"{d.relative_to(scene).as_posix()} ({_image_count(d)} images)" for d in models)
        raise ValueError(f"{scene}: {len(models)} COLMAP models, {listed}; pass --src {scene}/sparse/N (one model), "
                         "or merge them (colmap model_merger) into one")
    if models:
        return models[0]
    if _has_model(scene):
        return scene
    raise FileNotFoundError(f"{scene}: no COLMAP model (cameras.bin or cameras.txt in sparse/N, sparse or the "
                            "folder itself); point --src at a COLMAP scene")


def _read_dir(d: Path, points: bool) -> ColmapModel:
    if (d / "cameras.bin").exists():
        require(d / "images.bin", "COLMAP images.bin beside cameras.bin")
        return _read_bin(d, points)
    require(d / "images.txt", "COLMAP images.txt beside cameras.txt")
    return _read_txt(d, points)


def read_model(scene: str | Path, points: bool = True) -> ColmapModel:
    """Read the sparse model of a COLMAP scene (or model) folder, binary preferred, else text. ``points=False``
    reads only cameras and poses: the 2D observations are passed over and points3D is not opened."""
    return _read_dir(model_dir(Path(scene)), points)


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


def _scenes(src: Path) -> list[tuple[Path, Path]]:
    """``(scene, its model folder)``: ``src`` when it holds a model (or is one), else its sub-folders that do.
    Sub-folders with ``images/`` or ``sparse/`` but no model (a failed SfM) are skipped with one warning: they must
    not stop the other scenes."""
    try:
        return [(src, model_dir(src))]
    except FileNotFoundError as e:
        missing = e
    scenes, skipped = [], []
    for p in sorted(q for q in src.iterdir() if q.is_dir() and ((q / "sparse").exists() or (q / "images").is_dir())):
        try:
            scenes.append((p, model_dir(p)))
        except FileNotFoundError:
            skipped.append(p.name)
    if not scenes:
        raise missing
    if skipped:
        warnings.warn(f"{src}: skipped {len(skipped)} sub-folder(s), no COLMAP model in sparse/: "
                      f"{', '.join(skipped[:5])}{', ...' if len(skipped) > 5 else ''}", stacklevel=3)
    return scenes


def _scene_of(model: Path) -> Path:
    """The scene folder of a model folder given as ``--src`` (``SCENE/sparse/N``, ``SCENE/sparse``): the first of
    its parent and grandparent that holds ``images/``; the folder itself when it holds ``images/`` or none does."""
    if (model / "images").is_dir():
        return model
    return next((q for q in list(model.parents)[:2] if (q / "images").is_dir()), model)


def parse(src: str | Path) -> list[ParsedScene]:
    """One ParsedScene per COLMAP scene under ``src`` (views sorted by image name, the llffhold order)."""
    src = require(Path(src), "a COLMAP scene folder")
    out = []
    for sc, d in _scenes(src):
        root = _scene_of(d) if d == sc else sc
        m = _read_dir(d, points=False)
        _warn_unregistered(root / "images", {img["name"] for img in m.images.values()}, d if root != sc else None)
        views = []
        for img in sorted(m.images.values(), key=lambda x: x["name"]):
            model, w, h, params = m.cameras[img["camera_id"]]
            K, dist = intrinsics(model, params, str(d))
            views.append(ParsedView(name=img["name"], image_path=root / "images" / img["name"], w2c=w2c_of(img),
                                    K=K, width=w, height=h, dist=dist))
        out.append(ParsedScene(name=root.name, views=views, source="colmap", units="sfm", metres_per_unit=None,
                               extra={"model": str(d)}))
    return out


def _warn_unregistered(images: Path, registered: set[str], model: Path | None = None) -> None:
    """Warn, naming a few, when ``images`` holds photos the model did not register (or, for ``--src`` a ``model``
    folder, that are not in that one): they are left out, and the llffhold split counts the model's views only."""
    if not images.is_dir():
        return
    left = sorted(p.relative_to(images).as_posix() for p in images.rglob("*")
                  if p.suffix.lower() in PHOTO_SUFFIXES and p.relative_to(images).as_posix() not in registered)
    which = "the COLMAP model (not registered)" if model is None else f"the COLMAP model {model}"
    if left:
        warnings.warn(f"{images}: {len(left)} image(s) are not in {which} and are left "
                      f"out: {', '.join(left[:3])}{', ...' if len(left) > 3 else ''}", stacklevel=2)
