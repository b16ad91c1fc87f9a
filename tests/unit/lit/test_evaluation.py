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


def test_alignment_none_and_single_view_put_the_first_ground_truth_camera_at_the_origin():
    """As the network puts its first input camera. Context views are stored so (the identity), but the D2S teacher's
    dense views are not: with the identity it rendered from cameras off by the pose of dense view 0 (0.8 dB)."""
    from anycity.geometry import invert_rigid

    gt = _rand_w2c(1, 3)
    for pred, mode in ((gt + 1.0, "none"), (gt[:, :1], "sim3")):
        s, R, t = fit_gt_to_pred(pred, gt[:, : pred.shape[1]], mode)
        assert s.item() == 1.0
        torch.testing.assert_close(R[0], gt[0, 0, :3, :3]) and torch.testing.assert_close(t[0], gt[0, 0, :3, 3])
    placed = cameras_in_pred_frame(gt, *fit_gt_to_pred(gt, gt, "none"))
    torch.testing.assert_close(placed, gt @ invert_rigid(gt[:, :1]), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(placed[:, 0], torch.eye(4)[None], atol=1e-5, rtol=1e-5)
    ctx = gt @ invert_rigid(gt[:, :1])  # a sample's context views: the first at the origin, so nothing moves
    torch.testing.assert_close(cameras_in_pred_frame(ctx, *fit_gt_to_pred(ctx, ctx, "none")), ctx, atol=1e-5,
                               rtol=1e-5)
    with pytest.raises(ValueError, match="eval_align"):
        fit_gt_to_pred(gt, gt, "affine")


def test_evaluation_places_targets_relative_to_the_first_camera_as_the_network_predicted_it():
    """``"none"`` at evaluation (``anchor_first``): a network whose whole frame sits a rigid motion off the
    convention (its first camera not at the origin) gets its targets where its own frame has them, relative to its
    first camera; the training placement (at the origin) is off by that motion."""
    from anycity.geometry import invert_rigid

    gt = _rand_w2c(2, 5, seed=3)
    gt = gt @ invert_rigid(gt[:, :1])  # a sample's frame: the first context camera at the origin
    off = _rand_w2c(2, 1, seed=4)[:, 0]  # the network's frame: the ground truth's moved by a rigid motion
    pred = gt @ invert_rigid(off)[:, None]  # so its first camera is `off`, not the identity
    ctx, targets = pred[:, :3], gt[:, 3:]
    placed = cameras_in_pred_frame(targets, *fit_gt_to_pred(ctx, gt[:, :3], "none", anchor_first=True))
    torch.testing.assert_close(placed, pred[:, 3:], atol=1e-5, rtol=1e-5)
    at_origin = cameras_in_pred_frame(targets, *fit_gt_to_pred(ctx, gt[:, :3], "none"))
    assert (at_origin - pred[:, 3:]).abs().max() > 0.1
    # a network that does put its first camera at the origin places them the same either way
    torch.testing.assert_close(cameras_in_pred_frame(targets, *fit_gt_to_pred(gt[:, :3], gt[:, :3], "none", True)),
                               targets, atol=1e-5, rtol=1e-5)


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


@pytest.mark.parametrize("sh_coeffs", [1, 9])
def test_transform_gaussians_equals_moving_the_camera(sh_coeffs):
    """Also with view-dependent colour (degree 2): the moved Gaussians' SH turn with them."""
    from anycity.lit.evaluation import transform_gaussians
    from anycity.render import render

    g, w2c, K = _scene_and_cameras()
    g.sh = 0.5 * torch.randn(1, g.num_gaussians, sh_coeffs, 3, generator=torch.Generator().manual_seed(5))
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


def test_per_view_transforms_move_each_views_gaussians_by_its_own_transform():
    from anycity.lit.evaluation import transform_gaussians
    from anycity.structures import Gaussians

    g, _, _ = _scene_and_cameras()  # 300 Gaussians = 3 "views" of 100
    A = _rand_w2c(1, 3, seed=9)
    per_view = transform_gaussians(g, A)
    for j in range(3):
        part = Gaussians(*(x[:, 100 * j:100 * (j + 1)] for x in (g.means, g.quats, g.scales, g.opacities, g.sh)))
        whole = transform_gaussians(part, A[:, j])
        torch.testing.assert_close(per_view.means[:, 100 * j:100 * (j + 1)], whole.means)
        torch.testing.assert_close(per_view.quats[:, 100 * j:100 * (j + 1)], whole.quats)
    with pytest.raises(ValueError, match="voxel_size"):
        transform_gaussians(g, _rand_w2c(1, 7))


def _views_with_a_camera_error(backend="torch"):
    """Three views of one scene; the "network" got view 1's and view 2's cameras wrong by a few degrees and placed
    their (otherwise perfect) Gaussians with them: group j = inv(pred_j) @ gt_j @ scene."""
    from anycity.render import render
    from anycity.structures import Gaussians

    g = make_gaussians(B=1, N=400, seed=3, dtype=torch.float32, spread=(1.2, 1.0, 0.3), scale=(0.05, 0.15))
    gt, K = make_cameras(B=1, V=3, width=32, height=32, dtype=torch.float32, seed=4)
    images = render(g, gt, K, 32, 32, backend="torch").rgb.detach()
    err = torch.eye(4).repeat(1, 3, 1, 1)
    err[0, 1, :3, :3] = quat_to_rotmat(torch.tensor([1.0, 0.03, -0.04, 0.02]))
    err[0, 2, :3, :3] = quat_to_rotmat(torch.tensor([1.0, -0.03, 0.02, 0.03]))
    err[0, 1:, :3, 3] = torch.tensor([[0.05, -0.04, 0.03], [-0.04, 0.03, 0.05]])
    pred = err @ gt
    from anycity.lit.evaluation import transform_gaussians

    three = Gaussians(*(x.repeat(1, 3, *([1] * (x.dim() - 2))) for x in (g.means, g.quats, g.scales, g.opacities,
                                                                           g.sh)))
    placed = transform_gaussians(three, torch.linalg.inv(pred) @ gt)

    def render_rgb(scenes, cams):
        return render(scenes, cams, K[0].repeat(scenes.means.shape[0] // 3, 1, 1)[:, None], 32, 32,
                      backend=backend).rgb

    return placed, gt, pred, K, images, render_rgb


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_refine_context_cameras_recovers_the_relative_poses_from_the_context_images(backend):
    from anycity.lit.evaluation import refine_context_cameras, transform_gaussians
    from anycity.metrics.pose import relative_pose_errors

    placed, gt, pred, K, images, render_rgb = _views_with_a_camera_error(backend)
    with torch.inference_mode():  # as in Lightning's test and predict loops
        w2c, A = refine_context_cameras(render_rgb, placed, pred, images, steps=150, lr=0.01)
    assert w2c.shape == A.shape == (1, 3, 4, 4) and not w2c.requires_grad
    torch.testing.assert_close(w2c[:, 0], pred[:, 0])  # the reference view stays put
    before, after = relative_pose_errors(pred, gt)[0], relative_pose_errors(w2c, gt)[0]
    assert before.mean() > 4 and after.mean() < 0.5 * before.mean()
    # the moved Gaussians agree across views: each view's set now lies where the scene is
    moved = transform_gaussians(placed, A)
    drift = lambda g: (g.means[:, 400:] - g.means[:, :400].repeat(1, 2, 1)).norm(dim=-1).mean()  # noqa: E731
    assert drift(moved) < 0.5 * drift(placed)
    # view j's Gaussians through the refined camera project as they did through the predicted one
    from anycity.geometry import project_points

    for j in range(3):
        uv0, _ = project_points(placed.means[:, 400 * j:400 * (j + 1)], pred[:, j], K[:, j])
        uv1, _ = project_points(moved.means[:, 400 * j:400 * (j + 1)], w2c[:, j], K[:, j])
        torch.testing.assert_close(uv1, uv0, atol=1e-3, rtol=1e-3)
    same, eye = refine_context_cameras(render_rgb, placed, pred, images, steps=0)
    assert torch.equal(same, pred) and torch.equal(eye, torch.eye(4).expand(1, 3, 4, 4))


def test_refine_context_cameras_rejects_merged_gaussians():
    from anycity.lit.evaluation import refine_context_cameras
    from anycity.structures import Gaussians

    placed, _, pred, _, images, render_rgb = _views_with_a_camera_error()
    merged = Gaussians(placed.means, placed.quats, placed.scales, placed.opacities, placed.sh,
                       torch.ones(placed.means.shape[:2], dtype=torch.bool))
    with pytest.raises(ValueError, match="voxel_size=None"):
        refine_context_cameras(render_rgb, merged, pred, images, steps=5)


def test_test_time_fits_do_not_depend_on_the_batch():
    """Each sample is refined as if alone: its cameras are the same bits in a batch of one and of two (the fused
    renderer treats scenes independently). A mean over the batch made them depend on the batch-mates (Adam's eps)."""
    pytest.importorskip("numba")
    from anycity.lit.evaluation import align_target_poses, refine_context_cameras
    from anycity.render import render
    from anycity.structures import Gaussians

    placed, gt, pred, K, images, render_rgb = _views_with_a_camera_error("cpu")
    pair = Gaussians(*(torch.cat([x, x]) for x in (placed.means, placed.quats, placed.scales, placed.opacities,
                                                   placed.sh)))
    other = pred.clone()
    other[0, 1:, :3, 3] += 0.03  # the second sample: the same views with another camera error

    def one_view(scenes, cams):
        return render(scenes, cams, K[0, :1].expand(scenes.means.shape[0], 1, 3, 3), 32, 32, backend="cpu").rgb

    start = gt[:, :2].clone()
    start[..., :3, 3] += 0.02
    moved = start.clone()
    moved[..., :3, 3] -= 0.05  # another start for the second scene: rigid, as the renderer requires
    with torch.inference_mode():
        alone, _ = refine_context_cameras(render_rgb, placed, pred, images, steps=30)
        batched, _ = refine_context_cameras(render_rgb, pair, torch.cat([pred, other]), torch.cat([images, images]),
                                            steps=30)
        aligned = align_target_poses(one_view, placed, start, images[:, :2], steps=30, lr=0.01)
        aligned2 = align_target_poses(one_view, pair, torch.cat([start, moved]),
                                      torch.cat([images[:, :2], images[:, :2]]), steps=30, lr=0.01)
    assert torch.equal(batched[:1], alone) and torch.equal(aligned2[:1], aligned)


def test_region_psnr_keeps_an_exactly_rendered_image_and_skips_an_empty_region():
    """NaN (an empty region) leaves an image out of the region mean; +inf (the region rendered exactly) does not,
    as in the whole-image PSNR."""
    from anycity.lit.evaluation import EvalMetrics

    m = EvalMetrics(("scaffold",))
    gt = torch.rand(3, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    pred = gt.clone()
    pred[1:] = (pred[1:] + 0.1).clamp(0, 1)  # image 0 exact, images 1 and 2 not
    obs = torch.ones(3, 1, 8, 8, dtype=torch.bool)
    weak = torch.zeros(3, 1, 8, 8, dtype=torch.bool)
    weak[1] = True  # only image 1 has weak pixels
    m.update("scaffold", pred, gt, (obs[:, None], weak[:, None]))
    assert m.metrics["psnr_scaffold"].compute().item() == float("inf")
    assert m.metrics["psnr_obs_scaffold"].compute().item() == float("inf")
    from anycity.metrics.regions import masked_psnr
    assert m.metrics["psnr_weak_scaffold"].compute().item() == pytest.approx(
        masked_psnr(pred[1:2], gt[1:2], weak[1:2]).item())


def test_camera_refinement_turns_each_view_about_its_median_depth_point(monkeypatch):
    """A rotation delta of view i turns about the point at its Gaussians' median depth on its optical axis, so that
    point stays where it is; a pivot at the camera centre would swing it (an orbit correction would then need a
    coupled translation)."""
    import anycity.lit.evaluation as E
    from anycity.structures import Gaussians

    v, n = 2, 16
    g = torch.Generator().manual_seed(0)
    means = torch.cat([torch.rand(1, v * n, 2, generator=g) - 0.5, torch.full((1, v * n, 1), 5.0)], -1)
    gs = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(1, v * n, 1), torch.full((1, v * n, 3), 0.1),
                   torch.ones(1, v * n), torch.rand(1, v * n, 1, 3, generator=g))
    w2c = torch.eye(4).repeat(1, v, 1, 1)
    w2c[0, 1, :3, 3] = torch.tensor([-1.0, 0.0, 0.0])  # every view's Gaussians at camera z = 5
    monkeypatch.setattr(E, "_fit_deltas", lambda loss, shape, dev, steps, lr: (
        torch.tensor([0.0, 0.2, 0.0]).expand(*shape, 3), torch.zeros(*shape, 3)))
    _, A = E.refine_context_cameras(None, gs, w2c, torch.rand(1, v, 3, 8, 8, generator=g), steps=1)
    X = torch.linalg.inv(w2c[0, 1]) @ torch.tensor([0.0, 0.0, 5.0, 1.0])  # view 1's median-depth point
    torch.testing.assert_close(A[0, 1] @ X, X, atol=1e-5, rtol=0)
    assert not torch.allclose(A[0, 1], torch.eye(4), atol=1e-2)  # the delta did turn the view
