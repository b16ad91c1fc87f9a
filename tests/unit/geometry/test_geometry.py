"""Camera, rotation, projection, normal and alignment helpers."""

from __future__ import annotations

import math

import kornia
import pytest
import torch

from anycity.geometry import (
    c2w_to_w2c,
    camera_centers,
    camera_problem,
    crop_intrinsics,
    depth_to_normals,
    focal_to_fov,
    fov_to_focal,
    make_intrinsics,
    pixel_rays,
    project_points,
    quat_multiply,
    quat_to_rotmat,
    rescale_intrinsics,
    rotmat_to_quat,
    sim3_matrix,
    to_homogeneous,
    umeyama,
    unproject_depth,
    w2c_to_c2w,
    wxyz_to_xyzw,
    xyzw_to_wxyz,
)

F64 = torch.float64


def random_w2c(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    R = quat_to_rotmat(torch.randn(n, 4, generator=g, dtype=F64))
    t = torch.randn(n, 3, 1, generator=g, dtype=F64)
    return to_homogeneous(torch.cat([R, t], -1))


def test_quat_rotmat_roundtrip_and_properties():
    q = torch.randn(500, 4, dtype=F64)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(500, 3, 3))
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=F64))
    q2 = rotmat_to_quat(R)
    qn = q / q.norm(dim=-1, keepdim=True)
    qn = torch.where(qn[:, :1] < 0, -qn, qn)
    torch.testing.assert_close(q2, qn)
    # Agrees with kornia, which also uses wxyz.
    torch.testing.assert_close(R, kornia.geometry.conversions.quaternion_to_rotation_matrix(qn))


def test_quat_conventions():
    # 90 degrees about z, wxyz.
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=F64)
    torch.testing.assert_close(quat_to_rotmat(q) @ torch.tensor([1.0, 0, 0], dtype=F64),
                               torch.tensor([0.0, 1, 0], dtype=F64))
    torch.testing.assert_close(xyzw_to_wxyz(wxyz_to_xyzw(q)), q)
    a, b = torch.randn(2, 10, 4, dtype=F64)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b))


def test_w2c_c2w_inverse_and_centres():
    w2c = random_w2c(7)
    c2w = w2c_to_c2w(w2c)
    torch.testing.assert_close(c2w, torch.linalg.inv(w2c))
    torch.testing.assert_close(c2w_to_w2c(c2w), w2c)
    torch.testing.assert_close(camera_centers(w2c), c2w[:, :3, 3])


def test_intrinsics_rescale_crop_and_fov():
    K = make_intrinsics(100.0, 110.0, 64.0, 48.0).double()
    # A point's pixel coordinate scales with the image: (u, v) -> (u * sx, v * sy).
    p = torch.tensor([[0.3, -0.2, 2.0]], dtype=F64)
    I = torch.eye(4, dtype=F64)
    uv, _ = project_points(p, I, K)
    uv2, _ = project_points(p, I, rescale_intrinsics(K, 0.5, 0.25))
    torch.testing.assert_close(uv2, uv * torch.tensor([0.5, 0.25], dtype=F64))
    uv3, _ = project_points(p, I, crop_intrinsics(K, 10, 20))
    torch.testing.assert_close(uv3, uv - torch.tensor([10.0, 20.0], dtype=F64))
    fov = focal_to_fov(torch.tensor(100.0), 128)
    torch.testing.assert_close(fov_to_focal(fov, 128), torch.tensor(100.0))
    assert abs(focal_to_fov(torch.tensor(64.0), 128).item() - math.pi / 2) < 1e-6


def test_project_unproject_roundtrip():
    w2c = random_w2c(2, seed=3)[:, None]  # [2,1,4,4]
    K = make_intrinsics(50.0, 55.0, 20.0, 15.0).double().expand(2, 1, 3, 3)
    depth = 2 + torch.rand(2, 1, 1, 30, 40, dtype=F64)
    pts = unproject_depth(depth, K, w2c)  # [2,1,30,40,3]
    uv, z = project_points(pts.flatten(2, 3), w2c, K)
    torch.testing.assert_close(z, depth.flatten(2))
    v, u = torch.meshgrid(torch.arange(30) + 0.5, torch.arange(40) + 0.5, indexing="ij")
    torch.testing.assert_close(uv[0, 0], torch.stack([u, v], -1).flatten(0, 1).double())
    origins, dirs = pixel_rays(K, w2c, 30, 40)
    # The unprojected points lie on the pixel rays.
    to_pts = pts - origins[..., None, None, :]
    cos = (to_pts / to_pts.norm(dim=-1, keepdim=True) * dirs).sum(-1)
    torch.testing.assert_close(cos, torch.ones_like(cos))


def test_depth_to_normals_of_a_plane():
    # Plane z = 3 + 0.5 x seen by an identity camera: normal ∝ (-0.5, 0, 1), flipped towards the camera.
    K = make_intrinsics(30.0, 30.0, 16.0, 12.0).double()
    H, W = 24, 32
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    xn = (u.double() - 16) / 30  # x / z
    depth = (3 / (1 - 0.5 * xn))[None]  # z = 3 + 0.5 x with x = xn z
    n = depth_to_normals(depth, K)
    expected = torch.tensor([0.5, 0.0, -1.0], dtype=F64) / math.sqrt(1.25)
    torch.testing.assert_close(n[:, 5:-5, 5:-5].permute(1, 2, 0), expected.expand(H - 10, W - 10, 3), atol=1e-9, rtol=0)
    assert torch.all(n[:, 0] == 0)  # zero border


def test_depth_to_normals_masks_pixels_next_to_missing_depth():
    # A slanted plane with a hole of no depth (rendered depth is 0 where alpha is 0) and one NaN and one inf pixel:
    # every pixel is the plane's normal or zero, and zero exactly where it or a 4-neighbour has no depth.
    K = make_intrinsics(30.0, 30.0, 16.0, 12.0).double()
    H, W = 24, 32
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    depth = (3 / (1 - 0.5 * (u.double() - 16) / 30))[None]
    full = depth_to_normals(depth, K)
    depth[:, 8:14, 10:18] = 0.0
    depth[:, 4, 25], depth[:, 18, 5] = float("nan"), float("inf")
    depth.requires_grad_(True)
    n = depth_to_normals(depth, K)
    missing = ~((depth[0] > 0) & depth[0].isfinite())
    near = missing.clone()
    near[1:] |= missing[:-1]
    near[:-1] |= missing[1:]
    near[:, 1:] |= missing[:, :-1]
    near[:, :-1] |= missing[:, 1:]
    near[0], near[-1], near[:, 0], near[:, -1] = True, True, True, True
    assert torch.all(n[:, near] == 0)
    assert torch.equal(n[:, ~near], full[:, ~near])  # elsewhere exactly the normals without the hole
    n.sum().backward()
    assert torch.isfinite(depth.grad).all() and torch.all(depth.grad[0, missing] == 0)


def test_umeyama_recovers_a_similarity():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(50, 3, generator=g, dtype=F64)
    R = quat_to_rotmat(torch.randn(4, generator=g, dtype=F64))
    s, t = torch.tensor(2.5, dtype=F64), torch.tensor([1.0, -2.0, 0.5], dtype=F64)
    dst = s * src @ R.T + t
    s2, R2, t2 = umeyama(src, dst)
    torch.testing.assert_close(s2, s)
    torch.testing.assert_close(R2, R)
    torch.testing.assert_close(t2, t)
    T = sim3_matrix(s2, R2, t2)
    torch.testing.assert_close(src @ T[:3, :3].T + T[:3, 3], dst)
    with pytest.raises(ValueError, match="umeyama"):
        umeyama(src, dst[:10])



def test_umeyama_returns_a_proper_rotation_for_mirrored_and_noisy_three_point_data():
    """A mirror image has no rotation that fits it: the best proper one flips the axis of least spread as well, here
    R = diag(-1, 1, -1) and s = (9 + 4 - 1) / (9 + 4 + 1). Without the reflection fix R has det -1 (a mirror that
    turns the cameras and scenes it aligns inside out), and so does about half of all noisy 3-point fits."""
    src = torch.tensor([[3.0, 0, 0], [-3, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 1], [0, 0, -1]], dtype=F64)
    dst = src * torch.tensor([-1.0, 1.0, 1.0], dtype=F64) + torch.tensor([0.5, -1.0, 2.0], dtype=F64)
    s, R, t = umeyama(src, dst)
    torch.testing.assert_close(R, torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=F64)))
    torch.testing.assert_close(s, torch.tensor(12 / 14, dtype=F64))
    torch.testing.assert_close(t, torch.tensor([0.5, -1.0, 2.0], dtype=F64))
    g = torch.Generator().manual_seed(0)
    src = torch.randn(32, 3, 3, generator=g, dtype=F64)
    R_true = quat_to_rotmat(torch.randn(32, 4, generator=g, dtype=F64))
    dst = 1.5 * src @ R_true.transpose(-1, -2) + 0.01 * torch.randn(32, 3, 3, generator=g, dtype=F64)
    _, R, _ = umeyama(src, dst)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(32, dtype=F64))
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3, dtype=F64).expand(32, 3, 3))
    assert (R - R_true).abs().amax() < 0.1  # the right rotation, not merely a proper one

def test_umeyama_refuses_weights_of_another_shape_or_sign():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(6, 3, generator=g, dtype=F64)
    dst = 2 * src + 1
    for bad in (torch.ones(6, 1, dtype=F64), torch.ones(5, dtype=F64), torch.ones(2, 6, dtype=F64)):
        with pytest.raises(ValueError, match=r"umeyama: weights must have shape \[\.\.\., N\] = \(6,\)"):
            umeyama(src, dst, bad)  # [N, 1] used to broadcast silently into a batch of 6 alignments
    w = torch.ones(6, dtype=F64)
    w[2] = -0.5
    with pytest.raises(ValueError, match="umeyama: weights must be >= 0"):
        umeyama(src, dst, w)
    s, _, t = umeyama(src, dst, w.clamp_min(0))
    torch.testing.assert_close(s, torch.tensor(2.0, dtype=F64))


def _sound_camera():
    return torch.eye(4, dtype=F64).numpy(), torch.tensor([[30.0, 0, 8], [0, 30, 8], [0, 0, 1]], dtype=F64).numpy()


def test_camera_problem_refuses_each_unsound_part_naming_it():
    """A negative focal, a w2c bottom row other than [0, 0, 0, 1], a K last row other than [0, 0, 1] and a rotation
    block scaled by 0.2 % (R Rᵀ off by 4e-3, outside the 1e-3 tolerance) are each refused, with their own message."""
    w2c, K = _sound_camera()
    assert camera_problem(w2c, K) is None
    neg = K.copy()
    neg[0, 0] = -30
    assert "focal lengths > 0 (got fx=-30, fy=30)" in camera_problem(w2c, neg)
    row = w2c.copy()
    row[3] = [0, 0, 0, 2]
    assert "not a rigid rotation" in camera_problem(row, K)
    scaled = w2c.copy()
    scaled[:3, :3] *= 1.002
    assert "not a rigid rotation" in camera_problem(scaled, K)
    last = K.copy()
    last[2] = [0, 0, 2]
    said = camera_problem(w2c, last)
    assert said.startswith("K's last row must be [0, 0, 1], got [0, 0, 2]") and "focal" not in said


def test_camera_problem_refuses_the_skew_the_renderer_refuses():
    """A converter's check passes a K exactly when the renderer does: skew up to 1e-3 px is rounding, more (a
    BlendedMVS-style full 3x3 K with skew 5 px) is refused in one line naming skew, not at fit time."""
    from anycity.render.api import _check_intrinsics

    w2c, K = _sound_camera()
    for skew in (0.0, 5e-4, 2e-3, 5.0):
        for at in ((0, 1), (1, 0)):
            k = K.copy()
            k[at] = skew
            said = camera_problem(w2c, k)
            for dtype in (torch.float32, torch.float64):
                kt = torch.tensor(k, dtype=dtype)
                if said is None:
                    _check_intrinsics(kt, dtype, 16, 16)
                else:
                    with pytest.raises(ValueError, match="skew"):
                        _check_intrinsics(kt, dtype, 16, 16)
            assert (said is None) == (skew < 1e-3)
            if said is not None:
                assert said.startswith(f"intrinsics have skew {skew:.3g} px") and "zero skew" in said
                assert "\n" not in said
