"""BlendedMVS / MVSNet layout: ``PID/blended_images/%08d.jpg``, ``PID/cams/%08d_cam.txt`` (world-to-camera
OpenCV extrinsic + K), optional ``PID/rendered_depth_maps/%08d.pfm`` (metric z-depth, bottom row first)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from anycity.data.imagecheck import image_size
from anycity.data.parsers.base import ParsedScene, ParsedView, require


def read_pfm(path: str | Path) -> np.ndarray:
    """PFM -> float32 ``[H, W]`` or ``[H, W, 3]``, top row first."""
    with open(path, "rb") as f:
        kind = f.readline().strip()
        if kind not in (b"PF", b"Pf"):
            raise ValueError(f"{path}: not a PFM file (header {kind!r}, expected PF or Pf)")
        dims = f.readline().split()
        while not dims:
            dims = f.readline().split()
        w, h = int(dims[0]), int(dims[1])
        scale = float(f.readline().strip())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    c = 3 if kind == b"PF" else 1
    if data.size != w * h * c:
        raise ValueError(f"{path}: PFM holds {data.size} values, header says {w}x{h}x{c}; the file is truncated")
    return np.flipud(data.reshape(h, w, c) if c == 3 else data.reshape(h, w)).astype(np.float32)


def read_cam(path: Path) -> tuple[np.ndarray, np.ndarray]:
    text = require(path, "a BlendedMVS cam.txt").read_text()
    try:
        ext = text.split("extrinsic")[1].split("intrinsic")[0]
        intr = text.split("intrinsic")[1]
        E = np.array([float(x) for x in ext.split()][:16]).reshape(4, 4)
        K = np.array([float(x) for x in intr.split()][:9]).reshape(3, 3)
    except (IndexError, ValueError) as e:
        raise ValueError(f"{path}: expected 'extrinsic' + 4x4 and 'intrinsic' + 3x3 blocks ({e})") from e
    return E, K


def _image_size(img: Path, cam: Path) -> tuple[int, int]:
    """``(h, w)`` as stored, from the image's header (no decode): the size the cameras describe."""
    require(img, f"the image of {cam.name}")
    try:
        return image_size(img, as_shown=False)
    except Exception as e:  # noqa: BLE001 - any decoder error means the same thing to the user
        raise ValueError(f"{img}: not a readable image ({type(e).__name__}); re-download it, or remove {cam.name} "
                         "to leave the view out") from None


def _scene(d: Path) -> ParsedScene:
    views = []
    for cam in sorted(c for c in (d / "cams").glob("*_cam.txt") if not c.name.startswith(".")):  # not ._x (macOS)
        stem = cam.name[: -len("_cam.txt")]
        E, K = read_cam(cam)
        img = d / "blended_images" / f"{stem}.jpg"
        h, w = _image_size(img, cam)
        pfm = d / "rendered_depth_maps" / f"{stem}.pfm"
        depth = (lambda p=pfm: read_pfm(p)) if pfm.exists() else None
        views.append(ParsedView(name=img.name, image_path=img, w2c=E, K=K, width=w, height=h, depth=depth))
    return ParsedScene(name=d.name, views=views, source="blendedmvs", units="blendedmvs", metres_per_unit=None)


def parse(src: str | Path) -> list[ParsedScene]:
    src = require(Path(src), "a BlendedMVS scene (PID folder with cams/ and blended_images/)")
    if src.is_file():  # a cam.txt or an image: its scene holds many, so name the folder to pass
        pid = next((q for q in list(src.parents)[:2] if (q / "cams").is_dir()), None)
        raise ValueError(f"{src}: a file, not a BlendedMVS scene; pass --src the scene (PID) folder that holds cams/ "
                         f"and blended_images/{f': {pid}' if pid else ''}")
    dirs = [src] if (src / "cams").is_dir() else sorted(p for p in src.iterdir() if (p / "cams").is_dir())
    if not dirs:
        raise FileNotFoundError(f"{src}: no cams/ folder here or in its sub-folders; expected BlendedMVS PID folders")
    return [_scene(d) for d in dirs]
