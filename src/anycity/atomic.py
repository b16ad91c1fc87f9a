"""Crash-safe file writes: temp file + fsync + rename, and disk-full errors that name the path and the size.

A reader (or a rerun after SIGKILL / power loss) sees the old file or the new one, never a partial one; a folder
written by :func:`staged_folder` appears whole or not at all. Files an earlier run left are moved aside to
:func:`free_name`, never overwritten (:mod:`anycity.lit.keep`).
"""

from __future__ import annotations

import errno
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO


def free_name(path: Path) -> Path:
    """``a/metrics.csv`` -> the first of ``a/metrics.1.csv``, ``a/metrics.2.csv``, ... that does not exist."""
    n = 1
    while True:
        cand = path.with_name(f"{path.stem}.{n}{path.suffix}") if path.suffix else path.with_name(f"{path.name}.{n}")
        if not cand.exists():
            return cand
        n += 1


def check_writable_folder(path: str | os.PathLike, what: str) -> None:
    """Raise one line before any work when ``path`` (a folder to create or fill) cannot be written: the nearest
    part of it that exists is a file, or a folder this user may not write in. ``what`` names the option."""
    path = Path(path).absolute()
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        raise NotADirectoryError(f"{what} {path}: {existing} is a file, not a folder; pass a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{what} {path}: this user may not write in {existing}; pass a folder you can write "
                              "to, or change its permissions")


def atomic_write_bytes(path: str | os.PathLike, data: bytes | memoryview) -> None:
    """Write ``data`` to ``path`` via a temp file + fsync + rename: readers see the old or the new file, never
    a partial one. On ``ENOSPC``/``EDQUOT`` raises ``OSError`` naming the path and the bytes needed."""
    with atomic_open(path, size=len(data)) as f:
        f.write(data)


@contextmanager
def atomic_open(path: str | os.PathLike, tmp_dir: str | os.PathLike | None = None,
                size: int | None = None) -> Iterator[BinaryIO]:
    """A binary file to stream into that appears as ``path`` only when the block ends without an exception
    (temp file, flush, fsync, rename, folder fsync); on an exception the temp file is removed and ``path`` is
    unchanged. ``tmp_dir``: where the temp file lives (default: ``path``'s folder; it must be on the same
    filesystem). ``size``: the bytes it will take, for the disk-full message."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tmp_dir or path.parent) / f".{path.name}.tmp-{os.getpid()}"
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        publish(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            need = f"{size} bytes needed" if size is not None else "more space needed"
            raise OSError(e.errno, f"disk full writing {path}: {need}; free space on {path.parent} (the previous "
                                   "file, if any, is unchanged)") from e
        raise


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A hidden temporary path beside ``path``, with its suffix (for writers that take a file name and pick a
    format by it, as ffmpeg does), that becomes ``path`` (fsync, rename) only when the block ends without an
    exception; on one it is removed and ``path`` is unchanged."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        publish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def publish(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rename the finished, fsynced file (or folder of them) ``src`` to ``dst`` (same filesystem) and fsync
    ``dst``'s folder, so the new name survives a power loss."""
    os.replace(src, dst)
    _fsync_dir(Path(dst).parent)


@contextmanager
def staged_folder(path: str | os.PathLike) -> Iterator[Path]:
    """A folder to fill that appears as ``path`` only when the block ends without an exception: it is written as
    the hidden sibling ``.<name>.partial`` and renamed to ``path``, which must not exist. On an exception, or after
    a kill, there is no ``path``. A ``.<name>.partial`` that a killed run left is never read and is dropped here, as
    the shard writer drops its ``*.tar.partial`` files. Write the files inside fsynced (:func:`atomic_write_bytes`),
    so that the renamed folder also survives a power loss."""
    path = Path(path)
    stage = path.parent / f".{path.name}.partial"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    try:
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    if path.exists():  # the rename would replace an empty folder that appeared meanwhile
        raise FileExistsError(f"{path} appeared while it was being written; the new one is kept as {stage}")
    publish(stage, path)


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
