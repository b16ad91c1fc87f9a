"""Data throughput: synthetic generation speed, then samples/s and MB/s reading shards into ViewBatch.

    .venv/bin/python benchmarks/data.py [--root data/bench-448] [--samples 60]

Target (issue 3): >= 20 samples/s of 4 context + 12 dense views (+ targets) at 448x448 with 2 workers.
Shards are generated once (8 scenes x 48 views at 448x448) and reused.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from anycity.data.synthetic import synth
from anycity.lit.datamodule import AerialDataModule


def bench_synth(out: Path, scenes: int, views: int, size: str) -> float:
    index = synth(out, scenes=scenes, views=views, size=size, seed=0, trajectory="mixed")
    return index["seconds"]


def bench_read(root: Path, workers: int, samples: int, targets: int) -> tuple[float, float]:
    dm = AerialDataModule(root=str(root), num_context=4, num_dense=12, num_targets=targets, image_size=(448, 448),
                          batch_size=1, num_workers=workers, epoch_samples=samples, seed=0, with_normals=True)
    shard_bytes = sum(p.stat().st_size for p in root.glob("*.tar"))
    shard_samples = 8
    it = iter(dm.train_dataloader())
    next(it)  # worker start-up and first decode excluded
    t0 = time.perf_counter()
    n = 1
    for _ in it:
        n += 1
    dt = time.perf_counter() - t0
    rate = (n - 1) / dt
    return rate, rate * shard_bytes / shard_samples / 1e6


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default="data/bench-448")
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--targets", type=int, default=4)
    ap.add_argument("--skip-synth", action="store_true")
    a = ap.parse_args()
    if not a.skip_synth:
        s = bench_synth(Path("data/bench-synth-256"), 8, 48, "256x256")
        print(f"synth 8 scenes x 48 views at 256x256: {s:.1f} s (target <= 60 s)")
    root = Path(a.root)
    if not (root / "index.json").exists():
        s = bench_synth(root, 8, 48, "448x448")
        print(f"synth 8 scenes x 48 views at 448x448 (benchmark shards): {s:.1f} s")
    for workers in (0, 2):
        rate, mbs = bench_read(root, workers, a.samples, a.targets)
        print(f"read 4+12+{a.targets} views at 448x448, {workers} workers: {rate:.1f} samples/s, "
              f"{mbs:.0f} MB/s of shard data touched (target >= 20 samples/s with 2 workers)")


if __name__ == "__main__":
    main()
