"""``make gpu-check`` refuses in one line without CUDA; its code path runs at toy size on CPU (slow)."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.ddp_probe import subprocess_env

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: gpu-check would run")
def test_gpu_check_refuses_on_cpu_in_one_line():
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu_check.py")], capture_output=True, text=True,
                          env=subprocess_env(), timeout=120)
    assert proc.returncode == 2
    assert proc.stdout.count("\n") == 1 and "no CUDA" in proc.stdout


@pytest.mark.slow
def test_gpu_check_smoke_on_cpu():
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "gpu_check.py"), "--smoke-cpu"], capture_output=True,
                          text=True, env=subprocess_env(), timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for row in ("| stage1.yaml |", "| stage2.yaml |", "| inference 4 views |"):
        assert row in proc.stdout


def test_a_failing_check_becomes_a_fail_row_and_the_rest_still_run():
    from helpers.scripts import load_script

    gpu_check = load_script("gpu_check")
    rows = []

    def broken():
        raise RuntimeError("CUDA out of memory\nsecond line")

    assert gpu_check._guarded(rows, "stage1.yaml", broken) is None
    assert gpu_check._guarded(rows, "stage2.yaml", lambda: 7) == 7
    assert len(rows) == 1
    name, res, detail, _, _ = rows[0]
    assert (name, res) == ("stage1.yaml", "FAIL") and detail == "RuntimeError: CUDA out of memory"


def test_backend_check_without_gsplat_times_the_torch_renderer(monkeypatch):
    from helpers.scripts import load_script

    from anycity.render import api

    monkeypatch.setattr(api, "_module_available", lambda name: False if name == "gsplat" else True)
    gpu_check = load_script("gpu_check")
    res = gpu_check.check_backends(torch.device("cpu"), n=500, size=32)
    assert res.startswith("gsplat NOT INSTALLED; torch backend fwd+bwd ") and "(500 Gaussians, 4 x 32 px)" in res
