"""The sbatch scripts' own launch line, run as SLURM would run it: 1 node x 2 tasks on CPU, each task a process
with the SLURM_* variables srun sets. Both ranks must join one process group (Lightning's SLURMEnvironment, no
launcher of ours) and train; a second submission resumes from last.ckpt."""

import os
import re
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.ddp_probe import assert_params_equal, subprocess_env

ROOT = Path(__file__).resolve().parents[2]


def _launch_line(script: str) -> list[str]:
    """The command srun runs in ``docker/slurm/<script>``, srun and its options removed."""
    line = next(ln for ln in (ROOT / "docker" / "slurm" / script).read_text().splitlines() if ln.startswith("srun "))
    words = shlex.split(line)[1:]
    while words[0].startswith("--"):
        words.pop(0)
    return words


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _srun(words: list[str], run_dir: Path, extra: list[str], cwd: Path) -> list[str]:
    """Start the 2 tasks of one node as srun would, wait for both; returns their outputs."""
    argv = []
    for w in words:
        if w == "$@":
            argv += extra
        else:
            argv.append(w.replace("${RUN_DIR}", str(run_dir)))
    argv[0] = str(ROOT / argv[0])
    argv[1] = str(ROOT / argv[1])
    port, job = _free_port(), str(40000 + os.getpid() % 10000)
    procs = []
    for rank in (0, 1):
        env = subprocess_env()
        env.update(SLURM_JOB_ID=job, SLURM_JOB_NAME="anycity-test", SLURM_NNODES="1", SLURM_NTASKS="2",
                   SLURM_NTASKS_PER_NODE="2", SLURM_NODEID="0", SLURM_PROCID=str(rank), SLURM_LOCALID=str(rank),
                   SLURM_NODELIST="localhost", SLURM_JOB_NODELIST="localhost", MASTER_PORT=str(port),
                   CONTAINER="", ANYCITY=f"{shlex.quote(sys.executable)} -m anycity.cli")
        procs.append(subprocess.Popen(["bash", *argv], cwd=cwd, env=env, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True))
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=180)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out[-4000:]
    return outs


def _probe_overlay(tmp: Path, probe: Path) -> Path:
    path = tmp / "probe.yaml"
    path.write_text("trainer:\n  callbacks:\n"
                    "    - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
                    "      init_args: {save_last: true, save_top_k: 0, every_n_train_steps: 2}\n"
                    f"    - class_path: helpers.ddp_probe.DDPProbe\n      init_args: {{out_dir: {probe}}}\n")
    return path


def _run_stage1(ddp_shards, tmp_path, steps: int) -> list[str]:
    words = _launch_line("stage1.sbatch")
    assert words[:3] == ["docker/slurm/launch.sh", "configs/stage1.yaml", "${RUN_DIR}"] and words[-1] == "$@"
    extra = ["-c", str(ROOT / "configs" / "debug" / "cpu_ddp.yaml"), "--data.root", str(ddp_shards),
             "-c", str(_probe_overlay(tmp_path, tmp_path / "probe")), "--trainer.max_steps", str(steps)]
    return _srun(words, tmp_path / "runs" / "stage1", extra, tmp_path)


def test_sbatch_launch_line_one_node_two_tasks(ddp_shards, tmp_path):
    outs = _run_stage1(ddp_shards, tmp_path, 2)
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in outs[0] and "GLOBAL_RANK: 1, MEMBER: 2/2" in outs[1]
    assert_params_equal(tmp_path / "probe")  # both trained, in one process group (DDP kept them identical)
    ckpt = tmp_path / "runs" / "stage1" / "checkpoints" / "last.ckpt"
    assert torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"] == 2


@pytest.mark.slow
def test_requeued_job_resumes_from_last_ckpt(ddp_shards, tmp_path):
    _run_stage1(ddp_shards, tmp_path, 2)
    outs = _run_stage1(ddp_shards, tmp_path, 4)  # the same submission again, as after a requeue
    assert all(re.search(r"resuming from .*stage1/checkpoints/last.ckpt", o) for o in outs)
    ckpt = tmp_path / "runs" / "stage1" / "checkpoints" / "last.ckpt"
    assert torch.load(ckpt, map_location="cpu", weights_only=False)["global_step"] == 4
