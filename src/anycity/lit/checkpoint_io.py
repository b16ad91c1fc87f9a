"""Checkpoints that survive a crash and execute nothing when read.

``SafeCheckpointIO`` is the Trainer's checkpoint plugin (the CLI installs it by default):

- **save**: the checkpoint is serialised in memory, written to ``<name>.tmp-<pid>`` next to the target,
  flushed and fsynced, then ``os.replace``d over the target (atomic on POSIX) and the directory fsynced.
  A SIGKILL or power loss mid-write leaves the previous checkpoint intact; a full disk (``ENOSPC``) raises
  a one-line ``OSError`` naming the path and the bytes needed, and the partial temp file is removed.
- **load**: ``torch.load(weights_only=True)`` with an allow-list of the few non-tensor types a Lightning
  checkpoint holds, so a checkpoint crafted to run code on unpickling is refused with a one-line
  ``ValueError`` instead of being executed.
"""

from __future__ import annotations

import io
import os
import pickle
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from anycity.atomic import atomic_write_bytes


def _safe_globals() -> list:
    """Types a Lightning/anycity checkpoint legitimately pickles besides tensors and builtins."""
    import collections
    import pathlib

    allowed: list = [collections.defaultdict, collections.OrderedDict, pathlib.PosixPath, pathlib.WindowsPath,
                     pathlib.Path, dict, list, tuple, set, frozenset]
    try:  # LightningCLI stores the parsed config (hyper_parameters) as jsonargparse Namespaces
        from jsonargparse import Namespace

        allowed.append(Namespace)
    except ImportError:  # pragma: no cover
        pass
    try:
        from lightning.fabric.utilities.data import AttributeDict

        allowed.append(AttributeDict)
    except ImportError:  # pragma: no cover
        pass
    return allowed


def safe_torch_load(path: str | os.PathLike, map_location: Any = "cpu") -> Any:
    """``torch.load(path, weights_only=True)`` with the checkpoint allow-list; a file that tries to construct
    anything else (e.g. call ``os.system`` on unpickling) raises a one-line ``ValueError``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        with torch.serialization.safe_globals(_safe_globals()):
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"refusing to load {path}: it holds objects other than tensors and plain data ({first}); "
                         "only load checkpoints from a source you trust, or re-save it as a plain state_dict") from None
    except (RuntimeError, EOFError) as e:  # truncated / not a torch file
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ValueError(f"cannot read checkpoint {path}: {first}; the file is truncated or not a torch "
                         "checkpoint (use the previous checkpoint or rerun)") from None


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

        tmp = Path(path).with_name(f".{Path(path).name}.tmp-{os.getpid()}")
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
        _maybe_die_mid_write(path, buf.getbuffer())
        atomic_write_bytes(path, buf.getbuffer())

    def load_checkpoint(self, path, map_location: Any = lambda storage, loc: storage,
                        weights_only: bool | None = None) -> dict[str, Any]:
        if weights_only is False:
            raise ValueError(f"refusing weights_only=False for {path}: anycity only loads checkpoints as data")
        return safe_torch_load(path, map_location=map_location)

    def remove_checkpoint(self, path) -> None:
        Path(path).unlink(missing_ok=True)
