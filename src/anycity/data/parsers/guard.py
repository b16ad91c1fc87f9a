"""A converter's contract on hostile input: a correct result or one line naming the source and the fix.

:func:`guarded` wraps each ``parse(src)``: the parser's own ``ValueError``/``FileNotFoundError`` pass through
(folded to one line); any other failure on a malformed file (``IndexError``, ``KeyError``, ``struct.error``,
``UnicodeDecodeError``, JSON errors, ...) becomes a one-line ``ValueError``; and every parsed camera is checked,
so a damaged file cannot come back as a silently wrong camera (non-finite K, pose or lens terms, non-rigid,
non-positive focal). Lens terms that are finite but absurd are refused when the images are undistorted
(``base.undistort``).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import numpy as np

from anycity.geometry import camera_problem
from anycity.geometry.cameras import MAX_IMAGE_SIDE


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def check_scene_cameras(scenes, src, fmt: str) -> None:
    """Raise ``ValueError`` naming the view unless every camera is finite (lens terms too), rigid, has a positive
    focal, a last row 0 0 1 and no skew (:func:`anycity.geometry.camera_problem`)."""
    for sc in scenes:
        for v in sc.views:
            where = f"{src}: {fmt} view {v.name!r} of scene {sc.name!r}"
            problem = camera_problem(v.w2c, v.K)
            if problem:
                fix = "" if ";" in problem else "; the camera file is damaged, re-export it"  # its own fix
                raise ValueError(f"{where}: {problem}{fix}")
            if v.dist is not None and not np.all(np.isfinite(np.asarray(v.dist, float))):
                raise ValueError(f"{where}: lens distortion terms {np.asarray(v.dist).tolist()} are not finite; "
                                 "the camera file is damaged, re-export it")
            if not (0 < int(v.width) <= MAX_IMAGE_SIDE and 0 < int(v.height) <= MAX_IMAGE_SIDE):
                raise ValueError(f"{where}: image size {v.width}x{v.height} is outside 1..{MAX_IMAGE_SIDE}; "
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
