"""benchmarks/pose_correlation.py: its poses go through the project's pose metric, and a short fit learns
(the regressor itself, ``anycity.models.pose_prior``, has its unit tests in tests/unit/models/test_pose_prior.py)."""

import math

import torch
from helpers.scripts import load_script

from anycity.metrics.pose import relative_pose_errors


def _bench():
    return load_script("pose_correlation", "benchmarks")


def _yaw(deg: float, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype)


def test_rotation_error_of_its_poses_and_a_short_fit():
    """Its poses go through the project's pose metric (``relative_pose_errors``, ``anycity test``'s ``rre``)."""
    bench = _bench()
    f64 = torch.float64  # float32 rotations are orthonormal to 1e-7, which acos turns into 0.02 deg near 0
    R_gt = torch.stack([torch.eye(3, dtype=f64), _yaw(10, f64), _yaw(30, f64)])[None]

    def rre(R, R_ref):
        return relative_pose_errors(bench.as_w2c(R), bench.as_w2c(R_ref))[0]

    assert rre(R_gt, R_gt).abs().max() < 1e-3
    # pairs (0,1), (0,2), (1,2): 0, 5, 5 degrees
    R = torch.stack([torch.eye(3, dtype=f64), _yaw(10, f64), _yaw(25, f64)])[None]
    torch.testing.assert_close(rre(R, R_gt), torch.tensor([[0.0, 5.0, 5.0]]), atol=1e-2, rtol=0)
    t = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 2, 0]]], dtype=f64)
    torch.testing.assert_close(bench.as_w2c(R, t)[..., :3, 3], t)
    torch.manual_seed(0)
    net = bench.PairFlowPose()
    images = torch.rand(2, 3, 3, 48, 48)
    R_gt = torch.stack([torch.stack([torch.eye(3), _yaw(8), _yaw(-15)])] * 2)  # float32, as the network's
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    errors = []
    for _ in range(40):
        R = net(images)[..., :3, :3]
        loss = (R - R_gt).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        errors.append(rre(R.detach(), R_gt).mean().item())
    assert errors[-1] < 0.3 * errors[0]
