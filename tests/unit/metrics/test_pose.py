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
    assert rre.max() < 1e-4 and rte.max() < 1e-3  # float32 cameras moved by a float32 similarity
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



def test_auc_an_error_equal_to_a_threshold_is_not_below_it():
    """VGGT bins the worse error with np.histogram(bins=0..30): an error of exactly t degrees lands in [t, t + 1)
    and counts from threshold t + 1 on. Counting it at t would inflate every AUC on rounded or clamped errors."""
    rre = torch.tensor([1.0, 5.0, 0.0, 29.0])
    rte = torch.tensor([0.0, 0.0, 5.0, 2.0])
    expected = torch.tensor([29 / 30, 25 / 30, 25 / 30, 1 / 30])
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


def _axis_angle(axis, deg):
    """Rotation by ``deg`` about ``axis`` (Rodrigues, float64)."""
    k = torch.as_tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    Kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    a = math.radians(deg)
    return torch.eye(3, dtype=torch.float64) + math.sin(a) * Kx + (1 - math.cos(a)) * Kx @ Kx


def test_equal_float32_cameras_have_no_rotation_error():
    # acos((tr - 1) / 2) gave up to 0.09 deg here: float32 rotations are orthogonal only to ~1e-7, which moves a
    # trace of 3 by as much; the skew part of R_p^T R_g is exactly zero for equal cameras.
    g = torch.Generator().manual_seed(0)
    w2c = torch.eye(4).repeat(16, 8, 1, 1)
    w2c[..., :3, :3] = quat_to_rotmat(torch.randn(16, 8, 4, generator=g))
    w2c[..., :3, 3] = torch.randn(16, 8, 3, generator=g)
    rre, rte = relative_pose_errors(w2c, w2c.clone())
    assert rre.max() < 1e-4 and rte.max() < 1e-4


@pytest.mark.parametrize("deg", [0.01, 1.0, 90.0, 179.0, 180.0])
def test_known_rotation_angles(deg):
    # float32 cameras (as the network and the shards give them): camera 1 turned by deg more than the ground truth's
    axis = (0.3, -0.5, 0.8)
    R0 = _axis_angle((1.0, 2.0, -0.5), 40.0)
    gt = _cams([torch.eye(3), R0.float()], [(0, 0, 0), (1, 0, 0)])
    pred = _cams([torch.eye(3), (_axis_angle(axis, deg) @ R0).float()], [(0, 0, 0), (1, 0, 0)])
    assert relative_pose_errors(pred, gt)[0].item() == pytest.approx(deg, abs=1e-4)  # acos: 0.0072 for 0.01
    from anycity.metrics.pose import rotation_angle_deg

    assert rotation_angle_deg(_axis_angle(axis, deg)).item() == pytest.approx(deg, abs=1e-9)


def test_unbatched_or_mismatched_cameras_are_refused():
    w2c = _cams([torch.eye(3), _rot_y(20), _rot_y(-35)], [(0, 0, 0), (1, 0, 0.2), (-0.5, 0.3, 1)])
    for pred, gt in ((w2c[0], w2c[0]), (w2c, w2c[:, :2]), (w2c[:, :1], w2c[:, :1]), (w2c[..., :3, :], w2c)):
        with pytest.raises(ValueError, match=r"relative_pose_errors: .*\[B, V, 4, 4\].*add a batch dim with \[None\]"):
            relative_pose_errors(pred, gt)
    assert relative_pose_errors(w2c[0][None], w2c[0][None])[0].shape == (1, 3)
