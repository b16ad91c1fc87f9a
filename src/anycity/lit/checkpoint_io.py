"""Checkpoints that survive a crash and execute nothing when read.

``SafeCheckpointIO`` is the Trainer's checkpoint plugin (the CLI installs it by default):

- **save**: the checkpoint is serialised in memory, written to ``.anycity-tmp-<pid>-<16 hex digits>`` next to the
  target (:func:`anycity.atomic.temp_name`: never named after the target, so a leftover one cannot pass for an
  ``hpc_ckpt_<n>.ckpt`` in Lightning's HPC-resume scan), flushed and fsynced, given the mode of the file it
  replaces, then ``os.replace``d over the target (atomic on POSIX) and the directory fsynced. A SIGKILL or power
  loss mid-write leaves the previous checkpoint intact (and the temp file, which
  :func:`anycity.atomic.remove_stale_temp_files` removes); a full disk (``ENOSPC``) raises a one-line ``OSError``
  naming the path and the bytes needed, and the partial temp file is removed.
- **load**: :func:`anycity.safe_load.safe_torch_load`, ``torch.load(weights_only=True)`` with an allow-list of
  the few non-tensor types a Lightning checkpoint holds, so a checkpoint crafted to run code on unpickling is
  refused with a one-line ``ValueError`` instead of being executed.
- **check** (:func:`check_checkpoint_state`, from the modules' ``on_load_checkpoint``): a checkpoint whose weights
  do not fit the module (a renamed or missing key, another shape, a non-tensor value, a NaN) is refused in one line
  naming the file, instead of Lightning's many-line ``Error(s) in loading state_dict``.
- **remove**: a file, or a folder checkpoint (FSDP's sharded state dict) with what it holds, as Lightning's own; a
  symlink itself, never what it points to.
"""

from __future__ import annotations

import io
import os
import shutil
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from anycity.atomic import atomic_write_bytes, temp_name
from anycity.safe_load import safe_torch_load

__all__ = ["SafeCheckpointIO", "atomic_write_bytes", "checkpoint_source", "checkpoint_state",
           "check_checkpoint_state", "safe_torch_load"]

STAGES = {"ScaffoldModule": "Stage I", "RefinementModule": "Stage II"}


def checkpoint_source(module) -> str:
    """How messages name the checkpoint ``module`` is being restored from: ``--ckpt_path PATH`` under a Trainer
    (which sets its ``ckpt_path`` before ``on_load_checkpoint``), else ``checkpoint`` (``load_from_checkpoint``)."""
    path = getattr(getattr(module, "_trainer", None), "ckpt_path", None)
    return f"--ckpt_path {path}" if path else "checkpoint"


def checkpoint_state(checkpoint: dict, source: str = "checkpoint") -> dict:
    """``checkpoint["state_dict"]``, checked to be named tensors; one line starting with ``source`` otherwise. Run
    it before any hook reads the weights (e.g. the pose prior's rebuild reads their shapes)."""
    from anycity.models.pretrained import first_non_tensor

    sd = checkpoint.get("state_dict") if isinstance(checkpoint, dict) else None
    if not isinstance(sd, dict):
        raise ValueError(f"{source}: holds no state_dict of weights (a {type(sd).__name__}); the file is damaged or "
                         "not a checkpoint an anycity fit wrote")
    if (bad := first_non_tensor(sd)) is not None:
        raise ValueError(f"{source}: its state_dict holds a {bad[1]} under the key {bad[0]!r}, not a tensor; the file "
                         "is damaged: pass a checkpoint that an anycity fit wrote")
    return sd


def _class_hint(module, checkpoint: dict, source: str) -> str:
    """The fix for a checkpoint that does not fit ``module``: the other stage's checkpoint, or another config."""
    hp = checkpoint.get("hyper_parameters")
    theirs = str(hp.get("_class_path", "")).rpartition(".")[2] if isinstance(hp, dict) else ""
    ours = type(module).__name__
    path = source.removeprefix("--ckpt_path ") if source.startswith("--ckpt_path ") else "<that file>"
    if theirs == "ScaffoldModule" and ours == "RefinementModule":
        return (f"it is a Stage I (ScaffoldModule) checkpoint: start Stage II from it with "
                f"--model.init_args.init_from {path}, without --ckpt_path")
    if theirs and theirs != ours and (theirs in STAGES or ours in STAGES):
        return (f"it is a {STAGES.get(theirs, theirs)} ({theirs}) checkpoint, this is {STAGES.get(ours, ours)} "
                f"({ours}): run it with the config of the run that wrote it")
    return ("it was written for another network (model.preset / model.net) or by another anycity version: run it "
            "with the config of the run that wrote it, and the anycity version that wrote it")


def check_checkpoint_state(module, checkpoint: dict, finite_keys=None) -> None:
    """Refuse, in one line naming the file, a checkpoint whose ``state_dict`` would not load into ``module``: a
    non-tensor value, a missing or unexpected key (unless ``module.strict_loading`` is off), another shape, or a
    floating tensor with a NaN/Inf (among ``finite_keys``, all when None: one ``isfinite().all()`` per tensor). Keys
    and shapes are not compared under a strategy that restores into a sharded model (FSDP, DeepSpeed). Call it last
    in ``on_load_checkpoint``, once the hook has put back or dropped what it manages."""
    from anycity.models.pretrained import first_nonfinite, weight_problems

    source = checkpoint_source(module)
    sd = checkpoint_state(checkpoint, source)
    strategy = getattr(getattr(module, "_trainer", None), "strategy", None)
    # FSDP/DeepSpeed restore into the sharded model, whose state_dict() would gather every weight on every rank: their
    # own load names the keys
    sharded = bool(getattr(strategy, "restore_checkpoint_after_setup", False))
    problems = [] if sharded else weight_problems(module.state_dict(), sd,
                                                  strict=bool(getattr(module, "strict_loading", True)))
    if problems:
        raise ValueError(f"{source} does not fit this {type(module).__name__}: {'; '.join(problems)}; "
                         f"{_class_hint(module, checkpoint, source)}")
    keys = sd if finite_keys is None else [k for k in finite_keys if k in sd]
    if (bad := first_nonfinite((k, sd[k]) for k in keys)) is not None:
        raise ValueError(f"{source} holds non-finite values (NaN or Inf) in {bad}; the run diverged before it was "
                         "saved, or the file is damaged: use an earlier checkpoint")


_saves = 0


def _maybe_die_mid_write(path, data) -> None:
    """Fault injection for tests/reliability: ``ANYCITY_FAULT_KILL_IN_SAVE=k`` SIGKILLs this process half-way
    through writing the temp file of its k-th checkpoint save (exactly what a preemption mid-write leaves)."""
    global _saves
    k = os.environ.get("ANYCITY_FAULT_KILL_IN_SAVE")
    if not k:
        return
    _saves += 1
    if _saves == int(k):
        import signal

        tmp = temp_name(Path(path).parent)  # a temp name as atomic_write_bytes writes it
        with open(tmp, "wb") as f:
            f.write(data[: len(data) // 2])
            f.flush()
            os.fsync(f.fileno())
        os.kill(os.getpid(), signal.SIGKILL)


class SafeCheckpointIO(TorchCheckpointIO):
    """Atomic, fsynced checkpoint writes and ``weights_only`` reads (see the module docstring)."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"storage_options is not supported by {type(self).__name__}")
        buf = io.BytesIO()
        torch.save(checkpoint, buf)
        with buf.getbuffer() as view:  # released even on an error: a view alive when buf is freed is a BufferError
            _maybe_die_mid_write(path, view)
            atomic_write_bytes(path, view)

    def load_checkpoint(self, path, map_location: Any = lambda storage, loc: storage,
                        weights_only: bool | None = None) -> dict[str, Any]:
        if weights_only is False:
            raise ValueError(f"refusing weights_only=False for {path}: anycity only loads checkpoints as data")
        return safe_torch_load(path, map_location=map_location)

    def remove_checkpoint(self, path) -> None:
        """Remove a checkpoint file, or a folder one (FSDP's sharded state dict) with what it holds, as Lightning's
        own does. A symlink (``save_last="link"``) is removed itself, never what it points to."""
        path = Path(path)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)  # never follows a symlink inside the folder either
        else:
            path.unlink(missing_ok=True)
