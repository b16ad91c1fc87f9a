"""Image quality: per-image PSNR and SSIM (torchmetrics functional), the mean-colour baseline and the nearest-view
reference.

SSIM is Wang et al.'s: Gaussian window 11, sigma 1.5, averaged over the pixels whose whole window lies inside the
image (5 px in from each edge), as skimage's ``structural_similarity(gaussian_weights=True)`` and the feed-forward
papers' evaluation code (pixelSplat's ``compute_ssim``, used by NoPoSplat and AnySplat) average it. torchmetrics'
own mean also counts the border pixels, whose windows read a reflected image: at 48 px that is 38 % of the pixels.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure


def _flat(x: Tensor) -> Tensor:
    if x.dim() < 4:
        raise ValueError(f"images: expected [..., 3, H, W] with at least one leading dim, got {tuple(x.shape)}")
    return x.reshape(-1, *x.shape[-3:]).float()


def psnr(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image PSNR in dB of ``[..., 3, H, W]`` images in [0, 1] -> ``[M]`` (M = product of leading dims)."""
    p, t = _flat(pred).clamp(0, 1), _flat(target)
    return peak_signal_noise_ratio(p, t, data_range=1.0, dim=(1, 2, 3), reduction="none")


SSIM_BORDER = 5  # the 11-px window's half width: pixels nearer the edge than this are not averaged


def ssim_window_fits(images: Tensor) -> bool:
    """Whether ``[..., H, W]`` images have a pixel whose whole 11-px window lies inside (H, W > 10)."""
    return min(images.shape[-2:]) > 2 * SSIM_BORDER


def ssim_map(pred: Tensor, target: Tensor) -> Tensor:
    """SSIM of each pixel whose whole window lies inside the image (Gaussian window 11, sigma 1.5) of
    ``[..., 3, H, W]`` images in [0, 1] -> ``[M, 3, H - 10, W - 10]``."""
    p, t = _flat(pred).clamp(0, 1), _flat(target)
    b = SSIM_BORDER
    if not ssim_window_fits(p):
        raise ValueError(f"ssim: images of {tuple(p.shape[-2:])} px have no pixel whose 11-px window fits; "
                         f"score images larger than {2 * b} px on each side")
    _, full = structural_similarity_index_measure(p, t, data_range=1.0, reduction="none", return_full_image=True)
    return full[..., b:-b, b:-b]


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image SSIM (module docstring: the window's interior pixels) of ``[..., 3, H, W]`` images -> ``[M]``;
    NaN for images of 10 px or less on a side, where no window fits (skimage refuses them)."""
    if not ssim_window_fits(pred):
        return torch.full((_flat(pred).shape[0],), float("nan"), device=pred.device)
    return ssim_map(pred, target).mean(dim=(1, 2, 3))


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
