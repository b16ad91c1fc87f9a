"""A callback for the multi-process tests (tests/integration/test_ddp.py): records what each rank scored and its
final parameters, and can poison one rank's loss or gradient at one step."""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback


class DDPProbe(Callback):
    """Args:
        out_dir: where ``<split>_rank<r>.jsonl`` (one line per scored target view) and ``params_rank<r>.pt`` go.
        poison_rank, poison_step: the rank and optimiser step to poison (-1: never).
        poison: "loss" (the loss becomes NaN after backward) or "grad" (one gradient becomes inf).
    """

    def __init__(self, out_dir: str, poison_rank: int = -1, poison_step: int = -1, poison: str = "grad") -> None:
        self.out = Path(out_dir)
        self.poison_rank, self.poison_step, self.poison = poison_rank, poison_step, poison

    def _hit(self, trainer) -> bool:
        return trainer.global_rank == self.poison_rank and trainer.global_step == self.poison_step

    def on_before_backward(self, trainer, pl_module, loss) -> None:
        if self._hit(trainer) and self.poison == "loss":
            loss.data.fill_(math.nan)

    def on_after_backward(self, trainer, pl_module) -> None:
        if self._hit(trainer) and self.poison == "grad":
            p = next(p for p in pl_module.parameters() if p.grad is not None)
            p.grad.view(-1)[0] = math.inf

    def _record(self, trainer, batch, split: str) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        with open(self.out / f"{split}_rank{trainer.global_rank}.jsonl", "a") as f:
            for b, scene in enumerate(batch.scene):
                for i in batch.target.index[b].tolist():
                    f.write(json.dumps({"scene": scene, "view": int(i)}) + "\n")

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._record(trainer, batch, "val")

    def on_test_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0) -> None:
        self._record(trainer, batch, "test")

    def on_train_end(self, trainer, pl_module) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        torch.save({n: p.detach().cpu() for n, p in pl_module.named_parameters()},
                   self.out / f"params_rank{trainer.global_rank}.pt")
