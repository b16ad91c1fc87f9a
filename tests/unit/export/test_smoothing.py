"""The baked 3-D smoothing filter: a minimum size from the input cameras' sampling rate, density kept."""

from __future__ import annotations

import torch

from anycity.export.smoothing import sampling_rate, smooth_3d
from anycity.structures import Gaussians


def test_tiny_gaussians_grow_to_the_sampling_limit_big_ones_stay():
    w2c = torch.eye(4)[None, None].repeat(1, 2, 1, 1)
    w2c[0, 1, 2, 3] = 5.0  # the second camera is 5 units farther back: the points sit at z = 10 in it
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 24], [0, 0, 1]]).expand(1, 2, 3, 3)
    means = torch.tensor([[[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [100.0, 0.0, 5.0]]])
    g = Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).expand(1, 3, 4),
                  scales=torch.tensor([[[1e-5] * 3, [1.0] * 3, [1e-5] * 3]]), opacities=torch.full((1, 3), 0.8),
                  sh=torch.zeros(1, 3, 1, 3))
    nu = sampling_rate(means, w2c, K, 48, 48)
    torch.testing.assert_close(nu[0, :2], torch.tensor([8.0, 8.0]))  # f / z of the nearer camera (z = 5)
    s = smooth_3d(g, w2c, K, 48, 48)
    std = 0.2 ** 0.5 / 8.0
    torch.testing.assert_close(s.scales[0, 0], torch.full((3,), (std ** 2 + 1e-10) ** 0.5))
    assert s.opacities[0, 0] < 1e-6  # density kept: a tiny splat spread out becomes faint
    torch.testing.assert_close(s.scales[0, 1], g.scales[0, 1], rtol=2e-3, atol=0)
    assert abs(s.opacities[0, 1].item() - 0.8) < 1e-2
    assert s.scales[0, 2, 0] > 1e-3  # out of frame: still filtered at the rate of the cameras it is in front of
