"""Image quality: per-image PSNR (torchmetrics functional) and SSIM, the mean-colour baseline and the nearest-view
reference.

SSIM is the feed-forward papers' (pixelSplat's ``compute_ssim``, used by NoPoSplat and AnySplat: skimage's
``structural_similarity(win_size=11, gaussian_weights=True, data_range=1.0)`` with its defaults): Wang et al.'s
Gaussian window 11, sigma 1.5, K1 0.01, K2 0.03, the window's variances and covariance with skimage's default
sample-covariance factor ``NP / (NP - 1) = 121 / 120`` (``use_sample_covariance=True``), averaged over the pixels
whose whole window lies inside the image (5 px in from each edge). torchmetrics' SSIM is not used: it takes
population variances (a higher figure, by 2e-4 to 5e-4 on noisy 64 px images at SSIM 0.92 to 0.32), and its mean
also counts the border pixels, whose windows read a reflected image (at 48 px 38 % of the pixels).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio

from anycity.structures import image_range


def _flat(x: Tensor) -> Tensor:
    if x.dim() < 4:
        raise ValueError(f"images: expected [..., 3, H, W] with at least one leading dim, got {tuple(x.shape)}")
    return x.reshape(-1, *x.shape[-3:]).float()


def check_pair(name: str, pred: Tensor, target: Tensor) -> None:
    """One-line error unless ``pred`` and ``target`` are float ``[..., 3, H, W]`` images of one shape and ``target``
    is finite in [0, 1]. ``pred`` is not range-checked: a render may overshoot 1 (SH colours), and it is scored
    clamped. One reduction and one host sync."""
    for arg, x in (("pred", pred), ("target", target)):
        if x.dim() < 4 or x.shape[-3] != 3:
            hint = (f"; it looks channels-last: use {arg}.movedim(-1, -3)" if x.dim() >= 4 and x.shape[-1] == 3
                    else "" if x.dim() >= 4 else f"; add a batch dim with {arg}[None]")
            raise ValueError(f"{name}: {arg}: expected [..., 3, H, W] with at least one leading dim, got "
                             f"{tuple(x.shape)}{hint}")
        if not x.is_floating_point():
            raise ValueError(f"{name}: {arg}: expected float images in [0, 1], got dtype {x.dtype}; use "
                             f"{arg}.float() / 255 for 8-bit images")
    if pred.shape != target.shape:
        raise ValueError(f"{name}: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ; pass one target "
                         "per predicted image (no broadcasting)")
    if not target.numel() or target.is_meta:
        return
    lo, hi, fault = image_range(target)
    if fault == "nonfinite":
        raise ValueError(f"{name}: target: holds NaN or infinite values; find them with ~torch.isfinite(target)")
    if fault in ("signed", "normalised"):
        fix = {"signed": "it looks like [-1, 1]; use (x + 1) / 2",
               "normalised": "it looks mean/std-normalised (e.g. ImageNet); undo it: x * std + mean"}
        raise ValueError(f"{name}: target: expected values in [0, 1], got a minimum of {lo:.4g} (maximum {hi:.4g}); "
                         f"{fix[fault]}")
    if fault in ("0-255", "over"):
        fix = {"0-255": "it looks like 0-255; divide by 255", "over": "clamp it to [0, 1]"}
        raise ValueError(f"{name}: target: expected values in [0, 1], got a maximum of {hi:.4g}; {fix[fault]}")


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image PSNR in dB of float ``[..., 3, H, W]`` images -> ``[M]`` (M = product of leading dims). ``target``
    in [0, 1] and of ``pred``'s shape (:func:`check_pair`); ``pred`` is scored clamped to [0, 1]."""
    check_pair("psnr", pred, target)
    p, t = _flat(pred).clamp(0, 1), _flat(target)
    return peak_signal_noise_ratio(p, t, data_range=1.0, dim=(1, 2, 3), reduction="none")


SSIM_BORDER = 5  # the 11-px window's half width: pixels nearer the edge than this are not averaged
_SSIM_SIGMA = 1.5
_SSIM_C1, _SSIM_C2 = 0.01**2, 0.03**2  # (K1 L)^2, (K2 L)^2 with data range L = 1
_SSIM_COV_NORM = 121 / 120  # skimage's use_sample_covariance=True: NP / (NP - 1), NP = 11 * 11 window pixels


def ssim_window_fits(images: Tensor) -> bool:
    """Whether ``[..., H, W]`` images have a pixel whose whole 11-px window lies inside (H, W > 10)."""
    return min(images.shape[-2:]) > 2 * SSIM_BORDER


def _window_mean(x: Tensor) -> Tensor:
    """Gaussian-weighted mean (11 px, sigma 1.5, separable) of the windows inside ``[M, 1, H, W]`` ->
    ``[M, 1, H - 10, W - 10]``."""
    r = torch.arange(-SSIM_BORDER, SSIM_BORDER + 1, dtype=torch.float64)
    g = torch.exp(-(r**2) / (2 * _SSIM_SIGMA**2))
    g = (g / g.sum()).to(dtype=x.dtype, device=x.device)
    return F.conv2d(F.conv2d(x, g.view(1, 1, -1, 1)), g.view(1, 1, 1, -1))


def ssim_map(pred: Tensor, target: Tensor) -> Tensor:
    """SSIM (module docstring: skimage's, sample covariance) of each pixel whose whole window lies inside the
    image of float ``[..., 3, H, W]`` images -> ``[M, 3, H - 10, W - 10]``; inputs as :func:`psnr`'s."""
    check_pair("ssim", pred, target)
    return _ssim_map(pred, target)


def _ssim_map(pred: Tensor, target: Tensor) -> Tensor:
    p, t = _flat(pred).clamp(0, 1), _flat(target)
    b = SSIM_BORDER
    if not ssim_window_fits(p):
        raise ValueError(f"ssim: images of {tuple(p.shape[-2:])} px have no pixel whose 11-px window fits; "
                         f"score images larger than {2 * b} px on each side")
    m, c, h, w = p.shape
    # in float64: SSIM subtracts E[x]^2 from E[x^2], and a CUDA convolution of float32 runs in TF32 by default
    # (cudnn.allow_tf32), whose 10-bit inputs scored two identical 448 px images 0.994 (skimage: 1)
    x, y = p.reshape(m * c, 1, h, w).double(), t.reshape(m * c, 1, h, w).double()
    mx, my, xx, yy, xy = _window_mean(torch.cat([x, y, x * x, y * y, x * y])).split(m * c)
    vx = (xx - mx * mx).clamp_min(0) * _SSIM_COV_NORM
    vy = (yy - my * my).clamp_min(0) * _SSIM_COV_NORM
    cxy = (xy - mx * my) * _SSIM_COV_NORM
    s = ((2 * mx * my + _SSIM_C1) * (2 * cxy + _SSIM_C2)) / ((mx * mx + my * my + _SSIM_C1) * (vx + vy + _SSIM_C2))
    return s.reshape(m, c, h - 2 * b, w - 2 * b).to(p.dtype)


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image SSIM (module docstring: the window's interior pixels) of float ``[..., 3, H, W]`` images -> ``[M]``,
    inputs as :func:`psnr`'s; NaN for images of 10 px or less on a side, where no window fits (skimage refuses
    them)."""
    check_pair("ssim", pred, target)
    if not ssim_window_fits(pred):
        return torch.full((_flat(pred).shape[0],), float("nan"), device=pred.device)
    return _ssim_map(pred, target).mean(dim=(1, 2, 3))


def mean_colour_baseline(context: Tensor, target_shape: tuple[int, ...]) -> Tensor:
    """Baseline render: every target pixel set to the mean colour of the context views.

    Args:
        context: ``[B, V, 3, H, W]`` context images.
        target_shape: ``(B, T, 3, H', W')`` of the targets.
    Returns:
        ``[B, T, 3, H', W']``.
    """
    mean = context.float().mean(dim=(1, 3, 4))  # [B, 3]
    return mean[:, None, :, None, None].expand(*target_shape)


def nearest_view_reference(context: Tensor, context_index: Tensor, target_index: Tensor) -> Tensor:
    """Reference "render": each target is a copy of the context image nearest to it along the trajectory.

    A model that beats this has learnt more than to show the closest input (it is no 3D reconstruction).

    Args:
        context: ``[B, V, 3, H, W]`` context images.
        context_index, target_index: ``[B, V]`` and ``[B, T]`` trajectory positions of the views.
    Returns:
        ``[B, T, 3, H, W]`` (targets must share the context size).
    """
    if context_index.shape != context.shape[:2] or target_index.shape[0] != context.shape[0]:
        raise ValueError(f"nearest_view_reference: indices {tuple(context_index.shape)}, {tuple(target_index.shape)} "
                         f"do not match context images {tuple(context.shape)}")
    nearest = (target_index[:, :, None] - context_index[:, None, :]).abs().argmin(-1)  # [B, T]
    return torch.gather(context, 1, nearest[..., None, None, None].expand(-1, -1, *context.shape[2:]))
