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
# Resume: from the newest (by modification time) of Lightning's preemption checkpoints (RUN_DIR/hpc_ckpt_N.ckpt,
# saved on SIGUSR1, see job.sh) and RUN_DIR/checkpoints/last.ckpt, named explicitly with --ckpt_path (so the run is
# a resume: its checkpoints/ folder is kept and extended); else a fresh start. Task 0 then deletes the preemption
# checkpoints older than the one resumed from (each holds the whole optimiser state: 14 GB in Stage I).
# Arguments given to this script come before its own options: RUN_DIR, not a config's default_root_dir, names the
# run folder.
set -euo pipefail
config=$1 run_dir=$2
shift 2
resume=()
if [[ "${SLURM_PROCID:-0}" == 0 ]]; then  # temp files a killed save left (anycity.atomic); no task writes yet
    find "${run_dir}" "${run_dir}/checkpoints" -maxdepth 1 -type f -name '.anycity-tmp-*' -print -delete 2>/dev/null \
        | sed 's/^/launch.sh: deleted the unfinished save /' >&2 || true
fi
newest=$(ls -1t "${run_dir}"/hpc_ckpt_*.ckpt "${run_dir}"/checkpoints/last.ckpt "${run_dir}"/checkpoints/last-v*.ckpt \
    2>/dev/null | head -n 1 || true)  # last-vN.ckpt: an older anycity's resume of a moved run versioned its last
if [[ -n "${newest}" ]]; then
    resume=(--ckpt_path "${newest}")
    echo "launch.sh: resuming from ${newest}" >&2
    if [[ "${SLURM_PROCID:-0}" == 0 ]]; then
        for old in "${run_dir}"/hpc_ckpt_*.ckpt; do
            if [[ -e "${old}" && "${old}" != "${newest}" && "${old}" -ot "${newest}" ]]; then
                echo "launch.sh: deleting the older preemption checkpoint ${old}" >&2
                rm -f -- "${old}"
            fi
        done
    fi
fi
# shellcheck disable=SC2086  # CONTAINER and ANYCITY are command prefixes: word splitting intended
exec ${CONTAINER:-} ${ANYCITY:-anycity} fit -c "${config}" "$@" \
    --trainer.num_nodes "${SLURM_NNODES:-1}" --trainer.devices "${SLURM_NTASKS_PER_NODE:-1}" \
    --trainer.default_root_dir "${run_dir}" \
    --trainer.logger lightning.pytorch.loggers.CSVLogger --trainer.logger.init_args.save_dir "${run_dir}" \
    --trainer.logger.init_args.name "" --trainer.logger.init_args.version "" \
    ${resume[@]+"${resume[@]}"}
