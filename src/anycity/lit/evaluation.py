"""Evaluation helpers: map ground-truth cameras into the predicted frame (Sim(3) fit of the context cameras),
refine them photometrically (test-time pose alignment), and accumulate PSNR / SSIM / depth / pose metrics with
torchmetrics (DDP-safe)."""

from __future__ import annotations

from typing import Literal

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor, nn
from torchmetrics import MeanMetric
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from anycity.geometry import camera_centers, invert_rigid, transform_points, umeyama
from anycity.geometry.rotations import quat_multiply, rotmat_to_quat
from anycity.metrics.pose import pose_auc, relative_pose_errors
from anycity.structures import Gaussians

AlignMode = Literal["sim3", "none"]


def _frame_points(w2c: Tensor) -> Tensor:
    """``[B, V, 4, 4]`` -> ``[B, 4V, 3]``: camera centres plus points one spread-length along each camera axis,
    so that rotation and scale are determined even for nearly collinear trajectories."""
    c = camera_centers(w2c)  # [B, V, 3]
    spread = (c - c.mean(1, keepdim=True)).norm(dim=-1).mean(1).clamp_min(1e-3)  # [B]
    axes = w2c[..., :3, :3]  # rows = camera axes in world coordinates
    pts = c[:, :, None, :] + spread[:, None, None, None] * axes  # [B, V, 3, 3]
    return torch.cat([c[:, :, None, :], pts], dim=2).flatten(1, 2)


def fit_gt_to_pred(pred_w2c: Tensor, gt_w2c: Tensor, mode: AlignMode = "sim3") -> tuple[Tensor, Tensor, Tensor]:
    """Similarity ``p_pred = s R p_gt + t`` between the ground-truth and predicted context frames.

    Args:
        pred_w2c, gt_w2c: ``[B, V, 4, 4]`` the same context views, predicted and ground truth.
        mode: ``"sim3"`` (Umeyama fit; identity when V == 1) or ``"none"`` (identity: both frames put the first
            context camera at the origin with the same scale convention).
    Returns:
        ``s [B]``, ``R [B, 3, 3]``, ``t [B, 3]`` (float32, no gradient).
    """
    b = pred_w2c.shape[0]
    eye = torch.eye(3, device=pred_w2c.device).expand(b, 3, 3)
    ident = (torch.ones(b, device=pred_w2c.device), eye, torch.zeros(b, 3, device=pred_w2c.device))
    if mode == "none" or pred_w2c.shape[1] < 2:
        return ident
    if mode != "sim3":
        raise ValueError(f"eval_align: expected 'sim3' or 'none', got {mode!r}")
    with torch.no_grad(), torch.autocast(pred_w2c.device.type, enabled=False):
        s, R, t = umeyama(_frame_points(gt_w2c.float()), _frame_points(pred_w2c.float()))
    ok = torch.isfinite(s) & (s > 0) & torch.isfinite(R).flatten(1).all(1) & torch.isfinite(t).all(1)
    s = torch.where(ok, s, ident[0])
    R = torch.where(ok[:, None, None], R, ident[1])
    t = torch.where(ok[:, None], t, ident[2])
    return s, R, t


def cameras_in_pred_frame(gt_w2c: Tensor, s: Tensor, R: Tensor, t: Tensor) -> Tensor:
    """Ground-truth ``w2c [B, T, 4, 4]`` -> the same cameras in the predicted frame (rigid, predicted units).

    A point at camera depth z (ground-truth units) has depth ``s * z`` in the returned cameras.
    """
    Rc, tc = gt_w2c[..., :3, :3].float(), gt_w2c[..., :3, 3].float()
    Rn = Rc @ R.transpose(-1, -2)[:, None]
    tn = s[:, None, None] * tc - (Rn @ t[:, None, :, None])[..., 0]
    out = torch.zeros_like(gt_w2c, dtype=torch.float32)
    out[..., :3, :3], out[..., :3, 3], out[..., 3, 3] = Rn, tn, 1.0
    return out


def transform_gaussians(g: Gaussians, A: Tensor) -> Gaussians:
    """Apply a rigid transform ``A [B, 4, 4]`` (world to world) to a batch of B scenes: centres and rotations."""
    quats = quat_multiply(rotmat_to_quat(A[:, :3, :3])[:, None].expand_as(g.quats), g.quats)
    return Gaussians(transform_points(A, g.means), quats, g.scales, g.opacities, g.sh, g.valid)


def align_target_poses(render_rgb, gaussians: Gaussians, w2c: Tensor, images: Tensor, steps: int = 100,
                       lr: float = 0.005) -> Tensor:
    """Test-time pose alignment of target cameras (AnySplat's ``test.align_pose``; NoPoSplat's protocol).

    A pose-free model's scene sits in its own frame, so each held-out camera is refined photometrically before it
    is scored: Adam on a camera-frame rotation (axis-angle) and translation delta, Gaussians frozen, MSE against the
    target image. The camera moves by moving the scene the opposite way, so every render backend works (the fused
    CPU kernels have no camera gradients).

    Args:
        render_rgb: ``f(gaussians [B*T scenes], w2c [B*T, 1, 4, 4]) -> rgb [B*T, 1, 3, H, W]``.
        gaussians: the B scenes (no gradient needed).
        w2c: ``[B, T, 4, 4]`` initial target cameras in the scene's frame. images: ``[B, T, 3, H, W]`` targets.
    Returns:
        ``[B, T, 4, 4]`` refined cameras (no gradient).
    """
    b, t = w2c.shape[:2]
    if steps <= 0:
        return w2c
    with torch.inference_mode(False), torch.enable_grad():  # Lightning evaluates under inference mode
        cams = w2c.detach().float().reshape(b * t, 4, 4).clone()
        inv = invert_rigid(cams)
        scenes = Gaussians(*(None if x is None else x.detach().repeat_interleave(t, dim=0).clone()
                             for x in (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                       gaussians.sh, gaussians.valid)))
        target = images.detach().float().reshape(b * t, 1, *images.shape[2:]).clone()
        rot = torch.zeros(b * t, 3, device=cams.device, requires_grad=True)
        trans = torch.zeros(b * t, 3, device=cams.device, requires_grad=True)
        opt = torch.optim.Adam([rot, trans], lr=lr)

        def delta() -> Tensor:
            d = torch.eye(4, device=cams.device).repeat(b * t, 1, 1)
            d[:, :3, :3] = axis_angle_to_rotation_matrix(rot)
            d[:, :3, 3] = trans
            return d

        for _ in range(steps):
            # camera delta @ w2c == w2c applied to the scene moved by inv(w2c) @ delta @ w2c
            moved = transform_gaussians(scenes, inv @ delta() @ cams)
            loss = (render_rgb(moved, cams[:, None]) - target).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        with torch.no_grad():
            out = (delta() @ cams).reshape(b, t, 4, 4)
    return out.to(w2c.dtype)


class EvalMetrics(nn.Module):
    """Per-image PSNR / SSIM (torchmetrics) and per-image AbsRel / delta1 means, for named variants (plus PSNR of
    the ``baseline`` and ``nearest`` view references, and of ``<variant>_unaligned`` before test-time pose
    alignment), and the context cameras' mean relative rotation / translation-direction errors in degrees
    (``rre``, ``rte``) and pose AUC@30 (``pose_auc30``, in [0, 1]) over all view pairs.

    ``update(variant, pred, target)`` takes ``[M, 3, H, W]`` images; ``update_depth(variant, abs_rel, delta1)``
    takes per-image values. ``items()`` yields ``(name, metric)`` pairs ready for ``LightningModule.log``.
    """

    def __init__(self, variants: tuple[str, ...]) -> None:
        super().__init__()
        self.variants = variants
        m: dict[str, nn.Module] = {}
        for v in (*variants, *(f"{v}_unaligned" for v in variants), "baseline", "nearest"):
            m[f"psnr_{v}"] = PeakSignalNoiseRatio(data_range=1.0, dim=(1, 2, 3), reduction="elementwise_mean")
        for v in variants:
            m[f"ssim_{v}"] = StructuralSimilarityIndexMeasure(data_range=1.0)
            m[f"abs_rel_{v}"] = MeanMetric()
            m[f"delta1_{v}"] = MeanMetric()
        for name in ("rre", "rte", "pose_auc30"):  # predicted context cameras (shared by all variants)
            m[name] = MeanMetric()
        self.metrics = nn.ModuleDict(m)

    def update(self, variant: str, pred: Tensor, target: Tensor) -> None:
        p, t = pred.float().clamp(0, 1), target.float()
        self.metrics[f"psnr_{variant}"].update(p, t)
        if f"ssim_{variant}" in self.metrics:
            self.metrics[f"ssim_{variant}"].update(p, t)

    def update_depth(self, variant: str, abs_rel: Tensor, delta1: Tensor, valid: Tensor) -> None:
        if bool(valid.any()):
            self.metrics[f"abs_rel_{variant}"].update(abs_rel[valid])
            self.metrics[f"delta1_{variant}"].update(delta1[valid])

    def update_pose(self, pred_w2c: Tensor, gt_w2c: Tensor) -> None:
        """Relative pose errors of every context view pair, ``[B, V, 4, 4]`` predicted and ground truth."""
        if pred_w2c.shape[1] < 2:
            return
        rre, rte = relative_pose_errors(pred_w2c, gt_w2c)
        self.metrics["rre"].update(rre)
        self.metrics["rte"].update(rte)
        self.metrics["pose_auc30"].update(pose_auc(rre, rte, 30))

    def items(self):
        return self.metrics.items()
