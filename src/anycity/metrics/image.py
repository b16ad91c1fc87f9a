"""Image quality: per-image PSNR and SSIM (torchmetrics functional), and the mean-colour baseline."""

from __future__ import annotations

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
