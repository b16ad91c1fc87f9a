"""Network inference benchmark: forward wall time per preset, scaffold-only vs refined.

    python benchmarks/inference.py [--preset tiny] [--views 4] [--size 112] [--threads 2] [--repeats 5]

Times are the minimum over ``--repeats`` no-grad forwards after one warm-up. The named peer is the
issue's target for the tiny preset (4 views at 112x112 in <= 1 s on 2 cores); the ratio printed for the
refined pass is against the scaffold-only pass of the same network (the cost of Stage II at inference).
"""

from __future__ import annotations

import argparse
import time

import torch
from _bench import positive_int

TARGET_S = {"tiny": 1.0}


def best_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--views", type=positive_int, default=4)
    ap.add_argument("--size", type=positive_int, default=112,
                    help="square side in pixels (a multiple of the patch size)")
    ap.add_argument("--threads", type=positive_int, default=2)
    ap.add_argument("--repeats", type=positive_int, default=5)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    from anycity.models import build_network

    torch.manual_seed(0)
    net = build_network(args.preset).eval()
    params = sum(p.numel() for p in net.parameters())
    x = torch.rand(1, args.views, 3, args.size, args.size)
    with torch.no_grad():
        t_scaffold = best_time(lambda: net(x, refine=False), args.repeats)
        t_refined = best_time(lambda: net(x, refine=True), args.repeats)
    print(f"preset {args.preset}: {params / 1e6:.3f}M params, {args.views} views at {args.size}x{args.size}, "
          f"{args.threads} threads")
    print(f"  scaffold forward {t_scaffold * 1e3:8.1f} ms")
    print(f"  refined forward  {t_refined * 1e3:8.1f} ms  ({t_refined / t_scaffold:.2f}x the scaffold pass)")
    if args.preset in TARGET_S:
        print(f"  peer: issue target {TARGET_S[args.preset]:.1f} s -> refined forward at "
              f"{t_refined / TARGET_S[args.preset]:.2f}x the budget")


if __name__ == "__main__":
    main()
