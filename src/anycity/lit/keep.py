"""Nothing is overwritten behind the user's back: before a ``fit|validate|test|predict`` run, files an earlier
run left where this one will write are moved aside to the first free ``<name>.<N><suffix>`` (never deleted).

- the logger's ``metrics.csv`` / ``hparams.yaml`` and the saved ``config.yaml`` (CSVLogger with ``version: ""``
  reuses one folder, and Lightning would otherwise truncate them);
- a fresh ``fit``'s ``checkpoints/`` folder (a resume with ``--ckpt_path`` keeps and extends it);
- ``predict``'s export folder (``--export.out_dir`` or ``<log_dir>/predictions``), or only the scene's folder in
  it for a photo folder (so several scenes can be predicted into one ``out_dir``).
"""

from __future__ import annotations

import warnings
from pathlib import Path

from lightning.pytorch.utilities import rank_zero_info

from anycity.atomic import free_name

LOG_FILES = ("metrics.csv", "hparams.yaml", "config.yaml")


def move_aside(path: Path) -> Path | None:
    """Rename ``path`` (file or non-empty folder) to :func:`free_name`; returns the new path or None."""
    if not path.exists() or (path.is_dir() and not any(path.iterdir())):
        return None
    dest = free_name(path)
    path.rename(dest)
    rank_zero_info(f"anycity: kept the previous run's {path} as {dest}")
    return dest


def keep_previous_run(trainer, subcommand: str, ckpt_path=None, export_dir: str | None = None,
                      scene: str | None = None) -> list[Path]:
    """Move aside what an earlier run left where ``subcommand`` will write; returns the moved paths. ``scene``:
    the one scene a ``predict`` writes (a photo folder's name), when known."""
    # Lightning's CSVLogger then warns that "previous log files in this directory will be deleted": the files it
    # would overwrite are moved aside here, so that warning could only alarm
    warnings.filterwarnings("ignore", message=r"Experiment logs directory .* exists and is not empty")
    if trainer.global_rank != 0:
        return []
    moved = []
    dirs = {Path(trainer.default_root_dir)}
    if trainer.logger is not None and getattr(trainer.logger, "log_dir", None):
        dirs.add(Path(trainer.logger.log_dir))
    for d in dirs:
        for name in LOG_FILES:
            moved.append(move_aside(d / name))
    if subcommand == "fit" and ckpt_path is None:
        for cb in trainer.checkpoint_callbacks:
            ckpt_dir = Path(cb.dirpath) if cb.dirpath else None
            if ckpt_dir is None and trainer.loggers:
                lg = trainer.loggers[0]
                ckpt_dir = Path(lg.save_dir or trainer.default_root_dir) / str(lg.name or "") / (
                    lg.version if isinstance(lg.version, str) else f"version_{lg.version}") / "checkpoints"
            ckpt_dir = ckpt_dir or Path(trainer.default_root_dir) / "checkpoints"
            if ckpt_dir.is_dir() and any(ckpt_dir.glob("*.ckpt")):
                moved.append(move_aside(ckpt_dir))
    if subcommand == "predict":
        out = Path(export_dir) if export_dir else Path(trainer.log_dir or trainer.default_root_dir) / "predictions"
        moved.append(move_aside(out / scene if scene else out))
    return [m for m in moved if m is not None]
