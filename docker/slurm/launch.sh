#!/usr/bin/env bash
# One SLURM task of an anycity training job (srun starts one per GPU): enter the container, then `anycity fit`,
# resuming when the run directory holds a checkpoint. Lightning's SLURMEnvironment reads SLURM_PROCID,
# SLURM_LOCALID, SLURM_NODEID, SLURM_NTASKS and SLURM_NODELIST itself: nothing here computes ranks.
#   usage (from an sbatch script): srun docker/slurm/launch.sh CONFIG RUN_DIR [more anycity fit arguments]
# Environment:
#   CONTAINER  the command that enters the image, prepended to `anycity`; empty = the current environment. E.g.
#              "apptainer exec --nv --bind data:/work/data:ro,weights:/work/weights:ro,runs:/work/runs --pwd /work
#               anycity.sif" or, with enroot/pyxis, put --container-image=... on the srun line and leave this empty.
#   ANYCITY    the command (default: anycity).
# Resume order: Lightning's own preemption checkpoint (hpc_ckpt_*.ckpt, written on SIGUSR1 before it requeues the
# job; Lightning restores it by itself), else RUN_DIR/checkpoints/last.ckpt, else a fresh start.
set -euo pipefail
config=$1 run_dir=$2
shift 2
resume=()
if compgen -G "${run_dir}/hpc_ckpt_*.ckpt" >/dev/null; then
    echo "launch.sh: Lightning resumes from its preemption checkpoint in ${run_dir}" >&2
elif [[ -f "${run_dir}/checkpoints/last.ckpt" ]]; then
    resume=(--ckpt_path "${run_dir}/checkpoints/last.ckpt")
    echo "launch.sh: resuming from ${run_dir}/checkpoints/last.ckpt" >&2
fi
# shellcheck disable=SC2086  # CONTAINER and ANYCITY are command prefixes: word splitting intended
exec ${CONTAINER:-} ${ANYCITY:-anycity} fit -c "${config}" \
    --trainer.num_nodes "${SLURM_NNODES:-1}" --trainer.devices "${SLURM_NTASKS_PER_NODE:-1}" \
    --trainer.default_root_dir "${run_dir}" \
    --trainer.logger lightning.pytorch.loggers.CSVLogger --trainer.logger.init_args.save_dir "${run_dir}" \
    --trainer.logger.init_args.name "" --trainer.logger.init_args.version "" \
    "${resume[@]}" "$@"
