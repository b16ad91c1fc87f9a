"""Camera alignment into the predicted frame and the LR schedule."""

import pytest
import torch
from helpers.scenes import make_cameras, make_gaussians

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


def _scene_and_cameras():
    g = make_gaussians(B=1, N=300, seed=3, dtype=torch.float32, spread=(1.2, 1.0, 0.3), scale=(0.05, 0.15))
    w2c, K = make_cameras(B=1, V=2, width=32, height=32, dtype=torch.float32, seed=4)
    return g, w2c, K


def test_transform_gaussians_equals_moving_the_camera():
    from anycity.lit.evaluation import transform_gaussians
    from anycity.render import render

    g, w2c, K = _scene_and_cameras()
    A = _rand_w2c(1, 1, seed=7)[:, 0] * 0.1
    A[:, :3, :3] = quat_to_rotmat(torch.tensor([[1.0, 0.05, -0.03, 0.02]]))
    A[:, 3, 3] = 1.0
    moved = render(transform_gaussians(g, A), w2c, K, 32, 32, backend="torch").rgb
    camera = render(g, w2c @ A[:, None], K, 32, 32, backend="torch").rgb
    torch.testing.assert_close(moved, camera, atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_align_target_poses_recovers_a_perturbed_camera(backend):
    from anycity.lit.evaluation import align_target_poses
    from anycity.metrics import psnr
    from anycity.render import render

    g, w2c, K = _scene_and_cameras()
    images = render(g, w2c, K, 32, 32, backend="torch").rgb.detach()
    noise = torch.eye(4).repeat(1, 2, 1, 1)
    noise[..., :3, :3] = quat_to_rotmat(torch.tensor([[[1.0, 0.02, -0.03, 0.01], [1.0, -0.02, 0.01, 0.03]]]))
    noise[..., :3, 3] = torch.tensor([[[0.05, -0.04, 0.03], [-0.03, 0.05, -0.02]]])
    start = noise @ w2c

    def render_rgb(scenes, cams):
        return render(scenes, cams, K.reshape(-1, 1, 3, 3), 32, 32, backend=backend).rgb

    with torch.inference_mode():  # as in Lightning's test loop
        out = align_target_poses(render_rgb, g, start, images, steps=150, lr=0.005)
    assert out.shape == w2c.shape and not out.requires_grad
    # a distant slab-like scene trades a small rotation for a translation, so the image is the criterion
    before = psnr(render(g, start, K, 32, 32, backend="torch").rgb, images)
    after = psnr(render(g, out, K, 32, 32, backend="torch").rgb, images)
    assert (before < 20).all() and (after > 40).all()
    assert torch.equal(align_target_poses(render_rgb, g, start, images, steps=0), start)
