"""Loss conventions a plausible one-line bug would break silently: L_pres depth only where the scaffold has content,
the D2S depth ratio held constant, gradient matching and non-positive predictions treated as masked pixels."""

import torch

from anycity.losses import d2s_loss, depth_z_loss, preservation_loss
from anycity.structures import RenderOutput


def _r(rgb, depth, alpha):
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha)


def test_preservation_depth_only_where_the_scaffold_has_content():
    shape = (1, 1, 1, 2, 2)
    alpha = torch.zeros(shape)
    alpha[..., 0, 0] = 1.0  # one covered pixel; the other three are holes (depth 0) Stage II should fill
    depth = torch.zeros(shape)
    depth[..., 0, 0] = 2.0
    out = preservation_loss(_r(torch.zeros(1, 1, 3, 2, 2), torch.full(shape, 3.0), torch.ones(shape)),
                            _r(torch.zeros(1, 1, 3, 2, 2), depth, alpha))
    assert out["pres_depth"].item() == 1.0  # |3 - 2| at the covered pixel only


def test_d2s_scale_ratio_carries_no_gradient():
    shape = (1, 1, 1, 3, 3)
    t = torch.arange(1.0, 10.0).reshape(shape)
    s = (2.0 * t).clone()
    s[..., 0, 0] += 1.0  # one shape error; the median ratio is still 2
    s.requires_grad_()
    one = torch.ones(shape)
    d2s_loss(_r(torch.zeros(1, 1, 3, 3, 3), s, one), _r(torch.zeros(1, 1, 3, 3, 3), t, one))["d2s_depth"].backward()
    ref = torch.zeros(shape)
    ref[..., 0, 0] = 1.0 / 9  # d/ds of mean|s - 2 t| with k = 2 held constant
    torch.testing.assert_close(s.grad, ref)


def test_gradient_matching_ignores_pairs_with_an_invalid_pixel():
    gt = torch.rand(1, 1, 1, 16, 16, generator=torch.Generator().manual_seed(0)) + 1
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[..., 6:10, 6:10] = False  # a hole (sky) in the middle
    out = depth_z_loss(gt * 1.5, gt, mask, align=False)  # residual is the constant log 1.5 on every valid pixel
    assert out["depth_grad"].item() < 1e-6  # a constant residual has no gradient, holes or not


def test_a_non_positive_prediction_is_ignored_like_a_masked_pixel():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 1, 1, 8, 8, generator=g) + 1
    pred = gt * torch.exp(0.1 * torch.randn(gt.shape, generator=g))
    bad = pred.clone()
    bad[..., 0, 0] = 0.0  # an empty render pixel
    mask = torch.ones_like(gt, dtype=torch.bool)
    mask[..., 0, 0] = False
    torch.testing.assert_close(depth_z_loss(bad, gt)["total"], depth_z_loss(pred, gt, mask)["total"])


def test_gradient_matching_known_value_of_a_unit_step_across_scales():
    """A unit step in the residual between columns 3 and 4 of an 8x8 image: per level, the mean |difference| over
    all valid neighbour pairs (x and y), averaged over the dyadic levels 8x8, 4x4, 2x2, 1x1. A wrong divisor or a
    level that is not downsampled reweights edges against flat areas at every scale."""
    step = (torch.arange(8) >= 4).float().expand(8, 8).reshape(1, 1, 1, 8, 8)
    gt = torch.ones(1, 1, 1, 8, 8)
    pred = torch.exp(-step)  # residual log(gt / pred) = the step
    # 8x8: one jump per row (8) over 8*7 + 7*8 = 112 pairs
    one = depth_z_loss(pred, gt, align=False, grad_scales=1)["depth_grad"].item()
    assert abs(one - 8 / 112) < 1e-6
    # 4x4 (columns 0, 2, 4, 6): 4 jumps / 24 pairs; 2x2 (columns 0, 4): 2 / 4; 1x1: no pair, 0
    four = depth_z_loss(pred, gt, align=False, grad_scales=4)["depth_grad"].item()
    assert abs(four - (8 / 112 + 4 / 24 + 2 / 4 + 0) / 4) < 1e-6
