#!/usr/bin/env bash
# The batch shell of stage1.sbatch / stage2.sbatch (on the host, outside the container): starts one srun step of
# launch.sh tasks, and requeues the job when SLURM signals that the time limit is near.
#   usage: docker/slurm/job.sh CONFIG DEFAULT_RUN_DIR [more anycity fit arguments]
# RUN_DIR (environment) names the run folder. Unset, it is runs/ablations/<name> when the arguments name
# configs/ablations/<name>.yaml (so an ablation never shares the main run's folder), else DEFAULT_RUN_DIR.
#
# Requeue: the sbatch scripts ask for --signal=B:USR1@180, which SLURM sends to this shell alone. The trap forwards
# SIGUSR1 to the step (srun passes it to every task; at the end of its current step anycity.callbacks.requeue
# saves RUN_DIR/hpc_ckpt_N.ckpt with Lightning's SLURMEnvironment code), waits until that file is complete (checkpoints are written to a temporary name and
# renamed), then runs `scontrol requeue` here: inside the image there is no SLURM client, so Lightning's own requeue
# call fails there ("Requeuing SLURM job ... failed with error code 127", expected).
set -euo pipefail
config=$1 run_dir=${RUN_DIR:-$2}
shift 2
if [[ -z "${RUN_DIR:-}" ]]; then
    for arg in "$@"; do
        if [[ "${arg}" == *configs/ablations/*.yaml ]]; then run_dir=runs/ablations/$(basename "${arg}" .yaml); fi
    done
fi
mkdir -p "${run_dir}" runs/.cache   # runs/.cache: the image's /cache (apptainer images are read-only)
# Slurm >= 22.05: srun does not inherit --cpus-per-task from the allocation; each task runs DataLoader workers
if [[ -n "${SLURM_CPUS_PER_TASK:-}" ]]; then export SRUN_CPUS_PER_TASK=${SLURM_CPUS_PER_TASK}; fi
echo "job.sh: run folder ${run_dir}" >&2

newest_hpc() {  # the largest N of RUN_DIR/hpc_ckpt_N.ckpt, or nothing
    local f n=""
    for f in "${run_dir}"/hpc_ckpt_*.ckpt; do
        [[ -e "${f}" ]] || continue
        f=${f##*hpc_ckpt_}; f=${f%.ckpt}
        if [[ "${f}" =~ ^[0-9]+$ ]] && { [[ -z "${n}" ]] || (( f > n )); }; then n=${f}; fi
    done
    echo "${n}"
}

requeue() {
    local before after job=${SLURM_JOB_ID:?}
    [[ -n "${SLURM_ARRAY_JOB_ID:-}" ]] && job="${SLURM_ARRAY_JOB_ID}_${SLURM_ARRAY_TASK_ID}"
    before=$(newest_hpc)
    echo "job.sh: time limit near: the run saves ${run_dir}/hpc_ckpt_N.ckpt at the end of its step, then the job is requeued" >&2
    kill -USR1 "${step}" 2>/dev/null || true
    for _ in $(seq 170); do
        after=$(newest_hpc)
        [[ -n "${after}" && "${after}" != "${before}" ]] && break
        sleep 1
    done
    if [[ -z "${after}" || "${after}" == "${before}" ]]; then
        echo "job.sh: no new preemption checkpoint after 170 s; requeueing anyway (the run resumes from the newest)" >&2
    fi
    scontrol requeue "${job}" || echo "job.sh: scontrol requeue ${job} failed (already requeued?)" >&2
}

srun --kill-on-bad-exit=1 "$(dirname "$0")/launch.sh" "${config}" "${run_dir}" "$@" &
step=$!
trap requeue USR1
while true; do  # a trapped signal interrupts `wait`; wait again until the step itself has ended
    rc=0
    wait "${step}" || rc=$?
    kill -0 "${step}" 2>/dev/null || exit "${rc}"
done
