"""Camera loss: L1 (VGGT's default) or Huber on the 9-D pose encoding ``(T, quat, fov_h, fov_w)`` per refinement
iteration (VGGT)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def camera_loss(pose_enc_list: list[Tensor] | Tensor, gt_pose_enc: Tensor, gamma: float = 0.6,
                weight_t: float = 1.0, weight_r: float = 1.0, weight_fl: float = 0.5,
                huber_delta: float = 1.0, loss_type: str = "l1") -> dict[str, Tensor]:
    """Iteration-weighted L1 or Huber loss on pose encodings.

    Iteration ``i`` of ``n`` gets weight ``gamma ** (n - 1 - i)`` so the last (finest) prediction counts most;
    weights are normalised to sum to 1.

    Args:
        pose_enc_list: list of ``[B, V, 9]`` predictions (one per camera-head iteration) or a single tensor.
        gt_pose_enc: ``[B, V, 9]`` ground truth in the same frame and encoding.
        loss_type: "l1" (VGGT's training default: a constant pull at small errors, where pose precision matters)
            or "huber" (quadratic below ``huber_delta``).
    Returns:
        ``{"cam_t", "cam_r", "cam_fl", "total"}`` (translation, quaternion, field of view terms).
    """
    preds = [pose_enc_list] if isinstance(pose_enc_list, Tensor) else list(pose_enc_list)
    if not preds:
        raise ValueError("camera_loss: pose_enc_list is empty; expected at least one [B, V, 9] prediction")
    for p in preds:
        if p.shape != gt_pose_enc.shape or p.shape[-1] != 9:
            raise ValueError(f"camera_loss: expected predictions shaped like gt {tuple(gt_pose_enc.shape)} "
                             f"[B, V, 9], got {tuple(p.shape)}")
    if loss_type == "l1":
        dist = F.l1_loss
    elif loss_type == "huber":
        dist = lambda a, b: F.huber_loss(a, b, delta=huber_delta)  # noqa: E731
    else:
        raise ValueError(f"camera_loss: loss_type must be 'l1' or 'huber', got {loss_type!r}")
    n = len(preds)
    ws = torch.tensor([gamma ** (n - 1 - i) for i in range(n)])
    ws = ws / ws.sum()
    gt = gt_pose_enc.float()
    out = {k: gt.new_zeros(()) for k in ("cam_t", "cam_r", "cam_fl")}
    for wi, p in zip(ws.tolist(), preds, strict=True):
        p = p.float()
        # quaternions q and -q are the same rotation: compare against the closer sign
        q, qg = p[..., 3:7], gt[..., 3:7]
        sign = torch.where((q * qg).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        out["cam_t"] = out["cam_t"] + wi * dist(p[..., :3], gt[..., :3])
        out["cam_r"] = out["cam_r"] + wi * dist(q, sign * qg)
        out["cam_fl"] = out["cam_fl"] + wi * dist(p[..., 7:], gt[..., 7:])
    out["total"] = weight_t * out["cam_t"] + weight_r * out["cam_r"] + weight_fl * out["cam_fl"]
    return out
