"""MatrixCity aerial/street blocks (OpenGL camera-to-world) -> OpenCV, in metres.

Two pose files are understood (``--src`` a folder: its ``transforms.json`` if any, else its split files; never
``transforms_origin.json``, the poses before MatrixCity culled the views that look off the map):

* split files ``transforms_{train,test}*.json`` (``fl_x``, ``w``, ``h``, frames with ``file_path`` and
  ``transform_matrix``; translations in units of 100 m): translations are multiplied by 100
  (``world_from_source = diag(100, 100, 100, 1)``);
* raw block files ``transforms.json`` (``camera_angle_x``, frames with ``frame_index`` and ``rot_mat`` whose
  rotation is scaled by 0.01, translations in metres): the rotation is multiplied by 100, the world is kept.

Depth, ``NNNN.exr`` (or ``.npy``) named as the image, is looked for in ``depth/`` beside the images, in
``<block>_depth/`` beside the block folder, and in the release's own tree, each archive extracted where it lies
(``small_city/aerial/train/block_1`` -> ``small_city_depth*/aerial/train/block_1_depth``; the float32 release
first); a warning names the folders searched when none holds it. It is MatrixCity's z-depth in centimetres and is
converted to metres. Invalid: the float16 release's saturation value (65504 cm, which its own loader masks), the
sky's value (65535 cm, MatrixCity issue #22), non-finite values and values of 0 or less; valid depth beyond those
(the float32 release's far pixels of oblique aerial views) is kept. EXR is read with OpenCV when its build has the
OpenEXR codec, else with the ``OpenEXR`` package (``pip install 'anycity[exr]'``).

Raw block files give no image size: it is read from the first image's header (aerial renders are 1920x1080,
street renders 1000x1000). The split: a split file's name (``*test*`` test, ``*train*`` train), else the block
folder's (``block_1_test``) or the folder above it (``aerial/test/``).
"""

from __future__ import annotations

import functools
import glob
import json
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np

from anycity.data.imagecheck import image_size, read_image
from anycity.data.parsers.base import ParsedScene, ParsedView, c2w_gl_to_w2c, require

_DEPTH_EXTS = (".exr", ".npy")


def depth_dirs(images: Path) -> tuple[list[Path], list[str]]:
    """The existing folders that may hold the depth of the images in ``images``, most likely first, and the names
    of all searched (the release's sibling trees as glob patterns)."""
    images = images.absolute()
    cands = [images / "depth", images.with_name(images.name + "_depth")]
    shown = [str(c) for c in cands]
    # The release's depth tree is a sibling of one of the image folder's parents with "_depth*" added:
    # small_city/aerial/train/block_1 -> small_city_depth_float32/aerial/train/block_1_depth.
    for top in list(images.parents)[:3]:
        if top.parent == top:
            break
        sub = images.relative_to(top).parent / (images.name + "_depth")
        shown.append(str(top.parent / (top.name + "_depth*") / sub))
        trees = top.parent.glob(glob.escape(top.name) + "_depth*")
        cands += [t / sub for t in sorted(trees, key=lambda t: ("float32" not in t.name, t.name))]
    return [c for c in cands if c.is_dir()], shown


def read_exr(path: Path) -> np.ndarray:
    """``[H, W]`` float32: an EXR's first channel in OpenCV's order (B of an RGB file, as MatrixCity's loader reads
    it), with OpenCV when its build reads EXR, else with the OpenEXR package, else one line naming what to
    install."""
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # read once, at OpenCV's first EXR file
    import cv2

    if opencv_reads_exr():
        img = read_image(path, cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH)
        if img is None:
            raise ValueError(f"{path}: not a readable EXR; re-extract the depth archive")
        return np.asarray(img[..., 0] if img.ndim == 3 else img, np.float32)
    return _read_openexr(path)


@functools.cache
def opencv_reads_exr() -> bool:
    """Whether this OpenCV build has the OpenEXR codec (4.x: with ``OPENCV_IO_ENABLE_OPENEXR``; 5.0's wheels have
    none), by encoding and decoding one pixel: ``cv2.haveImageReader`` takes a path, which OpenCV 5 crashes on
    when it is not UTF-8."""
    import cv2

    try:
        ok, buf = cv2.imencode(".exr", np.ones((1, 1), np.float32))
        return bool(ok) and cv2.imdecode(buf, cv2.IMREAD_ANYCOLOR | cv2.IMREAD_ANYDEPTH) is not None
    except cv2.error:
        return False


def _read_openexr(path: Path) -> np.ndarray:
    try:
        import OpenEXR
    except ImportError:
        raise ValueError(f"{path}: cannot read EXR depth: this OpenCV build has no OpenEXR codec and the OpenEXR "
                         "package is not installed; pip install 'anycity[exr]' (or OpenEXR)") from None
    try:
        # the bytes of the name: OpenEXR refuses a str path that is not UTF-8 (a latin-1 folder name)
        channels = OpenEXR.File(os.fsencode(path), separate_channels=True).channels()
    except Exception as e:  # noqa: BLE001 - any damaged file: one line naming it
        raise ValueError(f"{path}: not a readable EXR ({type(e).__name__}); re-extract the depth archive") from None
    name = next((c for c in ("B", "Y", "R", "G") if c in channels), None)
    if name is None and len(channels) != 1:
        raise ValueError(f"{path}: EXR channels {sorted(channels)}, expected one depth channel or B/Y/R/G; "
                         "give the depth as MatrixCity releases it")
    return np.asarray(channels[name or next(iter(channels))].pixels, np.float32)


def _depth_loader(img: Path, dirs: list[Path]):
    """A loader of ``img``'s depth in metres ``[H, W]`` from the first of ``dirs`` that holds it, or None."""
    for d in dirs:
        for ext in _DEPTH_EXTS:
            p = d / (img.stem + ext)
            if p.exists():
                return lambda p=p: depth_metres(np.load(p) if p.suffix == ".npy" else read_exr(p))
    return None


INVALID_CM = (65504.0, 65535.0)  # float16 saturation; the sky (MatrixCity issue #22)


def depth_metres(cm: np.ndarray) -> np.ndarray:
    """MatrixCity z-depth in centimetres ``[H, W]`` -> metres, 0 where invalid (see the module docstring)."""
    cm = np.asarray(cm, np.float32)
    ok = np.isfinite(cm) & (cm > 0) & ~np.isin(cm, INVALID_CM)
    return np.where(ok, cm / 100.0, 0).astype(np.float32)


def _image_path(path: Path, fr: dict, raw: bool) -> Path:
    return path.parent / f"{int(fr['frame_index']):04d}.png" if raw else (path.parent / fr["file_path"]).resolve()


def _split_of(name: str) -> str | None:
    """``test``/``train`` when a file or folder name says so as a word (``transforms_test``, ``block_1_test``)."""
    words = set(re.split(r"[^a-z0-9]+|_", name.lower()))
    return "test" if "test" in words else "train" if "train" in words else None


def pose_files(src: Path) -> list[Path]:
    """The pose files ``--src`` names: itself (a json), else its ``transforms.json``, else its split files."""
    if src.suffix == ".json":
        return [src]
    if (src / "transforms.json").exists():
        return [src / "transforms.json"]
    split = sorted(p for p in src.glob("transforms_*.json") if _split_of(p.stem.removeprefix("transforms_")))
    if split:
        return split
    origin = " (transforms_origin.json, the poses before culling, is not read)" if (
        src / "transforms_origin.json").exists() else ""
    raise FileNotFoundError(f"{src}: no MatrixCity transforms.json (a block) or transforms_train.json / "
                            f"transforms_test.json (a pose folder){origin}; point --src at one")


def _intrinsics(meta: dict, frames: list, path: Path, raw: bool) -> tuple[np.ndarray, int, int]:
    """``(K [3, 3], w, h)`` of a pose file; a raw block file's size from its first image's header."""
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
    return K, w, h


def _c2w(fr: dict, raw: bool, where: str) -> np.ndarray:
    """OpenGL camera-to-world ``[4, 4]`` in metres of one frame."""
    if raw:
        c2w = np.asarray(fr["rot_mat"], float).copy()
        # The rotation is stored scaled by 0.01 in most blocks, unscaled in some (MatrixCity's own loaders test
        # which): divide by its column norm either way.
        c2w[:3, :3] /= np.linalg.norm(c2w[:3, :3], axis=0).mean()
    else:
        if "transform_matrix" not in fr:
            raise ValueError(f"{where}: missing 'transform_matrix'")
        c2w = np.asarray(fr["transform_matrix"], float).copy()
        c2w[:3, 3] *= 100.0  # 100 m units -> metres
    c2w[3, 3] = 1.0  # the files carry the rotation's scale there too; MatrixCity's loaders reset it
    return c2w


def _scene(path: Path, dirs: dict[Path, tuple[list[Path], list[str]]]) -> ParsedScene:
    """One pose file; ``dirs`` caches each image folder's depth folders."""
    meta = json.loads(require(path, "MatrixCity transforms_train.json / transforms.json").read_text())
    frames = meta.get("frames", [])
    raw = bool(frames) and "rot_mat" in frames[0]
    K, w, h = _intrinsics(meta, frames, path, raw)
    views = []
    for i, fr in enumerate(frames):
        img = _image_path(path, fr, raw)
        if img.parent not in dirs:
            dirs[img.parent] = depth_dirs(img.parent)
        views.append(ParsedView(name=img.name, image_path=img, w2c=c2w_gl_to_w2c(_c2w(fr, raw, f"{path} frame {i}")),
                                K=K, width=w, height=h, depth=_depth_loader(img, dirs[img.parent][0])))
    split = _split_of(path.stem) or _split_of(path.parent.name) or _split_of(path.parent.parent.name)
    return ParsedScene(name=f"{path.parent.name}_{path.stem}", views=views, source="matrixcity", units="metres",
                       metres_per_unit=1.0, world_from_source=np.eye(4) if raw else np.diag([100.0, 100, 100, 1]),
                       split=split, extra={"pose_file": path.name, "raw_block_json": raw})


def _warn_missing_depth(scenes: list[ParsedScene], dirs: dict[Path, tuple[list[Path], list[str]]]) -> None:
    """One warning for the views converted without depth, naming the folders searched for the first of them."""
    missing = [v for sc in scenes for v in sc.views if v.depth is None]
    if missing:
        n = sum(len(sc.views) for sc in scenes)
        searched = dirs[missing[0].image_path.parent][1]
        warnings.warn(f"MatrixCity: no depth for {len(missing)} of {n} views (e.g. {missing[0].image_path}; "
                      f"searched {', '.join(searched)}); they are converted without depth (extract the block's "
                      "depth archive into one of those folders to train with it)", stacklevel=3)


def parse(src: str | Path) -> list[ParsedScene]:
    """One ParsedScene per pose file of ``src`` (see the module docstring)."""
    dirs: dict[Path, tuple[list[Path], list[str]]] = {}
    scenes = [_scene(path, dirs) for path in pose_files(Path(src))]
    _warn_missing_depth(scenes, dirs)
    return scenes
