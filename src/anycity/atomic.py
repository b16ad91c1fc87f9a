"""Crash-safe file writes: temp file + fsync + rename, and disk-full errors that name the path and the size.

A reader (or a rerun after SIGKILL / power loss) sees the old file or the new one, never a partial one. Files an
earlier run left are moved aside to :func:`free_name`, never overwritten (:mod:`anycity.lit.keep`).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


def free_name(path: Path) -> Path:
    """``a/metrics.csv`` -> the first of ``a/metrics.1.csv``, ``a/metrics.2.csv``, ... that does not exist."""
    n = 1
    while True:
        cand = path.with_name(f"{path.stem}.{n}{path.suffix}") if path.suffix else path.with_name(f"{path.name}.{n}")
        if not cand.exists():
            return cand
        n += 1


def atomic_write_bytes(path: str | os.PathLike, data: bytes | memoryview) -> None:
    """Write ``data`` to ``path`` via a temp file + fsync + rename: readers see the old or the new file, never
    a partial one. On ``ENOSPC``/``EDQUOT`` raises ``OSError`` naming the path and the bytes needed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.errno in (errno.ENOSPC, errno.EDQUOT):
            raise OSError(e.errno, f"disk full writing {path}: {len(data)} bytes needed; free space on "
                                   f"{path.parent} (the previous file, if any, is unchanged)") from e
        raise
    _fsync_dir(path.parent)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:  # e.g. platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
