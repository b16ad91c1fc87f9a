"""Region diagnostic on hand-built scenes whose answer is known: a plane at z = 5 seen by cameras looking down +z."""

import math

import pytest
import torch

from anycity.geometry import make_intrinsics
from anycity.metrics.regions import lpips_or_none, masked_lpips, masked_psnr, masked_ssim, region_masks

H, W, F = 24, 32, 20.0  # a camera at x sees x in [cx - 4, cx + 4] on the plane z = 5


def _cams(xs):
    w2c = torch.eye(4).repeat(1, len(xs), 1, 1)
    w2c[0, :, 0, 3] = -torch.tensor(xs, dtype=torch.float32)
    return w2c, make_intrinsics(F, F, W / 2, H / 2).expand(1, len(xs), 3, 3).clone()


def _plane(n, z=5.0):
    return torch.full((1, n, 1, H, W), z)


def _column_x(j, z=5.0):
    """World x of the target pixel column j (target at x = 0) on the plane."""
    return (j + 0.5 - W / 2) / F * z


def test_plane_seen_by_two_views_is_observed_and_out_of_frame_is_weak():
    tw, tk = _cams([0.0])
    cw, ck = _cams([-1.0, 1.0])  # 2 * atan(1 / 5) = 22.6 deg of parallax on the plane
    obs, weak = region_masks(_plane(1), tw, tk, _plane(2), cw, ck)
    assert obs.shape == weak.shape == (1, 1, 1, H, W) and not (obs & weak).any() and (obs | weak).all()
    for j in range(W):
        x = _column_x(j)
        both = -3 <= x <= 3  # inside both context frames
        assert bool(obs[0, 0, 0, :, j].all()) == both, (j, x)
        assert bool(weak[0, 0, 0, :, j].all()) == (not both), (j, x)


def test_wall_hidden_behind_a_block_from_every_context_view_is_weak():
    tw, tk = _cams([0.0])
    cw, ck = _cams([-1.0, 1.0])
    ctx = _plane(2)
    ctx[..., :, 8:24] = 2.0  # a block at depth 2 in front of the middle of the plane in both context views
    obs, weak = region_masks(_plane(1), tw, tk, ctx, cw, ck)
    # target column j lands on context columns j + 4.5 and j - 3.5: for j in 12..19 both are inside the block, so the
    # plane there is occluded from every context view
    assert weak[0, 0, 0, :, 12:20].all() and not obs[0, 0, 0, :, 12:20].any()
    obs_open, _ = region_masks(_plane(1), tw, tk, _plane(2), cw, ck)
    assert obs_open[0, 0, 0, :, 12:20].all()  # without the block the same pixels are observed


def test_sky_is_in_neither_region():
    tw, tk = _cams([0.0])
    cw, ck = _cams([-1.0, 1.0])
    target = _plane(1)
    target[..., :5, :] = 0.0  # no depth: sky
    obs, weak = region_masks(target, tw, tk, _plane(2), cw, ck)
    assert not obs[..., :5, :].any() and not weak[..., :5, :].any()
    valid = torch.ones(1, 1, 1, H, W, dtype=torch.bool)
    valid[..., -3:, :] = False
    obs, weak = region_masks(_plane(1), tw, tk, _plane(2), cw, ck, target_valid=valid)
    assert not (obs | weak)[..., -3:, :].any()


def test_one_seeing_view_or_no_parallax_is_weak():
    tw, tk = _cams([0.0])
    obs, weak = region_masks(_plane(1), tw, tk, _plane(2), *_cams([0.0, 0.0]))  # same centre: no parallax
    assert not obs.any() and weak.all()
    obs, weak = region_masks(_plane(1), tw, tk, _plane(1), *_cams([0.0]))  # one view, min_views = 2
    assert not obs.any() and weak.all()
    obs, _ = region_masks(_plane(1), tw, tk, _plane(1), *_cams([0.0]), min_views=1, min_parallax_deg=0.0)
    assert obs.all()


def test_parallax_threshold():
    tw, tk = _cams([0.0])
    cw, ck = _cams([-0.1, 0.1])  # 2 * atan(0.1 / 5) = 2.3 deg at the plane's centre
    ang = math.degrees(2 * math.atan(0.1 / 5))
    obs, _ = region_masks(_plane(1), tw, tk, _plane(2), cw, ck, min_parallax_deg=ang + 0.5)
    assert not obs.any()
    obs, _ = region_masks(_plane(1), tw, tk, _plane(2), cw, ck, min_parallax_deg=ang - 0.5)
    assert obs[0, 0, 0, :, 10:22].all()


def test_depth_discontinuity_is_weak():
    tw, tk = _cams([0.0])
    cw, ck = _cams([-1.0, 1.0])
    target = _plane(1)
    target[..., :, 16:] = 4.0  # a step from 5 to 4 between columns 15 and 16 (20% jump)
    ctx = _plane(2)  # context depth: nearer everywhere is fine for visibility (the points are in front)
    obs, weak = region_masks(target, tw, tk, ctx, cw, ck, edge_thresh=0.1)
    assert weak[0, 0, 0, :, 15:17].all()
    obs2, _ = region_masks(target, tw, tk, ctx, cw, ck, edge_thresh=0.3)
    assert obs2[0, 0, 0, 5:-5, 15:17].all()


def test_masked_metrics():
    torch.manual_seed(0)
    target = torch.rand(2, 3, H, W)
    pred = target.clone()
    weak = torch.zeros(2, 1, H, W, dtype=torch.bool)
    weak[..., :, :10] = True
    pred[..., :, :10] = torch.rand(2, 3, H, 10)  # errors only inside the weak region
    from anycity.metrics import psnr

    full = torch.ones_like(weak)
    torch.testing.assert_close(masked_psnr(pred, target, full), psnr(pred, target))
    assert (masked_psnr(pred, target, ~weak) > 90).all()  # perfect outside the weak region
    assert (masked_psnr(pred, target, weak) < 20).all()
    assert torch.isnan(masked_psnr(pred, target, torch.zeros_like(weak))).all()
    s_obs, s_weak = masked_ssim(pred, target, ~weak & full), masked_ssim(pred, target, weak)
    assert (s_obs > s_weak).all() and torch.isnan(masked_ssim(pred, target, torch.zeros_like(weak))).all()
    with pytest.raises(ValueError, match="mask"):
        masked_psnr(pred, target, weak[:1])


def test_lpips_is_left_out_in_one_line_when_it_cannot_run_offline():
    metric, msg = lpips_or_none()
    if metric is None:
        assert msg.startswith("LPIPS: left out") and "\n" not in msg
    else:
        assert msg == "LPIPS: on"


def test_masked_lpips_scores_the_region_through_a_composite():
    torch.manual_seed(0)
    target = torch.rand(2, 3, H, W)
    pred = target.clone()
    region = torch.zeros(2, 1, H, W, dtype=torch.bool)
    region[..., :, :10] = True
    pred[..., :, :10] = 0.0
    l1 = lambda a, b: (a - b).abs().mean()  # a stand-in for LPIPS: any image distance
    inside = masked_lpips(l1, pred, target, region)
    outside = masked_lpips(l1, pred, target, ~region)
    assert (inside > 0).all() and (outside == 0).all()  # errors only inside the region count
    assert torch.isnan(masked_lpips(l1, pred, target, torch.zeros_like(region))).all()
