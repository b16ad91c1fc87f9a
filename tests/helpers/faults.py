"""Injected faults: a disk that fills up in the middle of a write; a shard with some members rewritten."""

from __future__ import annotations

import builtins
import errno
import io
import os
import sys
import tarfile
from pathlib import Path


class _HalfThenFull:
    """A file whose ``write`` writes half of what it is given, then fails as a full disk does."""

    def __init__(self, f):
        self.f = f

    def __enter__(self):
        return self

    def __exit__(self, *a):
        self.f.close()

    def __getattr__(self, name):
        return getattr(self.f, name)

    def write(self, data):
        data = bytes(data)
        self.f.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, "No space left on device")


def fail_writes_midway(monkeypatch, name: str) -> None:
    """Every file opened for writing whose path contains ``name`` fails half-way through its first write; so does
    the temp file ``anycity.atomic.atomic_open`` writes for such a path (a temp name never holds its target's)."""
    from anycity.atomic import TEMP_PREFIX

    real_open = builtins.open

    def fake_open(p, mode="r", *a, **k):
        f = real_open(p, mode, *a, **k)
        hit = name in os.fspath(p)
        if not hit and os.path.basename(os.fspath(p)).startswith(TEMP_PREFIX):
            target = sys._getframe(1).f_locals.get("path")  # the caller is atomic_open: its target
            hit = target is not None and name in os.fspath(target)
        return _HalfThenFull(f) if "w" in mode and hit else f

    monkeypatch.setattr(builtins, "open", fake_open)
    monkeypatch.setattr(io, "open", fake_open)  # pathlib's write_bytes / write_text


def rewrite_shard(src: Path, dst: Path, edit) -> Path:
    """Copy a shard, passing each member's ``(name, bytes)`` through ``edit`` (which returns the new bytes)."""
    with tarfile.open(src) as a, tarfile.open(dst, "w") as b:
        for m in a.getmembers():
            data = edit(m.name, a.extractfile(m).read())
            m.size = len(data)
            b.addfile(m, io.BytesIO(data))
    return dst
