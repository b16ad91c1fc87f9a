"""Training-step benchmark: wall time of one optimiser step (forward + renders + losses + backward + AdamW) for
Stage I and Stage II, built with the quickstart configs' model settings (``--preset`` other than tiny: that
preset with its defaults).

    python benchmarks/train_step.py [--preset tiny] [--size 48] [--context 4] [--targets 2] [--dense 6]
                                    [--backend auto] [--steps 5] [--threads 2]

Peer: the quickstart. The defaults are its batch (``configs/quickstart.yaml``: 48x48, 4 context + 2 target + 6
dense views); each stage's step time is also printed as the training minutes of the quickstart's ``max_steps``
for that stage (read from its configs). The whole quickstart (data, both stages, evaluation) must stay within 15
minutes on 2 cores; its training is the largest share. Data loading is not included here (``benchmarks/data.py``).
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import time
from pathlib import Path

import torch
import yaml
from _bench import positive_int

from anycity.geometry import make_intrinsics
from anycity.lit.base import make_adamw
from anycity.structures import ViewBatch, Views

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def quickstart() -> dict[str, tuple[int, dict]]:
    """``{module class name: (max_steps, init_args)}`` of the quickstart's two stages (the Stage II file overlays
    the Stage I one; ``init_from`` dropped: the benchmark starts from random weights)."""
    c1, c2 = (yaml.safe_load((CONFIGS / f).read_text()) for f in ("quickstart.yaml", "quickstart_stage2.yaml"))
    a1 = c1["model"]["init_args"]
    a2 = {**a1, **c2["model"]["init_args"]}
    a2.pop("init_from", None)
    return {"ScaffoldModule": (int(c1["trainer"]["max_steps"]), a1),
            "RefinementModule": (int(c2["trainer"].get("max_steps", c1["trainer"]["max_steps"])), a2)}


def _views(n: int, size: int, gen: torch.Generator) -> Views:
    w2c = torch.eye(4).repeat(1, n, 1, 1)
    w2c[..., 0, 3] = torch.linspace(0, 0.3, n)
    f = size * 0.87
    K = make_intrinsics(f, f, size / 2, size / 2).expand(1, n, 3, 3).clone()
    return Views(images=torch.rand(1, n, 3, size, size, generator=gen), w2c=w2c, K=K,
                 depth=torch.rand(1, n, 1, size, size, generator=gen) + 1,
                 mask=torch.ones(1, n, 1, size, size, dtype=torch.bool))


def _time_step(module, batch, steps: int) -> float:
    # the kernel configure_optimizers picks for the quickstart's 32-true precision
    opt = make_adamw([{"params": [p for p in module.parameters() if p.requires_grad]}], 1e-4, fused=True)
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


def _accepted(cls, kw: dict) -> dict:
    """The keys of ``kw`` that ``cls`` or one of its bases names in ``__init__`` (the Stage I settings a Stage II
    module has no use for are dropped, as LightningCLI drops them when the class_path changes)."""
    names = {n for c in cls.__mro__ if "__init__" in vars(c) for n in inspect.signature(c.__init__).parameters}
    return {k: v for k, v in kw.items() if k in names}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="tiny")
    p.add_argument("--size", type=positive_int, default=48)
    p.add_argument("--context", type=positive_int, default=4)
    p.add_argument("--targets", type=positive_int, default=2)
    p.add_argument("--dense", type=int, default=6)
    p.add_argument("--backend", default="auto")
    p.add_argument("--steps", type=positive_int, default=5)
    p.add_argument("--threads", type=positive_int, default=2)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    from anycity.lit import RefinementModule, ScaffoldModule

    gen = torch.Generator().manual_seed(0)
    batch = ViewBatch(context=_views(a.context, a.size, gen), target=_views(a.targets, a.size, gen),
                      dense=_views(a.dense, a.size, gen))
    stages = quickstart()
    same = (a.preset, a.size, a.context, a.targets, a.dense) == ("tiny", 48, 4, 2, 6)
    print(f"preset={a.preset} {a.size}x{a.size}, {a.context} context + {a.targets} target (+{a.dense} dense) views, "
          f"backend={a.backend}, {a.threads} threads")
    for cls in (ScaffoldModule, RefinementModule):
        n, kw = stages[cls.__name__]
        kw = _accepted(cls, kw) if a.preset == "tiny" else {}
        m = cls(**{**kw, "preset": a.preset, "render_backend": a.backend})
        m.log = lambda *args, **kwargs: None
        s = _time_step(m, batch, a.steps)
        print(f"{cls.__name__:17s} {s * 1000:8.1f} ms/step   x {n} quickstart steps = {s * n / 60:.1f} min of training"
              + ("" if same else " (another batch than the quickstart's)"))


if __name__ == "__main__":
    main()
