"""benchmarks/pose_correlation.py: the pair-correlation pose regressor reads content, not view order."""

import math

import torch
from helpers.scripts import load_script


def _bench():
    return load_script("pose_correlation", "benchmarks")


def _yaw(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def test_poses_are_per_view_content_not_position():
    bench = _bench()
    torch.manual_seed(0)
    net = bench.PairFlowPose().eval()
    images = torch.rand(2, 4, 3, 48, 48)
    R, t = net(images)
    assert R.shape == (2, 4, 3, 3) and t.shape == (2, 4, 3)
    torch.testing.assert_close(R[:, 0], torch.eye(3).expand(2, 3, 3))
    torch.testing.assert_close(R @ R.mT, torch.eye(3).expand(2, 4, 3, 3), atol=1e-5, rtol=0)
    order = [0, 3, 1, 2]  # views 1..3 shuffled: each keeps its own pose (no position embedding anywhere)
    R2, t2 = net(images[:, order])
    torch.testing.assert_close(R2, R[:, order], atol=1e-5, rtol=0)
    torch.testing.assert_close(t2, t[:, order], atol=1e-5, rtol=0)


def test_relative_rotation_error_and_a_short_fit():
    bench = _bench()
    R_gt = torch.stack([torch.eye(3), _yaw(10), _yaw(30)])[None]
    assert bench.relative_rotation_error(R_gt, R_gt).abs().max() < 1e-3
    R = torch.stack([torch.eye(3), _yaw(10), _yaw(25)])[None]  # pairs (0,1), (0,2), (1,2): 0, 5, 5 degrees
    torch.testing.assert_close(bench.relative_rotation_error(R, R_gt), torch.tensor([[0.0, 5.0, 5.0]]), atol=1e-2,
                               rtol=0)
    torch.manual_seed(0)
    net = bench.PairFlowPose()
    images = torch.rand(2, 3, 3, 48, 48)
    R_gt = torch.stack([torch.stack([torch.eye(3), _yaw(8), _yaw(-15)])] * 2)
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    errors = []
    for _ in range(40):
        R, _ = net(images)
        loss = (R - R_gt).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        errors.append(bench.relative_rotation_error(R.detach(), R_gt).mean().item())
    assert errors[-1] < 0.3 * errors[0]
