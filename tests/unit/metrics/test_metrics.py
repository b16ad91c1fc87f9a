"""Metrics on constructed cases with known answers."""

import math

import pytest
import torch

from anycity.metrics import depth_metrics, mean_colour_baseline, nearest_view_reference, psnr, ssim


def test_psnr_known_value_per_image():
    gt = torch.zeros(1, 2, 3, 8, 8)
    pred = gt.clone()
    pred[0, 0] = 0.1  # MSE 0.01 -> 20 dB
    pred[0, 1] = 0.01  # MSE 1e-4 -> 40 dB
    torch.testing.assert_close(psnr(pred, gt), torch.tensor([20.0, 40.0]), atol=1e-3, rtol=0)


def test_ssim_identity_and_range():
    img = torch.rand(1, 2, 3, 16, 16)
    torch.testing.assert_close(ssim(img, img), torch.ones(2), atol=1e-5, rtol=0)
    assert (ssim(img, torch.rand_like(img)) < 0.5).all()


def _ssim_reference(x, y):
    """Wang et al.'s SSIM in float64 numpy (Gaussian window 11, sigma 1.5, population variances), averaged over the
    pixels whose whole window lies inside the image, as skimage's structural_similarity(gaussian_weights=True,
    use_sample_covariance=False) averages it."""
    import numpy as np

    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[0]):
        for i in range(5, x.shape[1] - 5):
            for j in range(5, x.shape[2] - 5):
                a, b = x[c, i - 5:i + 6, j - 5:j + 6], y[c, i - 5:i + 6, j - 5:j + 6]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * a * a).sum() - ma**2, (w * b * b).sum() - mb**2
                cov = (w * a * b).sum() - ma * mb
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_is_wang_et_al_over_the_windows_inside_the_image():
    """The feed-forward papers' SSIM (skimage; pixelSplat's compute_ssim): border pixels, whose windows would read
    a padded image, are not averaged. A defect in the border ring changes it only through the windows it reaches."""
    gen = torch.Generator().manual_seed(0)
    gt = torch.rand(3, 24, 20, generator=gen)
    pred = (gt + 0.2 * torch.randn(3, 24, 20, generator=gen)).clamp(0, 1)
    got = ssim(pred[None], gt[None])
    assert got.shape == (1,)
    assert got.item() == pytest.approx(_ssim_reference(pred.double().numpy(), gt.double().numpy()), abs=1e-5)
    assert ssim(torch.rand(2, 3, 10, 32), torch.rand(2, 3, 10, 32)).isnan().all()  # no window fits: undefined


def test_mean_colour_baseline():
    ctx = torch.zeros(1, 2, 3, 4, 4)
    ctx[:, 0, 0] = 1.0  # red channel mean = 0.5
    base = mean_colour_baseline(ctx, (1, 3, 3, 5, 6))
    assert base.shape == (1, 3, 3, 5, 6)
    torch.testing.assert_close(base[0, 0, :, 0, 0], torch.tensor([0.5, 0.0, 0.0]))


def test_nearest_view_reference_copies_the_closest_context_view():
    ctx = torch.arange(3.0)[None, :, None, None, None].expand(2, 3, 3, 4, 4)  # view k is filled with k
    ci = torch.tensor([[1, 5, 9], [0, 10, 20]])
    ti = torch.tensor([[0, 6, 8, 3], [19, 4, 11, 0]])
    ref = nearest_view_reference(ctx, ci, ti)
    assert ref.shape == (2, 4, 3, 4, 4)
    torch.testing.assert_close(ref[:, :, 0, 0, 0], torch.tensor([[0.0, 1, 2, 0], [2, 0, 1, 0]]))
    with pytest.raises(ValueError, match="nearest_view_reference"):
        nearest_view_reference(ctx, ci[:, :2], ti)


def test_depth_metrics_known_values():
    gt = torch.ones(1, 1, 1, 2, 2)
    pred = torch.tensor([1.0, 1.1, 1.3, 2.0]).reshape(1, 1, 1, 2, 2)
    out = depth_metrics(pred, gt)
    assert out["abs_rel"].item() == pytest.approx((0 + 0.1 + 0.3 + 1.0) / 4)
    assert out["delta1"].item() == pytest.approx(0.5)
    mask = torch.tensor([True, True, False, False]).reshape(1, 1, 1, 2, 2)
    assert depth_metrics(pred, gt, mask)["delta1"].item() == 1.0


def test_a_pixel_the_render_leaves_empty_is_a_depth_failure_not_left_out():
    gt = torch.full((1, 1, 1, 2, 2), 2.0)
    pred = torch.tensor([2.0, 2.0, 0.0, float("nan")]).reshape(1, 1, 1, 2, 2)  # two holes
    out = depth_metrics(pred, gt)
    assert out["abs_rel"].item() == pytest.approx(0.5) and out["delta1"].item() == pytest.approx(0.5)
    aligned = depth_metrics(pred * 3, gt, align="median")  # the median comes from the covered pixels
    assert aligned["abs_rel"].item() == pytest.approx(0.5) and aligned["delta1"].item() == pytest.approx(0.5)


def test_depth_metrics_median_alignment_and_empty():
    gt = torch.rand(2, 1, 8, 8) + 1
    out = depth_metrics(3.0 * gt, gt, align="median")
    assert out["abs_rel"].max().item() < 1e-5 and out["delta1"].min().item() == 1.0
    empty = depth_metrics(gt, torch.zeros_like(gt))
    assert not empty["valid"].any() and not math.isnan(empty["abs_rel"].sum().item())
