"""NonFiniteGuard: a step whose loss or any gradient holds a NaN or an inf is skipped (one process here; the
two-rank agreement is in tests/integration/test_ddp.py)."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from torch import nn

from anycity.callbacks import nonfinite
from anycity.callbacks.nonfinite import NonFiniteGuard, all_finite


@pytest.fixture(params=["foreach", "per_tensor"])
def norm_path(request, monkeypatch):
    """Both total-norm paths: torch's foreach helper, and the one for torch < 2.6."""
    if request.param == "per_tensor":
        monkeypatch.setattr(nonfinite, "_total_norm", nonfinite._total_norm_per_tensor)
    return request.param


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
@pytest.mark.parametrize("where", [0, 2])
def test_all_finite_finds_one_bad_element_in_any_tensor(bad, where, norm_path):
    tensors = [torch.randn(7, 5), torch.randn(3, dtype=torch.bfloat16), torch.randn(2, 2, 4, dtype=torch.float64)]
    assert all_finite(tensors)
    tensors[where].view(-1)[3] = bad
    assert not all_finite(tensors)


def test_all_finite_is_not_fooled_by_a_norm_that_overflows(norm_path):
    assert all_finite([torch.full((4,), 3e38), torch.ones(2)])  # the L2 norm is inf, every element finite
    assert all_finite([])


class _Linear(pl.LightningModule):
    """Regression on fixed data; ``poison_step``'s gradient of ``layer.bias`` is set to inf after backward."""

    def __init__(self, poison_step: int):
        super().__init__()
        self.layer, self.poison_step = nn.Linear(3, 1), poison_step
        self.seen: list[torch.Tensor] = []

    def training_step(self, batch, batch_idx):
        self.seen.append(self.layer.weight.detach().clone())
        return ((self.layer(batch[0]) - batch[1]) ** 2).mean()  # finite on every step

    def on_after_backward(self):
        if self.global_step == self.poison_step:
            self.layer.bias.grad[0] = float("inf")

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

    def train_dataloader(self):
        x = torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
        return torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x, x.sum(1, keepdim=True)), batch_size=4)


def test_a_step_with_a_finite_loss_and_an_inf_gradient_is_skipped():
    guard = NonFiniteGuard()
    model = _Linear(poison_step=1)
    trainer = pl.Trainer(max_steps=3, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[guard])
    trainer.fit(model)
    assert guard.skipped == 1
    w0, w1, w2 = model.seen
    assert not torch.equal(w0, w1)  # step 0 updated the weights
    assert torch.equal(w1, w2)  # step 1, the poisoned one, left every parameter as it was
    assert torch.isfinite(model.layer.bias).all()


def test_a_run_whose_every_step_was_skipped_fails_at_its_end():
    """Fewer steps than max_skips, every one non-finite (e.g. Stage II on a Stage I that blew up): the run used to
    end with exit status 0 and an untrained checkpoint."""

    class _AlwaysInf(_Linear):
        def on_after_backward(self):
            self.layer.bias.grad[0] = float("inf")

    guard = NonFiniteGuard()
    trainer = pl.Trainer(max_steps=3, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[guard])
    with pytest.raises(RuntimeError, match="all 3 optimiser steps of this run were skipped"):
        trainer.fit(_AlwaysInf(poison_step=-1))
