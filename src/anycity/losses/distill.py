"""Stage II distillation: dense-to-sparse ``L_d2s`` and scaffold preservation ``L_pres``."""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.structures import RenderOutput


def _masked_l1(a: Tensor, b: Tensor, mask: Tensor | None = None) -> Tensor:
    err = (a - b).abs()
    if mask is None:
        return err.mean()
    w = mask.to(err.dtype).expand_as(err)
    return (err * w).sum() / w.sum().clamp_min(1.0)


def d2s_loss(student: RenderOutput, teacher: RenderOutput, depth_weight: float = 1.0,
             alpha_threshold: float = 0.5, scale_align: bool = True) -> dict[str, Tensor]:
    """L1 between the student's renders and the detached teacher's, on the dense cameras.

    Depth is compared only where the teacher is valid (teacher alpha > ``alpha_threshold`` and depth > 0). With
    ``scale_align`` the teacher's depth is first rescaled, per scene, by the median ratio of the student's depth to
    it (no gradient), so the term teaches the depth's shape and never its scale. Teacher and student are separate
    predictions (e.g. 12 and 4 views) whose depth-to-camera scales differ; pulling the student's depth to the teacher's
    scale would pull it off its own cameras.

    Args:
        student, teacher: renders ``[B, V, C, H, W]`` of the same cameras; the teacher is detached here.
    Returns:
        ``{"d2s_rgb", "d2s_depth", "total"}``.
    """
    t_rgb, t_depth, t_alpha = teacher.rgb.detach(), teacher.depth.detach().float(), teacher.alpha.detach()
    rgb = _masked_l1(student.rgb.float(), t_rgb.float())
    valid = (t_alpha > alpha_threshold) & (t_depth > 0)
    s_depth = student.depth.float()
    if scale_align:
        ratio = (s_depth.detach() / t_depth.clamp_min(1e-12)).masked_fill(~(valid & (s_depth.detach() > 0)), torch.nan)
        k = ratio.flatten(1).nanmedian(dim=1).values.nan_to_num(1.0)  # [B]; 1 where the scene has no valid pixel
        t_depth = t_depth * k.view(-1, *([1] * (t_depth.dim() - 1)))
    depth = _masked_l1(s_depth, t_depth, valid)
    return {"d2s_rgb": rgb, "d2s_depth": depth, "total": rgb + depth_weight * depth}


def preservation_loss(final: RenderOutput, scaffold: RenderOutput, depth_weight: float = 1.0) -> dict[str, Tensor]:
    """L1 between the final (refined) and the detached scaffold renders on the context cameras.

    Returns:
        ``{"pres_rgb", "pres_depth", "total"}``; depth only where the scaffold has alpha > 0.5.
    """
    s_rgb, s_depth = scaffold.rgb.detach(), scaffold.depth.detach()
    rgb = _masked_l1(final.rgb.float(), s_rgb.float())
    depth = _masked_l1(final.depth.float(), s_depth.float(), scaffold.alpha.detach() > 0.5)
    return {"pres_rgb": rgb, "pres_depth": depth, "total": rgb + depth_weight * depth}
