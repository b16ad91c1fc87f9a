"""LLFF ``poses_bounds.npy`` and BungeeNeRF ``poses_enu.json`` (rows of a 3x5 ``[c2w | (H, W, f)]`` + near, far).

LLFF camera columns are (down, right, back): OpenCV is ``[c1, c0, -c2]``. BungeeNeRF's are already OpenGL
(right, up, back): OpenCV is ``[c0, -c1, -c2]``. Images are the sorted files of ``images/``; K assumes a centred
principal point and is rescaled when the images are not the size recorded in the poses. The world is kept.
``--src`` is the scene folder or its pose file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from anycity.data.parsers.base import ParsedScene, ParsedView, require

_EXTS = {".jpg", ".jpeg", ".png"}


def _images(root: Path, n: int, where: Path) -> list[Path]:
    """The sorted images of ``root/images`` (any case; hidden files such as macOS ``._x.JPG`` are not images)."""
    imgs = sorted(p for p in require(root / "images", "an images/ folder").iterdir()
                  if p.suffix.lower() in _EXTS and not p.name.startswith("."))
    if len(imgs) != n:
        raise ValueError(f"{where}: {n} poses but {len(imgs)} images in {root / 'images'}; they must match 1:1")
    return imgs


def _views(rows: np.ndarray, imgs: list[Path], cols: tuple, where: Path) -> list[ParsedView]:
    if rows.ndim != 2 or rows.shape[1] != 17:
        raise ValueError(f"{where}: expected an [N, 17] array of poses, got shape {rows.shape}")
    views = []
    for r, img in zip(rows, imgs):
        m = r[:15].reshape(3, 5)
        h, w, f = m[:, 4]
        c = m[:, :3]
        R = np.stack([s * c[:, i] for i, s in cols], 1)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, m[:, 3]
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
        views.append(ParsedView(name=img.name, image_path=img, w2c=np.linalg.inv(c2w), K=K, width=int(round(w)),
                                height=int(round(h))))
    return views


def _pose_file(src: Path, name: str, what: str) -> Path:
    """``src`` itself when ``--src`` names a pose file (a file with ``name``'s suffix), else ``src / name``."""
    if src.is_file():
        if src.suffix.lower() != Path(name).suffix:
            raise ValueError(f"{src}: a file, not {what}; pass --src the scene folder that holds {name} and images/")
        return src
    return require(src / name, what)


def parse_llff(src: str | Path) -> list[ParsedScene]:
    path = _pose_file(Path(src), "poses_bounds.npy", "LLFF poses_bounds.npy")
    src = path.parent
    rows = np.load(path)
    views = _views(rows, _images(src, len(rows), path), ((1, 1), (0, 1), (2, -1)), path)
    return [ParsedScene(name=src.name, views=views, source="llff", units="llff", metres_per_unit=None,
                        extra={"bounds": rows[:, 15:].tolist()})]


def parse_bungeenerf(src: str | Path) -> list[ParsedScene]:
    path = _pose_file(Path(src), "poses_enu.json", "BungeeNeRF poses_enu.json")
    src = path.parent
    meta = json.loads(path.read_text())
    if "poses" not in meta:
        raise ValueError(f"{path}: missing key 'poses' (an [N, 17] list)")
    rows = np.asarray(meta["poses"], float)
    views = _views(rows, _images(src, len(rows), path), ((0, 1), (1, -1), (2, -1)), path)
    extra = {k: meta[k] for k in ("scene_scale", "scene_origin", "scale_split") if k in meta}
    return [ParsedScene(name=src.name, views=views, source="bungeenerf", units="bungeenerf", metres_per_unit=None,
                        extra=extra)]
