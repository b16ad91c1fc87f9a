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
