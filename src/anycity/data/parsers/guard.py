"""A converter's contract on hostile input: a correct result or one line naming the source and the fix.

:func:`guarded` wraps each ``parse(src)``: the parser's own ``ValueError``/``FileNotFoundError`` pass through
(folded to one line); any other failure on a malformed file (``IndexError``, ``KeyError``, ``struct.error``,
``UnicodeDecodeError``, JSON errors, ...) becomes a one-line ``ValueError``; and every parsed camera is checked,
so a damaged file cannot come back as a silently wrong camera (non-finite, non-rigid, non-positive focal).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

MAX_SIDE = 1 << 16  # image sides above this are a corrupt header, not a photo


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def check_scene_cameras(scenes, src, fmt: str) -> None:
    """Raise ``ValueError`` naming the view unless every camera is finite, rigid and has a positive focal."""
    for sc in scenes:
        for v in sc.views:
            where = f"{src}: {fmt} view {v.name!r} of scene {sc.name!r}"
            w2c, K = np.asarray(v.w2c, dtype=np.float64), np.asarray(v.K, dtype=np.float64)
            if w2c.shape != (4, 4) or K.shape != (3, 3):
                raise ValueError(f"{where}: expected w2c 4x4 and K 3x3, got {w2c.shape} and {K.shape}; "
                                 "the camera file is damaged, re-export it")
            if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
                raise ValueError(f"{where}: camera holds NaN/inf; the camera file is damaged, re-export it")
            R = w2c[:3, :3]
            with np.errstate(all="ignore"):  # a damaged matrix overflows quietly here, then fails the test below
                ortho, det = np.abs(R @ R.T - np.eye(3)).max(), np.linalg.det(R)
            if not (ortho <= 1e-3 and abs(det - 1) <= 1e-3 and np.abs(w2c[3] - [0, 0, 0, 1]).max() <= 1e-6):
                raise ValueError(f"{where}: camera pose is not a rigid rotation + translation; the camera file "
                                 "is damaged, re-export it")
            if not (K[0, 0] > 0 and K[1, 1] > 0) or np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
                raise ValueError(f"{where}: intrinsics need focal lengths > 0 (got fx={K[0, 0]:g}, "
                                 f"fy={K[1, 1]:g}); the camera file is damaged, re-export it")
            if not (0 < int(v.width) <= MAX_SIDE and 0 < int(v.height) <= MAX_SIDE):
                raise ValueError(f"{where}: image size {v.width}x{v.height} is outside 1..{MAX_SIDE}; "
                                 "the camera file is damaged, re-export it")


def guarded(fmt: str, parse: Callable) -> Callable:
    """``parse`` with the contract above."""

    @functools.wraps(parse)
    def run(src, *args, **kwargs):
        try:
            scenes = parse(src, *args, **kwargs)
        except FileNotFoundError as e:
            raise FileNotFoundError(_one_line(e)) from None
        except ValueError as e:
            msg = _one_line(e)
            if str(src) not in msg and Path(str(src)).name not in msg:
                msg = f"{src}: {msg}"
            raise ValueError(msg) from None
        except RecursionError:
            raise ValueError(f"{src}: cannot parse as {fmt}: nesting too deep; the file is damaged, "
                             "re-export it") from None
        except (MemoryError, OverflowError) as e:
            raise ValueError(f"{src}: cannot parse as {fmt}: a count or size in the file is absurd "
                             f"({type(e).__name__}); the file is damaged, re-export it") from None
        except Exception as e:  # noqa: BLE001 - any crash on a malformed file becomes the one-line contract
            raise ValueError(f"{src}: cannot parse as {fmt}: {type(e).__name__}: {_one_line(e)[:200]}; "
                             f"the file is truncated or damaged, re-export it") from None
        check_scene_cameras(scenes, src, fmt)
        return scenes

    return run
