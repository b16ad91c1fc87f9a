"""Chunked city prediction: wall time and peak RSS against the photo count.

    python benchmarks/city.py [--views 48 96 192 384] [--size 48] [--chunk 32] [--overlap 8] [--threads 2]

Each photo count runs in its own process (so peak RSS is that run's own): the tiny preset (random init, the
quickstart's ``camera_trunk_depth: 2``) reconstructs random 48x48 photos in overlapping chunks, then
:class:`anycity.city.ChunkedScene` aligns and merges them into one ``scene.ply`` + ``cameras.json`` (the same code
path as ``anycity predict``, minus Lightning and the optional camera refinement; one warm-up chunk runs
before the clock starts). A random network's geometry is
meaningless, so the inlier threshold is wide open: this measures cost, not accuracy. Goal: time linear in the photo
count, peak memory flat (within 20 %) from 96 to 384 photos.

    python benchmarks/city.py --align [--views 200 1000 2000] [--chunk 16] [--overlap 4]

The alignment alone (pairwise fits + checked pose graph, one thread) on oracle chunks of an orbit
(:mod:`anycity.city.oracle`, 0.3 % depth noise), each photo count in its own process: time and the peak RSS it adds.

    python benchmarks/city.py --loop-check

The pose graph's cycle check on oracle orbits with a loop chunk (chunks of 16/4): for consistent loops (noise, and
chunks stretched along themselves) and loop chunks whose halves were placed apart, the largest edge residual under
the pose graph over its inlier threshold, what was dropped, the loop's correction, and the camera errors against
the same chunks without the loop chunk.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import sys
import tempfile
import time
from pathlib import Path

from _bench import positive_int, run_child


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


def run_align(views: int, chunk: int, overlap: int) -> dict:
    import torch

    from anycity.city import align_chunks, plan_chunks
    from anycity.city.oracle import oracle_chunks, orbit_scene

    torch.set_num_threads(1)
    torch.autograd.functional.jacobian(lambda x: x * 2, torch.zeros(2), vectorize=True, strategy="forward-mode")
    w2c, pts = orbit_scene(views, arc=0.9)
    plan = plan_chunks(views, chunk, overlap)
    chunks, _ = oracle_chunks(w2c, pts, plan, depth_noise=0.003)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t0 = time.perf_counter()
    _, edges, _ = align_chunks(chunks)
    return {"views": views, "chunks": len(plan), "edges": len(edges), "time_s": round(time.perf_counter() - t0, 2),
            "added_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - rss0)}


def _stretched(chunk, beta: float):
    """``chunk`` scaled about its first camera by ``1 + beta * i / (V - 1)`` at its view i: a systematic drift."""
    import torch

    from anycity.city import ChunkGeometry
    from anycity.geometry.cameras import camera_centers

    c = camera_centers(chunk.w2c)
    f = 1 + beta * torch.linspace(0, 1, len(chunk.views), dtype=torch.float64)[:, None]
    w2c, points = chunk.w2c.clone(), c[:1, None] + (chunk.points - c[:1, None]) * f[..., None]
    w2c[:, :3, 3] = -(w2c[:, :3, :3] @ (c[:1] + (c - c[:1]) * f)[..., None])[..., 0]
    return ChunkGeometry(chunk.views, w2c, points)


def loop_check() -> None:
    import warnings

    import torch

    from anycity.city import ChunkGeometry, align_chunks, apply_sim3, plan_chunks, pose_graph, w2c_to_world
    from anycity.city.align import _exp_so3
    from anycity.city.oracle import camera_errors, oracle_chunks, orbit_scene, random_sim3
    from anycity.city.posegraph import LOOP_WARN_DEG, LOOP_WARN_SCALE, edge_rms
    from anycity.geometry.alignment import sim3_matrix

    torch.set_num_threads(1)
    warnings.simplefilter("ignore")

    def errors(chunks, S, n, w2c):
        own = {}
        for k, c in enumerate(chunks):
            for i, v in enumerate(c.views):
                own.setdefault(v, w2c_to_world(c.w2c[i], S[k]))
        e = camera_errors(torch.stack([own[v] for v in range(n)]), w2c)
        return f"{e['rot_deg_mean']:.2f} / {e['pos_rel_max']:.3f}"

    print("| photos | chunks | case | max residual / threshold | dropped | loop correction | rot° / pos (with) | "
          "rot° / pos (without) |\n|---|---|---|---|---|---|---|---|")
    for n in (60, 120, 400, 1000):
        w2c, pts = orbit_scene(n, arc=1.0)
        plan = plan_chunks(n, 16, 4, loop=True)
        for case, noise, beta, broken in (("noise 0.3 %", 0.003, 0, False), ("noise 3 %", 0.03, 0, False),
                                          ("noise 1 %, stretched 2 %", 0.01, 0.02, False),
                                          ("noise 1 %, stretched 5 %", 0.01, 0.05, False),
                                          ("noise 0.3 %, halves 20° apart", 0.003, 0, 20.0),
                                          ("noise 0.3 %, halves a random Sim(3) apart", 0.003, 0, True)):
            chunks, _ = oracle_chunks(w2c, pts, plan, rot_deg=30 * noise, centre_noise=noise, depth_noise=noise)
            chunks = [_stretched(c, beta) for c in chunks] if beta else chunks
            if broken:
                L, h, E = chunks[-1], 8, random_sim3(torch.Generator().manual_seed(9))
                if broken is not True:  # turned by that many degrees about the half's centre
                    c = L.points[h:].reshape(-1, 3).mean(0)
                    axis = torch.tensor([0.3, 0.5, 0.8], dtype=torch.float64) / 0.98 ** 0.5
                    R = _exp_so3(axis * math.radians(broken))
                    E = sim3_matrix(torch.tensor(1.0, dtype=torch.float64), R, c - R @ c)
                w, p = L.w2c.clone(), L.points.clone()
                w[h:], p[h:] = w2c_to_world(w[h:], E), apply_sim3(E, p[h:])
                chunks[-1] = ChunkGeometry(L.views, w, p)
            S, edges, rep = align_chunks(chunks)
            S_all = pose_graph(len(chunks), edges)[0]  # every edge, before the check
            worst = max(float(r) / e.fit.threshold for r, e in zip(edge_rms(S_all, edges), edges))
            corr = ""
            if "loop_rotation_deg" in rep:
                deg, scale = rep["loop_rotation_deg"], rep["loop_scale"]
                warns = deg > LOOP_WARN_DEG or max(scale, 1 / scale) > LOOP_WARN_SCALE
                corr = f"{deg:.1f}°, ×{scale:.3f}{' (warns)' if warns else ''}"
            S_open, _, _ = align_chunks(chunks[:-1])
            print(f"| {n} | {len(plan)} | {case} | {worst:.2f} | {rep['dropped_pairs'] or ''} | {corr} | "
                  f"{errors(chunks, S, n, w2c)} | {errors(chunks[:-1], S_open, n, w2c)} |", flush=True)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=positive_int, nargs="+", default=[48, 96, 192, 384])
    ap.add_argument("--size", type=positive_int, default=48)
    ap.add_argument("--chunk", type=positive_int, default=32)
    ap.add_argument("--overlap", type=int, default=8)
    ap.add_argument("--threads", type=positive_int, default=2)
    ap.add_argument("--align", action="store_true", help="the alignment alone on oracle chunks")
    ap.add_argument("--loop-check", action="store_true", help="the pose graph's cycle check on oracle loops")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.loop_check:
        loop_check()
        return
    if a.one:
        print(json.dumps(run_align(a.views[0], a.chunk, a.overlap) if a.align else
                         run_one(a.views[0], a.size, a.chunk, a.overlap, a.threads)))
        return
    if a.align:
        for v in a.views:
            cmd = [sys.executable, __file__, "--one", "--align", "--views", str(v), "--chunk", str(a.chunk),
                   "--overlap", str(a.overlap)]
            r = json.loads(run_child(cmd, f"city.py --align, {v} photos").splitlines()[-1])
            print(f"{r['views']:5d} photos  {r['chunks']:4d} chunks  {r['edges']:4d} edges  align {r['time_s']:6.2f} s"
                  f"  +{r['added_rss_mb']} MB peak RSS", flush=True)
        return
    rows = []
    for v in a.views:
        cmd = [sys.executable, __file__, "--one", "--views", str(v), "--size", str(a.size), "--chunk", str(a.chunk),
               "--overlap", str(a.overlap), "--threads", str(a.threads)]
        rows.append(json.loads(run_child(cmd, f"city.py, {v} photos").strip().splitlines()[-1]))
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
