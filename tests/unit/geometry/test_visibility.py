"""visible_views / count_visible on analytic scenes: in frame, in front, depth test with occlusion."""

from __future__ import annotations

import pytest
import torch
from helpers.raycast_scenes import H, W, intrinsics, look_at, render_depth

import anycity.geometry.visibility as visibility
from anycity.geometry import count_visible, unproject_depth, visible_views

BOX = ((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0))


def _cams(eyes, target=(0.0, 0.0, 0.0)):
    w2c = torch.stack([look_at(e, target) for e in eyes])[None]
    K = intrinsics().expand(1, len(eyes), 3, 3)
    return w2c, K


def test_ground_points_seen_and_box_occludes():
    w2c, K = _cams([(0.3, -0.2, 5.0), (4.0, 0.0, 3.0)])
    depth = render_depth(w2c, K, boxes=[BOX])
    top = torch.tensor([[0.0, 0.0, 1.0]])
    under = torch.tensor([[0.0, 0.0, 0.0]])  # ground under the box: hidden from both cameras
    far_ground = torch.tensor([[1.2, -1.0, 0.0]])
    pts = torch.cat([top, under, far_ground])[None]
    vis = visible_views(pts, depth, w2c, K)
    assert vis.shape == (1, 2, 3)
    assert vis[0, :, 0].all() and vis[0, :, 2].all()
    assert not vis[0, :, 1].any()
    torch.testing.assert_close(count_visible(pts, depth, w2c, K), torch.tensor([[2, 0, 2]]))


def test_own_depth_points_visible_and_pushed_back_points_hidden():
    w2c, K = _cams([(0.3, -0.2, 5.0)])
    depth = render_depth(w2c, K)  # no depth edges: every pixel's own point passes
    pts = unproject_depth(depth, K, w2c).reshape(1, -1, 3)
    assert visible_views(pts, depth, w2c, K).all()
    # Each point 20 % farther along its ray from the camera: behind the surface, so hidden (tolerance 5 %).
    centre = torch.linalg.inv(w2c[0, 0])[:3, 3]
    behind = centre + (pts - centre) * 1.2
    assert not visible_views(behind, depth, w2c, K).any()
    assert visible_views(centre + (pts - centre) * 1.03, depth, w2c, K).all()
    assert not visible_views(centre + (pts - centre) * 1.03, depth, w2c, K, depth_tol=0.01).any()


def test_out_of_frame_behind_camera_invalid_and_sky():
    w2c, K = _cams([(0.0, 0.0, 5.0)])
    depth = render_depth(w2c, K)  # looking straight down at the plane: all valid
    pts = torch.tensor([[[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 0.0, 10.0], [float("nan"), 0.0, 0.0]]])
    assert visible_views(pts, depth, w2c, K)[0, 0].tolist() == [True, False, False, False]
    assert not visible_views(pts[:, :1], torch.zeros_like(depth), w2c, K).any()
    assert not visible_views(pts[:, :1], depth, w2c, K, valid=torch.zeros_like(depth, dtype=torch.bool)).any()
    bad = depth.clone()
    bad[..., H // 2 - 1:H // 2 + 1, W // 2 - 1:W // 2 + 1] = float("nan")
    assert not visible_views(pts[:, :1], bad, w2c, K).any()


def test_depth_discontinuity_does_not_reveal_occluded_point():
    # Synthetic depth map: left half a near surface at z = 1, right half far at z = 10.
    K = intrinsics()[None, None]
    w2c = torch.eye(4)[None, None]
    depth = torch.full((1, 1, 1, H, W), 10.0)
    depth[..., : W // 2] = 1.0
    f, cx, cy = K[0, 0, 0, 0], K[0, 0, 0, 2], K[0, 0, 1, 2]

    def at(u, v, z):
        return torch.tensor([(u - cx) / f * z, (v - cy) / f * z, z])

    # Lands in the last near pixel, 0.2 px from the edge: a bilinear blend of 1 and 10 would be ~5.5 and let
    # this point at z = 3 through; the 2x2 minimum keeps it hidden.
    occluded = at(W // 2 - 0.2, H / 2 + 0.5, 3.0)
    near_edge = at(W // 2 - 0.2, H / 2 + 0.5, 1.0)  # on the near surface itself
    far_inside = at(W // 2 + 3.5, H / 2 + 0.5, 10.0)  # background well away from the edge
    vis = visible_views(torch.stack([occluded, near_edge, far_inside])[None], depth, w2c, K)
    assert vis[0, 0].tolist() == [False, True, True]


def test_chunking_matches_and_shapes(monkeypatch):
    w2c, K = _cams([(0.3, -0.2, 5.0), (4.0, 0.0, 3.0), (-3.0, 2.0, 2.5)])
    depth = render_depth(w2c, K, boxes=[BOX])
    g = torch.Generator().manual_seed(0)
    pts = (torch.rand(1, 500, 3, generator=g) - 0.5) * torch.tensor([4.0, 4.0, 2.0]) + torch.tensor([0, 0, 0.5])
    full = visible_views(pts, depth, w2c, K)
    monkeypatch.setattr(visibility, "_CHUNK_ELEMS", 64)
    torch.testing.assert_close(visible_views(pts, depth, w2c, K), full)
    assert 0 < full.sum() < full.numel()


def test_bad_shapes_raise():
    w2c, K = _cams([(0.0, 0.0, 5.0)])
    depth = render_depth(w2c, K)
    with pytest.raises(ValueError, match="points must be"):
        visible_views(torch.zeros(1, 3), depth, w2c, K)
    with pytest.raises(ValueError, match="w2c"):
        visible_views(torch.zeros(1, 4, 3), depth, w2c[:, :, :3], K)


def _at_pixel(u, v, z):
    """The camera-frame point ``[3]`` that the identity camera of ``intrinsics()`` sees at pixel (u, v), depth z."""
    K = intrinsics()
    return torch.tensor([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])


def _visible(points, depth, **kw):
    return visible_views(torch.stack(points)[None], depth, torch.eye(4)[None, None], intrinsics()[None, None],
                         **kw)[0, 0].tolist()


def test_sky_next_to_a_ground_pixel_does_not_hide_it():
    """Depth 0 is no surface: a ground point in the last valid column, 0.2 px from the sky, is visible."""
    depth = torch.full((1, 1, 1, H, W), 5.0)
    depth[..., W // 2:] = 0.0
    assert _visible([_at_pixel(W // 2 - 0.2, H / 2 + 0.5, 5.0)], depth) == [True]


@pytest.mark.parametrize("axis", ["column", "row"])
def test_the_pixel_a_point_falls_in_decides_it_has_depth(axis):
    """A point inside a pixel with no depth is not seen; one in the next pixel (1 px further) is, along u and v."""
    depth = torch.full((1, 1, 1, H, W), 5.0)
    if axis == "column":
        depth[..., W // 2] = 0.0
        pts = [_at_pixel(W // 2 + 0.3, H / 2 + 0.5, 5.0), _at_pixel(W // 2 + 1.3, H / 2 + 0.5, 5.0)]
    else:
        depth[..., H // 2, :] = 0.0
        pts = [_at_pixel(W / 2 + 0.5, H // 2 + 0.3, 5.0), _at_pixel(W / 2 + 0.5, H // 2 + 1.3, 5.0)]
    assert _visible(pts, depth) == [False, True]


def test_default_depth_tolerance_is_five_percent():
    """A point 4 % behind a flat surface is seen, 7 % behind hidden, at the default depth_tol (0.05)."""
    depth = torch.full((1, 1, 1, H, W), 10.0)
    pts = [_at_pixel(W / 2 + 0.5, H / 2 + 0.5, z) for z in (10.4, 10.7)]
    assert _visible(pts, depth) == [True, False]
