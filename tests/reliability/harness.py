"""Kill-and-resume harness: run ``anycity fit`` / ``anycity data ...`` in a subprocess, SIGKILL it, rerun.

Used by ``test_kill_resume.py`` (2 kill points in ``make test``, >= 10 per stage under ``-m slow``).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import torch

from anycity.lit.checkpoint_io import safe_torch_load

REPO = Path(__file__).resolve().parents[2]


def tiny_fit_args(shards: Path, run: Path, steps: int, stage2_from: Path | None = None) -> list[str]:
    """``anycity fit`` arguments of a tiny CPU run checkpointing every step into ``run/checkpoints``."""
    every = run.parent / f"{run.name}_ckpt_every_1.yaml"
    every.parent.mkdir(parents=True, exist_ok=True)
    every.write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
                     "    init_args: {save_last: true, save_top_k: 0, every_n_train_steps: 1}\n")
    stage2 = ["-c", str(REPO / "configs/quickstart_stage2.yaml")] if stage2_from else []
    args = ["fit", "-c", str(REPO / "configs/quickstart.yaml"), *stage2, "-c", str(every),
            "--data.root", str(shards), "--data.image_size", "[32, 32]", "--data.num_context", "2",
            "--data.num_targets", "1", "--data.num_dense", "2", "--data.shuffle_buffer", "1",
            "--trainer.max_steps", str(steps), "--trainer.val_check_interval", "1000",
            "--trainer.limit_val_batches", "0", "--trainer.log_every_n_steps", "1",
            "--trainer.default_root_dir", str(run), "--trainer.logger.init_args.save_dir", str(run),
            "--trainer.deterministic", "true",
            "--model.init_args.warmup_steps", "1", "--model.init_args.render_backend", "torch",
            "--progress.print_every", "1"]
    if stage2_from:
        args += ["--model.init_args.init_from", str(stage2_from)]
    return args


def env(**extra: str) -> dict:
    e = dict(os.environ, OMP_NUM_THREADS="1", NUMBA_NUM_THREADS="1", PYTHONUNBUFFERED="1", **extra)
    src = str(REPO / "src")
    e["PYTHONPATH"] = src + (os.pathsep + e["PYTHONPATH"] if e.get("PYTHONPATH") else "")
    return e


def start(args: list[str], log: Path, **env_extra: str) -> subprocess.Popen:
    log.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([sys.executable, "-m", "anycity.cli", *args], cwd=REPO, env=env(**env_extra),
                            stdout=open(log, "ab"), stderr=subprocess.STDOUT)


def run(args: list[str], log: Path, timeout: float = 600, **env_extra: str) -> int:
    p = start(args, log, **env_extra)
    try:
        return p.wait(timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        raise


def kill_after(args: list[str], log: Path, seconds: float, after: bytes | None = None, count: int = 1,
               timeout: float = 600) -> int:
    """Start, SIGKILL ``seconds`` later (if still running); returns the exit code (-9 when killed).

    ``after``: count the seconds from the ``count``-th time this launch's output holds these bytes (e.g. a
    training step's progress line), not from the start. Imports alone take 3 to 9 s on 2 cores, so a kill timed from the
    start can land before the run does anything; one timed from a step lands in training or a checkpoint write.
    """
    offset = log.stat().st_size if log.exists() else 0
    p = start(args, log)
    if after is not None:
        seen = b""
        while p.poll() is None and seen.count(after) < count:
            time.sleep(0.02)
            with open(log, "rb") as f:
                f.seek(offset)
                seen = f.read()
    t0 = time.monotonic()
    while p.poll() is None and time.monotonic() - t0 < seconds:
        time.sleep(0.02)
    if p.poll() is None:
        os.kill(p.pid, signal.SIGKILL)
    return p.wait(timeout)


def check_checkpoints(ckpt_dir: Path) -> int:
    """Every ``*.ckpt`` in ``ckpt_dir`` loads (weights_only); returns how many. Raises on an unreadable one."""
    n = 0
    for p in sorted(ckpt_dir.glob("*.ckpt")):
        safe_torch_load(p)
        n += 1
    return n


def params(ckpt: Path) -> dict[str, torch.Tensor]:
    return {k: v for k, v in safe_torch_load(ckpt)["state_dict"].items() if v.is_floating_point()}


def max_abs_diff(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k] - b[k]).abs().max()) if a[k].numel() else 0.0 for k in a)
