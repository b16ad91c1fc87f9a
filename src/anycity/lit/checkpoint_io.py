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

__all__ = ["SafeCheckpointIO", "atomic_write_bytes", "safe_torch_load"]


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
