"""Renderer benchmark: forward and forward+backward wall time and peak memory per backend.

    python benchmarks/render.py [--threads 2] [--repeats 5] [--cases 10k,100k,800k] [--backends torch,cpu]
    python benchmarks/render.py --device cuda [--backends torch,gsplat]    # on a GPU: peak is CUDA memory
    python benchmarks/render.py --cold-compile    # the cpu backend's first-use compile, per kernel

Each case runs in its own subprocess so that the peak RSS is that case's alone. Times are the minimum over
``--repeats`` runs after one warm-up. Scenes: random anisotropic Gaussians filling the view frustum, sized so that
100k Gaussians at 256x256 give about 40 footprint-box overlaps per pixel (the figure printed as "ovl/px").
The dense float64 reference of the tests runs on a small case for scale. Peers quoted in the printed footer come
from shared/research/renderer.md (same 2-core machine class): gsplat-pytorch (Mxbonn) 2287 ms fwd+bwd on the
100k case at 2 threads, so the ratio is printed only for ``--threads 2`` on the CPU.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import torch
from _bench import positive_int, run_child

ROOT = Path(__file__).resolve().parents[1]
CASES = {"10k": (10_000, 256, 256), "100k": (100_000, 256, 256), "800k": (800_000, 448, 448)}
PEER_MS = {"100k": 2287.0}  # gsplat-pytorch, fwd+bwd, 2 threads (research notes)
PEER_THREADS = 2


def make_scene(n: int, width: int, height: int, seed: int = 0, dtype=torch.float32):
    """N Gaussians uniformly in the frustum at z in [4, 8], footprints of ~0.6 px std (plus eps2d) at 256²."""
    from anycity.structures import Gaussians

    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    z = 4 + 4 * torch.rand(n, generator=g)
    u = torch.rand(n, generator=g) * width
    v = torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    base = 0.4 * z / f  # ~0.4 px std once projected, before the 0.3 px² low-pass (scene A of the research notes)
    scales = base[:, None] * torch.exp(0.5 * torch.randn(n, 3, generator=g))
    gauss = Gaussians(
        means=means[None].to(dtype),
        quats=torch.randn(1, n, 4, generator=g).to(dtype),
        scales=scales[None].to(dtype),
        opacities=(0.1 + 0.9 * torch.rand(1, n, generator=g))[None, 0].to(dtype),
        sh=(0.5 * torch.randn(1, n, 1, 3, generator=g)).to(dtype),
    )
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)[None, None]
    return gauss, torch.eye(4, dtype=dtype)[None, None], K


def _time(fn, repeats: int, device: str = "cpu") -> float:
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    fn()
    best = float("inf")
    for _ in range(repeats):
        sync()
        t = time.perf_counter()
        fn()
        sync()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def run_case(case: str, backend: str, threads: int, repeats: int, queue, device: str = "cpu") -> None:
    torch.set_num_threads(threads)
    from anycity.render import render
    from anycity.render.projection import project_gaussians

    n, w, h = CASES[case] if case in CASES else (500, 64, 64)
    g, w2c, K = make_scene(n, w, h, dtype=torch.float64 if backend == "reference" else torch.float32)
    if device != "cpu":
        g = type(g)(*[t.to(device) for t in (g.means, g.quats, g.scales, g.opacities, g.sh)])
        w2c, K = w2c.to(device), K.to(device)
    params = [g.means, g.quats, g.scales, g.opacities, g.sh]
    for p in params:
        p.requires_grad_(True)
    if backend == "reference":
        sys.path.insert(0, str(ROOT / "tests"))
        from helpers.render_reference import render_reference as fwd_fn

        def fwd():
            return fwd_fn(g, w2c, K, w, h)
    else:
        def fwd():
            return render(g, w2c, K, w, h, backend=backend)

    with torch.no_grad():
        proj = project_gaussians(*[p.detach() for p in params], torch.ones(1, n, dtype=torch.bool, device=device),
                                 w2c, K, w, h, 0.01, 1e10, False)
        # Footprint overlaps per pixel: continuous boxes of 2 x 3.33 sigma per axis (as the research notes count
        # them) and the integer boxes the binning actually enumerates.
        conic = proj.conic[proj.visible].double()
        det = conic[:, 0] * conic[:, 2] - conic[:, 1] ** 2
        box = (6.66 * (conic[:, 2] / det).sqrt()) * (6.66 * (conic[:, 0] / det).sqrt())
        r = proj.radius[proj.visible].double()
        overlaps = float(box.sum()) / (w * h)
        int_overlaps = float((4 * r[:, 0] * r[:, 1]).sum()) / (w * h)

    def fwd_only():
        with torch.no_grad():
            fwd()

    def fwd_bwd():
        out = fwd()
        (out.rgb.sum() + out.depth.mean() + out.alpha.sum()).backward()
        for p in params:
            p.grad = None

    reps = 1 if backend == "reference" else repeats
    t_f = _time(fwd_only, reps, device)
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    t_fb = _time(fwd_bwd, reps, device)
    if device == "cuda":  # the GPU's peak, allocated by torch during forward+backward
        rss_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    queue.put(dict(case=case, backend=backend, n=n, size=f"{w}x{h}", overlaps=overlaps, int_overlaps=int_overlaps,
                   fwd_ms=t_f, fwdbwd_ms=t_fb,
                   peak_rss_mb=rss_mb))


_COLD = textwrap.dedent("""
    import json, time
    import torch
    from numba.core import event
    from anycity.render import render
    from anycity.render.cpu_backend import _dispatchers
    from anycity.structures import Gaussians
    g = Gaussians(means=torch.tensor([[[0.0, 0.0, 3.0]]], requires_grad=True), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
                  scales=torch.full((1, 1, 3), 0.2), opacities=torch.ones(1, 1), sh=torch.ones(1, 1, 1, 3))
    K = torch.tensor([[[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]]])
    t = time.perf_counter()
    with event.install_recorder("numba:compile") as rec:
        render(g, torch.eye(4)[None, None], K, 16, 16, backend="cpu").rgb.sum().backward()
    total = time.perf_counter() - t
    kernels, start = {d.py_func for d in _dispatchers(4)}, {}
    per = {}
    for ts, ev in rec.buffer:
        f = ev.data["dispatcher"].py_func
        if f in kernels:
            if ev.is_start:
                start[f] = ts
            else:
                per[f.__name__] = per.get(f.__name__, 0.0) + ts - start[f]
    print(json.dumps({"total": total, "per_kernel": per}))
""")


def cold_compile() -> None:
    """First use of the cpu backend in a fresh process with an empty numba cache: wall time and each kernel's
    compile time (a kernel's own includes the serial functions it calls)."""
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(ROOT / "src"))
        out = run_child([sys.executable, "-c", _COLD], "render.py --cold-compile's child", env=env)
    r = json.loads(out.strip().splitlines()[-1])
    kernels = ", ".join(f"{k} {v:.1f} s" for k, v in sorted(r["per_kernel"].items(), key=lambda kv: -kv[1]))
    print(f"cpu backend, first use with an empty cache: {r['total']:.1f} s ({kernels})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=positive_int, default=2)
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--cases", default="10k,100k,800k", help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--backends", default="auto-available")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", help="also write the rows to this file")
    ap.add_argument("--cold-compile", action="store_true", help="only time the cpu backend's first-use compile")
    args = ap.parse_args(argv)
    cases = args.cases.split(",")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        ap.error(f"--cases: unknown case(s) {', '.join(map(repr, unknown))}; choose from {', '.join(CASES)}")
    if args.cold_compile:
        return cold_compile()
    sys.path.insert(0, str(ROOT / "src"))
    from anycity.render.api import _cpu_backend_available

    backends = args.backends.split(",") if args.backends != "auto-available" else (
        ["torch"] + (["cpu"] if _cpu_backend_available() else []))
    jobs = [(c, b) for c in cases for b in backends]
    if args.device == "cpu":  # the float64 dense reference is a CPU tool
        jobs += [("small", "reference"), ("small", "torch")]
    ctx = mp.get_context("spawn")
    rows = []
    peak = "peak MB is CUDA memory allocated in fwd+bwd" if args.device == "cuda" else "peak RSS is the whole process"
    print(f"device={args.device} threads={args.threads} repeats={args.repeats} (min of N; {peak})")
    print(f"{'case':>6} {'backend':>9} {'N':>8} {'size':>8} {'ovl/px':>7} {'int/px':>7} {'fwd ms':>9} "
          f"{'fwd+bwd ms':>11} {'peak MB':>8}")
    for case, backend in jobs:
        q = ctx.Queue()
        p = ctx.Process(target=run_case, args=(case, backend, args.threads, args.repeats, q, args.device))
        p.start()
        p.join()
        if p.exitcode != 0:
            print(f"{case:>6} {backend:>9}  failed (exit {p.exitcode})")
            continue
        r = q.get()
        rows.append(r)
        print(f"{r['case']:>6} {r['backend']:>9} {r['n']:>8} {r['size']:>8} {r['overlaps']:>7.1f} "
              f"{r['int_overlaps']:>7.1f} "
              f"{r['fwd_ms']:>9.1f} {r['fwdbwd_ms']:>11.1f} {r['peak_rss_mb']:>8.0f}")
    for r in rows:
        if r["case"] in PEER_MS and args.device == "cpu" and args.threads == PEER_THREADS:
            print(f"{r['case']} {r['backend']}: {PEER_MS[r['case']] / r['fwdbwd_ms']:.1f}x faster fwd+bwd than "
                  f"gsplat-pytorch ({PEER_MS[r['case']]:.0f} ms at {PEER_THREADS} threads, research notes); "
                  "target <= 250 ms (torch backend)")
    if args.device == "cpu" and args.threads != PEER_THREADS and any(r["case"] in PEER_MS for r in rows):
        print(f"(no gsplat-pytorch ratio: its figure is for {PEER_THREADS} threads; run with --threads {PEER_THREADS})")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
