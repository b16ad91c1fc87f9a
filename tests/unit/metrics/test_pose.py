"""Relative pose errors (all view pairs) and pose AUC on constructed cameras with known answers."""

import math

import pytest
import torch

from anycity.geometry import quat_to_rotmat
from anycity.metrics import pose_auc, relative_pose_errors


def _rot_y(deg):
    a = math.radians(deg)
    return torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _cams(rots, ts):
    w2c = torch.eye(4).repeat(1, len(rots), 1, 1)
    for k, (R, t) in enumerate(zip(rots, ts)):
        w2c[0, k, :3, :3], w2c[0, k, :3, 3] = R, torch.tensor(t, dtype=torch.float32)
    return w2c


def test_errors_are_zero_up_to_a_world_similarity():
    gt = _cams([torch.eye(3), _rot_y(20), _rot_y(-35)], [(0, 0, 0), (1, 0, 0.2), (-0.5, 0.3, 1)])
    R = quat_to_rotmat(torch.tensor([0.9, 0.2, -0.3, 0.1]))
    world = torch.eye(4)
    world[:3, :3], world[:3, 3] = R, torch.tensor([3.0, -1.0, 2.0])
    pred = gt @ torch.linalg.inv(world)  # the same cameras in another world frame ...
    pred[..., :3, 3] *= 2.5  # ... and another scale
    rre, rte = relative_pose_errors(pred, gt)
    assert rre.shape == rte.shape == (1, 3)
    assert rre.max() < 0.05 and rte.max() < 0.05
    assert pose_auc(rre, rte).min() == 1.0


def test_known_rotation_and_translation_errors():
    gt = _cams([torch.eye(3), _rot_y(20)], [(0, 0, 0), (1, 0, 0)])
    pred = _cams([torch.eye(3), _rot_y(30)], [(0, 0, 0), (0, 0, 2)])  # 10 deg more turn; t at 90 deg
    rre, rte = relative_pose_errors(pred, gt)
    assert rre.item() == pytest.approx(10.0, abs=1e-3)
    assert rte.item() == pytest.approx(90.0, abs=1e-3)
    flipped = _cams([torch.eye(3), _rot_y(20)], [(0, 0, 0), (-3, 0, 0)])  # direction sign is ambiguous (VGGT)
    assert relative_pose_errors(flipped, gt)[1].item() == pytest.approx(0.0, abs=1e-3)


def test_auc_counts_thresholds_below_the_worse_error():
    rre = torch.tensor([0.5, 10.5, 40.0, 2.0])
    rte = torch.tensor([0.2, 1.0, 0.0, 25.5])
    expected = torch.tensor([30 / 30, 20 / 30, 0.0, 5 / 30])
    torch.testing.assert_close(pose_auc(rre, rte, 30), expected)


def test_a_non_finite_predicted_camera_is_the_worst_error_in_every_pose_metric():
    gt = _cams([torch.eye(3), _rot_y(20), _rot_y(-35)], [(0, 0, 0), (1, 0, 0.2), (-0.5, 0.3, 1)])
    pred = gt.clone()
    pred[0, 2, 0, 3] = float("nan")
    rre, rte = relative_pose_errors(pred, gt)
    assert rre[0, 0] < 0.05 and rte[0, 0] < 0.05  # the pair of the two finite cameras
    torch.testing.assert_close(rre[0, 1:], torch.tensor([180.0, 180.0]))
    torch.testing.assert_close(rte[0, 1:], torch.tensor([90.0, 90.0]))
    assert pose_auc(rre, rte)[0, 1:].eq(0).all()  # and a mean of rre over all pairs counts them (no NaN to drop)
