"""Nothing is overwritten behind the user's back: files an earlier run left where a ``fit|validate|test|predict``
run will write are moved aside to the first free ``<name>.<N><suffix>`` (never deleted).

- before the run: the logger's ``metrics.csv`` / ``hparams.yaml`` and the saved ``config.yaml`` (CSVLogger with
  ``version: ""`` reuses one folder, and Lightning would otherwise truncate them). A ``validate|test|predict`` run
  in a training run's folder writes them to its ``<subcommand>/`` subfolder instead (:func:`separate_from_training`);
- when the run's first batch ends (:class:`KeepPreviousRun`), so that a run which fails before it leaves them
  where they were: a fresh ``fit``'s ``checkpoints/`` folder (a resume with ``--ckpt_path`` keeps and extends it),
  and ``predict``'s export folder (``--export.out_dir`` or ``<log_dir>/predictions``), or only the scene's folder
  in it for a photo folder (so several scenes can be predicted into one ``out_dir``).

Two runs never write one folder at once: each holds a run lock (:class:`RunLocks`) on its log folder, and a
``predict`` also on the export folder it moves aside, from before anything is moved until it ends.
"""

from __future__ import annotations

import os
import re
import socket
import warnings
from pathlib import Path

from lightning.pytorch import Callback
from lightning.pytorch.utilities import rank_zero_info

from anycity.atomic import HAS_FLOCK, free_name, try_flock

LOG_FILES = ("metrics.csv", "hparams.yaml", "config.yaml")
RUN_LOCK = ".anycity-run.lock"  # in a run's log folder; ``.<name>.anycity-run.lock`` beside an export folder


def move_aside(path: Path) -> Path | None:
    """Rename ``path`` (file or non-empty folder) to :func:`free_name`; returns the new path or None."""
    if not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return None
    while True:
        dest = free_name(path)
        try:  # a free name another process took meanwhile is never replaced: the next one is tried
            _rename_no_replace(path, dest)
            break
        except FileExistsError:
            continue
    rank_zero_info(f"anycity: kept the previous run's {path} as {dest}")
    return dest


def _rename_no_replace(path: Path, dest: Path) -> None:
    """Rename ``path`` to ``dest``, raising FileExistsError where ``dest`` exists (``os.rename`` replaces a file,
    and an empty folder): a file is linked then unlinked; a folder renamed over an empty one made here first."""
    if path.is_dir():
        dest.mkdir()  # FileExistsError where it exists; then only this process renames onto it
        try:
            path.rename(dest)
        except OSError:
            dest.rmdir()
            raise
        return
    try:
        os.link(path, dest)
    except FileExistsError:
        raise
    except OSError:  # a filesystem without hard links: check, then rename (the old, racy way)
        if dest.exists():
            raise FileExistsError(dest) from None
        path.rename(dest)
        return
    path.unlink()


PREDICT_OUTPUTS = ("scene.ply", "cameras.json", "chunks.json", "inputs", "renders")  # what an export writes


def holds_predict_output(path: Path) -> bool:
    """Whether ``path`` is what ``anycity predict`` exports: a scene folder, or a folder of scene folders."""
    folders = [path, *(c for c in path.iterdir() if c.is_dir())]
    return any((d / name).exists() for d in folders for name in PREDICT_OUTPUTS)


def keep_previous_run(trainer, subcommand: str, ckpt_path=None, export_root: Path | None = None,
                      scene: str | None = None) -> list[Path]:
    """Move aside the log files an earlier run left where ``subcommand`` will write (now: Lightning writes them
    at setup) and attach a :class:`KeepPreviousRun` for its checkpoints or exports; returns the paths moved now.
    ``export_root``: where a ``predict`` exports (``PredictionExport.root``); ``scene``: the one scene it writes (a
    photo folder's name), when known."""
    # Lightning's CSVLogger then warns that "previous log files in this directory will be deleted": the files it
    # would overwrite are moved aside here, so that warning could only alarm
    warnings.filterwarnings("ignore", message=r"Experiment logs directory .* exists and is not empty")
    # a fresh fit's ModelCheckpoint sees the earlier run's checkpoints until its first step moves them aside
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
    keep = None
    if trainer.fast_dev_run:
        # Lightning says that fast_dev_run suppresses checkpointing, but (2.6.6) ModelCheckpoint(save_last=True)
        # still writes one at the end of training, beside the earlier run's last.ckpt (as last-v1.ckpt)
        for cb in trainer.checkpoint_callbacks:
            cb.save_last = None
    if subcommand == "fit" and ckpt_path is None and not trainer.fast_dev_run:
        keep = KeepPreviousRun(_checkpoint_dirs(trainer), checkpoints=True)
    if subcommand == "predict" and export_root is not None:
        keep = KeepPreviousRun([export_root / scene if scene else export_root], checkpoints=False)
    if keep is not None:  # first in the list: its hooks run before ModelCheckpoint's and the export's
        trainer.callbacks.insert(0, keep)
    if trainer.fast_dev_run:  # its DummyLogger writes no log file (log_dir None: the fallback is a training's own)
        return []
    log_dir = Path(trainer.log_dir or trainer.default_root_dir)  # where Lightning writes them; every rank asks
    if trainer.global_rank != 0:
        return []
    moved = [move_aside(log_dir / name) for name in LOG_FILES]
    return [m for m in moved if m is not None]


def separate_from_training(trainer, subcommand: str) -> Path | None:
    """Point a ``validate``/``test``/``predict`` run whose log folder is a training run's (:func:`is_training_folder`)
    at that folder's ``<subcommand>/`` subfolder, so that its ``config.yaml``, ``metrics.csv``,
    previews and default ``predictions/`` leave the training's own files where they are. Returns the new log folder,
    or None (other subcommands and folders; loggers other than CSV and TensorBoard, whose folder is not
    ``<root>/<version>``)."""
    from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger

    lg = trainer.logger
    if subcommand == "fit" or not isinstance(lg, (CSVLogger, TensorBoardLogger)):
        return None
    if not is_training_folder(Path(lg.log_dir)):
        return None
    # read by log_dir; the logger writes nothing before the run
    lg._version = str(Path(_version_folder(lg)) / subcommand)
    return Path(lg.log_dir)


def is_training_folder(folder: Path) -> bool:
    """Whether ``folder`` is a training run's: it holds ``checkpoints/*.ckpt``, an earlier fit's
    ``checkpoints.<N>/*.ckpt`` (a fresh fit moves them there before it writes its first), or the run lock of a
    ``fit`` (running, or killed)."""
    if any(folder.glob("checkpoints/*.ckpt")):
        return True
    if any(re.fullmatch(r"checkpoints\.\d+", d.name) and any(d.glob("*.ckpt")) for d in folder.glob("checkpoints.*")):
        return True
    return _lock_holder(folder / RUN_LOCK).startswith("fit ")


def _version_folder(logger) -> str:
    """A logger's version as the folder Lightning names after it (``version_3``, or a string version as it is)."""
    return logger.version if isinstance(logger.version, str) else f"version_{logger.version}"


def _checkpoint_dirs(trainer) -> list[Path]:
    """Where the trainer's checkpoint callbacks write."""
    dirs = []
    for cb in trainer.checkpoint_callbacks:
        ckpt_dir = Path(cb.dirpath) if cb.dirpath else None
        if ckpt_dir is None and trainer.loggers:
            lg = trainer.loggers[0]
            ckpt_dir = Path(lg.save_dir or trainer.default_root_dir) / str(lg.name or "") / _version_folder(lg) / \
                "checkpoints"
        dirs.append(ckpt_dir or Path(trainer.default_root_dir) / "checkpoints")
    return dirs


class KeepPreviousRun(Callback):
    """Moves aside an earlier run's checkpoints (a fresh ``fit``) or export (``predict``) when this run's first batch
    ends, before anything of this run is written there. A run that stops earlier (a config or data error, a photo
    that does not decode, Ctrl-C at start-up) or writes no checkpoint (``fast_dev_run``) leaves them in place, so
    ``last.ckpt`` and the exported scene stay where the user left them. Under DDP the move happens when the loop
    starts, behind a barrier: rank 1 could otherwise export a sample before rank 0's first batch ends, into the
    folder rank 0 then moves aside.

    Args:
        paths: the folders to move aside.
        checkpoints: move a folder only when it holds ``*.ckpt`` files (else: when it is not empty).
    """

    def __init__(self, paths: list[Path], checkpoints: bool) -> None:
        self.paths = list(paths)
        self.checkpoints = checkpoints
        self.moved: list[Path] = []

    def _keep(self, trainer) -> None:
        if self.paths and trainer.global_rank == 0:
            for path in self.paths:
                if self.checkpoints and not (path.is_dir() and any(path.glob("*.ckpt"))):
                    continue
                dest = move_aside(path)
                if dest is not None:
                    self.moved.append(dest)
        self.paths = []

    def _at_start(self, trainer) -> None:
        if not self.checkpoints:  # an export folder: only an earlier export is moved aside, never other files
            for path in self.paths:
                if path.is_dir() and any(path.iterdir()) and not holds_predict_output(path):
                    raise ValueError(f"--export.out_dir: {path} holds files `anycity predict` did not write (it "
                                     "moves aside only its own earlier exports); pass another --export.out_dir")
        if trainer.world_size > 1:  # another rank may write before this one's first batch ends: all wait for the move
            self._keep(trainer)
            trainer.strategy.barrier("anycity-keep-previous-run")

    def on_train_start(self, trainer, *args, **kwargs) -> None:
        self._at_start(trainer)

    def on_predict_start(self, trainer, *args, **kwargs) -> None:
        self._at_start(trainer)

    def on_train_batch_end(self, trainer, *args, **kwargs) -> None:
        self._keep(trainer)

    def on_predict_batch_end(self, trainer, *args, **kwargs) -> None:
        self._keep(trainer)


class RunLocks:
    """Exclusive ``flock`` run locks, held until :meth:`release` (or the process's end: a killed run's lock needs no
    clean-up). Each lock file holds ``<subcommand> (pid N on host)`` for the other run's message and is removed
    when released. Not taken where the OS or the filesystem has no ``flock`` (the folders are then not guarded).

    Args:
        subcommand: this run's, e.g. ``fit``.
        enabled: false on every DDP rank but global rank 0, which alone writes the logs, checkpoints and moves.
    """

    def __init__(self, subcommand: str, enabled: bool = True) -> None:
        self.subcommand, self.enabled = subcommand, enabled
        self.held: list[tuple[int, Path, Path | None]] = []  # descriptor, lock file, topmost folder made for it

    def take(self, folder: Path, option: str, beside: bool = False) -> None:
        """Lock ``folder`` (made if missing): by ``<folder>/.anycity-run.lock``, or with ``beside`` (a folder that
        is moved aside) by ``.<name>.anycity-run.lock`` in its parent. ``option`` names the fix in the refusal.

        Raises:
            ValueError: another process holds it (one line: the folder, that run and the fix).
        """
        if not self.enabled or not HAS_FLOCK:
            return
        folder = Path(folder).absolute()
        lock = folder.parent / f".{folder.name}{RUN_LOCK}" if beside else folder / RUN_LOCK
        made = next((p for p in reversed([lock.parent, *lock.parent.parents]) if not p.exists()), None)
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = _flock(lock)
        if fd is False:
            holder = _lock_holder(lock) or "run"
            self._remove_made(lock.parent, made)
            raise ValueError(f"{folder}: another anycity {holder} is writing there; wait for it to end, or pass "
                             f"another {option}")
        if fd is not None:
            os.ftruncate(fd, 0)
            os.write(fd, f"{self.subcommand} (pid {os.getpid()} on {socket.gethostname()})\n".encode())
            self.held.append((fd, lock, made))

    def release(self) -> None:
        """Remove and unlock every lock taken (and the empty folders made for them), newest first."""
        while self.held:
            fd, lock, made = self.held.pop()
            try:
                if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                    lock.unlink()
            except OSError:
                pass
            os.close(fd)
            self._remove_made(lock.parent, made)

    @staticmethod
    def _remove_made(folder: Path, made: Path | None) -> None:
        """Remove ``folder`` and its parents up to ``made`` where this run made them and left them empty."""
        if made is None:
            return
        for p in (folder, *folder.parents):
            try:
                p.rmdir()
            except OSError:
                return
            if p == made:
                return


def _flock(lock: Path) -> int | None | bool:
    """An exclusive ``flock`` on the file ``lock`` (created): its descriptor, False where another process holds
    it, None where the filesystem has no ``flock``."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        taken = try_flock(fd)
        if not taken:  # another process holds it (False), or no flock here (None)
            os.close(fd)
            return taken
        try:  # the holder before removed the file as it released it: lock the file now at that path
            if os.fstat(fd).st_ino == os.stat(lock).st_ino:
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


def _lock_holder(lock: Path) -> str:
    """The run a lock file names (``fit (pid N on host)``), or "" (no file, or not written yet)."""
    try:
        return lock.read_text(errors="replace").strip()
    except OSError:
        return ""
