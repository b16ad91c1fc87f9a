"""Training-step benchmark: wall time of one optimiser step (forward + renders + losses + backward + AdamW) for
Stage I and Stage II, broken down into network forward, rendering and backward.

    python benchmarks/train_step.py [--preset tiny] [--size 64] [--context 4] [--targets 2] [--dense 6]
                                    [--backend auto] [--steps 5] [--threads 2]

Peer: the quickstart budget. ``configs/quickstart.yaml`` trains Stage I then Stage II on 2 CPU cores inside
10 minutes, so the printed ratio is (measured step time) / (the per-step budget that allows).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from anycity.geometry import make_intrinsics
from anycity.structures import ViewBatch, Views

QUICKSTART_BUDGET_S = 8 * 60  # training share of the 10-minute quickstart
QUICKSTART_STEPS = 450  # Stage I + Stage II steps in configs/quickstart*.yaml


def _views(n: int, size: int, gen: torch.Generator) -> Views:
    w2c = torch.eye(4).repeat(1, n, 1, 1)
    w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
    f = size * 0.87
    K = make_intrinsics(f, f, size / 2, size / 2).expand(1, n, 3, 3).clone()
    return Views(images=torch.rand(1, n, 3, size, size, generator=gen), w2c=w2c, K=K,
                 depth=torch.rand(1, n, 1, size, size, generator=gen) + 1,
                 mask=torch.ones(1, n, 1, size, size, dtype=torch.bool))


def _time_step(module, batch, steps: int) -> float:
    opt = torch.optim.AdamW([p for p in module.parameters() if p.requires_grad], lr=1e-4)
    times = []
    for i in range(steps + 1):
        t = time.perf_counter()
        loss = module.training_step(batch, i)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if i:  # the first step warms up kernels / numba compilation
            times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="tiny")
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--context", type=int, default=4)
    p.add_argument("--targets", type=int, default=2)
    p.add_argument("--dense", type=int, default=6)
    p.add_argument("--backend", default="auto")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    from anycity.lit import RefinementModule, ScaffoldModule

    gen = torch.Generator().manual_seed(0)
    batch = ViewBatch(context=_views(a.context, a.size, gen), target=_views(a.targets, a.size, gen),
                      dense=_views(a.dense, a.size, gen))
    budget = QUICKSTART_BUDGET_S / QUICKSTART_STEPS
    print(f"preset={a.preset} {a.size}x{a.size}, {a.context} context + {a.targets} target (+{a.dense} dense) views, "
          f"backend={a.backend}, {a.threads} threads")
    for cls, kw in ((ScaffoldModule, {"depth_warmup_steps": 0}), (RefinementModule, {})):
        m = cls(preset=a.preset, render_backend=a.backend, **kw)
        m.log = lambda *args, **kwargs: None
        s = _time_step(m, batch, a.steps)
        print(f"{cls.__name__:17s} {s * 1000:8.1f} ms/step   vs quickstart per-step budget {budget * 1000:.0f} ms: "
              f"{s / budget:.2f}x")


if __name__ == "__main__":
    main()
