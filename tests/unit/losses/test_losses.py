"""Losses on constructed cases with known answers."""

import math

import pytest
import torch

from anycity.geometry import make_intrinsics, unproject_depth
from anycity.losses import (
    align_scale_shift,
    camera_loss,
    d2s_loss,
    depth_z_loss,
    normal_loss,
    preservation_loss,
    ray_anchor_loss,
    regularizer_loss,
    rgb_loss,
)
from anycity.structures import Gaussians, RenderOutput


def test_rgb_mse_known_value_and_mask():
    pred = torch.zeros(1, 2, 3, 4, 4)
    gt = torch.full_like(pred, 0.5)
    assert rgb_loss(pred, gt)["total"].item() == pytest.approx(0.25)
    mask = torch.zeros(1, 2, 1, 4, 4, dtype=torch.bool)
    mask[0, 0] = True
    gt[0, 1] = 0.0  # error only where the mask is off
    out = rgb_loss(pred, gt, mask=mask)
    assert out["mse"].item() == pytest.approx(0.25)


def test_rgb_ssim_term_zero_on_identical_and_positive_otherwise():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(1, 1, 3, 16, 16, generator=g)
    assert rgb_loss(img, img, ssim_weight=0.2)["ssim"].item() == pytest.approx(0.0, abs=1e-5)
    out = rgb_loss(img, torch.rand(1, 1, 3, 16, 16, generator=g), ssim_weight=0.2)
    assert out["ssim"].item() > 0.5
    assert out["total"].item() == pytest.approx(out["mse"].item() + 0.2 * out["ssim"].item(), rel=1e-5)


def test_align_scale_shift_recovers_affine():
    x = torch.rand(3, 8, 8) + 0.1
    y = 2.5 * x - 0.7
    s, t = align_scale_shift(x, y, torch.ones_like(x))
    torch.testing.assert_close(s, torch.full((3,), 2.5), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(t, torch.full((3,), -0.7), rtol=1e-4, atol=1e-4)


def test_depth_loss_invariant_to_power_and_scale_but_not_to_structure():
    gt = torch.rand(2, 1, 1, 16, 16) * 5 + 1
    pred = 3.0 * gt**1.5  # affine in log-inverse depth
    out = depth_z_loss(pred, gt)
    assert out["depth_l1"].item() < 1e-4 and out["depth_grad"].item() < 1e-4
    shuffled = gt.flatten()[torch.randperm(gt.numel())].reshape(gt.shape)
    assert depth_z_loss(shuffled, gt)["total"].item() > 0.05


def test_depth_loss_ignores_masked_and_gradient_flows():
    gt = torch.rand(1, 1, 1, 8, 8) + 1
    pred = gt.clone()
    pred[..., :4, :] = 100.0  # garbage only in masked-out rows
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[..., :4, :] = False
    assert depth_z_loss(pred, gt, mask=mask)["total"].item() < 1e-4
    p = (gt * torch.exp(0.3 * torch.randn_like(gt))).requires_grad_()
    depth_z_loss(p, gt)["total"].backward()
    assert p.grad is not None and p.grad.abs().sum() > 0


def test_ray_anchor_zero_on_ray_and_known_offset():
    K = make_intrinsics(10.0, 10.0, 4.0, 4.0).expand(1, 1, 3, 3)
    w2c = torch.eye(4).expand(1, 1, 4, 4)
    depth = torch.rand(1, 1, 1, 8, 8) + 1.0
    means = unproject_depth(depth, K, w2c)  # [1, 1, 8, 8, 3] on the rays
    assert ray_anchor_loss(means, w2c, K).item() < 1e-5
    shifted = means.clone()
    shifted[..., 0] = shifted[..., 0] + 0.1 * shifted[..., 2]  # x/z off by 0.1 -> 0.1 * fx = 1 pixel in u
    assert ray_anchor_loss(shifted, w2c, K).item() == pytest.approx(1.0, rel=1e-4)
    mask = torch.zeros(1, 1, 1, 8, 8, dtype=torch.bool)
    mask[..., :2, :] = True
    shifted[..., 2:, :, :] = means[..., 2:, :, :]  # only the masked rows moved: the masked mean stays 1 pixel
    assert ray_anchor_loss(shifted, w2c, K, mask).item() == pytest.approx(1.0, rel=1e-4)



def test_ray_anchor_penalises_a_centre_behind_the_camera_in_pixels():
    """A centre 0.5 behind its camera costs (eps - z) * focal = about 50 px at f = 100: in pixels, like the
    reprojection error beside it; without the focal it would cost 0.5 and barely be pushed back in front."""
    K = make_intrinsics(100.0, 100.0, 0.5, 0.5).expand(1, 1, 3, 3)
    w2c = torch.eye(4).expand(1, 1, 4, 4)
    means = torch.tensor([0.0, 0.0, -0.5]).reshape(1, 1, 1, 1, 3)
    assert ray_anchor_loss(means, w2c, K).item() == pytest.approx((1e-2 + 0.5) * 100, rel=1e-5)


def test_ray_anchor_is_bounded_and_continuous_across_the_near_threshold():
    """The threshold was 1e-6 with a division by z above it: a centre 0.01 off its ray cost 625 px with a 3e8
    gradient at z = 2e-6 and 1e-8 px with a 0.1 gradient at z = 9e-7, so one pixel could set a step's direction
    after clipping. It is now the near plane (0.01), the loss continuous there and its gradient bounded."""
    K = make_intrinsics(100.0, 100.0, 0.5, 0.5).expand(1, 1, 3, 3)
    w2c = torch.eye(4).expand(1, 1, 4, 4)
    values, grads = [], []
    for z in (1.0, 1e-1, 1.0001e-2, 0.9999e-2, 1e-3, 2e-6, 9e-7, -0.1):
        means = torch.tensor([0.01 * max(z, 0.0), 0.0, z]).reshape(1, 1, 1, 1, 3).requires_grad_()
        loss = ray_anchor_loss(means, w2c, K)
        loss.backward()
        values.append(loss.item())
        grads.append(means.grad.abs().max().item())
    assert values[0] == pytest.approx(1.0, rel=1e-4)  # 0.01 off the ray at f = 100: 1 px at any depth in front
    assert values[2] == pytest.approx(values[3], abs=0.05)  # continuous at the threshold
    assert max(grads) <= 100 / 1e-2 + 100 + 1e-3  # bounded: f / eps (lateral) + f (depth deficit)
    assert values[-1] == pytest.approx((0.01 + 0.1) * 100, rel=1e-4)  # behind: the depth deficit, in pixels

def test_ray_anchor_nonzero_with_network_offsets_and_gradient_reaches_offset_conv():
    from anycity.models import build_network

    torch.manual_seed(0)
    net = build_network("tiny", completion=False)
    out = net(torch.rand(1, 2, 3, 32, 32), refine=False)
    assert ray_anchor_loss(out["pixel_means"], out["w2c"], out["K"]).item() < 1e-3  # zero offsets: on the rays
    with torch.no_grad():
        net.gaussian_head.offset_conv.bias.copy_(torch.tensor([0.05, -0.02, 0.0]))
    out = net(torch.rand(1, 2, 3, 32, 32), refine=False)
    loss = ray_anchor_loss(out["pixel_means"], out["w2c"], out["K"])
    fx, fy = out["K"][0, :, 0, 0], out["K"][0, :, 1, 1]
    # a lateral camera-frame offset (0.05, -0.02, 0) * z reprojects (0.05 fx, 0.02 fy) pixels away in every view
    assert loss.item() == pytest.approx((0.05 * fx + 0.02 * fy).mean().item(), rel=1e-4)
    loss.backward()
    assert net.gaussian_head.offset_conv.weight.grad.abs().sum() > 0
    assert net.gaussian_head.offset_conv.bias.grad.abs().sum() > 0


def _plane_render(h=12, w=12, tilt=0.0):
    K = make_intrinsics(10.0, 10.0, w / 2, h / 2).expand(1, 1, 3, 3)
    v = torch.arange(h).float()[:, None] + 0.5
    depth = (2.0 / (1.0 + tilt * (v - h / 2) / 10.0)).expand(h, w).reshape(1, 1, 1, h, w)
    return depth, K


def test_normal_loss_zero_for_matching_plane_normals():
    depth, K = _plane_render()
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12)
    out = normal_loss(depth, n, K, image=torch.rand(1, 1, 3, 12, 12))
    assert out["normal"].item() < 1e-6
    flipped = normal_loss(depth, -n, K)
    # 1 - cos = 2 everywhere; Huber(2, delta=0.1) = 0.1 * (2 - 0.05)
    assert flipped["normal"].item() == pytest.approx(0.1 * 1.95, rel=1e-4)


def test_normal_loss_is_zero_around_a_hole_in_the_render():
    # Rendered depth is 0 where alpha is 0 (sky beyond a roof edge): the pixels around the hole must not take a
    # difference against it; with perfect Gaussian normals the loss stays exactly zero.
    K = make_intrinsics(30.0, 30.0, 16.0, 16.0)[None, None]
    depth, alpha = torch.full((1, 1, 1, 32, 32), 3.0), torch.ones(1, 1, 1, 32, 32)
    depth[..., 10:20, 10:20], alpha[..., 10:20, 10:20] = 0.0, 0.0
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 32, 32)
    assert normal_loss(depth, n, K, alpha=alpha)["normal"].item() == 0.0
    assert normal_loss(depth, n, K)["normal"].item() == 0.0



def test_normal_loss_is_the_structure_weighted_sum_over_the_number_of_valid_pixels():
    """A grey ramp of slope 0.08 per column has a (normalised) Sobel gradient of 0.08 inside the image, so every
    interior pixel weighs exp(-edge_alpha * 0.08); the term is sum(w * Huber) / #valid, not / sum(w), which would
    undo the weighting whenever it is uniform and rescale the loss by the image's edge content otherwise."""
    depth, K = _plane_render()  # fronto-parallel plane: n_surf = (0, 0, -1)
    n = torch.tensor([1.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12)  # 45 degrees off
    huber = 0.1 * (1 - 1 / math.sqrt(2) - 0.05)  # Huber(1 - cos 45, delta=0.1)
    ramp = (0.08 * torch.arange(12.0)).expand(1, 1, 3, 12, 12)
    assert normal_loss(depth, n, K)["normal"].item() == pytest.approx(huber, rel=1e-5)
    for edge_alpha in (1.0, 5.0):
        out = normal_loss(depth, n, K, image=ramp, edge_alpha=edge_alpha)["normal"].item()
        assert out == pytest.approx(math.exp(-edge_alpha * 0.08) * huber, rel=1e-5), edge_alpha


def test_structure_weight_is_exp_of_minus_edge_alpha_times_the_gradient():
    """exp(-alpha * |grad I|) of the grey image: alpha = 2 squares the alpha = 1 weight; ignoring alpha would leave
    the configured edge relaxation of the normal and flatness terms without effect."""
    from anycity.losses import structure_weight

    ramp = (0.08 * torch.arange(12.0)).expand(1, 3, 12, 12)
    torch.testing.assert_close(structure_weight(ramp, 2.0)[..., 1:-1, 1:-1],
                               torch.full((1, 1, 10, 10), math.exp(-0.16)), rtol=1e-5, atol=0)
    image = torch.rand(1, 3, 12, 12, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(structure_weight(image, 2.0), structure_weight(image, 1.0) ** 2, rtol=1e-5, atol=1e-7)

def test_normal_flat_term_uses_min_scale():
    depth, K = _plane_render()
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12)
    scales = torch.tensor([[[1.0, 0.2, 3.0], [0.4, 2.0, 1.0]]])
    out = normal_loss(depth, n, K, scales=scales, flat_weight=0.5)
    assert out["flat"].item() == pytest.approx(0.3)
    assert out["total"].item() == pytest.approx(out["normal"].item() + 0.15, abs=1e-6)


def test_camera_loss_zero_at_gt_and_weights_last_iteration_most():
    gt = torch.randn(2, 3, 9)
    gt[..., 3:7] = torch.nn.functional.normalize(gt[..., 3:7], dim=-1)
    assert camera_loss([gt, gt], gt)["total"].item() == 0.0
    flipped = gt.clone()
    flipped[..., 3:7] *= -1  # same rotation
    assert camera_loss(flipped, gt)["cam_r"].item() == 0.0
    bad = gt + 0.5
    first_bad = camera_loss([bad, gt], gt, gamma=0.5)["total"].item()
    last_bad = camera_loss([gt, bad], gt, gamma=0.5)["total"].item()
    assert last_bad == pytest.approx(2 * first_bad, rel=1e-5)
    with pytest.raises(ValueError, match="9"):
        camera_loss([gt[..., :7]], gt)


def test_camera_loss_types_known_values():
    gt = torch.zeros(1, 2, 9)
    gt[..., 6] = 1.0  # identity quaternion (xyzw)
    pred = gt.clone()
    pred[..., 0] = 0.1  # translation x off by 0.1 in every view
    # mean over the 3 translation entries: L1 0.1 / 3; Huber (quadratic below delta) 0.5 * 0.1^2 / 3
    assert camera_loss(pred, gt)["cam_t"].item() == pytest.approx(0.1 / 3)
    assert camera_loss(pred, gt, loss_type="huber")["cam_t"].item() == pytest.approx(0.005 / 3)
    with pytest.raises(ValueError, match="loss_type"):
        camera_loss(pred, gt, loss_type="l2")


def _render(rgb, depth, alpha):
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha)


def test_d2s_depth_only_where_teacher_valid_and_teacher_detached():
    shape = (1, 2, 1, 4, 4)
    t_alpha = torch.zeros(shape)
    t_alpha[..., :2, :] = 1.0
    teacher = _render(torch.full((1, 2, 3, 4, 4), 0.5, requires_grad=True), torch.ones(shape), t_alpha)
    s_depth = torch.ones(shape)
    s_depth[..., 2:, :] = 50.0  # wrong only where the teacher is empty
    student = _render(torch.zeros(1, 2, 3, 4, 4, requires_grad=True), s_depth, torch.ones(shape))
    out = d2s_loss(student, teacher)
    assert out["d2s_depth"].item() == 0.0
    assert out["d2s_rgb"].item() == pytest.approx(0.5)
    out["total"].backward()
    assert teacher.rgb.grad is None and student.rgb.grad is not None


def test_d2s_depth_teaches_shape_not_scale():
    shape = (2, 3, 1, 4, 4)
    g = torch.Generator().manual_seed(0)
    t_depth = torch.rand(shape, generator=g) + 1.0
    teacher = _render(torch.zeros(2, 3, 3, 4, 4), t_depth, torch.ones(shape))
    scale = torch.tensor([2.0, 0.5]).view(2, 1, 1, 1, 1)  # the student's depth: the teacher's at another scale
    student = _render(torch.zeros(2, 3, 3, 4, 4), (t_depth * scale).requires_grad_(), torch.ones(shape))
    aligned = d2s_loss(student, teacher)
    assert aligned["d2s_depth"].item() == pytest.approx(0.0, abs=1e-6)
    aligned["total"].backward()
    assert student.depth.grad.abs().max().item() == 0.0  # no pull on the student's scale
    assert d2s_loss(student, teacher, scale_align=False)["d2s_depth"].item() > 0.3  # the unaligned term pulls it
    bumped = t_depth * scale
    bumped[0, 0, 0, 0, 0] += 1.0  # a shape error is still seen, in the student's units
    student = _render(torch.zeros(2, 3, 3, 4, 4), bumped, torch.ones(shape))
    assert d2s_loss(student, teacher)["d2s_depth"].item() == pytest.approx(1.0 / (2 * 3 * 16), rel=1e-5)


def test_preservation_loss_known_value():
    shape = (1, 1, 1, 2, 2)
    final = _render(torch.ones(1, 1, 3, 2, 2), torch.full(shape, 3.0), torch.ones(shape))
    scaffold = _render(torch.zeros(1, 1, 3, 2, 2), torch.full(shape, 2.0), torch.ones(shape))
    out = preservation_loss(final, scaffold)
    assert out["pres_rgb"].item() == 1.0 and out["pres_depth"].item() == 1.0 and out["total"].item() == 2.0


def _gaussians(n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(means=torch.randn(1, n, 3, generator=g), quats=torch.randn(1, n, 4, generator=g),
                     scales=torch.rand(1, n, 3, generator=g) + 0.1, opacities=torch.rand(1, n, generator=g),
                     sh=torch.randn(1, n, 1, 3, generator=g))


def test_regularizer_terms():
    g = _gaussians()
    zero = regularizer_loss(delta=[torch.zeros(2, 3)], gates=[torch.full((4,), 0.5)], final=g, scaffold=g)
    assert zero["reg_residual"].item() == 0.0 and zero["reg_stability"].item() == 0.0
    assert zero["reg_gate"].item() == pytest.approx(math.log(2), rel=1e-5)  # max binary entropy
    out = regularizer_loss(delta=[torch.full((2, 3), -2.0)], gates=torch.full((4,), 0.25), gate_mode="mean")
    assert out["reg_residual"].item() == 2.0 and out["reg_gate"].item() == pytest.approx(0.25)
    moved = Gaussians(g.means + 1.0, g.quats, g.scales, g.opacities, g.sh)
    assert regularizer_loss(final=moved, scaffold=g)["reg_stability"].item() == pytest.approx(1.0)
    # each attribute moved by 1 in turn (scales by a factor e: log-scale + 1) costs 1; all four together 4
    for moved in (Gaussians(g.means, g.quats, g.scales * math.e, g.opacities, g.sh),
                  Gaussians(g.means, g.quats, g.scales, g.opacities + 1.0, g.sh),
                  Gaussians(g.means, g.quats, g.scales, g.opacities, g.sh + 1.0)):
        assert regularizer_loss(final=moved, scaffold=g)["reg_stability"].item() == pytest.approx(1.0, rel=1e-5)
    moved = Gaussians(g.means + 1.0, g.quats, g.scales * math.e, g.opacities + 1.0, g.sh + 1.0)
    assert regularizer_loss(final=moved, scaffold=g)["reg_stability"].item() == pytest.approx(4.0, rel=1e-5)
    with pytest.raises(ValueError, match="gate_mode"):
        regularizer_loss(gate_mode="max")


def test_depth_loss_without_alignment_is_absolute():
    gt = torch.rand(1, 1, 1, 8, 8) + 1
    out = depth_z_loss(2.0 * gt, gt, align=False, grad_weight=0.0)
    assert out["depth_l1"].item() == pytest.approx(math.log(2.0), rel=1e-5)
    assert depth_z_loss(gt, gt, align=False)["total"].item() < 1e-6


def test_flatness_prior_averages_only_existing_gaussians():
    """A voxel merge pads each scene's Gaussians with invalid entries (scale 1e-4); they must not pull the mean
    smallest scale down."""
    from anycity.losses import normal_loss

    depth = torch.ones(1, 1, 1, 8, 8)
    normal = torch.zeros(1, 1, 3, 8, 8)
    normal[:, :, 2] = -1
    K = torch.tensor([[[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]])[None]
    scales = torch.full((1, 4, 3), 0.5)
    scales[0, 3] = 1e-4  # padding
    valid = torch.tensor([[True, True, True, False]])
    out = normal_loss(depth, normal, K, scales=scales, scales_valid=valid, flat_weight=1.0)
    assert out["flat"].item() == pytest.approx(0.5)
    assert normal_loss(depth, normal, K, scales=scales)["flat"].item() == pytest.approx((3 * 0.5 + 1e-4) / 4)


def _old_z_l1(pred, gt, mask):
    """L_z's L1 as it was before s >= 0 and the masked-value guard: the reference a normal case must equal."""
    p, g, m = pred.reshape(-1, *pred.shape[-2:]), gt.reshape(-1, *gt.shape[-2:]), mask.reshape(-1, *gt.shape[-2:])
    valid = ((g > 1e-6) & (p > 1e-6) & m).float()
    up, ug = -torch.log(p.clamp_min(1e-6)), -torch.log(g.clamp_min(1e-6))
    n = valid.sum((-1, -2))
    sp, st = (valid * up).sum((-1, -2)), (valid * ug).sum((-1, -2))
    spp, spt = (valid * up * up).sum((-1, -2)), (valid * up * ug).sum((-1, -2))
    s = (n * spt - sp * st) / (n * spp - sp * sp)
    t = (st - s * sp) / n
    residual = (s[:, None, None] * up + t[:, None, None] - ug) * valid
    return residual.abs().sum() / valid.sum()


def test_depth_loss_scores_an_inverted_map_and_leaves_a_positive_fit_bitwise_unchanged():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 32, 32, generator=g) * 4 + 1
    # near and far swapped: the least-squares scale in log-inverse depth is -1, which fitted it exactly (loss 0)
    inverted = depth_z_loss(5.0 / gt, gt)
    u = -torch.log(gt)
    # aligned by shift only (s = 1): the residual is -2 (u - mean u)
    assert inverted["depth_l1"].item() == pytest.approx(2 * (u - u.mean()).abs().mean().item(), rel=1e-5)
    assert inverted["total"].item() > 0.2
    # a right-way-up map (s > 0): value and gradient exactly as before
    mask = torch.rand(1, 1, 1, 32, 32, generator=g) > 0.2
    a = (gt * torch.exp(0.1 * torch.randn(gt.shape, generator=g))).requires_grad_()
    b = a.detach().clone().requires_grad_()
    new, old = depth_z_loss(a, gt, mask, grad_weight=0.0)["total"], _old_z_l1(b, gt, mask)
    torch.testing.assert_close(new, old, rtol=1e-5, atol=1e-7)  # the moments are centred now: float rounding only
    new.backward(), old.backward()
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-9)


def test_depth_loss_gives_an_inverted_map_a_gradient_towards_the_ground_truth():
    """A negative least-squares scale was clamped to s = 0 (the best constant): the inverted map scored > 0, but its
    residual no longer depended on the prediction, so L_depth had exactly zero gradient to correct it with."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 32, 32, generator=g) * 4 + 1
    pred = (5.0 / gt).requires_grad_()
    loss = depth_z_loss(pred, gt)["total"]
    loss.backward()
    assert pred.grad.abs().sum() > 0
    with torch.no_grad():  # a small step along the gradient lowers the loss: it points towards the ground truth
        assert depth_z_loss(pred - 0.1 * pred.grad / pred.grad.abs().max(), gt)["total"] < loss
    # per image: shift-only where the fit is negative, the plain least-squares fit (bitwise) where it is not
    x = torch.rand(2, 8, 8, generator=g) + 0.1
    y = torch.stack([-1.5 * x[0] + 0.3, 2.5 * x[1] - 0.7]) + 0.01 * torch.rand(2, 8, 8, generator=g)
    m = torch.ones_like(x)
    s, t = align_scale_shift(x, y, m)
    assert s[0] == 1
    torch.testing.assert_close(t[0], (y[0] - x[0]).mean())
    n, sp, st = m.sum((-1, -2)), x.sum((-1, -2)), y.sum((-1, -2))
    spp, spt = (x * x).sum((-1, -2)), (x * y).sum((-1, -2))
    s_fit = (n * spt - sp * st) / (n * spp - sp * sp)
    torch.testing.assert_close(s[1], s_fit[1], rtol=1e-5, atol=0.0)
    torch.testing.assert_close(t[1], (st[1] - s_fit[1] * sp[1]) / n[1], rtol=1e-5, atol=1e-6)
    # a constant ground truth (any fit's sign is rounding noise) still scores about 0, whatever the prediction
    for seed in range(8):
        pred = torch.rand(1, 1, 1, 32, 32, generator=torch.Generator().manual_seed(seed)) + 1
        assert depth_z_loss(pred, torch.full_like(pred, 2.0))["total"] < 1e-5


def test_depth_loss_ignores_non_finite_values_at_masked_pixels():
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(1, 2, 1, 16, 16, generator=g) * 3 + 1
    pred = (gt * torch.exp(0.2 * torch.randn(gt.shape, generator=g))).requires_grad_()
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[..., 0, :3] = False
    ref = depth_z_loss(pred, gt, mask)["total"]
    bad_gt, bad_pred = gt.clone(), pred.detach().clone()
    bad_gt[..., 0, 0], bad_gt[..., 0, 1], bad_pred[..., 0, 2] = float("inf"), float("nan"), float("nan")
    bad_pred.requires_grad_()
    out = depth_z_loss(bad_pred, bad_gt, mask)["total"]
    assert torch.equal(out, ref)
    out.backward()
    assert torch.isfinite(bad_pred.grad).all()
    # an unmasked infinite ground truth (sky stored as inf) is invalid too, not an infinite loss
    sky = gt.clone()
    sky[..., 0, :3] = float("inf")
    assert torch.equal(depth_z_loss(pred, sky)["total"], ref)


def test_normal_loss_skips_masked_pixels():
    depth, K = _plane_render(tilt=0.5)
    n = torch.tensor([0.0, 0.3, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12)  # off the plane's normal
    image = torch.rand(1, 1, 3, 12, 12, generator=torch.Generator().manual_seed(0))
    free = normal_loss(depth, n, K, image=image)
    assert free["normal"].item() > 1e-3
    every = normal_loss(depth, n, K, image=image, mask=torch.ones(1, 1, 1, 12, 12, dtype=torch.bool))
    assert torch.equal(every["normal"], free["normal"])
    sky = normal_loss(depth, n, K, image=image, mask=torch.zeros(1, 1, 1, 12, 12, dtype=torch.bool))
    assert sky["normal"].item() == 0.0


def test_flatness_prior_is_gated_like_the_normal_term():
    """Pixel-aligned Gaussians (one per pixel): sky pixels and pixels without a normal add no flatness pressure, and
    the structure weight relaxes it where the normal term is relaxed."""
    depth, K = _plane_render()
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12)
    s_min = torch.full((1, 1, 1, 12, 12), 0.1)
    s_min[..., :6, :] = 1.0  # the sky's Gaussians: large
    scales = torch.cat([s_min, 2 * s_min, 3 * s_min], 2).permute(0, 1, 3, 4, 2).reshape(1, 144, 3)
    mask = torch.ones(1, 1, 1, 12, 12, dtype=torch.bool)
    mask[..., :6, :] = False
    out = normal_loss(depth, n, K, scales=scales, mask=mask, flat_weight=2.0)
    assert out["flat"].item() == pytest.approx(0.1)  # the 1-pixel border has no normal: left out too
    assert out["total"].item() == pytest.approx(out["normal"].item() + 0.2, abs=1e-6)
    image = torch.rand(1, 1, 3, 12, 12, generator=torch.Generator().manual_seed(0))
    from anycity.losses import structure_weight

    weighted = normal_loss(depth, n, K, image=image, scales=scales, mask=mask)["flat"]
    valid = torch.zeros(12, 12, dtype=torch.bool)
    valid[6:11, 1:11] = True
    expected = (0.1 * structure_weight(image)[0, 0, 0][valid]).sum() / valid.sum()
    assert weighted.item() == pytest.approx(expected.item(), rel=1e-5)


def test_depth_loss_drops_pixels_below_the_confidence_threshold():
    """With conf_threshold, only pixels whose confidence reaches it are scored: a depth wrong only where the
    confidence is 0.1 costs nothing at threshold 0.5, and is seen without the threshold."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 16, 16, generator=g) + 1
    pred = gt.clone()
    pred[..., :8, :] = gt[..., :8, :] * torch.exp(torch.randn(1, 1, 1, 8, 16, generator=g))  # wrong in the top half
    conf = torch.ones_like(gt)
    conf[..., :8, :] = 0.1  # ... where the confidence is low
    assert depth_z_loss(pred, gt, confidence=conf, conf_threshold=0.5)["total"].item() < 1e-6
    assert depth_z_loss(pred, gt, confidence=conf)["total"].item() > 0.05


def test_depth_loss_total_weights_the_gradient_term_by_grad_weight():
    """total = depth_l1 + grad_weight * depth_grad."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 16, 16, generator=g) + 1
    pred = gt * torch.exp(0.3 * torch.randn(gt.shape, generator=g))
    out = depth_z_loss(pred, gt, grad_weight=0.25)
    assert out["depth_grad"].item() > 0.01
    assert out["total"].item() == pytest.approx(out["depth_l1"].item() + 0.25 * out["depth_grad"].item(), rel=1e-5)


def test_camera_loss_weighs_the_focal_term_half_by_default():
    """The default weights: translation and rotation 1, field of view 0.5 (VGGT's)."""
    gt = torch.zeros(1, 2, 9)
    gt[..., 6] = 1.0  # identity quaternion (xyzw)
    fov = gt.clone()
    fov[..., 7:] += 0.2  # only the field of view off
    out = camera_loss(fov, gt)
    assert out["cam_fl"].item() > 0 and out["total"].item() == pytest.approx(0.5 * out["cam_fl"].item(), rel=1e-5)
    moved = gt.clone()
    moved[..., :3] += 0.1  # only the translation off
    out = camera_loss(moved, gt)
    assert out["cam_t"].item() > 0 and out["total"].item() == pytest.approx(out["cam_t"].item(), rel=1e-5)


def test_normal_loss_skips_semi_transparent_pixels():
    """Only pixels with alpha above 0.5 are scored: normals 45 degrees off where alpha is 0.3 cost nothing."""
    depth, K = _plane_render()
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12).clone()
    alpha = torch.ones(1, 1, 1, 12, 12)
    n[..., :, :6] = torch.tensor([1.0, 0.0, -1.0]).view(3, 1, 1)  # wrong in the left half
    alpha[..., :, :6] = 0.3  # ... which is semi-transparent
    assert normal_loss(depth, n, K, alpha=alpha)["normal"].item() == 0.0
    assert normal_loss(depth, n, K)["normal"].item() > 0.001


def test_normal_loss_skips_pixels_without_a_gaussian_normal():
    """A zero rendered normal (no Gaussian normal there) is not scored as a disagreement with the surface."""
    depth, K = _plane_render()
    n = torch.tensor([0.0, 0.0, -1.0]).view(1, 1, 3, 1, 1).expand(1, 1, 3, 12, 12).clone()
    n[..., 3:6, 3:6] = 0.0
    assert normal_loss(depth, n, K)["normal"].item() == 0.0


def test_distillation_losses_send_no_gradient_into_their_references():
    """D2S's teacher, the preservation term's scaffold render and the stability regulariser's scaffold Gaussians
    are references: the backward pass reaches only the student / final side (depth as well as rgb)."""
    shape = (1, 1, 1, 4, 4)
    g = torch.Generator().manual_seed(0)

    def side():
        return _render(torch.rand(1, 1, 3, 4, 4, generator=g).requires_grad_(),
                       (torch.rand(shape, generator=g) + 1).requires_grad_(), torch.ones(shape))

    student, teacher = side(), side()
    d2s_loss(student, teacher)["total"].backward()
    assert teacher.depth.grad is None and teacher.rgb.grad is None
    assert student.depth.grad is not None and student.rgb.grad is not None
    final, scaffold = side(), side()
    preservation_loss(final, scaffold)["total"].backward()
    assert scaffold.depth.grad is None and scaffold.rgb.grad is None
    assert final.depth.grad is not None and final.rgb.grad is not None
    moved, ref = _gaussians(seed=1), _gaussians(seed=2)
    for gs in (moved, ref):
        gs.means.requires_grad_()
    regularizer_loss(final=moved, scaffold=ref)["total"].backward()
    assert ref.means.grad is None and moved.means.grad is not None


def test_scale_shift_fit_keeps_its_digits_when_the_spread_is_small_against_the_mean():
    """The fit's moments were raw float32 sums (n spp - sp^2): with a log-inverse depth of mean -3 and spread 0.01
    they cancelled, and a prediction exact up to an affine map (loss 0) fitted s = 140 for 100 and scored 0.07."""
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 128, 128, generator=g) * 2 + 1
    pred = 20.0 * gt ** 0.01  # -log pred = -log 20 + 0.01 (-log gt): exactly affine in log-inverse depth, s = 100
    s, _ = align_scale_shift(-torch.log(pred[0, 0]), -torch.log(gt[0, 0]), torch.ones(1, 128, 128))
    assert s.item() == pytest.approx(100.0, rel=1e-3)
    assert depth_z_loss(pred, gt, grad_weight=0.0)["total"].item() < 1e-3
