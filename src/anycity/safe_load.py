"""Reading torch files a user hands us (checkpoints, pretrained weights, a pose prior) as data only.

``torch.load(weights_only=True)`` with an allow-list of the few non-tensor types a Lightning checkpoint holds: a
file crafted to run code on unpickling is refused, and a truncated or foreign file is reported, each in one line
that names the file. Lightning-free, so ``models/`` reads its weight files the same way ``lit/`` reads checkpoints.
"""

from __future__ import annotations

import errno
import os
import pickle
from pathlib import Path
from typing import Any

import torch


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


def user_path(path: str | os.PathLike) -> Path:
    """A path the user typed, ``~`` expanded (a shell leaves ``--x ~/w.pt`` alone after ``=`` and in YAML)."""
    return Path(os.path.expanduser(os.fspath(path)))


def missing_reason(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be opened as a file or folder, as the end of a sentence naming it: ``"is a symlink loop"``,
    ``"is a broken symlink (to X)"`` or ``"not found"``; None when it exists."""
    try:
        os.stat(path)
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a symlink loop (a link that points back to itself); point it at the real file"
        if os.path.islink(path):
            return f"is a broken symlink (to {os.readlink(path)})"
        return "not found"
    except ValueError:  # an embedded NUL byte
        return "not found"
    return None


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    lines = [ln for ln in text.splitlines() if "GLOBAL" in ln or ln.strip().startswith("Unsupported")]
    return (lines[0] if lines else text.splitlines()[0]).strip() if text else type(e).__name__


def safe_torch_load(path: str | os.PathLike, map_location: Any = "cpu", *, mmap: bool = False,
                    what: str = "checkpoint") -> Any:
    """``torch.load(path, weights_only=True)`` with the checkpoint allow-list (``mmap``: memory-mapped when the
    file allows it, so a 5 GB file stays out of RAM). A file that tries to construct anything else (e.g. call
    ``os.system`` on unpickling) raises a one-line ``ValueError``, as does one that is truncated or not a torch
    file; a missing path, a symlink loop, or a folder, ``FileNotFoundError``. ``~`` in ``path`` is expanded.
    ``what`` names the file in the messages (e.g. ``"net.pose_prior"``)."""
    path = user_path(path)
    if path.is_dir():  # e.g. a sharded (FSDP/DeepSpeed) checkpoint folder; FileNotFoundError, as callers catch that
        raise FileNotFoundError(f"{what} {path} is a folder; pass the checkpoint file")
    if not path.is_file():
        why = missing_reason(path)
        raise FileNotFoundError(f"{what} not found: {path}" if why in (None, "not found") else f"{what} {path} {why}")

    def unreadable(e: BaseException) -> ValueError:
        return ValueError(f"cannot read {what} {path}: {_first_line(e)}; the file is truncated or not a torch file "
                          "(use the previous one or rerun)")

    try:
        with torch.serialization.safe_globals(_safe_globals()):
            if mmap:
                try:
                    return torch.load(path, map_location=map_location, weights_only=True, mmap=True)
                except RuntimeError as e:  # a legacy (non-zip) file cannot be mapped
                    if "mmap" not in str(e):
                        raise
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        if "GLOBAL" not in str(e):  # no object construction asked for: garbage, not a payload
            raise unreadable(e) from None
        raise ValueError(f"refusing to load {what} {path}: it holds objects other than tensors and plain data "
                         f"({_first_line(e)}); only load files from a source you trust, or re-save it as a plain "
                         "state_dict") from None
    except (FileNotFoundError, PermissionError, IsADirectoryError):  # the caller's one-line handling of these
        raise
    # truncated / not a torch file: a zip cut short raises OSError (EINVAL) or RuntimeError, text read as a legacy
    # pickle (an HTTP error page saved as the file) KeyError, IndexError or ValueError
    except (RuntimeError, EOFError, OSError, KeyError, IndexError, ValueError) as e:
        raise unreadable(e) from None
