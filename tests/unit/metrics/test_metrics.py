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
    """Wang et al.'s SSIM in float64 numpy (Gaussian window 11, sigma 1.5, sample variances: skimage's default
    use_sample_covariance=True multiplies the window's variances and covariance by 121 / 120), averaged over the
    pixels whose whole window lies inside the image, as skimage's structural_similarity(gaussian_weights=True)
    averages it. One window at a time, as the formula reads."""
    import numpy as np

    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2, n = 0.01**2, 0.03**2, 121 / 120
    vals = []
    for c in range(x.shape[0]):
        for i in range(5, x.shape[1] - 5):
            for j in range(5, x.shape[2] - 5):
                a, b = x[c, i - 5:i + 6, j - 5:j + 6], y[c, i - 5:i + 6, j - 5:j + 6]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = n * ((w * a * a).sum() - ma**2), n * ((w * b * b).sum() - mb**2)
                cov = n * ((w * a * b).sum() - ma * mb)
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def _skimage_ssim(x, y):
    """A port of skimage's structural_similarity(win_size=11, gaussian_weights=True, channel_axis=0,
    data_range=1.0) with its default use_sample_covariance=True, the call of pixelSplat's compute_ssim: separable
    Gaussian filtering of the whole image (scipy's "reflect" padding is numpy's "symmetric"), cov_norm
    NP / (NP - 1), then the mean of the map with 5 px cropped from every edge, per channel."""
    import numpy as np

    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    g /= g.sum()

    def filt(a):
        for axis in (0, 1):
            pad = [(0, 0), (0, 0)]
            pad[axis] = (5, 5)
            p = np.pad(a, pad, mode="symmetric")
            a = sum(wk * np.take(p, np.arange(k, k + a.shape[axis]), axis=axis) for k, wk in enumerate(g))
        return a

    cov_norm = 121 / 120
    means = []
    for a, b in zip(x, y):
        ux, uy = filt(a), filt(b)
        vx, vy = cov_norm * (filt(a * a) - ux * ux), cov_norm * (filt(b * b) - uy * uy)
        vxy = cov_norm * (filt(a * b) - ux * uy)
        s = ((2 * ux * uy + 0.01**2) * (2 * vxy + 0.03**2)) / ((ux**2 + uy**2 + 0.01**2) * (vx + vy + 0.03**2))
        means.append(s[5:-5, 5:-5].mean())
    return float(np.mean(means))


def test_ssim_is_wang_et_al_over_the_windows_inside_the_image():
    """The feed-forward papers' SSIM (skimage; pixelSplat's compute_ssim): border pixels, whose windows would read
    a padded image, are not averaged. A defect in the border ring changes it only through the windows it reaches."""
    gen = torch.Generator().manual_seed(0)
    gt = torch.rand(3, 24, 20, generator=gen)
    pred = (gt + 0.2 * torch.randn(3, 24, 20, generator=gen)).clamp(0, 1)
    got = ssim(pred[None], gt[None])
    assert got.shape == (1,)
    assert got.item() == pytest.approx(_ssim_reference(pred.double().numpy(), gt.double().numpy()), abs=1e-6)
    assert ssim(torch.rand(2, 3, 10, 32), torch.rand(2, 3, 10, 32)).isnan().all()  # no window fits: undefined


@pytest.mark.parametrize("noise", [0.02, 0.05, 0.1])
def test_ssim_matches_skimage_default_sample_covariance(noise):
    """pixelSplat / NoPoSplat / AnySplat score SSIM with skimage's default use_sample_covariance=True: the figure
    is 2e-4 to 5e-4 below the population-variance SSIM (torchmetrics') on these images, so that one is refused."""
    import numpy as np

    rng = np.random.default_rng(0)
    box = np.ones(5) / 5
    base = rng.random((3, 64, 48))
    base = np.apply_along_axis(lambda r: np.convolve(r, box, "same"), 1, base)
    base = np.apply_along_axis(lambda r: np.convolve(r, box, "same"), 2, base)  # smooth, natural-ish
    pred = np.clip(base + noise * rng.standard_normal(base.shape), 0, 1)
    got = ssim(torch.tensor(pred)[None], torch.tensor(base)[None]).item()
    assert got == pytest.approx(_skimage_ssim(pred, base), abs=1e-6)


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
    # under-prediction: max(p/g, g/p) is 2 for 0.5 (fails) and 1/0.85 = 1.18 for 0.85 (passes)
    under = depth_metrics(torch.tensor([0.5, 0.85]).reshape(1, 1, 1, 1, 2), torch.ones(1, 1, 1, 1, 2))
    assert under["delta1"].item() == pytest.approx(0.5)
    assert under["abs_rel"].item() == pytest.approx((0.5 + 0.15) / 2)


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


def _pair(v=2, size=16):
    g = torch.Generator().manual_seed(0)
    t = torch.rand(1, v, 3, size, size, generator=g)
    return (t + 0.05 * torch.randn(t.shape, generator=g)).clamp(0, 1), t


@pytest.mark.parametrize("metric", [psnr, ssim])
@pytest.mark.parametrize(("target", "match"), [
    # these scored silently: -43 dB for a 0-255 target, view 1 against view 0's target, channels-last as channels
    (lambda t: (t * 255).round().to(torch.uint8), r"target: expected float images in \[0, 1\], got dtype "
                                                    r"torch.uint8; use target.float\(\) / 255"),
    (lambda t: t * 255, r"target: expected values in \[0, 1\], got a maximum of .*; it looks like 0-255; "
                        r"divide by 255"),
    (lambda t: t * 2 - 1, r"target: expected values in \[0, 1\], got a minimum of .*; it looks like \[-1, 1\]; "
                          r"use \(x \+ 1\) / 2"),
    # a little above 1 (a resize's overshoot kept unclamped): scored as if in range
    (lambda t: t * 1.05, r"target: expected values in \[0, 1\], got a maximum of 1\.0\d*; clamp it to \[0, 1\]$"),
    (lambda t: t[:, :1], r"pred \(1, 2, 3, 16, 16\) and target \(1, 1, 3, 16, 16\) differ; pass one target per "),
    (lambda t: t.permute(0, 1, 3, 4, 2), r"target: expected \[\.\.\., 3, H, W\] .*; it looks channels-last: use "
                                         r"target.movedim\(-1, -3\)"),
    (lambda t: t.index_fill(4, torch.tensor([3]), float("nan")), "target: holds NaN"),
])
def test_psnr_and_ssim_refuse_targets_they_would_score_wrongly(metric, target, match):
    pred, t = _pair()
    with pytest.raises(ValueError, match=f"{metric.__name__}: {match}"):
        metric(pred, target(t))


@pytest.mark.parametrize("metric", [psnr, ssim])
def test_psnr_and_ssim_refuse_integer_or_channels_last_predictions(metric):
    pred, t = _pair()
    with pytest.raises(ValueError, match=f"{metric.__name__}: pred: expected float images"):
        metric((pred * 255).to(torch.uint8), t)
    with pytest.raises(ValueError, match="pred: expected .* it looks channels-last"):
        metric(pred.permute(0, 1, 3, 4, 2), t)


def test_psnr_and_ssim_accept_targets_at_the_ends_of_the_range_and_small_images():
    pred, t = _pair()
    t[..., 0, 0], t[..., 0, 1] = 0.0, 1.0
    assert torch.isfinite(psnr(pred, t)).all() and torch.isfinite(ssim(pred, t)).all()
    assert torch.isfinite(psnr(pred.half(), t.bfloat16())).all()  # any float dtype
    p, t = _pair(size=8)
    assert ssim(p, t).isnan().all()  # no window fits: still NaN, not an error


def test_depth_metrics_refuses_a_mask_of_another_shape_than_gt():
    """A mask with one view where gt has three used to crash deep inside with a broadcast RuntimeError; it is a
    one-line ValueError naming mask and gt's shape. A mask of gt's shape is taken."""
    gt = torch.rand(2, 3, 1, 8, 8) + 1
    with pytest.raises(ValueError, match=r"^depth_metrics: mask \(2, 1, 1, 8, 8\) must have gt's shape \(2, 3, 1, 8, "
                                         r"8\)"):
        depth_metrics(gt + 1, gt, mask=torch.ones(2, 1, 1, 8, 8, dtype=torch.bool))
    out = depth_metrics(gt, gt, mask=torch.ones(2, 3, 1, 8, 8, dtype=torch.bool))
    assert out["abs_rel"].shape == (6,) and out["delta1"].min().item() == 1.0


def test_median_alignment_takes_both_medians_over_the_covered_pixels_only():
    """With the far pixels left empty the gt median is the covered pixels' (1), not all valid pixels' (4): the two
    covered pixels align exactly and the three holes score AbsRel 1 each, so AbsRel 3/5 and delta1 2/5."""
    gt = torch.tensor([1.0, 1.0, 4.0, 4.0, 4.0]).reshape(1, 1, 1, 1, 5)
    pred = torch.tensor([2.0, 2.0, 0.0, 0.0, 0.0]).reshape(1, 1, 1, 1, 5)
    out = depth_metrics(pred, gt, align="median")
    assert out["abs_rel"].item() == pytest.approx(0.6) and out["delta1"].item() == pytest.approx(0.4)


def test_a_zero_or_negative_prediction_is_a_hole_not_a_covered_pixel():
    """Depth 0 (nothing rendered) is left out of the median alignment and fails; a negative depth scores AbsRel 1 as a
    hole does, not |p - g| / g."""
    gt = torch.full((1, 1, 1, 1, 3), 2.0)
    out = depth_metrics(torch.tensor([4.0, 0.0, 0.0]).reshape(1, 1, 1, 1, 3), gt, align="median")
    assert out["abs_rel"].item() == pytest.approx(2 / 3) and out["delta1"].item() == pytest.approx(1 / 3)
    neg = depth_metrics(torch.tensor([-1.0]).reshape(1, 1, 1, 1, 1), torch.tensor([2.0]).reshape(1, 1, 1, 1, 1))
    assert neg["abs_rel"].item() == 1.0 and neg["delta1"].item() == 0.0


def test_delta1_threshold_is_strict():
    """delta1 counts max(d/d*, d*/d) < 1.25: a ratio of exactly 5/4 fails."""
    gt = torch.tensor([4.0, 4.0]).reshape(1, 1, 1, 1, 2)
    pred = torch.tensor([5.0, 4.0]).reshape(1, 1, 1, 1, 2)
    assert depth_metrics(pred, gt)["delta1"].item() == 0.5


def test_ssim_does_not_depend_on_the_convolution_precision(monkeypatch):
    """On CUDA a float32 convolution runs in TF32 (10-bit inputs) by default; SSIM subtracts E[x]^2 from E[x^2], so
    it scored two identical 448 px images 0.994. Emulated here: float32 convolutions round their inputs to 10 bits
    (the old code scored this smooth image 0.988 against itself)."""
    import torch.nn.functional as F

    from anycity.metrics.image import ssim

    real = F.conv2d

    def tf32(t):
        i = t.float().contiguous().view(torch.int32)
        return ((i + 0x1000) & ~0x1FFF).view(torch.float32)  # round to nearest, 10-bit mantissa

    def conv(x, w, *a, **k):
        return real(tf32(x), tf32(w), *a, **k) if x.dtype == torch.float32 else real(x, w, *a, **k)

    yy, xx = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 64), indexing="ij")
    img = (0.5 + 0.3 * torch.sin(6 * xx) * torch.cos(4 * yy))[None, None].expand(1, 3, 64, 64).clone()
    exact = float(ssim(img, img * 0.9))
    monkeypatch.setattr(F, "conv2d", conv)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-9)
    assert float(ssim(img, img * 0.9)) == pytest.approx(exact, abs=1e-9)
