"""Crash-safe file writes: temp file + fsync + rename, and disk-full errors that name the path and the size.

A reader (or a rerun after SIGKILL / power loss) sees the old file or the new one, never a partial one; a folder
written by :func:`staged_folder` appears whole or not at all, also when two runs write it at once (each fills its
own stage ``.<name>.partial/<pid>-<8 hex>-<host>/``). Files an earlier run left are moved aside to
:func:`free_name`, never overwritten (:mod:`anycity.lit.keep`).

Temp files: :func:`atomic_open` writes ``.anycity-tmp-<pid>-<16 hex digits>`` and :func:`atomic_path`
``.anycity-tmp-<pid>-<16 hex digits><suffix>`` (the target's suffix, e.g. ``.mp4``) in the target's folder (or
``tmp_dir``), then renames it over the target. The name never contains the target's name: Lightning's HPC-resume
scan reads the digits after ``hpc_ckpt_`` (and ``hpc_save_path`` those after ``ckpt_``) in every file name of the
folder, so a temp file named after ``hpc_ckpt_2.ckpt`` that a kill left would become "version 2<pid>" and break
every later resume. The random part keeps two threads writing one path apart. A temp file that a killed process
left is never read; :func:`stale_temp_files` / :func:`remove_stale_temp_files` list or remove them, and a shell
script may do the same, while no anycity process writes in that folder::

    find FOLDER -maxdepth 1 -type f -name '.anycity-tmp-*' -delete

A file that is replaced keeps its permission bits (a private ``0o600`` checkpoint stays private).
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
import socket
import stat
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

try:
    import fcntl
except ImportError:  # not POSIX: no flock, and what it guards goes unguarded
    fcntl = None

HAS_FLOCK = fcntl is not None

TEMP_PREFIX = ".anycity-tmp-"
"""Every temp file this module writes is named ``TEMP_PREFIX + "<pid>-<16 hex digits>" [+ suffix]``."""
_TEMP_RE = re.compile(re.escape(TEMP_PREFIX) + r"\d+-[0-9a-f]{16}(\.[^/]*)?")
_writing: set[str] = set()  # this process's temp files being written now (not stale)
_STAGE_RE = re.compile(r"(\d+)-[0-9a-f]{8}-(.+)")  # a stage's name in ``.<name>.partial``: <pid>-<8 hex>-<host>
STAGE_MARK = ".anycity-stage"
"""The file that marks a stage as this run's while it is filled (removed before the stage is renamed): a stage removed
and re-created by someone's ``mkdir -p`` lacks it (an inode number may be reused at once)."""
_stages: dict[str, Path] = {}  # this process's stages being filled -> the folder each becomes


def temp_name(folder: str | os.PathLike, suffix: str = "") -> Path:
    """A fresh temp file name in ``folder``: ``.anycity-tmp-<pid>-<16 hex digits><suffix>``. It never contains the
    name of the file it will become (see the module docstring), and differs per call (threads of one process)."""
    return Path(folder) / f"{TEMP_PREFIX}{os.getpid()}-{secrets.token_hex(8)}{suffix}"


def stale_temp_files(folder: str | os.PathLike, min_age_s: float = 0.0) -> list[Path]:
    """The temp files (see :func:`temp_name`) in ``folder`` (not its subfolders) that were last modified at least
    ``min_age_s`` seconds ago, except those this process is writing now. Call it when no other process writes in
    ``folder`` (a job's start), or with a ``min_age_s`` longer than any write takes."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    now, out = time.time(), []
    for p in sorted(folder.iterdir()):
        if not _TEMP_RE.fullmatch(p.name) or os.path.abspath(p) in _writing:
            continue
        try:
            st = p.lstat()
        except FileNotFoundError:  # published or removed meanwhile
            continue
        if stat.S_ISREG(st.st_mode) and now - st.st_mtime >= min_age_s:
            out.append(p)
    return out


def remove_stale_temp_files(folder: str | os.PathLike, min_age_s: float = 0.0) -> list[Path]:
    """Remove :func:`stale_temp_files` (temp files that killed writers left in ``folder``); returns them."""
    gone = stale_temp_files(folder, min_age_s)
    for p in gone:
        p.unlink(missing_ok=True)
    return gone


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
    part of it that exists is a file, or a folder this user may not write in, or a part of it is a broken link.
    ``what`` names the option."""
    path = Path(path).absolute()
    for existing in (path, *path.parents):
        if existing.exists():
            break
        if existing.is_symlink():  # mkdir would raise a bare FileExistsError on it
            raise NotADirectoryError(f"{what} {path}: {existing} is a broken link (to {os.readlink(existing)}); "
                                     "create its target, remove the link, or pass another folder")
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
    _make_parent(path)
    tmp = temp_name(tmp_dir or path.parent)
    _writing.add(os.path.abspath(tmp))
    try:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            _keep_mode(path, f.fileno())
            os.fsync(f.fileno())
        publish(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            need = f"{size} bytes needed" if size is not None else "more space needed"
            raise OSError(e.errno, f"disk full writing {path}: {need}; free space on {path.parent} (the previous "
                                   "file, if any, is unchanged)") from e
        raise
    finally:
        _writing.discard(os.path.abspath(tmp))


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A hidden temporary path beside ``path`` (:func:`temp_name`), with its suffix (for writers that take a file
    name and pick a format by it, as ffmpeg does), that becomes ``path`` (fsync, rename) only when the block ends
    without an exception; on one it is removed and ``path`` is unchanged."""
    path = Path(path)
    _make_parent(path)
    tmp = temp_name(path.parent, path.suffix)
    _writing.add(os.path.abspath(tmp))
    try:
        yield tmp
        with open(tmp, "rb") as f:
            _keep_mode(path, f.fileno())
            os.fsync(f.fileno())
        publish(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        _writing.discard(os.path.abspath(tmp))


def publish(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rename the finished, fsynced file (or folder of them) ``src`` to ``dst`` (same filesystem) and fsync
    ``dst``'s folder, so the new name survives a power loss."""
    os.replace(src, dst)
    _fsync_dir(Path(dst).parent)


@contextmanager
def staged_folder(path: str | os.PathLike) -> Iterator[Path]:
    """A folder to fill that appears as ``path`` only when the block ends without an exception: it is written as
    this run's own stage ``.<name>.partial/<pid>-<8 hex>-<host>/`` beside ``path`` and renamed to ``path``, which
    must not exist. On an exception, or after a kill, there is no ``path``. Two runs writing ``path`` at once each
    fill their own stage; a stage whose run no longer runs (same host, pid gone) is never read and is dropped here,
    as the shard writer drops its ``*.tar.partial`` files. When ``path`` appeared meanwhile (another run published
    first), this run's complete copy is moved to ``.<name>.kept-<pid>-<8 hex>`` (never dropped automatically) and
    ``FileExistsError`` names it. Write the files inside fsynced (:func:`atomic_write_bytes`), so that the renamed
    folder also survives a power loss; :func:`atomic_open` refuses to re-create a stage removed meanwhile."""
    path = Path(path)
    box = path.parent / f".{path.name}.partial"
    _drop_stale_stages(box)
    stage = _new_stage(box)
    (stage / STAGE_MARK).touch()
    key = os.path.abspath(stage)
    _stages[key] = path
    try:
        try:
            yield stage
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
        try:
            (stage / STAGE_MARK).unlink()
        except FileNotFoundError:  # removed (and maybe re-created by a mkdir(parents=True)) while written
            shutil.rmtree(stage, ignore_errors=True)
            raise _stage_gone(stage, path) from None
        _publish_stage(stage, path)
    finally:
        _stages.pop(key, None)
        try:
            box.rmdir()  # only when no other run's stage is left in it
        except OSError:
            pass


def _new_stage(box: Path) -> Path:
    """Create this run's own stage folder ``box/<pid>-<8 hex>-<host>`` (``box`` made as needed)."""
    for _ in range(100):
        box.mkdir(parents=True, exist_ok=True)
        stage = box / f"{os.getpid()}-{secrets.token_hex(4)}-{socket.gethostname()}"
        try:
            stage.mkdir()
            return stage
        except FileNotFoundError:  # another run removed the empty box between the two mkdirs
            continue
    raise FileExistsError(f"{box}: other runs keep removing this staging folder; run one writer of "
                          f"{box.parent / box.name[1:].removesuffix('.partial')} at a time")


def _drop_stale_stages(box: Path) -> None:
    """Remove what ``box`` holds except the stages of runs that still run (or run on another host: no way to
    tell); an entry not named as a stage is an older anycity's leftover (it wrote its files into ``box``)."""
    try:
        entries = list(box.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return
    host = socket.gethostname()
    for p in entries:
        m = _STAGE_RE.fullmatch(p.name)
        if m and (m[2] != host or pid_runs(int(m[1]))):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)


def _publish_stage(stage: Path, path: Path) -> None:
    """Rename the finished ``stage`` to ``path``; if ``path`` is there (another run published first), move the
    stage to a kept name and raise one line naming it."""
    if not path.exists():  # the rename would replace an empty folder that appeared meanwhile
        try:
            publish(stage, path)
            return
        except OSError:
            if not path.exists():
                raise
    kept = path.parent / f".{path.name}.kept-{os.getpid()}-{secrets.token_hex(4)}"
    os.rename(stage, kept)
    raise FileExistsError(f"{path} appeared while this run wrote it (another run?); this run's complete copy is "
                          f"kept as {kept}")


def _make_parent(path: Path) -> None:
    """Create ``path``'s folder. Inside a stage this process fills (:func:`staged_folder`) only the folders below
    the stage are made: a stage removed meanwhile is one line, not silently re-created half empty."""
    if _stages:
        parent = Path(os.path.abspath(path.parent))
        chain = [parent, *parent.parents]
        for i, d in enumerate(chain):
            if str(d) not in _stages:
                continue
            target = _stages[str(d)]
            if not (d / STAGE_MARK).is_file():
                raise _stage_gone(d, target)
            try:
                for sub in reversed(chain[:i]):
                    sub.mkdir(exist_ok=True)
            except FileNotFoundError:
                raise _stage_gone(d, target) from None
            return
    path.parent.mkdir(parents=True, exist_ok=True)


def _stage_gone(stage: Path, target: Path) -> FileNotFoundError:
    return FileNotFoundError(f"{stage}: this run's unfinished copy of {target} was removed while it was written "
                             f"(by another program?); nothing is published, rerun to write {target}")


def try_flock(fd: int) -> bool | None:
    """An exclusive, non-blocking ``flock`` on the open descriptor ``fd``: True when taken (held until ``fd`` is
    closed or the process ends), False when another process holds it, None where the OS or the filesystem (a network
    one) has no ``flock``, so the caller goes unguarded. ``fd`` stays open either way."""
    if fcntl is None:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:
        return None
    return True


def pid_runs(pid: int) -> bool:
    """Whether process ``pid`` of this host runs (another user's counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (EPERM), or no way to tell: assume it runs
        return True
    return True


def _keep_mode(target: Path, fd: int) -> None:
    """Give the temp file open as ``fd`` the permission bits of ``target`` when that exists, so replacing a file
    keeps its mode (a fresh temp file gets ``0o666 & ~umask``, which would make a ``0o600`` file world-readable)."""
    try:
        mode = stat.S_IMODE(os.stat(target).st_mode)
    except OSError:  # no file to replace (or not one we may stat): the temp file's own mode
        return
    os.fchmod(fd, mode)


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
