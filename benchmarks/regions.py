"""Region diagnostic shares on the quickstart's test cities for a grid of thresholds (how the defaults were chosen).

    python benchmarks/regions.py [--data data/quickstart]    # needs the quickstart shards (make quickstart)

Prints, per setting, the share of target pixels that are observation-supported, weak and sky, and the time per
batch of :func:`anycity.metrics.regions.region_masks`.
"""

from __future__ import annotations

import argparse
import time

import torch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="data/quickstart")
    args = p.parse_args()
    from pathlib import Path

    if not (Path(args.data) / "index.json").is_file():
        print(f"benchmarks/regions.py: skipped, no shards at {args.data} (run make quickstart first, or pass --data)")
        return
    from anycity.lit.datamodule import AerialDataModule
    from anycity.metrics.regions import region_masks

    dm = AerialDataModule(root=args.data, image_size=(48, 48), patch_size=8, num_context=4, num_targets=2,
                          num_dense=6, batch_size=1, num_workers=0)
    dm.setup("test")
    batches = list(dm.test_dataloader())
    grid = [dict(min_parallax_deg=a, depth_tol=0.1, edge_thresh=0.3, min_views=m) for m in (2, 3)
            for a in (1.0, 2.0, 5.0)]
    grid += [dict(min_parallax_deg=2.0, depth_tol=t, edge_thresh=e, min_views=2) for t in (0.05, 0.15)
             for e in (0.2, 0.3, 0.5)]
    print(f"{len(batches)} test batches, {sum(b.target.num_views for b in batches)} target views")
    print("| min_views | parallax (deg) | depth_tol | edge_thresh | observed | weak | sky | ms/batch |")
    print("|---|---|---|---|---|---|---|---|")
    for kw in grid:
        obs = weak = total = 0.0
        t0 = time.perf_counter()
        for b in batches:
            c, t = b.context, b.target
            o, w = region_masks(t.depth, t.w2c, t.K, c.depth, c.w2c, c.K, target_valid=t.mask, context_valid=c.mask,
                                **kw)
            obs, weak, total = obs + o.sum().item(), weak + w.sum().item(), total + o.numel()
        ms = 1000 * (time.perf_counter() - t0) / len(batches)
        print(f"| {kw['min_views']} | {kw['min_parallax_deg']:g} | {kw['depth_tol']:g} | {kw['edge_thresh']:g} | "
              f"{obs / total:.3f} | {weak / total:.3f} | {1 - (obs + weak) / total:.3f} | {ms:.1f} |")


if __name__ == "__main__":
    torch.set_grad_enabled(False)
    main()
