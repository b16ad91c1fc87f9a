"""Camera alignment into the predicted frame and the LR schedule."""

import pytest
import torch

from anycity.geometry import project_points, quat_to_rotmat
from anycity.lit.base import warmup_cosine
from anycity.lit.evaluation import cameras_in_pred_frame, fit_gt_to_pred


def _rand_w2c(b, v, seed=0):
    g = torch.Generator().manual_seed(seed)
    T = torch.eye(4).repeat(b, v, 1, 1)
    T[..., :3, :3] = quat_to_rotmat(torch.randn(b, v, 4, generator=g))
    T[..., :3, 3] = torch.randn(b, v, 3, generator=g)
    return T


def test_sim3_fit_recovers_transform_and_depth_scales():
    gt = _rand_w2c(2, 4)
    s = torch.tensor([2.0, 0.5])
    R = quat_to_rotmat(torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.2, 0.7, 0.1, -0.4]]))
    t = torch.tensor([[0.3, -1.0, 2.0], [0.0, 0.5, 0.1]])
    pred = cameras_in_pred_frame(gt, s, R, t)
    s2, R2, t2 = fit_gt_to_pred(pred, gt)
    torch.testing.assert_close(s2, s, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(R2, R, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(t2, t, atol=1e-4, rtol=1e-4)
    # a world point seen by a camera: depth in the predicted frame = s * depth in the ground-truth frame
    p = torch.randn(2, 1, 3)
    p_pred = s[:, None, None] * p @ R.transpose(-1, -2) + t[:, None]
    eye = torch.eye(3).expand(2, 1, 3, 3)
    _, z_gt = project_points(p[:, None], gt[:, :1], eye)
    _, z_pred = project_points(p_pred[:, None], pred[:, :1], eye)
    torch.testing.assert_close(z_pred.flatten(), s * z_gt.flatten(), atol=1e-4, rtol=1e-4)


def test_alignment_none_and_single_view_are_identity():
    gt = _rand_w2c(1, 3)
    for pred, mode in ((gt + 1.0, "none"), (gt[:, :1], "sim3")):
        s, R, t = fit_gt_to_pred(pred, gt[:, : pred.shape[1]], mode)
        assert s.item() == 1.0 and torch.equal(R[0], torch.eye(3)) and t.abs().sum() == 0
    torch.testing.assert_close(cameras_in_pred_frame(gt, *fit_gt_to_pred(gt, gt, "none")), gt)
    with pytest.raises(ValueError, match="eval_align"):
        fit_gt_to_pred(gt, gt, "affine")


def test_warmup_cosine_shape():
    assert warmup_cosine(0, 10, 100, 0.1) == pytest.approx(0.1)
    assert warmup_cosine(9, 10, 100, 0.1) == pytest.approx(1.0)
    assert warmup_cosine(10, 10, 100, 0.1) == pytest.approx(1.0)
    assert warmup_cosine(55, 10, 100, 0.1) == pytest.approx(0.55)
    assert warmup_cosine(100, 10, 100, 0.1) == pytest.approx(0.1)
    assert warmup_cosine(500, 10, 100, 0.1) == pytest.approx(0.1)
