"""Chunked city prediction: wall time and peak RSS against the photo count.

    python benchmarks/city.py [--views 48 96 192 384] [--size 48] [--chunk 32] [--overlap 8] [--threads 2]

Each photo count runs in its own process (so peak RSS is that run's own): the tiny preset (random init, the
quickstart's ``camera_trunk_depth: 2``) reconstructs random 48x48 photos in overlapping chunks, then
:class:`anycity.city.ChunkedScene` aligns and merges them into one ``scene.ply`` + ``cameras.json`` (the same code
path as ``anycity predict``, minus Lightning and the optional camera refinement; one warm-up chunk runs
before the clock starts). A random network's geometry is
meaningless, so the inlier threshold is wide open: this measures cost, not accuracy. Goal: time linear in the photo
count, peak memory flat (within 20 %) from 96 to 384 photos.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_one(views: int, size: int, chunk: int, overlap: int, threads: int) -> dict:
    import torch

    from anycity.city import ChunkedScene, plan_chunks
    from anycity.models import build_network

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    net = build_network("tiny", camera_trunk_depth=2).eval()
    plan = plan_chunks(views, chunk, overlap)
    with torch.no_grad():  # warm-up outside the timing: first-call allocations and lazy imports (functorch)
        net(torch.rand(1, chunk, 3, size, size), refine=False)
    torch.autograd.functional.jacobian(lambda x: x * 2, torch.zeros(2), vectorize=True, strategy="forward-mode")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        scene = ChunkedScene(plan, [f"{i:04d}.png" for i in range(views)], (size, size), rel_threshold=1e3)
        g = torch.Generator().manual_seed(0)
        for k, idx in enumerate(plan):
            images = torch.rand(1, len(idx), 3, size, size, generator=g)  # a chunk's photos, loaded on demand
            with torch.no_grad():
                out = net(images, refine=False)
            scene.add(k, out["gaussians"], out["w2c"][0], out["K"][0])
            del out, images
        t_net = time.perf_counter() - t0
        rep = scene.finish(Path(d) / "out")
        ply_mb = (Path(d) / "out" / "scene.ply").stat().st_size / 2**20
    total = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux
    return {"views": views, "chunks": len(plan), "time_s": round(total, 2), "network_s": round(t_net, 2),
            "align_merge_s": round(total - t_net, 2), "peak_rss_mb": round(rss, 1), "gaussians": rep["gaussians"],
            "ply_mb": round(ply_mb, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, nargs="+", default=[48, 96, 192, 384])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--chunk", type=int, default=32)
    ap.add_argument("--overlap", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.one:
        print(json.dumps(run_one(a.views[0], a.size, a.chunk, a.overlap, a.threads)))
        return
    rows = []
    for v in a.views:
        cmd = [sys.executable, __file__, "--one", "--views", str(v), "--size", str(a.size), "--chunk", str(a.chunk),
               "--overlap", str(a.overlap), "--threads", str(a.threads)]
        res = subprocess.run(cmd, capture_output=True, text=True, check=True)
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"{r['views']:5d} views  {r['chunks']:3d} chunks  {r['time_s']:7.2f} s (network {r['network_s']:.2f}, "
              f"align+merge {r['align_merge_s']:.2f})  {r['time_s'] / r['views'] * 1000:6.1f} ms/view  "
              f"peak RSS {r['peak_rss_mb']:7.1f} MB  {r['gaussians']} Gaussians ({r['ply_mb']} MB ply)", flush=True)
    by = {r["views"]: r for r in rows}
    if 96 in by and 384 in by:
        print(f"peak RSS 384 vs 96 views: {by[384]['peak_rss_mb'] / by[96]['peak_rss_mb']:.3f}x (goal <= 1.2); "
              f"time per view 384 vs 96: {by[384]['time_s'] / 384 / (by[96]['time_s'] / 96):.3f}x (goal ~1)")


if __name__ == "__main__":
    main()
