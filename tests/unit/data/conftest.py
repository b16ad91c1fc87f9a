"""Shared fixtures: tiny synthetic shards (8-view training windows; built once per session) and the shared real
data folder; a child-process runner and non-UTF-8 file names."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from anycity.data.synthetic import synth

SHARED = Path(__file__).resolve().parents[3] / ".." / "shared"
REAL = SHARED / "data" / "real_aerial"


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    synth(out, scenes=4, views=16, size="40x48", seed=3, trajectory="mixed", workers=1, depth_dtype="float32",
          window=8, stride=4)
    return out


@pytest.fixture(autouse=True)
def _one_thread():
    """The data code runs many small tensor ops; one thread is faster and kinder to a shared CPU."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def child():
    """``run(code, *args)``: ``code`` in a fresh Python (``sys.argv[1:]`` = ``args``, str or bytes); returns its
    stdout. A crash there (OpenCV's SIGSEGV) fails the test instead of ending pytest."""
    def run(code: str, *args) -> str:
        env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
        r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=300,
                           errors="backslashreplace")
        assert r.returncode == 0, f"the child exited with {r.returncode} (-11: SIGSEGV):\n{r.stderr[-3000:]}"
        return r.stdout

    return run


@pytest.fixture
def latin1_path():
    """``make(folder, name: bytes, data=None)``: ``folder / name`` created (a folder when ``data`` is None, else a
    file holding it) under a name that is not UTF-8, e.g. ``b"caf\\xe9.jpg"`` (latin-1, as an old camera card or zip
    gives it); returned as Python's surrogate-escaped ``str``. Skips where the filesystem refuses such names."""
    def make(folder: str | Path, name: bytes, data: bytes | None = None) -> str:
        path = os.path.join(os.fsencode(folder), name)
        try:
            if data is None:
                os.makedirs(path)
            else:
                with open(path, "wb") as f:
                    f.write(data)
        except OSError as e:
            pytest.skip(f"this filesystem refuses a file name that is not UTF-8 ({e})")
        return os.fsdecode(path)

    return make
