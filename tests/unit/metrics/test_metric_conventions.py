"""Metric conventions a plausible one-line bug would break silently: clamped renders scored, the depth test's 2x2 taps
at pixel centres, masked target pixels making no depth edges, AUC@30."""

import pytest
import torch
from helpers.raycast_scenes import H, W, intrinsics, look_at, render_depth

from anycity.geometry import visible_views
from anycity.metrics.image import psnr, ssim
from anycity.metrics.pose import pose_auc
from anycity.metrics.regions import masked_psnr, region_masks


def test_overshooting_renders_are_scored_clamped():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(1, 3, 32, 32, generator=g)
    pred = target + 0.3 * torch.randn(target.shape, generator=g)  # an SH colour can exceed 1 (clamped at 0 only)
    torch.testing.assert_close(psnr(pred, target), psnr(pred.clamp(0, 1), target))
    torch.testing.assert_close(ssim(pred, target), ssim(pred.clamp(0, 1), target))


def test_a_point_within_half_a_pixel_behind_an_edge_is_hidden():
    K = intrinsics()[None, None]
    depth = torch.full((1, 1, 1, H, W), 10.0)
    depth[..., : W // 2] = 1.0
    f, cx, cy = K[0, 0, 0, 0], K[0, 0, 0, 2], K[0, 0, 1, 2]
    u, v, z = W // 2 + 0.2, H / 2 + 0.5, 3.0  # first far pixel, 0.2 px from the edge, between the two surfaces
    p = torch.tensor([(u - cx) / f * z, (v - cy) / f * z, z])
    assert not visible_views(p[None, None], depth, torch.eye(4)[None, None], K)[0, 0, 0]  # 2x2 taps reach the near


def test_invalid_target_pixels_do_not_make_depth_edges():
    O = (0.0, 0.0, 0.0)
    tw = torch.stack([look_at((0.0, -4.0, 4.0), O)])[None]
    cw = torch.stack([look_at((-2.0, -4.0, 4.0), O), look_at((2.0, -4.0, 4.0), O)])[None]
    tK, cK = intrinsics().expand(1, 1, 3, 3), intrinsics().expand(1, 2, 3, 3)
    td, cd = render_depth(tw, tK), render_depth(cw, cK)
    valid = td > 0
    valid[..., H // 2, W // 2] = False  # e.g. a masked-out pixel whose stored depth is junk
    junk = td.clone()
    junk[..., H // 2, W // 2] = 1000.0
    a = region_masks(td, tw, tK, cd, cw, cK, target_valid=valid)
    b = region_masks(junk, tw, tK, cd, cw, cK, target_valid=valid)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])  # what a masked pixel holds changes nothing


def test_masked_psnr_scores_overshooting_renders_clamped():
    """masked_psnr over a full mask clamps the render to [0, 1] as psnr does: equal to both on an overshooting one."""
    g = torch.Generator().manual_seed(0)
    target = torch.rand(2, 3, 32, 32, generator=g)
    pred = target + 0.3 * torch.randn(target.shape, generator=g)
    full = torch.ones(2, 1, 32, 32, dtype=torch.bool)
    torch.testing.assert_close(masked_psnr(pred, target, full), masked_psnr(pred.clamp(0, 1), target, full))
    torch.testing.assert_close(masked_psnr(pred, target, full), psnr(pred, target))


def test_pose_auc_defaults_to_thirty_degrees():
    """AUC@30 by default: a pair 25 degrees off stays below 5 of the thresholds 1..30."""
    assert pose_auc(torch.tensor([25.0]), torch.tensor([0.0])).item() == pytest.approx(5 / 30)
