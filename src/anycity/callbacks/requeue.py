"""SLURM's time-limit signal saves the preemption checkpoint at the next safe point, not wherever it lands.

Lightning's ``SLURMEnvironment`` (``auto_requeue``) saves ``hpc_ckpt_N.ckpt`` from inside its SIGUSR1 handler, so
the save happens wherever the main thread is. A signal between ``optimizer.step()`` and Lightning counting the
batch gives a file with the weights and AdamW moments of step k but the step count and LR schedule of k-1: the
resumed run trains that batch a second time. :class:`RequeueAtSafePoint` (the CLI adds it to every fit) replaces
that handler with one that only notes the signal; Lightning's own save-and-requeue then runs at the end of the
next training batch that steps the optimiser, or at the end of a validation of the fit, on every rank at the same
step (under DDP the ranks agree on it by one reduction per batch while the handler is in place).
"""

from __future__ import annotations

import signal
import threading

import lightning.pytorch as pl
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_warn

# The Lightning internals this callback reads (Lightning >= 2.6): the cluster environment the signal connector
# asks, the connector's own save-and-requeue, and the epoch loop's test of whether a batch steps the optimiser.
PRIVATE_API = ("_accelerator_connector", "_signal_connector._slurm_sigusr_handler_fn",
               "fit_loop.epoch_loop._should_accumulate")


def missing_private_api(trainer: pl.Trainer) -> list[str]:
    """The names of :data:`PRIVATE_API` that ``trainer`` lacks (empty: all there)."""
    missing = []
    for name in PRIVATE_API:
        obj = trainer
        for part in name.split("."):
            obj = getattr(obj, part, None)
        if obj is None:
            missing.append(name)
    return missing


def _requeue_signal(trainer: pl.Trainer) -> int | None:
    """The signal Lightning saves and requeues on (``SLURMEnvironment.requeue_signal``), or None when it does not
    (no SLURM, ``auto_requeue: false``, Windows)."""
    from lightning.fabric.plugins.environments import SLURMEnvironment

    env = getattr(getattr(trainer, "_accelerator_connector", None), "cluster_environment", None)
    if not isinstance(env, SLURMEnvironment) or not env.auto_requeue or not hasattr(signal, "SIGUSR1"):
        return None
    return env.requeue_signal


class RequeueAtSafePoint(Callback):
    """Defers Lightning's SLURM time-limit checkpoint and requeue to the next safe point of a fit.

    Installed when the fit starts (the sanity check or the first batch), and only over Lightning's own handler: a
    handler someone else set is left alone, and so is Lightning's when its internals (:data:`PRIVATE_API`) have
    moved (with a warning). Lightning puts the process's earlier handler back when the run ends. Add it after the
    checkpoint callbacks (the CLI appends it to ``trainer.callbacks``), so that the saved state holds their save
    of the same step.
    """

    def __init__(self) -> None:
        self._signum: int | None = None  # the signal received and not yet acted on
        self._active = False  # our handler is in place of Lightning's

    def _on_signal(self, signum: int, frame) -> None:
        self._signum = signum  # only this: the main thread may be anywhere in a step

    def _install(self, trainer: pl.Trainer) -> None:
        sig = _requeue_signal(trainer)
        if self._active or sig is None or threading.current_thread() is not threading.main_thread():
            return
        missing = missing_private_api(trainer)
        if missing:
            rank_zero_warn(f"RequeueAtSafePoint: this Lightning has no {', '.join(missing)}, so a SLURM time-limit "
                           "checkpoint is saved wherever the signal lands (a resume may repeat one batch)")
            return
        lightnings = trainer._signal_connector._slurm_sigusr_handler_fn
        if lightnings in (getattr(signal.getsignal(sig), "signal_handlers", None) or []):  # its _HandlersCompose
            signal.signal(sig, self._on_signal)
            self._signum, self._active = None, True

    def _act(self, trainer: pl.Trainer) -> None:
        """Save ``hpc_ckpt_N.ckpt`` and requeue (Lightning's code) when any rank received the signal. Not after a
        batch that only accumulates gradients: the saved state would lose them."""
        if not self._active or trainer.fit_loop.epoch_loop._should_accumulate():
            return
        pending = self._signum is not None
        if trainer.world_size > 1:  # every rank saves at the same step: the save is collective
            pending = trainer.strategy.reduce_boolean_decision(pending, all=False)
        if pending:
            signum = self._signum or _requeue_signal(trainer)
            self._signum = None  # first: a signal during the save asks for another one
            trainer._signal_connector._slurm_sigusr_handler_fn(signum, None)

    def on_sanity_check_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._install(trainer)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._install(trainer)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        self._act(trainer)

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.state.fn == TrainerFn.FITTING and not trainer.sanity_checking:
            self._act(trainer)

    def teardown(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._active, self._signum = False, None
