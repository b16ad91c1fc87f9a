"""The fused CPU kernels' cache follows the constants they read, and threads never launch the kernels at once."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("numba", reason="the fused CPU backend needs numba (pip install 'anycity[cpu]')")

from helpers.scenes import make_cameras, make_gaussians  # noqa: E402

from anycity.render import _numba_cache, render  # noqa: E402
from anycity.structures import Gaussians  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")
NUMBA_CACHE = Path(_numba_cache.__file__)

# Two copies of a one-line kernel reading a constant imported from another file, the second stamped; run in a fresh
# process (no torch: fast). Prints [value, cache hits, cache misses] of each.
_PROBE = textwrap.dedent("""
    import importlib.util, json, sys
    sys.path.insert(0, sys.argv[1])
    spec = importlib.util.spec_from_file_location("numba_cache", sys.argv[2])
    numba_cache = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(numba_cache)
    import plain_kernel, stamped_kernel
    numba_cache.stamp_constants([stamped_kernel.add_step])
    out = []
    for kernel in (plain_kernel.add_step, stamped_kernel.add_step):
        value = kernel(1)
        out.append([value, sum(kernel.stats.cache_hits.values()), sum(kernel.stats.cache_misses.values())])
    print(json.dumps(out))
""")


def test_an_edited_imported_constant_makes_the_cached_kernel_compile_again(tmp_path: Path):
    """numba keeps a kernel's cache while the kernel's own file is unchanged, though it froze the constants the
    kernel imports (projection.ALPHA_MAX, sh.C1, ...) into it: edit one and the kernel ran on the old value.
    ``stamp_constants`` makes the cache follow them; an unchanged constant still loads from the cache."""
    (tmp_path / "consts.py").write_text("STEP = 1\n")
    for name in ("plain_kernel", "stamped_kernel"):
        (tmp_path / f"{name}.py").write_text("import numba\n\nfrom consts import STEP\n\n\n"
                                             "@numba.njit(cache=True)\ndef add_step(x):\n    return x + STEP\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))

    def probe():  # -> [[value, cache hits, cache misses] of the plain kernel, the same of the stamped one]
        res = subprocess.run([sys.executable, "-c", _PROBE, str(tmp_path), str(NUMBA_CACHE)], env=env,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        return json.loads(res.stdout)

    assert probe() == [[2, 0, 1], [2, 0, 1]]  # both compiled and cached
    (tmp_path / "consts.py").write_text("STEP = 10\n")
    plain, stamped = probe()
    assert plain == [2, 1, 0]  # numba alone: the stale kernel, loaded from its cache
    assert stamped == [11, 0, 1]  # stamped: compiled again with the new value
    assert probe()[1] == [11, 1, 0]  # and cached: the stamp is the same in a new process


def test_every_renderer_kernel_cache_is_stamped_with_its_modules_constants(monkeypatch):
    """Each kernel of the fused backend (entry points and the helpers they call, both channel counts) carries the
    digest of its module's constants; changing one (here as if projection.ALPHA_MAX or sh.C3 were edited) turns
    the cached entries stale, so numba compiles instead of loading. Checked without compiling anything."""
    from anycity.render import _cpu_project as proj
    from anycity.render import _cpu_raster as rast
    from anycity.render import cpu_backend
    from anycity.render._numba_cache import constants_digest, stamp_constants

    g, w2c, K = make_gaussians(N=5, dtype=torch.float32), *make_cameras(1, 1, 8, 8, dtype=torch.float32)
    render(g, w2c, K, 8, 8, backend="cpu")  # the cache holds this session's kernels
    kernels = {id(d): d for D in (4, 7) for d in cpu_backend._all_dispatchers(D)}.values()
    assert {"project_fwd", "_project_bwd_chunk", "bin_pairs", "raster_fwd"} <= {d.__name__ for d in kernels}
    for disp in kernels:
        source, digest = disp._cache._cache_file._source_stamp
        assert source == disp._cache._impl.locator.get_source_stamp(), disp.__name__
        assert digest == constants_digest(disp.py_func.__globals__), disp.__name__

    fwd = cpu_backend.raster_kernels(4)[0]
    assert fwd._cache._cache_file._load_index()  # a fresh entry: loaded, not compiled
    before = {m: constants_digest(vars(m)) for m in (proj, rast)}
    try:
        monkeypatch.setattr(rast, "AMAX", np.float32(0.5))
        monkeypatch.setattr(proj, "_C3", proj._C3 * 2)
        assert all(constants_digest(vars(m)) != before[m] for m in (proj, rast))
        stamp_constants([fwd])
        assert fwd._cache._cache_file._load_index() == {}  # stale: numba would compile the kernel again
    finally:
        monkeypatch.undo()
        stamp_constants([fwd])
    assert fwd._cache._cache_file._load_index()


_ALPHA_PROBE = textwrap.dedent("""
    import json, sys, torch
    sys.path.insert(0, sys.argv[1])
    import anycity
    from anycity.render import render
    from anycity.structures import Gaussians
    assert anycity.__file__.startswith(sys.argv[1])
    g = Gaussians(means=torch.tensor([[[0.0, 0.0, 3.0]]]), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
                  scales=torch.full((1, 1, 3), 0.3), opacities=torch.ones(1, 1), sh=torch.ones(1, 1, 1, 3))
    K = torch.tensor([[[[16.0, 0, 8.5], [0, 16.0, 8.5], [0, 0, 1]]]])  # the mean on a pixel centre: α = the cap
    print(json.dumps([render(g, torch.eye(4)[None, None], K, 16, 16, backend=b).alpha.max().item()
                      for b in ("torch", "cpu")]))
""")


@pytest.mark.slow
def test_the_renderer_follows_an_edited_projection_constant(tmp_path: Path):
    """End to end on a copy of the package: edit projection.ALPHA_MAX and the fused kernels cap α at the new value
    (they kept 0.99 from their cache). Compiles the kernels twice in a fresh cache: minutes on 2 cores."""
    import shutil

    import anycity

    shutil.copytree(Path(anycity.__file__).parent, tmp_path / "anycity", ignore=shutil.ignore_patterns("__pycache__"))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))

    def probe():
        res = subprocess.run([sys.executable, "-c", _ALPHA_PROBE, str(tmp_path)], env=env, capture_output=True,
                             text=True, timeout=900)
        assert res.returncode == 0, res.stderr
        return json.loads(res.stdout.strip().splitlines()[-1])

    assert probe() == pytest.approx([0.99, 0.99], abs=1e-6)
    projection = tmp_path / "anycity" / "render" / "projection.py"
    text = projection.read_text()
    assert "ALPHA_MAX = 0.99\n" in text
    projection.write_text(text.replace("ALPHA_MAX = 0.99\n", "ALPHA_MAX = 0.5\n"))
    assert probe() == pytest.approx([0.5, 0.5], abs=1e-6)


def _leaf_scene():
    g = make_gaussians(B=1, N=40, K=4, seed=3, dtype=torch.float32)
    return Gaussians(**{k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS})


def _render_and_grad(g, w2c, K):
    out = render(g, w2c, K, 24, 16, backend="cpu", render_normals=True)
    grads = torch.autograd.grad(out.rgb.sum() + out.depth.mean() + out.normal.sum(), [g.means, g.sh])
    return [out.rgb.detach(), out.depth.detach(), *grads]


def test_threads_never_launch_the_kernels_at_once(monkeypatch):
    """numba's "workqueue" threading layer (no OpenMP, no TBB: a slim Docker image) aborts the process when two
    threads launch a parallel kernel at once, e.g. the viewer's "Save render" in viser's threads. Every kernel call,
    forward and backward, is wrapped here to record overlaps (with a sleep inside to make them likely); two threads
    rendering and differentiating concurrently get the sequential results."""
    from anycity.render import _cpu_project as proj
    from anycity.render import _cpu_raster as rast
    from anycity.render import cpu_backend

    g, (w2c, K) = _leaf_scene(), make_cameras(1, 2, 24, 16, dtype=torch.float32)
    expected = _render_and_grad(g, w2c, K)  # also compiles/loads the kernels before they are wrapped
    state = {"inside": 0, "overlaps": 0, "calls": 0}
    count = threading.Lock()

    def wrap(kernel):
        def call(*args):
            with count:
                state["inside"] += 1
                state["calls"] += 1
                state["overlaps"] += state["inside"] > 1
            time.sleep(0.002)
            try:
                return kernel(*args)
            finally:
                with count:
                    state["inside"] -= 1
        return call

    for module, name in ((proj, "project_fwd"), (proj, "project_bwd"), (rast, "depth_order"), (rast, "bin_pairs")):
        monkeypatch.setattr(module, name, wrap(getattr(module, name)))
    raster = cpu_backend.raster_kernels(7)
    monkeypatch.setitem(cpu_backend._kernels, 7, tuple(wrap(k) for k in raster))

    results = [None, None]

    def job(i):
        results[i] = [_render_and_grad(g, w2c, K) for _ in range(4)]

    threads = [threading.Thread(target=job, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert state["calls"] == 2 * 4 * 6 and state["overlaps"] == 0
    for per_thread in results:
        for got in per_thread:
            for a, b in zip(got, expected):
                torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.slow
def test_two_threads_render_under_the_workqueue_threading_layer():
    """The process that two threads render in survives numba's "workqueue" layer (it aborted it before). A fresh
    process with torch (about 8 s on 2 cores): the kernel-overlap test above checks the same lock in-process."""
    script = textwrap.dedent("""
        import json, sys, threading, torch
        sys.path.insert(0, sys.argv[1])
        import numba
        from helpers.scenes import make_cameras, make_gaussians
        from anycity.render import render
        from anycity.structures import Gaussians
        torch.set_num_threads(2)
        g = make_gaussians(N=60, K=4, dtype=torch.float32)
        g = Gaussians(**{k: getattr(g, k).requires_grad_(True) for k in ("means", "quats", "scales", "opacities",
                                                                         "sh")})
        w2c, K = make_cameras(1, 2, 32, 24, dtype=torch.float32)
        def run():
            out = render(g, w2c, K, 32, 24, backend="cpu")
            grad, = torch.autograd.grad(out.rgb.sum() + out.depth.mean(), [g.means])
            return out.rgb.detach(), grad
        expected, results = run(), {}
        def job(i):
            results[i] = [run() for _ in range(6)]
        threads = [threading.Thread(target=job, args=(i,)) for i in range(2)]
        [t.start() for t in threads]
        [t.join() for t in threads]
        same = all(torch.equal(a, b) for r in results.values() for got in r for a, b in zip(got, expected))
        print(json.dumps([numba.threading_layer(), len(results), same]))
    """)
    env = dict(os.environ, NUMBA_THREADING_LAYER="workqueue")
    res = subprocess.run([sys.executable, "-c", script, str(Path(__file__).parents[2])], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(res.stdout.strip().splitlines()[-1]) == ["workqueue", 2, True]
