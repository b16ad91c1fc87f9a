"""``cameras.json``: predicted cameras of a reconstruction (OpenCV w2c, K in pixels, image size)."""

from __future__ import annotations

import json
from pathlib import Path

from torch import Tensor

from anycity.atomic import atomic_write_bytes

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
    """Read and check a ``cameras.json``: a ``views`` list, each with ``name``, ``w2c`` (4x4), ``K`` (3x3) and a
    positive ``width`` / ``height``. A file that is not that raises a one-line ``ValueError`` naming it."""
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
    for i, v in enumerate(views):
        if not isinstance(v, dict):
            raise bad(f"view {i} is a {type(v).__name__}, not an object")
        for key, shape in (("w2c", (4, 4)), ("K", (3, 3))):
            m = v.get(key)
            ok = isinstance(m, list) and len(m) == shape[0] and all(
                isinstance(r, list) and len(r) == shape[1] and all(isinstance(x, (int, float)) for x in r) for r in m)
            if not ok:
                raise bad(f"view {i} has no {shape[0]}x{shape[1]} numeric '{key}'")
        for key in ("width", "height"):
            if not isinstance(v.get(key), int) or v[key] <= 0:
                raise bad(f"view {i} has no positive integer '{key}'")
        if not isinstance(v.get("name", ""), str):
            raise bad(f"view {i}'s 'name' is not a string")
    return cams
