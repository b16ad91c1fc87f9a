"""The torch backend against the dense float64 reference: forward outputs and gradients, plus input checks."""

from __future__ import annotations

import pytest
import torch
from helpers.render_reference import render_reference
from helpers.scenes import make_cameras, make_gaussians

from anycity.render import api, render, resolve_backend
from anycity.render.torch_backend import render_torch
from anycity.structures import Gaussians

F64 = torch.float64


def _loss_weights(B, V, H, W, normals, dtype=F64, seed=3):
    g = torch.Generator().manual_seed(seed)
    names = ["rgb", "depth", "alpha"] + (["normal"] if normals else [])
    chans = {"rgb": 3, "depth": 1, "alpha": 1, "normal": 3}
    return {n: torch.randn(B, V, chans[n], H, W, generator=g, dtype=dtype) for n in names}


def compare(gauss, w2c, K, W, H, *, normals=False, background=None, check_grads=True, atol=1e-9, **kw):
    """Forward and gradients of the torch backend vs the reference, both float64."""
    params = [gauss.means, gauss.quats, gauss.scales, gauss.opacities, gauss.sh]
    params = [p.detach().clone().requires_grad_(True) for p in params]
    B, V = w2c.shape[:2]
    weights = _loss_weights(B, V, H, W, normals)

    def run(fn):
        g = Gaussians(*params, valid=gauss.valid)
        out = fn(g, w2c, K, W, H, background=background, render_normals=normals, **kw)
        loss = sum((getattr(out, n) * w).sum() for n, w in weights.items())
        grads = torch.autograd.grad(loss, params, allow_unused=True) if loss.requires_grad else [None] * 5
        return out, grads

    ref, g_ref = run(render_reference)
    out, g_out = run(lambda *a, **k: render(*a, backend="torch", **k))
    for name in weights:
        torch.testing.assert_close(getattr(out, name), getattr(ref, name), atol=atol, rtol=1e-7, msg=name)
    if check_grads:
        for name, a, b in zip(["means", "quats", "scales", "opacities", "sh"], g_out, g_ref):
            a = torch.zeros_like(params[0]) if a is None and b is None else a
            b = torch.zeros_like(a) if b is None else b
            torch.testing.assert_close(a, b, atol=1e-8 * (1 + b.abs().max().item()), rtol=1e-6, msg=name)
    return out, ref


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3, 4])
def test_matches_reference_sh_degrees(sh_degree):
    g = make_gaussians(B=1, N=60, K=(sh_degree + 1) ** 2, seed=sh_degree)
    w2c, K = make_cameras(1, 1, 40, 32)
    out, _ = compare(g, w2c, K, 40, 32)
    assert out.alpha.max() > 0.5  # the scene is actually seen


def test_batch_views_nonsquare_normals_background():
    g = make_gaussians(B=2, N=70, K=4, seed=5)
    w2c, K = make_cameras(2, 3, 36, 20)
    bg = torch.rand(2, 3, 3, dtype=F64)
    out, ref = compare(g, w2c, K, 36, 20, normals=True, background=bg)
    assert out.rgb.shape == (2, 3, 3, 20, 36) and out.normal.shape == (2, 3, 3, 20, 36)
    assert not torch.allclose(out.rgb[:, 0], out.rgb[:, 1])  # different cameras see different images
    # Where nothing is hit, the pixel is exactly the background.
    empty = ref.alpha[:, :, 0] == 0
    if empty.any():
        torch.testing.assert_close(out.rgb.permute(0, 1, 3, 4, 2)[empty],
                                   bg[:, :, None, None].expand(-1, -1, 20, 36, -1)[empty])


@pytest.mark.parametrize("tile_size", [4, 8, 16])
def test_tile_size_and_chunking_do_not_change_the_image(tile_size):
    g = make_gaussians(B=1, N=120, K=1, seed=7)
    w2c, K = make_cameras(1, 2, 33, 27)
    ref = render_reference(g, w2c, K, 33, 27)
    valid = torch.ones(1, 120, dtype=torch.bool)
    out = render_torch(g.means, g.quats, g.scales, g.opacities, g.sh, valid, w2c, K, 33, 27,
                       torch.zeros(1, 2, 3, dtype=F64), 0.01, 1e10, False, tile_size=tile_size, chunk_elements=3000)
    torch.testing.assert_close(out[0], ref.rgb, atol=1e-10, rtol=0)


def test_no_gaussians():
    g = make_gaussians(N=0)
    w2c, K = make_cameras(1, 2, 16, 12)
    out = render(g, w2c, K, 16, 12, background=torch.tensor([0.2, 0.3, 0.4], dtype=F64), backend="torch")
    assert out.rgb.shape == (1, 2, 3, 12, 16)
    assert torch.all(out.alpha == 0) and torch.all(out.depth == 0)
    torch.testing.assert_close(out.rgb[0, 0, :, 5, 5], torch.tensor([0.2, 0.3, 0.4], dtype=F64))


def test_everything_behind_the_camera_gives_background_and_zero_gradients():
    g = make_gaussians(N=30, z=-4.0)
    w2c, K = make_cameras(1, 1, 16, 16)
    means = g.means.clone().requires_grad_(True)
    out = render(Gaussians(means, g.quats, g.scales, g.opacities, g.sh), w2c, K, 16, 16, backend="torch")
    assert torch.all(out.alpha == 0)
    out.rgb.sum().backward()  # the graph stays connected even though nothing is visible
    assert torch.all(means.grad == 0)


def test_gaussians_larger_than_the_image_and_empty_tiles():
    g = make_gaussians(N=6, spread=(0.2, 0.2, 0.2), scale=(1.5, 3.0), seed=11)  # each covers the whole image
    small = make_gaussians(N=5, spread=(0.05, 0.05, 0.1), scale=(0.005, 0.01), seed=12)  # a few pixels only
    w2c, K = make_cameras(1, 1, 48, 40)
    compare(g, w2c, K, 48, 40, normals=True)
    out, _ = compare(small, w2c, K, 48, 40)
    assert (out.alpha[0, 0, 0] == 0).float().mean() > 0.5  # most tiles are empty


def test_masked_gaussians_contribute_nothing():
    g = make_gaussians(B=2, N=50, K=4, seed=13)
    valid = torch.rand(2, 50, generator=torch.Generator().manual_seed(0)) > 0.5
    masked = Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh, valid=valid)
    w2c, K = make_cameras(2, 2, 24, 24)
    out, _ = compare(masked, w2c, K, 24, 24)
    # Same image as rendering only the valid subset, scene by scene.
    for b in range(2):
        keep = valid[b]
        sub = Gaussians(g.means[b:b + 1, keep], g.quats[b:b + 1, keep], g.scales[b:b + 1, keep],
                        g.opacities[b:b + 1, keep], g.sh[b:b + 1, keep])
        torch.testing.assert_close(render(sub, w2c[b:b + 1], K[b:b + 1], 24, 24, backend="torch").rgb, out.rgb[b:b + 1])


def test_early_stop_and_alpha_cap_semantics():
    """Gaussians stacked in depth on the centre pixel's ray: α capped at 0.99, and compositing stops before the
    Gaussian that would bring T to <= 1e-4 (that one is not blended)."""
    N = 4
    colours = (0.9, 0.1, 0.5, 0.3)
    g = Gaussians(
        means=torch.tensor([[[0.0, 0.0, 2.0 + i] for i in range(N)]], dtype=F64),
        quats=torch.tensor([[[1.0, 0, 0, 0]] * N], dtype=F64),
        scales=torch.full((1, N, 3), 1.0, dtype=F64),
        opacities=torch.tensor([[0.98, 1.0, 1.0, 1.0]], dtype=F64),
        sh=torch.stack([torch.full((3,), (c - 0.5) / 0.28209479177387814, dtype=F64) for c in colours])[None, :, None],
    )
    w2c = torch.eye(4, dtype=F64)[None, None]
    K = torch.tensor([[[[8.0, 0, 4.5], [0, 8.0, 4.5], [0, 0, 1]]]], dtype=F64)  # means project onto pixel (4, 4)
    out, _ = compare(g, w2c, K, 9, 9)
    # α = 0.98, then 0.99 (capped from 1.0): T = 0.02 * 0.01 = 2e-4; the third would give 2e-6 <= 1e-4 -> stop.
    torch.testing.assert_close(out.alpha[0, 0, 0, 4, 4], torch.tensor(1 - 2e-4, dtype=F64), atol=1e-12, rtol=0)
    expected = 0.98 * colours[0] + 0.02 * 0.99 * colours[1]
    torch.testing.assert_close(out.rgb[0, 0, :, 4, 4], torch.full((3,), expected, dtype=F64), atol=1e-12, rtol=0)
    expected_z = (0.98 * 2.0 + 0.02 * 0.99 * 3.0) / (1 - 2e-4)
    torch.testing.assert_close(out.depth[0, 0, 0, 4, 4], torch.tensor(expected_z, dtype=F64), atol=1e-12, rtol=0)


_BACKENDS = [
    "torch",
    pytest.param("cpu", marks=pytest.mark.skipif(not api._cpu_backend_available(), reason="needs numba")),
    pytest.param("gsplat", marks=pytest.mark.skipif(not (torch.cuda.is_available() and api._module_available("gsplat")),
                                                    reason="needs gsplat and CUDA")),
]


def _one_gaussian_on_axis(z: float, scale: float, backend: str):
    """One Gaussian on the optical axis at depth ``z``, an identity camera and a K with a 20 px focal (24 x 16)."""
    device = "cuda" if backend == "gsplat" else "cpu"
    g = Gaussians(means=torch.tensor([[[0.0, 0.0, z]]]), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
                  scales=torch.full((1, 1, 3), scale), opacities=torch.full((1, 1), 0.9),
                  sh=torch.ones(1, 1, 1, 3)).to(device=device)
    K = torch.tensor([[20.0, 0, 12.0], [0, 20.0, 8.0], [0, 0, 1]], device=device)[None, None]
    return g, torch.eye(4, device=device)[None, None], K


@pytest.mark.parametrize("backend", _BACKENDS)
def test_a_gaussian_beyond_the_far_plane_is_culled_by_every_backend(backend):
    """One Gaussian on the optical axis at z = 5 (a 2 px std): far = 4 culls it (alpha 0 everywhere), far = 6 keeps
    it. A backend that ignored ``far`` would draw geometry the caller clipped away (e.g. a distant backdrop)."""
    g, w2c, K = _one_gaussian_on_axis(5.0, 0.5, backend)
    culled = render(g, w2c, K, 24, 16, near=0.01, far=4.0, backend=backend)
    assert torch.all(culled.alpha == 0) and torch.all(culled.depth == 0)
    kept = render(g, w2c, K, 24, 16, near=0.01, far=6.0, backend=backend)
    assert kept.alpha.max() > 0.8
    torch.testing.assert_close(kept.depth[0, 0, 0, 8, 12].cpu(), torch.tensor(5.0))


@pytest.mark.parametrize("backend", _BACKENDS)
def test_a_gaussian_before_the_near_plane_is_culled_by_every_backend(backend):
    """One small Gaussian on the optical axis at z = 0.5, in front of the camera: near = 1 culls it (alpha and depth
    0 everywhere), near = 0.1 keeps it. A backend that culled only z <= 0 would draw geometry between the camera and
    the near plane the caller set (e.g. floaters right in front of the lens)."""
    g, w2c, K = _one_gaussian_on_axis(0.5, 0.05, backend)
    culled = render(g, w2c, K, 24, 16, near=1.0, far=10.0, backend=backend)
    assert torch.all(culled.alpha == 0) and torch.all(culled.depth == 0)
    kept = render(g, w2c, K, 24, 16, near=0.1, far=10.0, backend=backend)
    assert kept.alpha.max() > 0.5


def test_gradcheck_tiny():
    g = make_gaussians(N=4, K=4, seed=17, scale=(0.15, 0.3), spread=(0.3, 0.3, 0.2))
    params = [p.clone().requires_grad_(True) for p in (g.means, g.quats, g.scales, g.opacities, g.sh)]

    def fn(w, h, *ps):
        w2c, K = make_cameras(1, 1, w, h)
        out = render(Gaussians(*ps), w2c, K, w, h, render_normals=True, backend="torch")
        return out.rgb, out.depth, out.alpha, out.normal

    # Every output, randomly projected (fast mode), and the full Jacobian of rgb on a smaller image.
    assert torch.autograd.gradcheck(lambda *ps: fn(10, 8, *ps), params, eps=1e-6, atol=1e-5, rtol=1e-4,
                                    fast_mode=True)
    assert torch.autograd.gradcheck(lambda *ps: fn(5, 4, *ps)[0], params, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_float32_close_to_float64():
    g = make_gaussians(B=1, N=200, K=9, seed=19)
    w2c, K = make_cameras(1, 2, 48, 40)
    ref = render(g, w2c, K, 48, 40, backend="torch")
    g32 = g.to(dtype=torch.float32)
    out = render(g32, w2c.float(), K.float(), 48, 40, backend="torch")
    torch.testing.assert_close(out.rgb.double(), ref.rgb, atol=2e-4, rtol=0)
    torch.testing.assert_close(out.alpha.double(), ref.alpha, atol=2e-4, rtol=0)


def test_float32_under_bf16_autocast_and_from_half_inputs():
    g = make_gaussians(B=1, N=100, K=4, seed=23, dtype=torch.float32)
    w2c, K = make_cameras(1, 1, 24, 20, dtype=torch.float32)
    ref = render(g, w2c, K, 24, 20, backend="torch")
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = render(g, w2c, K, 24, 20, backend="torch")
    assert out.rgb.dtype == torch.float32
    torch.testing.assert_close(out.rgb, ref.rgb)
    half = render(g.to(dtype=torch.bfloat16), w2c, K, 24, 20, backend="torch")
    assert half.rgb.dtype == torch.float32


def test_auto_backend_resolution():
    assert resolve_backend("torch", torch.device("cpu")) == "torch"
    assert resolve_backend("auto", torch.device("cpu"), torch.float64) == "torch"  # fused kernels are float32
    with pytest.raises(ValueError, match="backend"):
        resolve_backend("vulkan", torch.device("cpu"))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda a: a.update(w2c=a["w2c"][0]), "w2c"),
        (lambda a: a.update(K=a["K"][:, :, :2]), "K"),
        (lambda a: a.update(width=0), "width"),
        (lambda a: a.update(height=-3), "height"),
        (lambda a: a.update(width=16.0), "width"),
        (lambda a: a.update(backend="opengl"), "backend"),
        (lambda a: a["w2c"].__setitem__((0, 0, 0, 0), float("nan")), "w2c"),
        (lambda a: a["w2c"].__setitem__((0, 0, slice(None, 3), slice(None, 3)), 0.0), "w2c"),
        (lambda a: a["K"].__setitem__((0, 0, 0, 0), 0.0), "K"),
        (lambda a: a.update(background=torch.zeros(4, dtype=F64)), "background"),
        (lambda a: a.update(near=2.0, far=1.0), "near"),
        (lambda a: a.update(near=0.0), r"near/far: expected 1e-06 <= near"),  # 1/z overflows: NaN gradients
        (lambda a: a.update(near=1e-7), "near/far"),
        (lambda a: a.update(near=4.0, far=4.0), r"near/far: expected .* <= near < far"),  # an empty depth range
        # cameras for another batch of scenes, or more intrinsics than views, were not refused
        (lambda a: a.update(gaussians=make_gaussians(B=2, N=10)), r"w2c: expected shape \[B, V, 4, 4\] with B=2"),
        (lambda a: a.update(K=a["K"].expand(2, -1, -1, -1).clone()), r"K: expected shape \[B, V, 3, 3\] with B=1"),
        (lambda a: a.update(K=a["K"].repeat(1, 2, 1, 1)), r"K: expected V=1 cameras like w2c"),
        (lambda a: a["w2c"][..., :3, :].mul_(2.0), r"w2c: the rotation block .* not orthonormal"),  # wrong SH centre
        (lambda a: a["w2c"][..., 0, :3].mul_(1.01), "w2c: the rotation block"),
        # gsplat inverts the whole 4x4 for the SH camera centre: a zero row (a 3x4 [R|t] padded with zeros) crashed it,
        # a homogeneous scale moved the centre; the torch and cpu backends ignored the row
        (lambda a: a["w2c"].__setitem__((0, 0, 3, 3), 0.0), r"w2c: bottom row w2c\[..., 3, :\] must be \[0, 0, 0, 1\]"),
        (lambda a: a["w2c"].__setitem__((0, 0, 3, 3), 2.0), "w2c: bottom row"),
        (lambda a: a["w2c"].__setitem__((0, 0, 3, 1), 0.1), "w2c: bottom row"),
        # a reflection passed the orthonormality check and rendered a mirrored image
        (lambda a: a["w2c"][..., 1, :].neg_(), r"w2c: .* determinant -1 .* must be \+1; a flipped axis: check the y"),
        (lambda a: a.update(background=torch.tensor([float("nan"), 0, 0], dtype=F64)), "background: contains NaN"),
        (lambda a: a.update(background=torch.tensor([0, float("inf"), 0], dtype=F64)), "background: contains NaN"),
        # the backends disagree outside [0, 1] (the fused kernels cut footprints at 3.33 sigma, torch does not)
        (lambda a: a["gaussians"].opacities.__setitem__((0, 3), 1.5),
         r"gaussians.opacities: expected values in \[0, 1\], got \[.*, 1.5\]; apply sigmoid"),
        (lambda a: a["gaussians"].opacities.__setitem__((0, 3), -0.25), "gaussians.opacities: expected values in"),
        (lambda a: a["K"].__setitem__((0, 0, 0, 1), 5.0), r"K: skew .* 5 px"),  # ignored by the renderer
        (lambda a: a["K"].__setitem__((0, 0, 1, 0), -0.01), "K: skew"),
        (lambda a: a["K"].__setitem__((0, 0, 2, 2), 2.0), r"K: last row must be \[0, 0, 1\]"),
        (lambda a: a["K"].__setitem__((0, 0, 2, 0), 1e-3), "K: last row"),
        # intrinsics divided by W and H rendered a near-empty image without a word
        (lambda a: a["K"][..., :2, :].div_(16.0),
         r"K looks normalised \(fx 1.1, cx 0.5813 for a 16x16 image\); multiply rows 0 and 1 by W and H"),
        (lambda a: a.update(gaussians=Gaussians(**{**vars(a["gaussians"]), "scales": a["gaussians"].scales.log()})),
         r"gaussians.scales: .* these look like log-scales .*: pass scales.exp\(\)"),
        (lambda a: a.update(gaussians=Gaussians(**{**vars(a["gaussians"]), "means": a["gaussians"].means[..., :2]})),
         "means"),
        (lambda a: a["gaussians"].opacities.__setitem__((0, 0), float("inf")), "opacities"),
        (lambda a: a.update(gaussians=Gaussians(**{**vars(a["gaussians"]), "sh": torch.zeros(1, 10, 5, 3, dtype=F64)})),
         "sh"),
        (lambda a: a.update(gaussians="not gaussians"), "gaussians"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(mutate, match):
    w2c, K = make_cameras(1, 1, 16, 16)
    args = dict(gaussians=make_gaussians(N=10), w2c=w2c, K=K, width=16, height=16, backend="torch")
    mutate(args)
    with pytest.raises(ValueError, match=match):
        render(args.pop("gaussians"), args.pop("w2c"), args.pop("K"), args.pop("width"), args.pop("height"), **args)


def test_rigid_cameras_and_pinhole_intrinsics_pass_in_every_dtype():
    """The rigidity and pinhole checks leave room for rounding: a float32 or bfloat16 rotation, skew and last-row
    entries of float noise; a 1 % scale of the rotation block and a 0.01 px skew are refused."""
    w2c, K = make_cameras(1, 3, 16, 16)
    g = make_gaussians(N=10)
    K[..., 0, 1] = 1e-6
    K[..., 2, :2] = 1e-9
    for dtype in (torch.float32, torch.bfloat16, torch.float16):
        render(g, w2c.to(dtype), K.to(dtype), 16, 16, backend="torch")
    render(g, w2c, K, 16, 16, near=1e-6, backend="torch")
    w2c[0, 1, :3, :3] *= 1.01
    with pytest.raises(ValueError, match="w2c: the rotation block"):
        render(g, w2c.float(), K, 16, 16, backend="torch")
    w2c[0, 1, :3, :3] /= 1.01
    K[0, 2, 0, 1] = 0.01
    with pytest.raises(ValueError, match="K: skew"):
        render(g, w2c, K.float(), 16, 16, backend="torch")


def test_tiny_images_with_small_pixel_focals_and_extreme_network_outputs_render():
    # the normalised-K check leaves images of 8 px and less alone: their pixel focals and centres can be that small
    g = make_gaussians(N=10)
    for w in (2, 8):
        K = torch.tensor([[1.5, 0, w / 2], [0, 1.5, 1.0], [0, 0, 1]], dtype=F64).expand(1, 1, 3, 3)
        render(g, torch.eye(4, dtype=F64)[None, None], K.clone(), w, 2, backend="torch")
    # the network's softplus scales underflow to 0 and a zero raw quaternion stays zero: every render validates,
    # so they must still render (finite)
    from anycity.models.gaussians import activate_raw

    raw = torch.zeros(10, 8 + 3)
    raw[:5, 1:4] = -200.0
    raw[:5, 7] = 1.0  # xyzw identity: rows 0-4 have zero scales only, rows 5-9 zero quaternions only
    a = activate_raw(raw, 0)
    assert (a["scales"][:5] == 0).all() and (a["quats"][5:] == 0).all()
    g = Gaussians(means=g.means.float(), **{k: v[None].float() for k, v in a.items()})
    w2c, K = make_cameras(1, 1, 16, 16, dtype=torch.float32)
    out = render(g, w2c, K, 16, 16, backend="torch")
    assert torch.isfinite(out.rgb).all() and out.alpha.max() > 0
