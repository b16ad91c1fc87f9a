"""Half-precision (float16 / bfloat16) inputs to the unprojections and the Sim(3) fit: shards store float16 depth,
and a half pixel grid puts the pixel centres of wide images pixels off."""

from __future__ import annotations

import pytest
import torch

from anycity.geometry import (
    make_intrinsics,
    pixel_grid,
    pixel_rays,
    project_points,
    quat_to_rotmat,
    umeyama,
    unproject_depth,
    unproject_depth_to_camera,
)

H, W = 4, 1920
HALF = (torch.float16, torch.bfloat16)


@pytest.mark.parametrize("dtype", HALF)
def test_half_depth_with_float32_cameras_unprojects_at_the_exact_pixel_centres(dtype):
    # 7.0 is exact in both half dtypes; the cameras are float32, so the points come back in float32 and must
    # reproject onto the pixel centres (a bfloat16 grid put u = 1500.5 at 1504).
    K = make_intrinsics(1000.0, 1000.0, W / 2, H / 2)
    depth = torch.full((1, 1, H, W), 7.0, dtype=dtype)
    pts = unproject_depth(depth, K, torch.eye(4))
    assert pts.dtype == torch.float32
    uv, z = project_points(pts.reshape(1, -1, 3), torch.eye(4), K)
    assert (uv.reshape(H, W, 2) - pixel_grid(H, W)).abs().max() < 0.01
    torch.testing.assert_close(z, torch.full_like(z, 7.0))


@pytest.mark.parametrize("dtype", HALF)
def test_all_half_inputs_give_the_float32_result_rounded_once(dtype):
    # Inputs all in a half dtype keep that output dtype (as before); the only error left is the output's rounding.
    K = make_intrinsics(1000.0, 1000.0, W / 2, H / 2)
    depth = torch.full((1, 1, H, W), 7.0)
    cam = unproject_depth_to_camera(depth.to(dtype), K.to(dtype))
    assert cam.dtype == dtype
    assert torch.equal(cam, unproject_depth_to_camera(depth, K.to(dtype).float()).to(dtype))
    w2c = torch.eye(4)
    world = unproject_depth(depth.to(dtype), K.to(dtype), w2c.to(dtype))
    assert world.dtype == dtype
    assert torch.equal(world, unproject_depth(depth, K.to(dtype).float(), w2c).to(dtype))
    origins, dirs = pixel_rays(K.to(dtype), w2c.to(dtype), H, W)
    ref_o, ref_d = pixel_rays(K.to(dtype).float(), w2c, H, W)
    assert origins.dtype == dirs.dtype == dtype
    assert torch.equal(origins, ref_o.to(dtype)) and torch.equal(dirs, ref_d.to(dtype))


@pytest.mark.parametrize("dtype", HALF)
def test_umeyama_fits_half_precision_points_in_float32(dtype):
    # torch's SVD has no half kernel (it raised NotImplementedError): the fit runs in float32, the result comes
    # back in the input dtype.
    g = torch.Generator().manual_seed(0)
    src = torch.randn(2, 40, 3, generator=g)
    R = quat_to_rotmat(torch.randn(2, 4, generator=g))
    s, t = torch.tensor([2.0, 0.5]), torch.tensor([[1.0, -2.0, 0.5], [0.0, 3.0, -1.0]])
    dst = s[:, None, None] * src @ R.transpose(-1, -2) + t[:, None]
    s2, R2, t2 = umeyama(src.to(dtype), dst.to(dtype), torch.ones(2, 40, dtype=dtype))
    assert s2.dtype == R2.dtype == t2.dtype == dtype
    tol = dict(atol=0.05, rtol=0.02)  # the inputs' own rounding (bfloat16: 8 bits)
    torch.testing.assert_close(s2.float(), s, **tol)
    torch.testing.assert_close(R2.float(), R, **tol)
    torch.testing.assert_close(t2.float(), t, **tol)
    s3, R3, t3 = umeyama(src.to(dtype), dst.to(dtype))
    assert torch.equal(s3, s2) and torch.equal(R3, R2) and torch.equal(t3, t2)


def test_umeyama_float32_and_float64_are_unchanged():
    g = torch.Generator().manual_seed(1)
    src = torch.randn(30, 3, generator=g, dtype=torch.float64)
    dst = 3 * src + 1
    for dtype in (torch.float32, torch.float64):
        s, R, t = umeyama(src.to(dtype), dst.to(dtype))
        assert s.dtype == R.dtype == t.dtype == dtype
        torch.testing.assert_close(s, torch.tensor(3.0, dtype=dtype))
    # float64 weights with float32 points promote, as before
    assert umeyama(src.float(), dst.float(), torch.ones(30, dtype=torch.float64))[0].dtype == torch.float64
