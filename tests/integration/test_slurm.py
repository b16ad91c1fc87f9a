"""The sbatch scripts' own batch shell (docker/slurm/job.sh), run as SLURM would run it on one CPU node: a stand-in
``srun`` starts 2 tasks of ``launch.sh`` with the SLURM_* variables srun sets, and a stand-in ``scontrol`` records
what it is asked. Both ranks must join one process group (Lightning's SLURMEnvironment, no launcher of ours) and
train; SIGUSR1 to the batch shell (``--signal=B:USR1``) must leave a complete preemption checkpoint before the job
is requeued; and the requeued job resumes from the newest checkpoint."""

import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from helpers.ddp_probe import assert_params_equal, subprocess_env

ROOT = Path(__file__).resolve().parents[2]

FAKE_SRUN = r"""#!/usr/bin/env bash
# srun for tests: SLURM_NTASKS copies of the command here, each with its SLURM_PROCID/SLURM_LOCALID; a SIGUSR1 to
# srun goes to every task, as the real srun forwards it
while [[ "$1" == --* ]]; do shift; done
pids=()
for ((r = 0; r < SLURM_NTASKS; r++)); do
    SLURM_PROCID=$r SLURM_LOCALID=$r "$@" &
    pids+=($!)
done
trap 'kill -USR1 "${pids[@]}" 2>/dev/null' USR1
rc=0
for p in "${pids[@]}"; do
    while true; do s=0; wait "$p" || s=$?; kill -0 "$p" 2>/dev/null || break; done
    if (( s != 0 )); then rc=$s; fi
done
exit $rc
"""

FAKE_SCONTROL = """#!/usr/bin/env bash
echo "$* by $(cat /proc/$PPID/comm)" >> "$SCONTROL_LOG"   # by bash: job.sh; by python: Lightning's own handler
"""


def _sbatch_line(script: str) -> list[str]:
    """The command ``docker/slurm/<script>`` hands over to, e.g. ['docker/slurm/job.sh', CONFIG, RUN_DIR, '$@']."""
    line = next(ln for ln in (ROOT / "docker" / "slurm" / script).read_text().splitlines() if ln.startswith("exec "))
    return shlex.split(line)[1:]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _job(tmp: Path, extra: list[str]) -> subprocess.Popen:
    """Start stage1.sbatch's batch shell as its own process group; stdout+stderr go to tmp/job-<n>.out."""
    words = _sbatch_line("stage1.sbatch")
    assert words[0] == "docker/slurm/job.sh" and words[-1] == "$@"
    bin_dir = tmp / "bin"
    bin_dir.mkdir(exist_ok=True)
    for name, text in (("srun", FAKE_SRUN), ("scontrol", FAKE_SCONTROL)):
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    env = subprocess_env()
    env.update(PATH=f"{bin_dir}{os.pathsep}{env['PATH']}", SCONTROL_LOG=str(tmp / "scontrol.log"),
               SLURM_JOB_ID=str(40000 + os.getpid() % 10000), SLURM_JOB_NAME="anycity-test", SLURM_NNODES="1",
               SLURM_NTASKS="2", SLURM_NTASKS_PER_NODE="2", SLURM_NODEID="0", SLURM_NODELIST="localhost",
               SLURM_JOB_NODELIST="localhost", MASTER_PORT=str(_free_port()), CONTAINER="",
               ANYCITY=f"{shlex.quote(sys.executable)} -m anycity.cli", RUN_DIR=str(tmp / "runs" / "stage1"))
    log = tmp / f"job-{len(list(tmp.glob('job-*.out')))}.out"
    argv = ["bash", str(ROOT / words[0]), str(ROOT / words[1]), *words[2:-1], *extra]
    return subprocess.Popen(argv, cwd=tmp, env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT,
                            start_new_session=True)


def _extra(ddp_shards, tmp: Path, steps: int) -> list[str]:
    probe = tmp / "probe.yaml"
    probe.write_text("trainer:\n  callbacks:\n"
                     "    - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
                     "      init_args: {save_last: true, save_top_k: 0, every_n_train_steps: 2}\n"
                     f"    - class_path: helpers.ddp_probe.DDPProbe\n      init_args: {{out_dir: {tmp / 'probe'}}}\n")
    return ["-c", str(ROOT / "configs" / "debug" / "cpu_ddp.yaml"), "--data.root", str(ddp_shards), "-c", str(probe),
            "--trainer.max_steps", str(steps)]


def _wait_for(cond, proc: subprocess.Popen, what: str, timeout: float = 150.0) -> None:
    t0 = time.monotonic()
    while not cond():
        assert proc.poll() is None, f"the job ended (rc {proc.returncode}) before {what}"
        assert time.monotonic() - t0 < timeout, f"no {what} after {timeout:.0f} s"
        time.sleep(0.5)


def _step(path: Path) -> int:
    return torch.load(path, map_location="cpu", weights_only=False)["global_step"]


def test_time_limit_signal_saves_then_requeues(ddp_shards, tmp_path):
    """SIGUSR1 to the batch shell: every task saves RUN_DIR/hpc_ckpt_1.ckpt, then job.sh runs scontrol requeue."""
    run = tmp_path / "runs" / "stage1"
    proc = _job(tmp_path, _extra(ddp_shards, tmp_path, 100_000))
    try:
        _wait_for((run / "checkpoints" / "last.ckpt").exists, proc, "checkpoints/last.ckpt (training started)")
        os.kill(proc.pid, signal.SIGUSR1)
        requeued = tmp_path / "scontrol.log"
        _wait_for(lambda: requeued.exists() and
                  f"requeue {40000 + os.getpid() % 10000} by bash" in requeued.read_text(), proc, "job.sh's requeue")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # SLURM ends the requeued job's steps
        proc.wait()
    out = _log(tmp_path)
    assert "GLOBAL_RANK: 0, MEMBER: 1/2" in out and "GLOBAL_RANK: 1, MEMBER: 2/2" in out, out[-3000:]
    assert "time limit near" in out and "no new preemption checkpoint" not in out, out[-3000:]
    assert _step(run / "hpc_ckpt_1.ckpt") >= 2  # complete: it loads, and it holds trained steps


def _log(tmp: Path) -> str:
    return "".join(p.read_text() for p in sorted(tmp.glob("job-*.out")))


@pytest.mark.slow
def test_requeued_job_resumes_from_the_newest_checkpoint(ddp_shards, tmp_path):
    run = tmp_path / "runs" / "stage1"
    test_time_limit_signal_saves_then_requeues(ddp_shards, tmp_path)
    candidates = [run / "hpc_ckpt_1.ckpt", run / "checkpoints" / "last.ckpt"]
    newest = max(candidates, key=lambda p: p.stat().st_mtime)
    start = _step(newest)
    proc = _job(tmp_path, _extra(ddp_shards, tmp_path, start + 2))  # the same submission, as after the requeue
    assert proc.wait(timeout=300) == 0, _log(tmp_path)[-4000:]
    out = _log(tmp_path)
    assert re.search(rf"launch.sh: resuming from {re.escape(str(newest))}", out), out[-3000:]
    assert _step(run / "checkpoints" / "last.ckpt") == start + 2
    assert_params_equal(tmp_path / "probe")  # both ranks resumed and trained in one process group
    if newest != candidates[0]:  # a preemption checkpoint older than the one resumed from is deleted
        assert not candidates[0].exists()


def test_launch_resumes_from_the_newest_of_the_preemption_and_last_checkpoints(tmp_path):
    """launch.sh names the newest (by modification time) of RUN_DIR/hpc_ckpt_*.ckpt, checkpoints/last.ckpt and an
    older anycity's versioned checkpoints/last-vN.ckpt (a moved run's resume wrote those, and launch.sh went back to
    the stale last.ckpt); a fresh RUN_DIR starts afresh."""
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)

    def launch() -> str:
        env = {**os.environ, "ANYCITY": "echo anycity", "CONTAINER": "", "SLURM_PROCID": "1"}
        out = subprocess.run(["bash", str(ROOT / "docker/slurm/launch.sh"), "cfg.yaml", str(run)], env=env,
                             capture_output=True, text=True, check=True)
        return out.stderr + out.stdout

    assert "--ckpt_path" not in launch()
    for name, mtime in (("checkpoints/last.ckpt", 1000), ("hpc_ckpt_1.ckpt", 1001), ("checkpoints/last-v1.ckpt", 1002)):
        (run / name).write_bytes(b"x")
        os.utime(run / name, (mtime, mtime))
    assert f"launch.sh: resuming from {run / 'checkpoints' / 'last-v1.ckpt'}" in launch()
    os.utime(run / "hpc_ckpt_1.ckpt", (1003, 1003))
    assert f"--ckpt_path {run / 'hpc_ckpt_1.ckpt'}" in launch()
