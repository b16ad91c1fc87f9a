"""Similarity (Sim(3)) alignment of point sets and camera trajectories (Umeyama, 1991)."""

from __future__ import annotations

import torch
from torch import Tensor


def umeyama(
    src: Tensor, dst: Tensor, weights: Tensor | None = None, with_scale: bool = True
) -> tuple[Tensor, Tensor, Tensor]:
    """Least-squares s, R, t with ``dst ≈ s * R @ src + t``.

    Args:
        src, dst: ``[..., N, 3]`` corresponding points (N >= 3, not collinear for a unique R).
        weights: ``[..., N]`` non-negative weights (exactly ``src.shape[:-1]``: no broadcasting), or None.
    Returns:
        s ``[...]``, R ``[..., 3, 3]``, t ``[..., 3]`` in the dtype ``src``, ``dst`` (and ``weights``) promote
        to; the fit runs in float32 at least (torch's SVD has no float16/bfloat16 kernel).

    Gradients: the SVD has no usable gradient for degenerate inputs (fewer than 3 non-collinear points, or
    repeated singular values, e.g. symmetric point sets give NaN); callers align under ``torch.no_grad()``.
    """
    if src.shape != dst.shape or src.shape[-1] != 3:
        raise ValueError(f"umeyama: src and dst must both be [..., N, 3], got {tuple(src.shape)} and "
                         f"{tuple(dst.shape)}")
    if weights is not None:
        if tuple(weights.shape) != tuple(src.shape[:-1]):
            raise ValueError(f"umeyama: weights must have shape [..., N] = {tuple(src.shape[:-1])} like src without "
                             f"its last dim, got {tuple(weights.shape)}; squeeze or reshape them")
        if bool((weights < 0).any()):
            raise ValueError("umeyama: weights must be >= 0 (a negative weight gives an arbitrary scale); clamp them "
                             "with weights.clamp_min(0)")
    out = torch.promote_types(src.dtype, dst.dtype)
    if weights is not None:
        out = torch.promote_types(out, weights.dtype)
    work = torch.promote_types(out, torch.float32)
    src, dst = src.to(work), dst.to(work)
    w = torch.ones(src.shape[:-1], dtype=work, device=src.device) if weights is None else weights.to(work)
    w = w / w.sum(-1, keepdim=True).clamp_min(1e-12)
    mu_s = (w[..., None] * src).sum(-2)
    mu_d = (w[..., None] * dst).sum(-2)
    xs, xd = src - mu_s[..., None, :], dst - mu_d[..., None, :]
    cov = (w[..., None, None] * xd[..., :, None] * xs[..., None, :]).sum(-3)  # [..., 3, 3]
    U, S, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.det(U) * torch.det(Vh))
    D = torch.ones_like(S)
    D[..., 2] = d
    R = U @ torch.diag_embed(D) @ Vh
    var_s = (w * (xs * xs).sum(-1)).sum(-1)
    s = (S * D).sum(-1) / var_s.clamp_min(1e-12) if with_scale else torch.ones_like(var_s)
    t = mu_d - s[..., None] * (R @ mu_s[..., None])[..., 0]
    return s.to(out), R.to(out), t.to(out)


def sim3_matrix(s: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """s ``[...]``, R ``[..., 3, 3]``, t ``[..., 3]`` -> ``[..., 4, 4]`` matrix of p -> s R p + t."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = s[..., None, None] * R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T
