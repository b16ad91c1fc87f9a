"""Evaluation metrics under DDP: every rank computes and logs the same set of metrics, in the same order.

A rank may hold no evaluation sample at all (fewer held-out scenes than ranks x workers: the evaluation
shards are split sample by sample, see :func:`anycity.data.pipeline.make_pipeline`). torchmetrics syncs its
states inside ``compute()``, a collective: if one rank computes a metric that another rank skips (because it
never updated it), the ranks wait in different collectives and the job hangs or dies with a gloo/NCCL size
mismatch. So the set of metrics to log is agreed on first (an all-gather of "updated here" flags), then every
rank computes exactly those, at epoch end.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn
from torchmetrics.image import PeakSignalNoiseRatio

# the values logged here are already reduced over ranks (torchmetrics syncs inside compute())
warnings.filterwarnings("ignore", message=".*when logging on epoch level in distributed setting.*")


def updated_anywhere(module, metrics: nn.ModuleDict | dict) -> list[str]:
    """Names of the metrics that at least one rank updated (one all-gather; local flags without DDP)."""
    names = list(metrics.keys())
    flags = torch.tensor([bool(metrics[n].update_called) for n in names], dtype=torch.float32,
                         device=module.device)
    world = getattr(getattr(module, "_trainer", None), "world_size", 1)
    if world > 1 and names:
        flags = module.all_gather(flags).reshape(world, len(names)).amax(0)
    return [n for n, f in zip(names, flags.tolist()) if f > 0]


def union_over_ranks(module, items: set[str]) -> set[str]:
    """The union of every rank's ``items`` (one ``all_gather_object``; ``items`` itself without DDP). Every rank
    calls it."""
    world = getattr(getattr(module, "_trainer", None), "world_size", 1)
    if world <= 1 or not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return set(items)
    gathered: list = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(gathered, sorted(items))
    return {x for rank in gathered for x in rank}


def _empty_update(m) -> None:
    """Give a metric that this rank never updated empty list states of the right dtypes: torchmetrics fills
    them with float32 placeholders, and a rank whose real state is int64 (PSNR's pixel counts) then gathers a
    different byte count (gloo aborts, NCCL hangs). Scalar states need nothing."""
    if m.update_called or not any(isinstance(getattr(m, a), list) for a in m._reductions):
        return
    if isinstance(m, PeakSignalNoiseRatio):
        m.update(torch.empty(0, 3, 1, 1, device=m.device), torch.empty(0, 3, 1, 1, device=m.device))
    else:
        raise TypeError(f"log_eval_metrics: no empty update for {type(m).__name__} with list states; add one here")


def log_eval_metrics(module, metrics, split: str, prog_bar_prefix: str = "psnr") -> dict[str, float]:
    """Compute (synced across ranks), log as ``<split>/<name>`` and reset ``metrics`` (an ``EvalMetrics``).

    Called from ``on_{validation,test}_epoch_end`` on every rank. Returns the logged values."""
    table = dict(metrics.items())
    out: dict[str, float] = {}
    for name in updated_anywhere(module, table):
        m = table[name]
        _empty_update(m)
        with warnings.catch_warnings():  # a rank that saw no sample computes from the other ranks' states
            warnings.filterwarnings("ignore", message=".*compute.*before.*update.*")
            value = m.compute()
        module.log(f"{split}/{name}", value, sync_dist=False,
                   prog_bar=name.startswith(prog_bar_prefix) and split == "val")
        out[name] = float(value)
    for m in table.values():
        m.reset()
    return out
