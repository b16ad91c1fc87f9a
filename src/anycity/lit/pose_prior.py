"""Pretraining of the pair-correlation pose prior (:mod:`anycity.models.pose_prior`), beyond the paper.

``scripts/pose_prior.py`` fits it with a Lightning ``Trainer`` on the context views of the training split and
their ground-truth poses (the supervision the camera loss uses), and saves the weights for ``net.pose_prior``.
"""

from __future__ import annotations

import lightning.pytorch as pl
import torch
from torch import Tensor

from anycity.lit.base import schedule_steps
from anycity.metrics.pose import relative_pose_errors
from anycity.models.pose_prior import PairFlowPose
from anycity.structures import ViewBatch


class PosePriorModule(pl.LightningModule):
    """L1 on the rotation matrix and translation of context views 1..V-1, in the sample's normalised frame (view 0
    is the identity). AdamW with a one-cycle schedule over ``trainer.max_steps``. Validation and test log
    ``rre``: the mean relative rotation error over every context view pair, as ``anycity test`` computes it."""

    def __init__(self, channels: int = 48, grid: int = 12, lr: float = 1e-3, weight_decay: float = 1e-4):
        super().__init__()
        self.save_hyperparameters()
        self.net = PairFlowPose(channels, grid)

    def loss(self, batch: ViewBatch) -> Tensor:
        err = self.net(batch.context.images)[:, 1:] - batch.context.w2c[:, 1:].float()
        return err[..., :3, :3].abs().mean() + err[..., :3, 3].abs().mean()

    def training_step(self, batch: ViewBatch, batch_idx: int) -> Tensor:
        loss = self.loss(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=batch.context.images.shape[0])
        return loss

    def _rre(self, batch: ViewBatch) -> None:
        rre, _ = relative_pose_errors(self.net(batch.context.images), batch.context.w2c)
        b = batch.context.images.shape[0]
        self._rre_sums += torch.stack([rre.mean().detach().float() * b, rre.new_tensor(float(b))])

    def _log_rre(self, stage: str) -> None:
        """Log ``{stage}/rre``, the batch-size-weighted mean over every rank's batches, with one all-gather that
        every rank joins, also one that held no evaluation sample (``sync_dist`` logging would have left it out of
        the collective and hung the others); nothing when no rank had one."""
        sums = self._rre_sums
        if self.trainer.world_size > 1:
            sums = self.all_gather(sums).reshape(-1, 2).sum(0)
        if float(sums[1]) > 0:
            self.log(f"{stage}/rre", sums[0] / sums[1])

    def on_validation_epoch_start(self) -> None:
        self._rre_sums = torch.zeros(2, device=self.device)

    on_test_epoch_start = on_validation_epoch_start

    def validation_step(self, batch: ViewBatch, batch_idx: int) -> None:
        self._rre(batch)

    def test_step(self, batch: ViewBatch, batch_idx: int) -> None:
        self._rre(batch)

    def on_validation_epoch_end(self) -> None:
        self._log_rre("val")

    def on_test_epoch_end(self) -> None:
        self._log_rre("test")

    def configure_optimizers(self) -> dict:
        opt = torch.optim.AdamW(self.parameters(), self.hparams.lr, weight_decay=self.hparams.weight_decay)
        total = max(schedule_steps(self.trainer), 4)  # OneCycleLR needs a warm-up of >= 1 step
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, self.hparams.lr, total_steps=total,
                                                    pct_start=max(0.05, 2 / total))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}
