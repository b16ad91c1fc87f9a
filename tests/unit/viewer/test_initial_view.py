"""``anycity view``'s frame: the up axis its orbit controls turn about, its first camera, the frustums' shape."""

import math

import numpy as np
import pytest
import torch

from anycity.viewer.server import frustum_shape, initial_view

from .test_video_path import _look_at


def _ground(n=2000, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.cat([torch.rand(n, 2, generator=g) * 20 - 10, torch.rand(n, 1, generator=g)], -1).numpy()


def test_a_nadir_grid_turns_about_the_vertical_and_starts_tilted():
    """Straight-down cameras: their "up" (-y) lies on the ground; orbiting about it swung the city like a door."""
    w2c = torch.stack([_look_at((x, y, 20.0), (x, y, 0.0), up=(0.0, 1.0, 0.0))
                       for x in (-6.0, 0.0, 6.0) for y in (-6.0, 0.0, 6.0)])
    up, position, look_at = initial_view(torch.linalg.inv(w2c).numpy(), _ground())
    np.testing.assert_allclose(up, [0, 0, 1], atol=0.05)
    view = (look_at - position) / np.linalg.norm(look_at - position)
    assert math.degrees(math.acos(-view @ up)) == pytest.approx(30.0, abs=1.0)  # looking down, not along the axis
    assert position[2] > 15


def test_an_oblique_orbit_starts_behind_its_cameras_looking_at_the_scene():
    w2c = torch.stack([_look_at((15 * math.cos(a), 15 * math.sin(a), 12.0)) for a in np.linspace(0, 1.0, 5)])
    c2w = torch.linalg.inv(w2c).numpy()
    up, position, look_at = initial_view(c2w, _ground())
    np.testing.assert_allclose(up, [0, 0, 1], atol=0.05)
    np.testing.assert_allclose(look_at, np.median(_ground(), 0))
    fwd = c2w[:, :3, 2].mean(0)
    view = (look_at - position) / np.linalg.norm(look_at - position)
    assert view @ fwd / np.linalg.norm(fwd) > 0.999  # the mean input camera's direction, kept
    assert np.linalg.norm(position - look_at) > np.linalg.norm(c2w[:, :3, 3].mean(0) - look_at)


def test_a_frustum_has_its_cameras_field_of_view_on_both_axes():
    K = np.array([[48.3, 0, 28], [0, 34.4, 20], [0, 0, 1]])
    fov_y, aspect = frustum_shape(K, 56, 40)
    assert math.tan(fov_y / 2) == pytest.approx(20 / 34.4)
    assert aspect * math.tan(fov_y / 2) == pytest.approx(28 / 48.3)  # horizontal: W / 2 / fx, not from fy


def test_the_viewer_cameras_focal_comes_from_its_vertical_field_of_view():
    from anycity.viewer.server import camera_w2c

    _, K = camera_w2c([1.0, 0, 0, 0], [0.0, 0, 0], 1.0, 96, 64)
    f = 32 / math.tan(0.5)  # half the height over tan(fov_y / 2), on both axes
    torch.testing.assert_close(K[0, 0], torch.tensor([[f, 0, 48], [0, f, 32], [0, 0, 1]]))
