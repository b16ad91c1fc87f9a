"""Image quality: per-image PSNR and SSIM (torchmetrics functional), the mean-colour baseline and the nearest-view
reference."""

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


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Per-image SSIM (Gaussian window 11, sigma 1.5) of ``[..., 3, H, W]`` images -> ``[M]``."""
    p, t = _flat(pred).clamp(0, 1), _flat(target)
    return structural_similarity_index_measure(p, t, data_range=1.0, reduction="none")


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
