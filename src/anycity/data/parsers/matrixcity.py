"""MatrixCity aerial/street blocks (OpenGL camera-to-world) -> OpenCV, in metres.

Two pose files are understood:

* split files ``transforms_{train,test}.json`` (``fl_x``, ``w``, ``h``, frames with ``file_path`` and
  ``transform_matrix``; translations in units of 100 m): translations are multiplied by 100
  (``world_from_source = diag(100, 100, 100, 1)``);
* raw block files ``transforms.json`` (``camera_angle_x``, frames with ``frame_index`` and ``rot_mat`` whose
  rotation is scaled by 0.01, translations in metres): the rotation is multiplied by 100, the world is kept.

Depth, when a ``depth`` folder (or ``<block>_depth``) beside the images holds ``NNNN.exr`` (or ``.npy``), is
MatrixCity's z-depth in centimetres and is converted to metres. Invalid: the float16 release's saturation value
(65504 cm, which its own loader masks), the sky's value (65535 cm, MatrixCity issue #22), non-finite values and
values of 0 or less; valid depth beyond those (the float32 release's far pixels of oblique aerial views) is kept.

Raw block files give no image size: it is read from the first image's header (aerial renders are 1920x1080,
street renders 1000x1000). Split files say which split they hold by name: ``*test*`` is test, ``*train*`` train.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from anycity.data.imagecheck import image_size
from anycity.data.parsers.base import ParsedScene, ParsedView, c2w_gl_to_w2c, require


def _depth_loader(img: Path):
    for d in (img.parent / "depth", img.parent.with_name(img.parent.name + "_depth")):
        for ext in (".exr", ".npy"):
            p = d / (img.stem + ext)
            if p.exists():
                def load(p=p):
                    if p.suffix == ".npy":
                        cm = np.load(p).astype(np.float32)
                    else:
                        os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
                        import cv2

                        cm = cv2.imread(str(p), cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH)
                        if cm is None:
                            raise ValueError(f"{p}: unreadable EXR; set OPENCV_IO_ENABLE_OPENEXR=1 before starting")
                        cm = cm[..., 0] if cm.ndim == 3 else cm
                    return depth_metres(cm)
                return load
    return None


INVALID_CM = (65504.0, 65535.0)  # float16 saturation; the sky (MatrixCity issue #22)


def depth_metres(cm: np.ndarray) -> np.ndarray:
    """MatrixCity z-depth in centimetres ``[H, W]`` -> metres, 0 where invalid (see the module docstring)."""
    cm = np.asarray(cm, np.float32)
    ok = np.isfinite(cm) & (cm > 0) & ~np.isin(cm, INVALID_CM)
    return np.where(ok, cm / 100.0, 0).astype(np.float32)


def _image_path(path: Path, fr: dict, raw: bool) -> Path:
    return path.parent / f"{int(fr['frame_index']):04d}.png" if raw else (path.parent / fr["file_path"]).resolve()


def parse(src: str | Path) -> list[ParsedScene]:
    src = Path(src)
    files = [src] if src.suffix == ".json" else sorted(src.glob("transforms_*.json")) or [src / "transforms.json"]
    out = []
    for path in files:
        meta = json.loads(require(path, "MatrixCity transforms_train.json / transforms.json").read_text())
        frames = meta.get("frames", [])
        raw = bool(frames) and "rot_mat" in frames[0]
        if "w" in meta and "h" in meta:
            w, h = int(meta["w"]), int(meta["h"])
        elif frames:  # raw block files: aerial and street renders differ in size
            first = require(_image_path(path, frames[0], raw), f"the first image of {path}")
            try:
                h, w = image_size(first, as_shown=False)
            except Exception as e:  # noqa: BLE001 - any unreadable header: one line naming the file
                raise ValueError(f"{first}: not a readable image ({type(e).__name__}); replace it") from None
        else:
            w, h = 1920, 1080  # no frames: no view is written, the size is never used
        fx = float(meta["fl_x"]) if "fl_x" in meta else 0.5 * w / math.tan(0.5 * float(meta["camera_angle_x"]))
        K = np.array([[fx, 0, meta.get("cx", w / 2)], [0, float(meta.get("fl_y", fx)), meta.get("cy", h / 2)],
                      [0, 0, 1]], float)
        views = []
        for i, fr in enumerate(frames):
            if raw:
                c2w = np.asarray(fr["rot_mat"], float).copy()
                # The rotation is stored scaled by 0.01 in most blocks, unscaled in some (MatrixCity's own loaders
                # test which): divide by its column norm either way.
                c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0).mean()
            else:
                if "transform_matrix" not in fr:
                    raise ValueError(f"{path} frame {i}: missing 'transform_matrix'")
                c2w = np.asarray(fr["transform_matrix"], float).copy()
                c2w[:3, 3] *= 100.0  # 100 m units -> metres
            img = _image_path(path, fr, raw)
            c2w[3, 3] = 1.0  # the files carry the rotation's scale there too; MatrixCity's loaders reset it
            views.append(ParsedView(name=img.name, image_path=img, w2c=c2w_gl_to_w2c(c2w), K=K, width=w, height=h,
                                    depth=_depth_loader(img)))
        T = np.eye(4) if raw else np.diag([100.0, 100.0, 100.0, 1.0])
        split = "test" if "test" in path.stem else "train" if "train" in path.stem else None
        out.append(ParsedScene(name=f"{path.parent.name}_{path.stem}", views=views, source="matrixcity", units="metres",
                               metres_per_unit=1.0, world_from_source=T, split=split,
                               extra={"pose_file": path.name, "raw_block_json": raw}))
    return out
