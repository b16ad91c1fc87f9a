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
