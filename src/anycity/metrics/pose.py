"""Relative camera pose errors over all view pairs (VGGT / PoseDiffusion protocol) and their AUC."""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry import invert_rigid


def _angle_deg(cos: Tensor) -> Tensor:
    return torch.rad2deg(torch.acos(cos.clamp(-1.0, 1.0)))


def relative_pose_errors(pred_w2c: Tensor, gt_w2c: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and translation-direction errors of every view pair ``i < j``.

    Args:
        pred_w2c, gt_w2c: ``[B, V, 4, 4]`` the same views, predicted and ground truth (any frames and scales:
            only relative poses are compared).
    Returns:
        ``rre [B, P]``: angle of ``R_rel_pred^T R_rel_gt`` in degrees; ``rte [B, P]``: angle between the relative
        translations in degrees, sign-agnostic (``min(a, 180 - a)``, as VGGT); P = V (V - 1) / 2. A pair with a
        non-finite predicted camera gets the largest errors, 180 and 90 degrees, in every metric built on them.
    """
    v = pred_w2c.shape[1]
    i, j = torch.triu_indices(v, v, offset=1, device=pred_w2c.device)

    def rel(w2c: Tensor) -> tuple[Tensor, Tensor]:
        w2c = w2c.double()
        T = w2c[:, j] @ invert_rigid(w2c[:, i])  # camera i -> camera j
        return T[..., :3, :3], T[..., :3, 3]

    (Rp, tp), (Rg, tg) = rel(pred_w2c), rel(gt_w2c)
    tr = (Rp.transpose(-1, -2) @ Rg).diagonal(dim1=-2, dim2=-1).sum(-1)
    rre = _angle_deg((tr - 1) / 2)
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
