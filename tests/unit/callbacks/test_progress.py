"""LossProgressBar's plain lines (stdout not a terminal): one per optimiser step, on global rank 0 only."""

import re
from types import SimpleNamespace

import lightning.pytorch as pl
import torch

from anycity.callbacks import LossProgressBar


class _Tiny(pl.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(3, 1)

    def training_step(self, batch, batch_idx):
        loss = ((self.layer(batch[0]) - batch[1]) ** 2).mean()
        self.log("train/rgb", loss, prog_bar=True)
        return loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.01)


def test_plain_lines_once_per_optimiser_step_under_accumulation(capsys):
    x = torch.randn(16, 3, generator=torch.Generator().manual_seed(0))
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True)), batch_size=2)
    trainer = pl.Trainer(accelerator="cpu", devices=1, max_steps=4, accumulate_grad_batches=2, logger=False,
                         enable_checkpointing=False, enable_model_summary=False,
                         callbacks=[LossProgressBar(print_every=1, force_plain=True)])
    trainer.fit(_Tiny(), loader)
    steps = re.findall(r"\] step (\d+)/4 ", capsys.readouterr().out)
    assert steps == ["1", "2", "3", "4"]  # no "step 0" before the first step, no line twice


def test_plain_lines_only_on_global_rank_zero(capsys):
    for rank in (1, 0):  # each DDP process has its own bar; only rank 0's prints (its own local loss otherwise)
        bar = LossProgressBar(print_every=1, force_plain=True)
        bar.get_metrics = lambda trainer, module: {"rgb": 0.5}
        trainer = SimpleNamespace(global_step=1, is_global_zero=rank == 0, max_steps=3, current_epoch=0)
        bar.on_train_batch_end(trainer, _Tiny(), None, None, 0)
    assert capsys.readouterr().out.count("] step 1/3 ") == 1


def test_a_run_ended_by_max_epochs_prints_its_last_step_once(capsys):
    """max_steps=-1: the last step got a line only when it was a multiple of print_every (14 steps, every 5: the
    log ended at step 10)."""
    x = torch.randn(14, 3, generator=torch.Generator().manual_seed(0))
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True)), batch_size=2)
    trainer = pl.Trainer(accelerator="cpu", devices=1, max_epochs=2, logger=False, enable_checkpointing=False,
                         enable_model_summary=False, callbacks=[LossProgressBar(print_every=5, force_plain=True)])
    trainer.fit(_Tiny(), loader)
    lines = re.findall(r"\] step (\d+)/\? epoch (\d+) ", capsys.readouterr().out)
    assert trainer.global_step == 14
    assert lines == [("5", "0"), ("10", "1"), ("14", "1")]  # the last step's epoch, not the one after it


def test_the_last_step_line_is_not_repeated_and_only_on_rank_zero(capsys):
    from tqdm import tqdm

    for rank, printed in ((1, -1), (0, -1), (0, 7)):
        bar = LossProgressBar(print_every=5, force_plain=True)
        bar.get_metrics = lambda trainer, module: {"rgb": 0.5}
        bar._train_progress_bar, bar._printed = tqdm(disable=True), printed
        trainer = SimpleNamespace(global_step=7, is_global_zero=rank == 0, max_steps=-1, current_epoch=1)
        bar.on_train_end(trainer, _Tiny())
    assert capsys.readouterr().out.count("] step 7/? ") == 1


def test_print_every_zero_prints_every_step(capsys):
    x = torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True)), batch_size=2)
    trainer = pl.Trainer(accelerator="cpu", devices=1, max_steps=2, logger=False, enable_checkpointing=False,
                         enable_model_summary=False, callbacks=[LossProgressBar(print_every=0, force_plain=True)])
    trainer.fit(_Tiny(), loader)  # print_every=0 is read as 1, not a ZeroDivisionError (step % 0)
    assert re.findall(r"\] step (\d+)/2 ", capsys.readouterr().out) == ["1", "2"]
