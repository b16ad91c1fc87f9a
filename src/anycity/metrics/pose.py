"""Relative camera pose errors over all view pairs (VGGT / PoseDiffusion protocol) and their AUC."""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry import invert_rigid


def _angle_deg(cos: Tensor) -> Tensor:
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def rotation_angle_deg(R: Tensor) -> Tensor:
    """Rotation angle in degrees of ``[..., 3, 3]`` (near-)rotation matrices -> ``[...]``, in [0, 180].

    ``atan2(|vee(R - R^T)| / 2, (tr R - 1) / 2)``: sin and cos of the angle from the skew and the symmetric part.
    ``acos((tr R - 1) / 2)`` alone reads the angle of a near-identity off a cosine within float32 rounding of 1,
    and so gives up to 0.09 deg for two equal float32 rotations; the skew part keeps small angles exact.
    """
    sin = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]],
                      dim=-1).norm(dim=-1) / 2
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.rad2deg(torch.atan2(sin, cos))


def relative_pose_errors(pred_w2c: Tensor, gt_w2c: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and translation-direction errors of every view pair ``i < j``.

    Args:
        pred_w2c, gt_w2c: ``[B, V, 4, 4]`` the same views, predicted and ground truth, V >= 2 (any frames and
            scales: only relative poses are compared).
    Returns:
        ``rre [B, P]``: angle of ``R_rel_pred^T R_rel_gt`` in degrees (:func:`rotation_angle_deg`, computed in
        float64); ``rte [B, P]``: angle between the relative translations in degrees, sign-agnostic
        (``min(a, 180 - a)``, as VGGT); P = V (V - 1) / 2. A pair with a non-finite predicted camera gets the
        largest errors, 180 and 90 degrees, in every metric built on them.
    """
    if pred_w2c.dim() != 4 or pred_w2c.shape[-2:] != (4, 4) or pred_w2c.shape != gt_w2c.shape \
            or pred_w2c.shape[1] < 2:
        raise ValueError(f"relative_pose_errors: pred_w2c and gt_w2c must both be [B, V, 4, 4] with V >= 2 and the "
                         f"same shape, got {tuple(pred_w2c.shape)} and {tuple(gt_w2c.shape)}; for one scene add a "
                         "batch dim with [None]")
    v = pred_w2c.shape[1]
    i, j = torch.triu_indices(v, v, offset=1, device=pred_w2c.device)

    def rel(w2c: Tensor) -> tuple[Tensor, Tensor]:
        w2c = w2c.double()
        T = w2c[:, j] @ invert_rigid(w2c[:, i])  # camera i -> camera j
        return T[..., :3, :3], T[..., :3, 3]

    (Rp, tp), (Rg, tg) = rel(pred_w2c), rel(gt_w2c)
    rre = rotation_angle_deg(Rp.transpose(-1, -2) @ Rg)
    cos_t = (tp * tg).sum(-1) / (tp.norm(dim=-1) * tg.norm(dim=-1)).clamp_min(1e-12)
    rte = _angle_deg(cos_t.abs())
    bad = ~(torch.isfinite(Rp).flatten(-2).all(-1) & torch.isfinite(tp).all(-1))
    return rre.masked_fill(bad, 180.0).float(), rte.masked_fill(bad, 90.0).float()


def pose_auc(rre: Tensor, rte: Tensor, max_threshold: int = 30) -> Tensor:
    """Per-pair contribution to AUC@``max_threshold``: the fraction of thresholds ``1..max_threshold`` degrees that
    ``max(rre, rte)`` stays below. Its mean over all pairs is the usual pose AUC (VGGT's ``calculate_auc``)."""
    err = torch.maximum(rre, rte)[..., None]
    thresholds = torch.arange(1, max_threshold + 1, device=err.device, dtype=err.dtype)
    return (err < thresholds).float().mean(-1)
