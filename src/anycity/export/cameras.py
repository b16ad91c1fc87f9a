"""``cameras.json``: predicted cameras of a reconstruction (OpenCV w2c, K in pixels, image size)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from torch import Tensor

from anycity.atomic import atomic_write_bytes
from anycity.geometry.cameras import MAX_IMAGE_SIDE, camera_problem

SCHEMA_VERSION = 1


def cameras_to_dict(w2c: Tensor, K: Tensor, width: int, height: int, names: list[str] | None = None,
                    scale: float | None = None) -> dict:
    """One scene's cameras ``w2c [V, 4, 4]``, ``K [V, 3, 3]`` -> a JSON-serialisable dict.

    ``scale`` (metres per world unit) is recorded when known so the scene can be mapped back to metres.
    """
    if w2c.dim() != 3 or w2c.shape[-2:] != (4, 4) or K.shape != (w2c.shape[0], 3, 3):
        raise ValueError(f"cameras_to_dict: expected w2c [V, 4, 4] and K [V, 3, 3], got {tuple(w2c.shape)} "
                         f"and {tuple(K.shape)}")
    names = names or [f"{i:03d}" for i in range(w2c.shape[0])]
    views = [{"name": n, "w2c": w.tolist(), "K": k.tolist(), "width": width, "height": height}
             for n, w, k in zip(names, w2c.detach().cpu().double(), K.detach().cpu().double(), strict=True)]
    return {"schema_version": SCHEMA_VERSION, "convention": "opencv_w2c", "units": "normalised",
            "metres_per_unit": scale, "views": views}


def save_cameras(path: str | Path, w2c: Tensor, K: Tensor, width: int, height: int, names: list[str] | None = None,
                 scale: float | None = None) -> None:
    """Write :func:`cameras_to_dict` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, json.dumps(cameras_to_dict(w2c, K, width, height, names, scale), indent=1).encode())


def load_cameras(path: str | Path) -> dict:
    """Read and check a ``cameras.json``: convention ``opencv_w2c`` and a schema version this code reads (when
    given), a ``views`` list, each with an optional ``name`` (a photo's file name: no ``/``, ``\\``, NUL, ``.`` or
    ``..``, since the exports write ``images/<name>.png``), a finite rigid ``w2c`` (4x4), a finite ``K`` (3x3)
    with focal lengths > 0, last row 0 0 1 and no skew (:func:`anycity.geometry.camera_problem`) and the same
    ``width`` / ``height`` (1..65536) as the others, and a ``metres_per_unit`` that is positive or null. A file that
    is not that raises a one-line ``ValueError`` naming it (JSON's ``NaN``, a zeroed rotation or a string scale
    would otherwise reach the COLMAP and nerfstudio exports, the viewer and the fly-through)."""
    path = Path(path)

    def bad(what: str) -> ValueError:
        return ValueError(f"{path}: {what}; it is not a cameras.json written by `anycity predict` (re-run predict, "
                          "or remove it to export the Gaussians alone)")

    try:
        cams = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise bad(f"not JSON ({e})") from None
    views = cams.get("views") if isinstance(cams, dict) else None
    if not isinstance(views, list) or not views:
        raise bad("no 'views' list")
    if cams.get("convention", "opencv_w2c") != "opencv_w2c":  # e.g. OpenGL camera-to-world: read as w2c, wrong
        raise bad(f"its 'convention' is {str(cams['convention'])[:40]!r}, not 'opencv_w2c'")
    version = cams.get("schema_version", SCHEMA_VERSION)
    if not isinstance(version, int) or isinstance(version, bool) or version > SCHEMA_VERSION:
        raise bad(f"its 'schema_version' is {str(version)[:40]!r}; this anycity reads up to {SCHEMA_VERSION} "
                  "(a newer anycity wrote it? upgrade)")
    for i, v in enumerate(views):
        if not isinstance(v, dict):
            raise bad(f"view {i} is a {type(v).__name__}, not an object")
        for key, shape in (("w2c", (4, 4)), ("K", (3, 3))):
            m = v.get(key)
            ok = isinstance(m, list) and len(m) == shape[0] and all(
                isinstance(r, list) and len(r) == shape[1]
                and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in r) for r in m)
            if not ok:
                raise bad(f"view {i} has no {shape[0]}x{shape[1]} numeric '{key}'")
        problem = camera_problem(v["w2c"], v["K"])
        if problem:
            raise bad(f"view {i}: {problem}")
        for key in ("width", "height"):
            side = v.get(key)
            if not isinstance(side, int) or isinstance(side, bool) or not 0 < side <= MAX_IMAGE_SIDE:
                raise bad(f"view {i} has no positive integer '{key}' (at most {MAX_IMAGE_SIDE})")
        if (v["width"], v["height"]) != (views[0]["width"], views[0]["height"]):
            raise bad(f"view {i} is {v['width']}x{v['height']}, view 0 {views[0]['width']}x{views[0]['height']} "
                      "(one predict writes one image size)")
        name = v.get("name", "000")
        if not isinstance(name, str):
            raise bad(f"view {i}'s 'name' is not a string")
        if name in ("", ".", "..") or any(c in name for c in "/\\\0"):  # the exports write images/<name>.png
            raise bad(f"view {i}'s 'name' {name[:60]!r} is not a plain file name (empty, '.', '..', or holding /, \\ "
                      "or NUL)")
    scale = cams.get("metres_per_unit")
    if scale is not None and not (isinstance(scale, (int, float)) and not isinstance(scale, bool)
                                  and 0 < scale < math.inf):  # no float(): a 400-digit JSON integer overflows it
        raise bad(f"'metres_per_unit' is {str(scale)[:40]!r}, not a positive number or null")
    return cams
