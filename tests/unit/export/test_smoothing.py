"""The baked 3-D smoothing filter: a minimum size from the input cameras' sampling rate, 2-D mass kept."""

from __future__ import annotations

import torch

from anycity.export.smoothing import best_camera, sampling_rate, smooth_3d
from anycity.render import render
from anycity.render.projection import EPS2D
from anycity.structures import Gaussians


def _gaussians(means, scales, opacity=0.8):
    n = means.shape[1]
    return Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4), scales=scales,
                     opacities=torch.full((1, n), opacity), sh=torch.zeros(1, n, 1, 3))


def test_tiny_gaussians_grow_to_the_sampling_limit_big_ones_stay():
    w2c = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    w2c[0, 1, 2, 3] = 5.0  # the second camera is 5 units farther back: the points sit at z = 10 in it
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]]).expand(1, 2, 3, 3)
    means = torch.tensor([[[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [100.0, 0.0, 5.0]]])
    g = _gaussians(means, torch.tensor([[[1e-5] * 3, [1.0] * 3, [1e-5] * 3]]))
    nu = sampling_rate(means, w2c, K, 48, 48)
    torch.testing.assert_close(nu[0, :2], torch.tensor([8.0, 8.0]))  # f / z of the nearer camera (z = 5)
    s = smooth_3d(g, w2c, K, 48, 48)
    std = 0.2 ** 0.5 / 8.0
    torch.testing.assert_close(s.scales[0, 0], torch.full((3,), (std ** 2 + 1e-10) ** 0.5))
    # 2-D mass kept in the sampling camera: a sub-pixel splat's 0.3 px² footprint grows to 0.5 px², so its peak
    # falls to 0.3 / 0.5 of its opacity (not to ~0, as Mip-Splatting's 3-D density rule would make it)
    torch.testing.assert_close(s.opacities[0, 0], torch.tensor(0.8 * EPS2D / (EPS2D + 0.2)), rtol=1e-4, atol=0)
    torch.testing.assert_close(s.scales[0, 1], g.scales[0, 1], rtol=2e-3, atol=0)
    assert abs(s.opacities[0, 1].item() - 0.8) < 1e-2
    assert s.scales[0, 2, 0] > 1e-3  # out of frame: still filtered at the rate of the cameras it is in front of
    assert 0 < s.opacities[0, 2] < 0.8


def test_a_gaussian_behind_every_camera_is_kept_as_it_is():
    w2c = torch.eye(4)[None, None]
    K = torch.tensor([[48.3, 0, 28], [0, 34.4, 20], [0, 0, 1]]).expand(1, 1, 3, 3)
    means = torch.tensor([[[3.0, 2.0, -0.5], [50.0, 40.0, -1e-3], [0.0, 0.0, -2.0], [0.0, 0.0, 5.0]]])
    g = _gaussians(means, torch.full((1, 4, 3), 1e-3), opacity=0.9)
    s = smooth_3d(g, w2c, K, 56, 40)
    torch.testing.assert_close(s.opacities[0, :3], g.opacities[0, :3])  # was NaN: inf / inf footprints
    torch.testing.assert_close(s.scales[0, :3], g.scales[0, :3])
    assert torch.isfinite(s.opacities).all() and s.scales[0, 3, 0] > 1e-3


def test_render_at_the_input_camera_keeps_each_splats_mass_and_zoom_in_has_no_holes():
    """A thin sub-pixel splat (a 1e-5 flat disc, as the network predicts them) renders with the same integrated
    alpha before and after the filter at the input resolution, and at 8x zoom it covers pixels instead of
    vanishing into the low-pass."""
    w2c = torch.eye(4)[None, None]
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]])[None, None]
    g = _gaussians(torch.tensor([[[0.01, -0.02, 5.0]]]), torch.tensor([[[2e-3, 1e-3, 1e-7]]]), opacity=0.3)
    s = smooth_3d(g, w2c, K, 48, 48)
    mass = [render(x, w2c, K, 48, 48).alpha.sum().item() for x in (g, s)]
    assert abs(mass[1] / mass[0] - 1) < 0.03, mass
    zoom = K.clone()
    zoom[..., :2, :] *= 8
    covered = [(render(x, w2c, zoom, 384, 384).alpha > 0.05).sum().item() for x in (g, s)]
    assert covered[1] > 10 * covered[0], covered


def test_chunked_opacity_computation_matches_one_pass(monkeypatch):
    import anycity.export.smoothing as smoothing

    gen = torch.Generator().manual_seed(0)
    means = torch.randn(1, 50, 3, generator=gen) * 0.3 + torch.tensor([0.0, 0.0, 5.0])
    g = Gaussians(means=means, quats=torch.randn(1, 50, 4, generator=gen),
                  scales=torch.rand(1, 50, 3, generator=gen) * 0.01, opacities=torch.rand(1, 50, generator=gen),
                  sh=torch.zeros(1, 50, 1, 3))
    w2c = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    w2c[0, 1, 0, 3] = 0.5
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]]).expand(1, 2, 3, 3)
    whole, nu = smooth_3d(g, w2c, K, 48, 48), sampling_rate(means, w2c, K, 48, 48)
    monkeypatch.setattr(smoothing, "CHUNK", 7)
    chunked = smooth_3d(g, w2c, K, 48, 48)
    torch.testing.assert_close(chunked.opacities, whole.opacities, rtol=0, atol=0)
    torch.testing.assert_close(chunked.scales, whole.scales, rtol=0, atol=0)
    torch.testing.assert_close(sampling_rate(means, w2c, K, 48, 48), nu, rtol=0, atol=0)


def test_the_per_camera_tensors_are_built_a_chunk_at_a_time(monkeypatch):
    """``_best_camera`` builds ~9 ``[B, V, N]`` tensors: only the determinant loop was chunked, so a 64-view scene of
    200k Gaussians peaked at +530 MB (r07_mem_smooth.py). Every call now sees at most CHUNK Gaussians."""
    import anycity.export.smoothing as smoothing

    seen = []
    best = smoothing._best_camera

    def spy(means, *args):
        seen.append(means.shape[1])
        return best(means, *args)

    monkeypatch.setattr(smoothing, "_best_camera", spy)
    monkeypatch.setattr(smoothing, "CHUNK", 16)
    means = torch.randn(1, 50, 3, generator=torch.Generator().manual_seed(1)) * 0.3 + torch.tensor([0.0, 0.0, 5.0])
    w2c = torch.eye(4)[None, None].repeat(1, 3, 1, 1)
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]]).expand(1, 3, 3, 3)
    s = smooth_3d(_gaussians(means, torch.full((1, 50, 3), 1e-4)), w2c, K, 48, 48)
    assert s.scales.shape == (1, 50, 3) and seen == [16, 16, 16, 2]
    seen.clear()
    assert sampling_rate(means, w2c, K, 48, 48).shape == (1, 50) and seen == [16, 16, 16, 2]  # provenance's too
    empty = smooth_3d(_gaussians(means[:, :0], torch.zeros(1, 0, 3)), w2c, K, 48, 48)
    assert empty.scales.shape == (1, 0, 3) and empty.opacities.shape == (1, 0)


def test_a_centre_no_camera_frames_takes_a_camera_it_is_in_front_of():
    w2c = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    w2c[0, 1, :3, :3] = torch.diag(torch.tensor([-1.0, 1, -1]))  # camera 1 looks down -z from z = 10
    w2c[0, 1, 2, 3] = 10.0
    K = torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]]).expand(1, 2, 3, 3)
    means = torch.tensor([[[50.0, 0, -2]]])  # behind camera 0; z = 12 in camera 1, far out of its frame
    nu, cam = best_camera(means, w2c, K, 48, 32)
    assert cam.item() == 1
    torch.testing.assert_close(nu, torch.tensor([[40.0 / 12]]))


def test_the_frame_test_uses_width_for_u_and_height_for_v():
    # 96x32 images: camera 0 (z = 5, nu = 8) sees the centre at u = 80, inside the width but beyond the height;
    # camera 1 (z = 10, nu = 4) sees it at u = 32
    K = torch.tensor([[40.0, 0, 48], [0, 40, 16], [0, 0, 1]]).expand(1, 2, 3, 3)
    w2c = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    w2c[0, 1, 2, 3] = 5.0
    w2c[0, 1, 0, 3] = -8.0
    nu = sampling_rate(torch.tensor([[[4.0, 0.0, 5.0]]]), w2c, K, 96, 32)
    torch.testing.assert_close(nu, torch.tensor([[8.0]]))


def test_the_sampling_rate_takes_the_larger_focal_length():
    K = torch.tensor([[40.0, 0, 24], [0, 20, 16], [0, 0, 1]])[None, None]
    nu = sampling_rate(torch.tensor([[[0.0, 0, 5]]]), torch.eye(4)[None, None], K, 48, 32)
    torch.testing.assert_close(nu, torch.tensor([[8.0]]))  # max(fx, fy) / z = 40 / 5


def test_a_long_thin_footprint_keeps_its_float64_opacity():
    """The gain sqrt(det(before) / det(after)) of a needle seen edge-on cancelled in float32: a 3000 px needle's
    opacity was exported at the 0.9 clamp instead of 0.697."""
    import math

    from anycity.geometry import make_intrinsics, quat_to_rotmat

    s = 3000.0 * 3 / 32
    q = torch.tensor([math.cos(math.pi / 8), 0, 0, math.sin(math.pi / 8)])
    g = Gaussians(means=torch.tensor([[[0, 0, 3.0]]]), quats=q[None, None], scales=torch.tensor([[[s, 0, 0]]]),
                  opacities=torch.tensor([[0.9]]), sh=torch.zeros(1, 1, 1, 3))
    w2c, K = torch.eye(4)[None, None], make_intrinsics(32.0, 32.0, 16.0, 16.0)[None, None]
    out = smooth_3d(g, w2c, K, 32, 32)
    T = torch.tensor([[32 / 3, 0, 0], [0, 32 / 3, 0]], dtype=torch.float64)  # the footprint Jacobian at (0, 0, 3)
    R = quat_to_rotmat(q.double())
    before = T @ (R * torch.tensor([s * s, 0, 0], dtype=torch.float64)) @ R.T @ T.T + EPS2D * torch.eye(2).double()
    after = before + (0.2 / (32 / 3) ** 2) * T @ T.T
    expected = 0.9 * math.sqrt(torch.linalg.det(before) / torch.linalg.det(after))
    assert abs(out.opacities.item() - expected) < 1e-4 and expected < 0.75
