"""A callback for the multi-process tests (tests/integration/test_ddp.py): records what each rank scored and its
final parameters, and can poison one rank's loss or gradient at one step."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import torch
from lightning.pytorch.callbacks import Callback


class DDPProbe(Callback):
    """Args:
        out_dir: where ``<split>_rank<r>.jsonl`` (one line per scored target view) and ``params_rank<r>.pt`` go.
        poison_rank, poison_step: the rank and optimiser step to poison (-1: never).
        poison: "loss" (the loss becomes NaN after backward), "grad" (one gradient becomes inf) or "forward" (the
            camera token is inf for that step, so the whole forward is NaN, as an overflow makes it; NaN images are
            refused by the network's input check instead).
    """

    def __init__(self, out_dir: str, poison_rank: int = -1, poison_step: int = -1, poison: str = "grad") -> None:
        self.out = Path(out_dir)
        self.poison_rank, self.poison_step, self.poison = poison_rank, poison_step, poison

    def _hit(self, trainer) -> bool:
        return trainer.global_rank == self.poison_rank and trainer.global_step == self.poison_step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        if self._hit(trainer) and self.poison == "forward":
            token = pl_module.net.aggregator.camera_token
            self._saved = token.detach().clone()
            with torch.no_grad():
                token.fill_(math.inf)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if getattr(self, "_saved", None) is not None:  # the step was skipped: the ranks' weights agree again
            with torch.no_grad():
                pl_module.net.aggregator.camera_token.copy_(self._saved)
            self._saved = None

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


ROOT = Path(__file__).resolve().parents[2]


def subprocess_env() -> dict:
    """This environment for a CLI subprocess: our src/ and tests/ importable, no leftover rank/SLURM variables (a
    child that sees them believes it is already a worker or a SLURM task)."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("SLURM_") and k not in ("LOCAL_RANK", "RANK", "WORLD_SIZE", "NODE_RANK",
                                                       "MASTER_ADDR", "MASTER_PORT", "PL_TRAINER_GPUS")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests"), env.get("PYTHONPATH", "")])
    return env


def make_shards(out: Path) -> Path:
    """30 cities x 8 views at 32x32: 24 train, 3 val and 3 test scenes (one sample each)."""
    from anycity.data.cli import data_main

    data_main(["synth", "--out", str(out), "--scenes", "30", "--views", "8", "--size", "32x32", "--workers", "1"])
    return out


def assert_params_equal(probe: Path) -> None:
    """The two ranks' final parameters (written by :class:`DDPProbe`) are finite and bit-identical."""
    p0, p1 = (torch.load(probe / f"params_rank{r}.pt", weights_only=True) for r in (0, 1))
    assert p0.keys() == p1.keys() and p0
    for k in p0:
        assert torch.isfinite(p0[k]).all(), k
        torch.testing.assert_close(p0[k], p1[k], rtol=0, atol=0, msg=k)
