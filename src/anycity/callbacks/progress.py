"""Progress display that shows the loss terms: tqdm bars on a terminal, plain periodic lines otherwise."""

from __future__ import annotations

import sys
import time
from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import TQDMProgressBar


def _short(name: str) -> str:
    return name.split("/", 1)[1] if name.startswith("train/") else name


class LossProgressBar(TQDMProgressBar):
    """TQDM bar whose postfix lists the ``prog_bar`` loss terms with short names (``train/rgb`` -> ``rgb``).

    When stdout is not a terminal (``make``, CI, log files) the bars are replaced by one line every
    ``print_every`` optimiser steps: step, epoch, loss terms and elapsed time, and one for the last step when the
    run ends. Only global rank 0 prints (as the bars show only there), once per optimiser step however many batches
    it accumulates.

    Args:
        refresh_rate: tqdm refresh rate in batches.
        print_every: steps between plain lines in non-interactive mode.
        force_plain: always use plain lines.
    """

    def __init__(self, refresh_rate: int = 1, print_every: int = 10, force_plain: bool = False) -> None:
        super().__init__(refresh_rate=refresh_rate)
        self.print_every = max(1, print_every)
        self.plain = force_plain or not sys.stdout.isatty()
        self._t0 = time.monotonic()
        self._printed = -1  # the optimiser step of the last plain line
        self._epoch = 0  # the epoch of the last training batch
        if self.plain:
            self.disable()

    def get_metrics(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)
        return {_short(k): v for k, v in metrics.items()}

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._t0 = time.monotonic()
        self._printed = trainer.global_step  # no line before the first step (nor the resumed one's again)
        super().on_train_start(trainer, pl_module)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        if not self.plain:
            return super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)
        step, self._epoch = trainer.global_step, trainer.current_epoch
        if not trainer.is_global_zero or step == self._printed:  # other ranks; an accumulating batch
            return
        if step % self.print_every == 0 or step == trainer.max_steps:
            self._print_line(trainer, pl_module, self._epoch)

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        super().on_train_end(trainer, pl_module)
        # the last step is a multiple of print_every only by chance when max_epochs, not max_steps, ends the run
        if self.plain and trainer.is_global_zero and trainer.global_step != self._printed:
            self._print_line(trainer, pl_module, self._epoch)  # the last step's epoch: current_epoch moved past it

    def _print_line(self, trainer: pl.Trainer, pl_module: pl.LightningModule, epoch: int) -> None:
        """One plain line for optimiser step ``trainer.global_step`` of ``epoch``: loss terms, elapsed time."""
        step = self._printed = trainer.global_step
        terms = " ".join(f"{k}={float(v):.4g}" if isinstance(v, (int, float)) else f"{k}={v}"
                         for k, v in self.get_metrics(trainer, pl_module).items())
        total = trainer.max_steps if trainer.max_steps and trainer.max_steps > 0 else "?"
        print(f"[{type(pl_module).__name__}] step {step}/{total} epoch {epoch} {terms} "
              f"({time.monotonic() - self._t0:.0f}s)", flush=True)
