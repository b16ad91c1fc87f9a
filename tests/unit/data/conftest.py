"""Shared fixtures: tiny synthetic shards (8-view training windows; built once per session) and the shared real
data folder."""

from __future__ import annotations

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
