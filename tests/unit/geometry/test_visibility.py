"""visible_views: frame bounds, in front of the camera, and the depth test (occlusion)."""

import torch

from anycity.geometry import make_intrinsics
from anycity.geometry.visibility import count_visible, visible_views


def _cams(xs, h=24, w=32, f=20.0):
    w2c = torch.eye(4).repeat(1, len(xs), 1, 1)
    w2c[0, :, 0, 3] = -torch.tensor(xs)  # camera centre at (x, 0, 0), looking down +z
    return w2c, make_intrinsics(f, f, w / 2, h / 2).expand(1, len(xs), 3, 3)


def test_points_in_frame_in_front_and_not_occluded():
    w2c, K = _cams([0.0, 1.0])
    depth = torch.full((1, 2, 1, 24, 32), 5.0)
    pts = torch.tensor([[[0.0, 0.0, 5.0],     # on the surface: both see it
                         [0.0, 0.0, 7.0],     # behind the surface at depth 5: occluded in both
                         [0.0, 0.0, 3.0],     # in front of the surface: seen
                         [0.0, 0.0, -5.0],    # behind the cameras
                         [4.5, 0.0, 5.0]]])   # x = 4.5 at z = 5: outside camera 0 (|x| <= 4), inside camera 1
    vis = visible_views(pts, depth, w2c, K)
    assert vis.shape == (1, 2, 5)
    assert vis[0, :, 0].all() and not vis[0, :, 1].any() and vis[0, :, 2].all() and not vis[0, :, 3].any()
    assert vis[0, :, 4].tolist() == [False, True]
    assert count_visible(pts, depth, w2c, K).tolist() == [[2, 0, 2, 0, 1]]


def test_no_surface_and_invalid_pixels_see_nothing():
    w2c, K = _cams([0.0])
    pts = torch.tensor([[[0.0, 0.0, 5.0]]])
    assert not visible_views(pts, torch.zeros(1, 1, 1, 24, 32), w2c, K).any()  # sky everywhere
    depth = torch.full((1, 1, 1, 24, 32), 5.0)
    valid = torch.zeros(1, 1, 1, 24, 32, dtype=torch.bool)
    assert not visible_views(pts, depth, w2c, K, valid=valid).any()
    assert visible_views(pts, depth, w2c, K, valid=~valid).all()


def test_depth_tolerance_is_relative():
    w2c, K = _cams([0.0])
    depth = torch.full((1, 1, 1, 24, 32), 10.0)
    pts = torch.tensor([[[0.0, 0.0, 10.4], [0.0, 0.0, 10.6]]])
    assert visible_views(pts, depth, w2c, K, depth_tol=0.05).tolist() == [[[True, False]]]
