"""The fused numba backend against the torch backend and the dense float64 reference, forward and backward."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from unittest.mock import ANY

import pytest
import torch

pytest.importorskip("numba", reason="the fused CPU backend needs numba (pip install 'anycity[cpu]')")

from helpers.render_reference import render_reference  # noqa: E402

from anycity.geometry import quat_to_rotmat  # noqa: E402
from anycity.render import render, resolve_backend  # noqa: E402
from anycity.structures import Gaussians  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")
CAMS = ("w2c", "K", "background")


def make_scene(B=1, V=1, N=120, W=40, H=32, sh_degree=0, seed=0, scale=0.06, z_range=(2.0, 5.0)):
    """B scenes of N random Gaussians in front of V cameras that look roughly the same way."""
    g = torch.Generator().manual_seed(seed)
    z = z_range[0] + (z_range[1] - z_range[0]) * torch.rand(B, N, generator=g)
    f = 0.9 * W
    u, v = (torch.rand(B, N, generator=g) - 0.5) * 1.2 * W, (torch.rand(B, N, generator=g) - 0.5) * 1.2 * H
    means = torch.stack([u * z / f, v * z / f, z], -1)
    gauss = Gaussians(
        means=means.double(),
        quats=torch.randn(B, N, 4, generator=g).double(),
        scales=(scale * torch.exp(0.5 * torch.randn(B, N, 3, generator=g))).double(),
        opacities=(0.05 + 0.9 * torch.rand(B, N, generator=g)).double(),
        sh=(0.4 * torch.randn(B, N, (sh_degree + 1) ** 2, 3, generator=g)).double(),
    )
    q = torch.cat([torch.ones(B, V, 1), 0.05 * torch.randn(B, V, 3, generator=g)], -1)
    q[:, 0] = torch.tensor([1.0, 0, 0, 0])
    w2c = torch.eye(4).repeat(B, V, 1, 1)
    w2c[..., :3, :3] = quat_to_rotmat(q)
    w2c[:, 1:, :3, 3] = 0.2 * torch.randn(B, V - 1, 3, generator=g)
    K = torch.tensor([[f, 0, W / 2], [0, 0.95 * f, H / 2 + 1.5], [0, 0, 1]]).repeat(B, V, 1, 1)
    return gauss, w2c.double(), K.double()


def cast(gauss: Gaussians, dtype, grad=True) -> Gaussians:
    fields = {k: getattr(gauss, k).detach().to(dtype).requires_grad_(grad) for k in PARAMS}
    return Gaussians(**fields, valid=gauss.valid)


def loss_fn(out, weights):
    loss = (out.rgb * weights["rgb"]).sum() + (out.alpha * weights["alpha"]).sum()
    loss = loss + (out.depth * weights["depth"]).sum()
    if out.normal is not None:
        loss = loss + (out.normal * weights["normal"]).sum()
    return loss


def run(backend, gauss, w2c, K, W, H, weights, dtype=torch.float32, background=None, **kw):
    """Render and differentiate ``loss_fn`` w.r.t. the Gaussians (PARAMS) and the cameras and background (CAMS)."""
    g = cast(gauss, dtype)
    B, V = w2c.shape[:2]
    bg = torch.zeros(3) if background is None else background
    cams = [t.detach().to(dtype).clone().requires_grad_(True) for t in (w2c, K, bg.expand(B, V, 3))]
    args = (g, cams[0], cams[1], W, H)
    kw["background"] = cams[2]
    out = render_reference(*args, **kw) if backend == "reference" else render(*args, backend=backend, **kw)
    params = [getattr(g, k) for k in PARAMS] + cams
    grads = torch.autograd.grad(loss_fn(out, {k: w.to(dtype) for k, w in weights.items()}), params,
                                allow_unused=True)
    grads = [torch.zeros_like(p) if gr is None else gr for p, gr in zip(params, grads)]
    return out, dict(zip(PARAMS + CAMS, grads))


def make_weights(B, V, W, H, seed=1):
    g = torch.Generator().manual_seed(seed)
    return {
        "rgb": torch.randn(B, V, 3, H, W, generator=g).double(),
        "alpha": torch.randn(B, V, 1, H, W, generator=g).double(),
        # depth = Σwz / α is ill-conditioned where α is tiny; weight it only where a surface is clearly hit
        "depth": 0.1 * torch.randn(B, V, 1, H, W, generator=g).double(),
        "normal": torch.randn(B, V, 3, H, W, generator=g).double(),
    }


def compare(gauss, w2c, K, W, H, *, grad_tol=2e-3, img_tol=2e-5, against=("reference", "torch"), **kw):
    B, V = w2c.shape[:2]
    weights = make_weights(B, V, W, H)
    ref_out, _ = run("reference", gauss, w2c, K, W, H, weights, dtype=torch.float64, **kw)
    weights["depth"] = weights["depth"] * (ref_out.alpha.detach() > 0.5)
    out, grads = run("cpu", gauss, w2c, K, W, H, weights, **kw)
    for name in against:
        dtype = torch.float64 if name == "reference" else torch.float32
        ref, ref_grads = run(name, gauss, w2c, K, W, H, weights, dtype=dtype, **kw)
        for field in ("rgb", "alpha", "normal"):
            a, b = getattr(out, field), getattr(ref, field)
            if b is not None:
                assert (a.double() - b.double()).abs().max() < img_tol, (name, field)
        hit = ref.alpha > 0.5
        dz = (out.depth.double() - ref.depth.double()).abs() / ref.depth.double().abs().clamp_min(1e-6)
        assert dz[hit].max() < 1e-4 if hit.any() else True, name
        for k in PARAMS + CAMS:
            a, b = grads[k].double(), ref_grads[k].double()
            scale = b.norm()
            if scale == 0:
                assert a.abs().max() == 0, (name, k)
            else:
                assert (a - b).norm() / scale < grad_tol, (name, k, ((a - b).norm() / scale).item())
    return out, grads


def test_auto_picks_cpu_for_float32():
    assert resolve_backend("auto", torch.device("cpu"), torch.float32) == "cpu"
    assert resolve_backend("auto", torch.device("cpu"), torch.float64) == "torch"


def test_basic_scene_matches_reference_and_torch():
    gauss, w2c, K = make_scene(N=150, W=40, H=32, seed=0)
    out, _ = compare(gauss, w2c, K, 40, 32)
    assert out.alpha.max() > 0.5  # the scene is not empty


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
def test_sh_degrees(degree):
    gauss, w2c, K = make_scene(N=80, W=24, H=32, sh_degree=degree, seed=degree)
    compare(gauss, w2c, K, 24, 32)


@pytest.mark.parametrize("normals", [True, False])
def test_batched_views_non_square_background_normals(normals):
    B, V, W, H = 2, 2, 36, 20
    gauss, w2c, K = make_scene(B=B, V=V, N=90, W=W, H=H, sh_degree=1, seed=3)
    bg = torch.rand(B, V, 3, generator=torch.Generator().manual_seed(5)).double()
    out, _ = compare(gauss, w2c, K, W, H, background=bg, render_normals=normals)
    assert out.normal is None if not normals else out.normal.shape == (B, V, 3, H, W)
    assert not torch.equal(out.rgb[0, 0], out.rgb[0, 1])  # different cameras, different images


def test_huge_gaussians_and_saturated_pixels():
    gauss, w2c, K = make_scene(N=40, W=32, H=24, seed=4, scale=0.6)  # footprints larger than the image
    gauss.opacities.data = 0.9 + 0.1 * gauss.opacities.data  # many pixels reach the T <= 1e-4 stop
    out, _ = compare(gauss, w2c, K, 32, 24)
    assert (out.alpha > 0.99).float().mean() > 0.5


@pytest.mark.parametrize("degree", [0, 3])
def test_camera_gradients_where_the_jacobian_is_clamped(degree):
    """Large Gaussians centred beyond the clamp limit (x/z past the image plus 15 % of the field of view) still
    cover the image: their Jacobian is taken at the limit, which moves with fx and cx; and each camera's SH view
    direction moves with its pose."""
    W, H = 32, 24
    gauss, w2c, K = make_scene(B=1, V=2, N=60, W=W, H=H, sh_degree=degree, seed=11, scale=0.5)
    side = torch.arange(60) % 4  # push a quarter of the means beyond each clamp limit
    z = gauss.means.data[0, :, 2]
    gauss.means.data[0, side == 0, 0] = 1.05 * z[side == 0]
    gauss.means.data[0, side == 1, 0] = -1.0 * z[side == 1]
    gauss.means.data[0, side == 2, 1] = 0.95 * z[side == 2]
    gauss.means.data[0, side == 3, 1] = -0.95 * z[side == 3]
    u = gauss.means[0, :, :2] / z[:, None] * K[0, 0, [0, 1], [0, 1]] + K[0, 0, [0, 1], [2, 2]]
    assert ((u[:, 0] > 1.15 * W) | (u[:, 0] < -0.15 * W) | (u[:, 1] > 1.15 * H) | (u[:, 1] < -0.15 * H)).all()
    out, grads = compare(gauss, w2c, K, W, H)
    assert out.alpha.max() > 0.3 and grads["K"].abs().sum() > 0


def test_empty_tiles_and_masked_gaussians():
    gauss, w2c, K = make_scene(N=60, W=48, H=40, seed=6, scale=0.02)
    gauss.means.data[..., :2] = gauss.means.data[..., :2].abs()  # lower-right quadrant only: empty tiles
    valid = torch.rand(1, 60, generator=torch.Generator().manual_seed(7)) > 0.4
    masked = Gaussians(**{k: getattr(gauss, k) for k in PARAMS}, valid=valid)
    out, grads = compare(masked, w2c, K, 48, 40)
    assert out.alpha[..., :12, :16].max() == 0
    assert grads["means"][~valid].abs().max() == 0 and grads["sh"][~valid].abs().max() == 0
    kept = Gaussians(**{k: getattr(gauss, k)[valid][None] for k in PARAMS})
    ref = render(cast(kept, torch.float32, grad=False), w2c.float(), K.float(), 48, 40, backend="cpu")
    assert torch.allclose(out.rgb, ref.rgb, atol=1e-6)


def test_no_gaussians_and_all_behind_camera():
    bg = torch.tensor([0.2, 0.4, 0.6])
    gauss, w2c, K = make_scene(N=0)
    out, grads = run("cpu", gauss, w2c, K, 40, 32, make_weights(1, 1, 40, 32), background=bg.double())
    assert torch.allclose(out.rgb, bg.view(1, 1, 3, 1, 1).expand_as(out.rgb)) and out.alpha.max() == 0
    gauss, w2c, K = make_scene(N=30, z_range=(-3.0, -1.0))
    out, grads = run("cpu", gauss, w2c, K, 40, 32, make_weights(1, 1, 40, 32))
    assert out.alpha.max() == 0 and out.depth.max() == 0
    assert all(grads[k].abs().max() == 0 for k in PARAMS + ("w2c", "K"))


def test_thread_count_does_not_change_bits():
    gauss, w2c, K = make_scene(B=1, V=2, N=300, W=64, H=48, sh_degree=2, seed=8)
    weights = make_weights(1, 2, 64, 48)
    threads = torch.get_num_threads()
    results = []
    try:
        for n in (1, 2, 1):
            torch.set_num_threads(n)
            out, grads = run("cpu", gauss, w2c, K, 64, 48, weights, render_normals=True)
            results.append([out.rgb, out.depth, out.alpha, out.normal, *grads.values()])
    finally:
        torch.set_num_threads(threads)
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_bad_dtype_and_forked_children_are_refused(monkeypatch):
    gauss, w2c, K = make_scene(N=5)
    with pytest.raises(ValueError, match="float32"):
        render(gauss, w2c, K, 8, 8, backend="cpu")
    from anycity.render import cpu_backend

    g32 = cast(gauss, torch.float32, grad=False)
    render(g32, w2c.float(), K.float(), 8, 8, backend="cpu")  # kernels have run in this process
    monkeypatch.setitem(cpu_backend._state, "pid", os.getpid() + 1)  # ... as if this were a forked child

    class Info:
        id = 3

    with pytest.raises(RuntimeError, match="child process forked"):
        render(g32, w2c.float(), K.float(), 8, 8, backend="cpu")
    monkeypatch.setattr(torch.utils.data, "get_worker_info", lambda: Info())
    with pytest.raises(RuntimeError, match="DataLoader worker 3"):
        render(g32, w2c.float(), K.float(), 8, 8, backend="cpu")


def test_forked_dataloader_worker_raises_a_clear_error():
    gauss, w2c, K = make_scene(N=5)
    g32, w2c, K = cast(gauss, torch.float32, grad=False), w2c.float(), K.float()
    render(g32, w2c, K, 8, 8, backend="cpu")

    class Renders(torch.utils.data.Dataset):
        def __len__(self):
            return 1

        def __getitem__(self, i):
            return render(g32, w2c, K, 8, 8, backend="cpu").rgb

    loader = torch.utils.data.DataLoader(Renders(), num_workers=1, multiprocessing_context="fork")
    with pytest.raises(RuntimeError, match="not fork-safe"):
        next(iter(loader))


_CACHE_PROBE = textwrap.dedent("""
    import json, time
    t = time.perf_counter()
    import torch
    from anycity.render import render
    from anycity.render import cpu_backend
    from anycity.structures import Gaussians
    g = Gaussians(means=torch.tensor([[[0.0, 0.0, 3.0]]], requires_grad=True), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
                  scales=torch.full((1, 1, 3), 0.2), opacities=torch.ones(1, 1), sh=torch.ones(1, 1, 1, 3))
    K = torch.tensor([[[[16.0, 0, 8], [0, 16.0, 8], [0, 0, 1]]]])
    render(g, torch.eye(4)[None, None], K, 16, 16, backend="cpu").rgb.sum().backward()
    stats = {d.__name__: [sum(d.stats.cache_hits.values()), sum(d.stats.cache_misses.values())]
             for d in cpu_backend._dispatchers(4)}
    print(json.dumps({"seconds": time.perf_counter() - t, "stats": stats}))
""")


def _probe(env) -> dict:
    res = subprocess.run([sys.executable, "-c", _CACHE_PROBE], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1]) | {"stderr": res.stderr}


def test_second_process_loads_the_compile_cache():
    """A fresh process finds every kernel in the cache (populated by this session's earlier calls)."""
    gauss, w2c, K = make_scene(N=5)
    render(cast(gauss, torch.float32), w2c.float(), K.float(), 8, 8, backend="cpu").rgb.sum().backward()
    result = _probe(dict(os.environ))
    for name, (hits, misses) in result["stats"].items():
        assert hits >= 1 and misses == 0, (name, result)
    assert "compiling" not in result["stderr"]


_TINY_PROBE = textwrap.dedent("""
    import importlib.util, json, sys
    sys.path.insert(0, sys.argv[1])
    import tiny_kernel
    spec = importlib.util.spec_from_file_location("numba_cache", sys.argv[2])
    numba_cache = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(numba_cache)
    dropped = numba_cache.repair_cache([tiny_kernel.add_one]) if sys.argv[3] == "repair" else []
    values = [tiny_kernel.add_one(1)] + ([tiny_kernel.add_one(1.5)] if len(sys.argv) > 4 else [])
    print(json.dumps({"dropped": dropped, "value": values[0] if len(values) == 1 else values}))
""")


def test_an_unreadable_kernel_cache_is_dropped_and_compiled_again(tmp_path: Path):
    """A truncated cache file (a disk that filled up, a copy cut short) made numba fail every call with an
    UnpicklingError; repair_cache drops it with one warning naming it, numba compiles again, the next process loads.
    A one-line kernel, imported without torch, keeps this fast."""
    from anycity.render import cpu_backend

    (tmp_path / "tiny_kernel.py").write_text("import numba\n\n\n@numba.njit(cache=True)\ndef add_one(x):\n"
                                             "    return x + 1\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    module = Path(cpu_backend.__file__).with_name("_numba_cache.py")

    def probe(mode):
        return subprocess.run([sys.executable, "-c", _TINY_PROBE, str(tmp_path), str(module), mode], env=env,
                              capture_output=True, text=True, timeout=120)

    assert json.loads(probe("repair").stdout) == {"dropped": [], "value": 2}  # compiled, cache written
    (data,) = (tmp_path / "cache").rglob("*.nbc")
    data.write_bytes(data.read_bytes()[:100])
    broken = probe("plain")
    assert broken.returncode != 0 and "UnpicklingError" in broken.stderr
    repaired = probe("repair")
    dropped = json.loads(repaired.stdout)["dropped"]
    assert json.loads(repaired.stdout)["value"] == 2 and len(dropped) == 1 and dropped[0].endswith(".nbi")
    assert f"{dropped[0]} is unreadable (UnpicklingError: pickle data was truncated)" in repaired.stderr
    assert json.loads(probe("plain").stdout) == {"dropped": [], "value": 2}  # the new cache loads


def test_a_missing_cache_entry_does_not_hide_a_damaged_one(tmp_path: Path):
    """A kernel compiled for two signatures has two data files: one deleted, the other truncated. The check used to
    stop at the missing one (numba recompiles that by itself) and leave the truncated one to fail the call."""
    from anycity.render import cpu_backend

    (tmp_path / "tiny_kernel.py").write_text("import numba\n\n\n@numba.njit(cache=True)\ndef add_one(x):\n"
                                             "    return x + 1\n")
    module = Path(cpu_backend.__file__).with_name("_numba_cache.py")
    for missing in (0, 1):  # whichever comes first in numba's index
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / f"cache{missing}"))

        def probe(mode, env=env):
            return subprocess.run([sys.executable, "-c", _TINY_PROBE, str(tmp_path), str(module), mode, "two"],
                                  env=env, capture_output=True, text=True, timeout=120)

        assert json.loads(probe("plain").stdout)["value"] == [2, 2.5]
        files = sorted((tmp_path / f"cache{missing}").rglob("*.nbc"))
        assert len(files) == 2
        files[missing].unlink()
        files[1 - missing].write_bytes(files[1 - missing].read_bytes()[:100])
        repaired = probe("repair")
        assert json.loads(repaired.stdout) == {"dropped": [ANY], "value": [2, 2.5]}, repaired.stderr


def test_the_kernel_cache_is_checked_once_per_process_and_channel_count(monkeypatch):
    from anycity.render import cpu_backend

    seen = []
    monkeypatch.setattr(cpu_backend, "repair_cache", lambda ds: seen.append({d.__name__ for d in ds}) or [])
    monkeypatch.setitem(cpu_backend._state, "checked", set())
    gauss, w2c, K = make_scene(N=5)
    for normals in (False, False, True):
        render(cast(gauss, torch.float32), w2c.float(), K.float(), 8, 8, backend="cpu", render_normals=normals)
    assert len(seen) == 2  # D = 4, then D = 7
    assert {"project_fwd", "project_bwd", "raster_fwd", "raster_bwd", "_project_fwd_chunk"} <= seen[0]


@pytest.mark.slow
def test_cold_cache_in_a_fresh_directory(tmp_path: Path):
    """NUMBA_CACHE_DIR is honoured: the first process compiles (and says so), the second only loads."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    first, second = _probe(env), _probe(env)
    assert "compiling" in first["stderr"]
    assert all(misses >= 1 for _, misses in first["stats"].values())
    assert all(hits >= 1 and misses == 0 for hits, misses in second["stats"].values())
    assert second["seconds"] < first["seconds"] / 2
    assert any(tmp_path.rglob("*.nbi"))


def test_each_channel_count_has_its_own_kernel_cache_files():
    """numba names a kernel's cache index after its qualname, which the D = 4 and D = 7 compositing closures shared:
    two processes compiling both at once (``make test``'s workers) could both write data file 1 of that one index,
    and later processes loaded one D's machine code under the other's key (silently wrong renders)."""
    from anycity.render import cpu_backend

    paths = {D: [Path(d._cache._cache_file._index_path).name for d in cpu_backend.raster_kernels(D)] for D in (4, 7)}
    assert len({*paths[4], *paths[7]}) == 4, paths
    assert [p.split("-")[0] for p in paths[7]] == ["_cpu_raster.raster_fwd_d7", "_cpu_raster.raster_bwd_d7"], paths
    assert [d.__name__ for d in cpu_backend.raster_kernels(7)] == ["raster_fwd", "raster_bwd"]  # messages keep names


def test_non_contiguous_fields_add_no_kernel_specialisation():
    """The model's sh (sh_degree >= 1) is a transposed view: backward allocated its gradients with empty_like, which
    kept the strides, so numba compiled project_bwd again for that layout (6-11 s, unannounced). The gradients are
    the same bits as for contiguous fields, and no kernel gains a signature."""
    from anycity.render import cpu_backend

    gauss, w2c, K = make_scene(N=30, sh_degree=1)

    def grads(g):
        out = render(g, w2c.float(), K.float(), 40, 32, backend="cpu")
        (out.rgb.square().sum() + out.depth.sum()).backward()
        return [getattr(g, k).grad for k in PARAMS]

    ref = grads(cast(gauss, torch.float32))
    counts = [len(d.signatures) for d in cpu_backend._dispatchers(4)]
    fields = {k: getattr(gauss, k).detach().float() for k in PARAMS}
    # stored channel-first and viewed as [B, N, ...], as a head's output is
    fields["means"] = fields["means"].transpose(1, 2).contiguous().transpose(1, 2)
    fields["sh"] = fields["sh"].permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
    g = Gaussians(**{k: v.requires_grad_() for k, v in fields.items()})
    assert not g.means.is_contiguous() and not g.sh.is_contiguous()
    got = grads(g)
    assert [len(d.signatures) for d in cpu_backend._dispatchers(4)] == counts
    for name, a, b in zip(PARAMS, got, ref):
        assert torch.equal(a, b), name


def test_the_fused_kernels_follow_an_edited_fov_clamp(monkeypatch):
    """projection.FOV_CLAMP (how far outside the image the EWA Jacobian is clamped) is read at call time by both
    backends, so an edited value reaches the fused kernels too; the cpu backend had 0.3 written out."""
    from helpers.scenes import make_cameras, make_gaussians

    from anycity.render import projection

    g = make_gaussians(N=40, dtype=torch.float32, z=2.0, spread=(3.0, 3.0, 0.5), scale=(0.3, 1.0))  # many off-frame
    w2c, K = make_cameras(1, 1, 40, 32, dtype=torch.float32)

    def both():
        return [render(g, w2c, K, 40, 32, backend=b).rgb for b in ("torch", "cpu")]

    before = both()
    monkeypatch.setattr(projection, "FOV_CLAMP", 0.0)
    torch_rgb, cpu_rgb = both()
    assert (torch_rgb - before[0]).abs().max() > 1e-2  # the clamp matters in this scene
    torch.testing.assert_close(cpu_rgb, torch_rgb, atol=2e-5, rtol=0)
