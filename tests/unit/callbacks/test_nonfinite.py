"""NonFiniteGuard: a step whose loss or any gradient holds a NaN or an inf is skipped (one process here; the
two-rank agreement is in tests/integration/test_ddp.py)."""

from __future__ import annotations

from types import SimpleNamespace

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


class _Fp16(pl.LightningModule):
    """A finite loss whose float16 backward overflows at large loss scales; a NaN loss at ``nan_step``."""

    def __init__(self, nan_step: int = -1):
        super().__init__()
        torch.manual_seed(0)
        self.layer, self.nan_step = nn.Linear(16, 16), nan_step

    def training_step(self, batch, batch_idx):
        loss = (self.layer(batch[0]).float() * 30.0).pow(2).mean()  # the layer runs in float16 under autocast
        return loss * float("nan") if self.global_step == self.nan_step else loss

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=1e-6)

    def train_dataloader(self):
        x = torch.randn(64, 16, generator=torch.Generator().manual_seed(0))
        return torch.utils.data.DataLoader(torch.utils.data.TensorDataset(x), batch_size=8)


def _fit_16_mixed(model, steps, accumulate=1):
    from lightning.pytorch.plugins import MixedPrecision

    # growth_interval 2 stands in for the default 2000: the scaler doubles its scale until the gradients overflow
    scaler = torch.amp.GradScaler("cpu", init_scale=2.0 ** 4, growth_interval=2)
    scales = [scaler.get_scale()]  # after each step: the scaler halves its scale on a step it skipped

    class _Scales(pl.Callback):
        def on_train_batch_end(self, *args):
            scales.append(scaler.get_scale())

    guard = NonFiniteGuard(max_skips=1)
    trainer = pl.Trainer(max_steps=steps, accelerator="cpu", plugins=[MixedPrecision("16-mixed", "cpu", scaler=scaler)],
                         accumulate_grad_batches=accumulate, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[guard, _Scales()])
    trainer.fit(model)
    return guard, sum(b < a for a, b in zip(scales, scales[1:]))


def test_the_grad_scalers_overflow_steps_are_left_to_it_under_16_mixed():
    """16-mixed's GradScaler overflows the gradients on purpose about once per growth_interval and skips those steps
    itself; the guard counted each as a non-finite skip, warned, and stopped healthy long runs at max_skips."""
    guard, overflows = _fit_16_mixed(_Fp16(), steps=24)
    assert overflows >= 3  # more than max_skips
    assert guard.skipped == 0


def test_a_nan_loss_is_still_skipped_under_16_mixed():
    guard, _ = _fit_16_mixed(_Fp16(nan_step=1), steps=3)
    assert guard.skipped == 1


def test_a_nan_loss_on_an_earlier_micro_batch_is_skipped_under_16_mixed_with_accumulation():
    """With accumulate_grad_batches > 1 the guard kept only the last micro-batch's loss: a NaN on the first made the
    GradScaler skip the step unseen (not counted, max_skips never reached, the run 'trained' nothing)."""

    class _NanFirstMicroBatch(_Fp16):
        def training_step(self, batch, batch_idx):
            loss = super().training_step(batch, batch_idx)
            return loss * float("nan") if batch_idx == 2 else loss  # the first of step 1's two micro-batches

    guard, _ = _fit_16_mixed(_NanFirstMicroBatch(), steps=3, accumulate=2)
    assert guard.skipped == 1
    guard, _ = _fit_16_mixed(_Fp16(), steps=3, accumulate=2)  # the flag is reset at every step
    assert guard.skipped == 0


def _fit_linear(model, guard, steps=3):
    trainer = pl.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[guard])
    trainer.fit(model)
    return trainer


def test_a_skipped_step_leaves_adamw_weights_and_step_count_untouched():
    """The gradients are dropped (set to None), not zeroed: AdamW would still move a zero-gradient parameter
    (momentum, weight decay) and count the step."""

    class _AdamW(_Linear):
        def configure_optimizers(self):
            return torch.optim.AdamW(self.parameters(), lr=0.1, weight_decay=0.01)

    torch.manual_seed(0)
    guard, model = NonFiniteGuard(), _AdamW(poison_step=1)
    trainer = _fit_linear(model, guard)
    assert guard.skipped == 1
    w0, w1, w2 = model.seen
    assert not torch.equal(w0, w1)  # step 0 updated the weights
    assert torch.equal(w1, w2)  # the poisoned step moved nothing, not even by momentum or weight decay
    assert {int(s["step"]) for s in trainer.optimizers[0].state.values()} == {2}  # 3 steps, one skipped


def test_a_disabled_guard_skips_nothing():
    torch.manual_seed(0)
    guard, model = NonFiniteGuard(enabled=False), _Linear(poison_step=1)
    _fit_linear(model, guard)
    assert guard.skipped == 0
    assert not torch.isfinite(model.layer.bias).all()  # the inf gradient reached the weights


def test_the_skip_count_is_restored_from_a_checkpoint():
    guard = NonFiniteGuard()
    guard.load_state_dict({"skipped": 5})
    assert guard.skipped == 5
    assert guard.state_dict() == {"skipped": 5}
    guard.load_state_dict({})  # a checkpoint from before the count was saved
    assert guard.skipped == 0


@pytest.mark.filterwarnings("ignore:NonFiniteGuard. skipped")
def test_the_run_stops_on_the_first_skip_past_max_skips():
    """max_skips=2 allows two skipped steps; the third raises, naming the count and the limit."""
    guard = NonFiniteGuard(max_skips=2)
    p = nn.Parameter(torch.zeros(2))
    opt = torch.optim.SGD([p], lr=0.1)
    trainer = SimpleNamespace(precision_plugin=SimpleNamespace(), world_size=1, global_step=0)
    module = SimpleNamespace(device=torch.device("cpu"), log=lambda *a, **k: None)
    for _ in range(2):
        p.grad = torch.tensor([float("nan"), 0.0])
        guard.on_before_optimizer_step(trainer, module, opt)
    assert guard.skipped == 2
    p.grad = torch.tensor([float("nan"), 0.0])
    with pytest.raises(RuntimeError, match=r"^NonFiniteGuard: 3 steps skipped .*\(> nonfinite\.max_skips=2\)"):
        guard.on_before_optimizer_step(trainer, module, opt)
