"""``last.ckpt`` holds the step a finished fit ended at.

Lightning (2.6) writes ``last.ckpt`` at the end of training only when its ``ModelCheckpoint`` saved nothing during
the run. So a ``max_steps`` that is not a multiple of ``every_n_train_steps`` left ``last.ckpt`` at the last
multiple (a 1500-step quickstart Stage I: step 1000), and whatever read it next (Stage II's ``init_from``, ``test``,
``--ckpt_path last``) silently took the older weights. The CLI adds :class:`FinalLastCheckpoint` to every run.
"""

from __future__ import annotations

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

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        missing = missing_private_api()
        if missing:
            rank_zero_warn(f"FinalLastCheckpoint: this Lightning's ModelCheckpoint has no {', '.join(missing)}, so "
                           f"last.ckpt may hold an earlier step than the final {trainer.global_step}")
            return
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and not cb._should_skip_saving_checkpoint(trainer):
                cb._save_last_checkpoint(trainer, cb._monitor_candidates(trainer))
