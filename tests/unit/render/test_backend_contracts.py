"""Contracts every render backend shares: outputs are ordinary tensors, gradients are never silently dropped,
mixed-precision inputs render in float32, and "auto" only picks a backend that supports the inputs."""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers.scenes import make_cameras, make_gaussians

from anycity.geometry import make_intrinsics
from anycity.render import api, render, resolve_backend
from anycity.structures import Gaussians

F32 = torch.float32
PARAMS = ("means", "quats", "scales", "opacities", "sh")
needs_numba = pytest.mark.skipif(not api._cpu_backend_available(), reason="the fused CPU backend needs numba")


def _scene(K=1):
    """One tiny float32 scene with leaf parameters, and its camera."""
    g = make_gaussians(B=1, N=30, K=K, seed=5, dtype=F32)
    g = Gaussians(**{k: getattr(g, k).detach().clone().requires_grad_(True) for k in PARAMS})
    w2c, K = make_cameras(1, 1, 24, 16, dtype=F32)
    return g, w2c, K


def _grads(g: Gaussians) -> list[torch.Tensor]:
    return [getattr(g, k).grad.clone() for k in PARAMS]


@needs_numba
def test_cpu_outputs_accept_inplace_ops_like_the_torch_backend():
    grads = {}
    for inplace in (True, False):
        g, w2c, K = _scene()
        out = render(g, w2c, K, 24, 16, backend="cpu")
        hole = out.alpha.detach() < 0.5
        if inplace:
            out.rgb.clamp_(0, 1)
            out.depth[hole] = 0.0
            rgb, depth = out.rgb, out.depth
        else:
            rgb, depth = out.rgb.clamp(0, 1), torch.where(hole, torch.zeros_like(out.depth), out.depth)
        (rgb.sum() + depth.sum()).backward()
        grads[inplace] = _grads(g)
    for a, b in zip(grads[True], grads[False]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@needs_numba
def test_cpu_backward_ignores_edits_of_detached_outputs():
    grads = {}
    for touch in (False, True):
        g, w2c, K = _scene()
        out = render(g, w2c, K, 24, 16, backend="cpu")
        loss = out.depth.sum() + out.alpha.sum() + out.rgb.sum()
        if touch:  # e.g. normalising a detached copy for a preview, in place
            for t in (out.depth, out.alpha, out.rgb):
                t.detach().mul_(3.0)
        loss.backward()
        grads[touch] = _grads(g)
    for a, b in zip(grads[True], grads[False]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


@needs_numba
@pytest.mark.parametrize("backend", ["cpu", "auto"])
def test_fused_cpu_gives_camera_and_background_gradients_like_the_torch_backend(backend):
    got = {}
    for name in (backend, "torch"):
        g, w2c, K = _scene(K=4)
        cams = [t.clone().requires_grad_(True) for t in (w2c, K, torch.full((3,), 0.2))]
        out = render(g, cams[0], cams[1], 24, 16, background=cams[2], render_normals=True, backend=name)
        (out.rgb.sum() + out.depth.mean() + out.alpha.sum() + out.normal.sum()).backward()
        got[name] = [c.grad for c in cams]
    for a, b in zip(got[backend], got["torch"]):
        assert a is not None and a.abs().sum() > 0
        torch.testing.assert_close(a, b, rtol=2e-4, atol=1e-4)
    assert resolve_backend("auto", torch.device("cpu"), F32) == "cpu"


def test_gsplat_refuses_an_intrinsics_gradient_it_cannot_give():
    """gsplat's projection returns no gradient for Ks: refused in one line, before any CUDA call."""
    from anycity.render.gsplat_backend import render_gsplat

    g, w2c, K = _scene()
    args = (g.means, g.quats, g.scales, g.opacities, g.sh, torch.ones(1, 30, dtype=torch.bool), w2c)
    with pytest.raises(ValueError, match=r"gsplat.*K requires grad.*K\.detach\(\)"):
        render_gsplat(*args, K.clone().requires_grad_(True), 24, 16, torch.zeros(1, 1, 3), 0.01, 1e10, False)
    with torch.no_grad(), pytest.raises(ValueError, match="needs CUDA"):  # no gradient wanted: on to the CUDA check
        render_gsplat(*args, K.clone().requires_grad_(True), 24, 16, torch.zeros(1, 1, 3), 0.01, 1e10, False)


@pytest.mark.parametrize("backend", ["torch", "auto"] + (["cpu"] if api._cpu_backend_available() else []))
@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "sh"])
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16], ids=["bfloat16", "float16"])
def test_low_precision_fields_render_in_float32(field, backend, dtype):
    """A float16 or bfloat16 field (a mixed-precision head) is upcast: the image is float32 and equals the render
    of the same values cast to float32 beforehand."""
    g, w2c, K = _scene(K=4)
    fields = {k: getattr(g, k).detach() for k in PARAMS}
    fields[field] = fields[field].to(dtype)
    out = render(Gaussians(**fields), w2c, K, 24, 16, backend=backend)
    ref = render(Gaussians(**fields).float(), w2c, K, 24, 16, backend=backend)
    assert out.rgb.dtype == F32
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=0)


def test_make_intrinsics_follows_its_inputs():
    assert make_intrinsics(10.0, 11.0, 4.0, 3.0).dtype == F32
    f64 = make_intrinsics(torch.tensor([10.0, 20.0], dtype=torch.float64), 11.0, 4, 3.0)
    assert f64.dtype == torch.float64 and f64.shape == (2, 3, 3)
    assert f64[1, 0, 0] == 20.0 and f64[0, 1, 1] == 11.0 and f64[0, 2, 2] == 1.0
    assert make_intrinsics(torch.tensor(10), 11.0, 4.0, 3.0).dtype == F32  # integer tensors: float32
    meta = make_intrinsics(torch.ones(5, device="meta"), 1.0, 2.0, 3.0)
    assert meta.device.type == "meta" and meta.shape == (5, 3, 3)


def test_auto_on_cuda_picks_gsplat_only_for_float32(monkeypatch):
    monkeypatch.setattr(api, "_module_available", lambda name: True)
    cuda = torch.device("cuda")  # a device object only: no CUDA needed
    assert resolve_backend("auto", cuda, F32) == "gsplat"
    for dtype in (torch.float64, torch.float16, torch.bfloat16):
        assert resolve_backend("auto", cuda, dtype) == "torch"


def test_auto_on_cuda_without_gsplat_falls_back_to_torch_not_the_cpu_kernels(monkeypatch):
    """On CUDA without gsplat, "auto" falls back to the torch backend even where numba is installed: the fused
    kernels run on CPU tensors only."""
    monkeypatch.setattr(api, "_module_available", lambda name: name != "gsplat")
    monkeypatch.setattr(api, "_cpu_backend_available", lambda: True)
    with warnings.catch_warnings():  # the fallback warning is given once per process
        warnings.simplefilter("ignore")
        assert resolve_backend("auto", torch.device("cuda"), F32) == "torch"


def test_auto_on_cuda_skips_a_gsplat_without_kernels_and_an_explicit_request_is_refused(monkeypatch):
    """gsplat installed without its CUDA kernels: "auto" falls back to torch, and backend="gsplat" is refused in
    one line naming the missing kernels rather than failing inside the first CUDA call."""
    monkeypatch.setattr(api, "_module_available", lambda name: True)
    monkeypatch.setattr(api, "_gsplat_kernels", lambda: False)
    with warnings.catch_warnings():  # the fallback warning is given once per process
        warnings.simplefilter("ignore")
        assert resolve_backend("auto", torch.device("cuda"), F32) == "torch"
    with pytest.raises(ValueError, match="gsplat is installed without its CUDA kernels"):
        api._load("gsplat")


@needs_numba
def test_a_single_background_colour_reaches_every_view_of_the_cpu_backend():
    """A [3] background with several views is expanded to [B, V, 3] for every backend: the fused kernels composite
    it under each view as the torch backend does."""
    g = make_gaussians(N=30, dtype=F32)
    w2c, K = make_cameras(1, 2, 16, 16, dtype=F32)
    bg = torch.tensor([0.2, 0.3, 0.4])
    cpu, ref = (render(g, w2c, K, 16, 16, background=bg, backend=b) for b in ("cpu", "torch"))
    assert (ref.alpha < 0.5).any()  # some of the background shows
    torch.testing.assert_close(cpu.rgb, ref.rgb, atol=1e-5, rtol=0)


@needs_numba
def test_a_gaussian_exactly_on_the_near_or_far_plane_is_kept_by_every_backend():
    """z == near (or far) in float32 is kept, as the torch backend and gsplat compare: the fused kernels compared
    the float64 z of the float32 mean with the float64 plane and culled it (0.01 is not a float32)."""
    for near, far, z in ((0.01, 1e10, 0.01), (1e-3, 0.3, 0.3)):
        g = Gaussians(means=torch.tensor([[[0.0, 0.0, z]]]), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
                      scales=torch.full((1, 1, 3), 1e-4 * z / 0.01), opacities=torch.full((1, 1), 0.9),
                      sh=torch.ones(1, 1, 1, 3))
        K = make_intrinsics(21.6, 21.6, 12.0, 8.0)[None, None]
        alpha = {b: render(g, torch.eye(4)[None, None], K, 24, 16, near=near, far=far, backend=b).alpha
                 for b in ("torch", "cpu")}
        assert alpha["torch"].max() > 0.4, (near, far)
        torch.testing.assert_close(alpha["cpu"], alpha["torch"], rtol=0, atol=1e-6)


@pytest.mark.parametrize("scale", [1e12, 1e18, 1e20])
def test_a_huge_but_finite_scale_renders_on_the_torch_backend(scale):
    """One Gaussian of a huge finite scale beside an ordinary one: its footprint radius wrapped in the int32 cast
    (an IndexError in the tile binning). Now it covers the image as on the fused CPU backend (float64 inside);
    past float32's range of 2D covariances (1e20) it is culled, and neither image nor gradients turn NaN."""
    def scene(n):
        fields = dict(means=torch.tensor([[[0.0, 0, 4], [0.5, 0, 6]]]), quats=torch.tensor([[[1.0, 0, 0, 0]] * 2]),
                      scales=torch.tensor([[[0.1] * 3, [scale] * 3]]), opacities=torch.full((1, 2), 0.8),
                      sh=torch.tensor([[[[1.0, 1, 1]], [[1.0, 0, 0]]]]))
        return Gaussians(**{k: v[:, :n].clone().requires_grad_(True) for k, v in fields.items()})
    w2c, K = torch.eye(4)[None, None], make_intrinsics(30.0, 30.0, 16.0, 16.0)[None, None]
    g = scene(2)
    out = render(g, w2c, K, 32, 32, backend="torch")
    (out.rgb.sum() + out.depth.sum() + out.alpha.sum()).backward()
    assert all(torch.isfinite(t).all() for t in (out.rgb, out.depth, out.alpha, *_grads(g)))
    if scale < 1e20:
        assert out.alpha.amin() > 0.79  # the huge Gaussian covers every pixel
        if api._cpu_backend_available():
            cpu = render(g, w2c, K, 32, 32, backend="cpu")
            torch.testing.assert_close(out.rgb, cpu.rgb, rtol=0, atol=1e-6)
            torch.testing.assert_close(out.alpha, cpu.alpha, rtol=0, atol=1e-6)
    else:
        alone = render(scene(1), w2c, K, 32, 32, backend="torch")
        assert torch.equal(out.rgb, alone.rgb) and torch.equal(out.alpha, alone.alpha)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_a_long_thin_footprint_renders_as_in_float64(backend):
    """A needle (a flat Gaussian seen edge-on) lying diagonally in the image: the torch backend took det(Σ2D) as
    ca cc - cb², whose two terms agree in nearly every float32 digit there (alpha off by 0.13 at a 3000 px std); the
    fused kernels work in float64."""
    import math

    def needle(dtype):
        s = 3000.0 * 3 / 32  # a 3000 px standard deviation at z = 3, f = 32
        q = torch.tensor([[[math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)]]], dtype=dtype)  # 45 deg in image
        g = Gaussians(means=torch.tensor([[[0, 0, 3.0]]], dtype=dtype), quats=q,
                      scales=torch.tensor([[[s, 0, 0]]], dtype=dtype), opacities=torch.tensor([[0.9]], dtype=dtype),
                      sh=torch.full((1, 1, 1, 3), 0.5, dtype=dtype))
        w2c = torch.eye(4, dtype=dtype)[None, None]
        K = make_intrinsics(32.0, 32.0, 16.0, 16.0).to(dtype)[None, None]
        return g, w2c, K

    ref = render(*needle(torch.float64), 32, 32, backend="torch").alpha
    out = render(*needle(torch.float32), 32, 32, backend=backend).alpha
    assert (out.double() - ref).abs().max() < 1e-4
