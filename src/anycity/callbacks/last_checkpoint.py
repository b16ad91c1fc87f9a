"""``last.ckpt`` holds the step a finished fit ended at, and a resumed fit's newest step.

Lightning (2.6) writes ``last.ckpt`` at the end of training only when its ``ModelCheckpoint`` saved nothing during
the run. So a ``max_steps`` that is not a multiple of ``every_n_train_steps`` left ``last.ckpt`` at the last
multiple (a 1500-step quickstart Stage I: step 1000), and whatever read it next (Stage II's ``init_from``, ``test``,
``--ckpt_path last``) silently took the older weights. The CLI adds :class:`FinalLastCheckpoint` to every run.
"""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback, ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_warn

# The ModelCheckpoint internals this callback calls (Lightning >= 2.6): the skip test of its own saves (fast_dev_run,
# not fitting, already saved at this step), the metrics that format its file name, and its save of ``last``.
# tests/integration/test_cli_tiny.py checks that they are still there.
PRIVATE_API = ("_should_skip_saving_checkpoint", "_monitor_candidates", "_save_last_checkpoint")


def missing_private_api() -> list[str]:
    """The names of :data:`PRIVATE_API` that this Lightning's ``ModelCheckpoint`` lacks (empty: all there)."""
    return [name for name in PRIVATE_API if not callable(getattr(ModelCheckpoint, name, None))]


class FinalLastCheckpoint(Callback):
    """When a fit ends, every ``ModelCheckpoint`` with ``save_last`` that did not save at the final step writes its
    ``last`` checkpoint for that step (``save_last="link"`` with top-k files links to the newest of them, as
    Lightning does).

    It runs on every rank: ``trainer.save_checkpoint`` is collective under DDP, and whether to save depends only on
    the global step, the same on every rank. Lightning calls ``on_train_end`` only when the training loop ends by
    itself (``max_steps``, ``max_epochs``, a callback's ``should_stop``): an exception, SIGTERM (also under SLURM)
    or Ctrl-C goes to ``on_exception`` instead, so an interrupted run writes nothing here."""

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """A resumed fit writes its ``last`` over the folder's ``last.ckpt``: Lightning restores where it wrote
        ``last`` only when the checkpoint folder's path is the one stored (not for a copied or moved run, or one
        named relative in one SLURM job and absolute in the next), and else wrote ``last-v1.ckpt`` beside the old
        ``last.ckpt``, which ``launch.sh``, Stage II's ``init_from`` and ``--ckpt_path last`` then read."""
        if not trainer.ckpt_path:
            return
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and cb.dirpath and not cb.last_model_path:
                last = cb.format_checkpoint_name({}, cb.CHECKPOINT_NAME_LAST)  # the name its next save compares
                if Path(last).is_file():
                    cb.last_model_path = last

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        missing = missing_private_api()
        if missing:
            rank_zero_warn(f"FinalLastCheckpoint: this Lightning's ModelCheckpoint has no {', '.join(missing)}, so "
                           f"last.ckpt may hold an earlier step than the final {trainer.global_step}")
            return
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and not cb._should_skip_saving_checkpoint(trainer):
                cb._save_last_checkpoint(trainer, cb._monitor_candidates(trainer))
