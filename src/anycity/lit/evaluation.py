"""Evaluation helpers: refine the predicted context cameras from the context images (test-time camera
refinement), map ground-truth cameras into the predicted frame (Sim(3) fit of the context cameras), refine them
photometrically (test-time target pose alignment), and accumulate PSNR / SSIM / depth / pose metrics with
torchmetrics (DDP-safe)."""

from __future__ import annotations

from typing import Literal

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix
from torch import Tensor, nn
from torchmetrics import MeanMetric
from torchmetrics.image import PeakSignalNoiseRatio

from anycity.geometry import camera_centers, invert_rigid, transform_points, umeyama
from anycity.geometry.rotations import quat_multiply, rotmat_to_quat
from anycity.metrics.image import ssim
from anycity.metrics.pose import pose_auc, relative_pose_errors
from anycity.render.sh import sh_rotation
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


def fit_gt_to_pred(pred_w2c: Tensor, gt_w2c: Tensor, mode: AlignMode = "sim3",
                   anchor_first: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Similarity ``p_pred = s R p_gt + t`` between the ground-truth and predicted context frames.

    Args:
        pred_w2c, gt_w2c: ``[B, V, 4, 4]`` the same context views, predicted and ground truth.
        mode: ``"sim3"`` (Umeyama fit; as ``"none"`` when V == 1) or ``"none"`` (the first-camera convention,
            unscaled: the ground truth's scale is taken as the network's own). ``"none"`` maps the first
            ground-truth camera onto the origin, where training pins the network's first camera (the identity
            for context views, whose first camera is the origin, but not for the D2S teacher's dense views).
        anchor_first: with ``"none"``, map the first ground-truth camera onto the network's first camera as it
            predicted it instead: evaluation places targets relative to the first context view, and the network
            never puts it exactly at the origin (1-3 deg off for the quickstart model).
    Returns:
        ``s [B]``, ``R [B, 3, 3]``, ``t [B, 3]`` (float32, no gradient).
    """
    b = pred_w2c.shape[0]
    first = gt_w2c[:, 0].detach().float().to(pred_w2c.device)
    ident = (torch.ones(b, device=pred_w2c.device), first[:, :3, :3], first[:, :3, 3])
    if mode == "none" or pred_w2c.shape[1] < 2:
        if not anchor_first:
            return ident
        # a point's coordinates in the first camera are the same in both frames: R0p x_p + t0p = R0g x_g + t0g
        pred0 = pred_w2c[:, 0].detach().float()
        Rt = pred0[:, :3, :3].transpose(-1, -2)
        return ident[0], Rt @ first[:, :3, :3], (Rt @ (first[:, :3, 3] - pred0[:, :3, 3])[..., None])[..., 0]
    if mode != "sim3":
        raise ValueError(f"eval_align: expected 'sim3' or 'none', got {mode!r}")
    finite = torch.isfinite(pred_w2c).flatten(1).all(1) & torch.isfinite(gt_w2c).flatten(1).all(1)
    with torch.no_grad(), torch.autocast(pred_w2c.device.type, enabled=False):  # SVD raises on NaN: one rank would
        s, R, t = umeyama(_frame_points(gt_w2c.float().nan_to_num()),  # die while the others wait (DDP)
                          _frame_points(pred_w2c.float().nan_to_num()))
    ok = finite & torch.isfinite(s) & (s > 0) & torch.isfinite(R).flatten(1).all(1) & torch.isfinite(t).all(1)
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
    """Rigid world-to-world transforms of a batch of B scenes: centres, rotations and the SH bands (a view's
    colour field turns with its Gaussians, ``render.sh.sh_rotation``).

    ``A [B, 4, 4]`` moves each scene; ``A [B, V, 4, 4]`` moves each view's pixel-aligned Gaussians (N = V*H*W in
    view order, as the network emits them without voxel merging) by its own transform.
    """
    per_view = A[:, None] if A.dim() == 3 else A
    b, n = g.means.shape[:2]
    v = per_view.shape[1]
    if n % v:
        raise ValueError(f"transform_gaussians: {n} Gaussians do not split into {v} views of pixel-aligned "
                         "Gaussians; per-view transforms need the network's unmerged output (voxel_size=None)")
    means = transform_points(per_view, g.means.unflatten(1, (v, n // v)))
    rot = rotmat_to_quat(per_view[..., :3, :3])[:, :, None].expand(b, v, n // v, 4)
    quats = quat_multiply(rot, g.quats.unflatten(1, (v, n // v)))
    sh = g.sh
    if g.sh_degree >= 1:
        D = sh_rotation(per_view[..., :3, :3], g.sh_degree).to(sh.dtype)  # [B, V, K, K]
        sh = torch.einsum("bvij,bvnjc->bvnic", D, sh.unflatten(1, (v, n // v))).flatten(1, 2)
    return Gaussians(means.flatten(1, 2), quats.flatten(1, 2), g.scales, g.opacities, sh, g.valid)


def _se3(rot: Tensor, trans: Tensor) -> Tensor:
    """Axis-angle ``[..., 3]`` and translation ``[..., 3]`` -> ``[..., 4, 4]`` rigid transforms."""
    out = torch.eye(4, device=rot.device).expand(*rot.shape[:-1], 4, 4).clone()
    out[..., :3, :3] = axis_angle_to_rotation_matrix(rot.reshape(-1, 3)).reshape(*rot.shape[:-1], 3, 3)
    out[..., :3, 3] = trans
    return out


def _fit_deltas(loss_fn, shape: tuple[int, ...], device, steps: int, lr: float) -> tuple[Tensor, Tensor]:
    """Adam on zero-initialised axis-angle and translation deltas of ``shape + (3,)``; ``loss_fn(rot, trans)``."""
    rot = torch.zeros(*shape, 3, device=device, requires_grad=True)
    trans = torch.zeros(*shape, 3, device=device, requires_grad=True)
    opt = torch.optim.Adam([rot, trans], lr=lr)
    for _ in range(steps):
        loss = loss_fn(rot, trans)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return rot.detach(), trans.detach()


def _frozen(g: Gaussians, repeats: int) -> Gaussians:
    """Detached copies of the B scenes, each repeated ``repeats`` times (normal tensors even when ``g`` was made
    under inference mode)."""
    return Gaussians(*(None if x is None else x.detach().repeat_interleave(repeats, dim=0).clone()
                       for x in (g.means, g.quats, g.scales, g.opacities, g.sh, g.valid)))


def align_target_poses(render_rgb, gaussians: Gaussians, w2c: Tensor, images: Tensor, steps: int = 100,
                       lr: float = 0.005) -> Tensor:
    """Test-time pose alignment of target cameras (AnySplat's ``test.align_pose``; NoPoSplat's protocol).

    A pose-free model's scene sits in its own frame, so each held-out camera is refined photometrically before it
    is scored: Adam on a camera-frame rotation (axis-angle) and translation delta, Gaussians frozen, MSE against the
    target image (per sample, summed over the batch: a sample's fit does not depend on its batch-mates). The camera
    moves by moving the scene the opposite way (the same image, and it needs no camera gradient from the backend).

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
        scenes = _frozen(gaussians, t)
        target = images.detach().float().reshape(b * t, 1, *images.shape[2:]).clone()

        def loss(rot: Tensor, trans: Tensor) -> Tensor:
            # camera delta @ w2c == w2c applied to the scene moved by inv(w2c) @ delta @ w2c
            moved = transform_gaussians(scenes, inv @ _se3(rot, trans) @ cams)
            # each sample's own mean, summed: a sample is fitted as if alone, whatever the batch holds
            return (render_rgb(moved, cams[:, None]) - target).square().reshape(b, -1).mean(1).sum()

        rot, trans = _fit_deltas(loss, (b * t,), cams.device, steps, lr)
        out = (_se3(rot, trans) @ cams).reshape(b, t, 4, 4)
    return out.to(w2c.dtype)


def refine_context_cameras(render_rgb, gaussians: Gaussians, w2c: Tensor, images: Tensor, steps: int = 50,
                           lr: float = 0.01) -> tuple[Tensor, Tensor]:
    """Test-time refinement of the predicted context cameras from the context images alone (a photometric bundle
    adjustment with the structure frozen).

    Every view's pixel-aligned Gaussians ride on that view's camera, so a camera error shows up as the views'
    Gaussian sets disagreeing. Each view but the first (the reference frame) gets a rigid delta, a rotation about
    the point at its Gaussians' median depth on its optical axis (an orbit-like correction is then one rotation
    instead of a coupled rotation and translation) plus a translation, fitted by Adam so that all views' Gaussians,
    rendered together into every context camera, reproduce the context images (MSE per sample, summed over the
    batch). No target image is used.
    Each step renders V scenes of V*H*W Gaussians (cost grows as V^2 H W): meant for a sparse context.

    Args:
        render_rgb: ``f(gaussians [B*V scenes], w2c [B*V, 1, 4, 4]) -> rgb [B*V, 1, 3, H, W]``; scene ``b*V + i``
            is rendered into context camera ``i`` of scene ``b``.
        gaussians: B scenes of N = V*H*W pixel-aligned Gaussians in view order (no gradient needed).
        w2c: ``[B, V, 4, 4]`` predicted context cameras. images: ``[B, V, 3, H, W]`` the context images.
    Returns:
        ``w2c [B, V, 4, 4]``, the refined cameras (the first unchanged), and ``A [B, V, 4, 4]``, the world transform
        of each view's Gaussians (:func:`transform_gaussians`) that puts the scene in agreement with them: view i's
        Gaussians moved by ``A_i`` project through ``w2c_i`` exactly as before through the predicted camera.
    """
    b, v = w2c.shape[:2]
    eye = torch.eye(4, device=w2c.device, dtype=w2c.dtype).expand(b, v, 4, 4)
    if steps <= 0 or v < 2:
        return w2c, eye
    n = gaussians.means.shape[1]
    if gaussians.valid is not None or n % v:
        raise ValueError(f"camera refinement: expected {v} views of pixel-aligned Gaussians, got {n} Gaussians"
                         f"{' with a valid mask' if gaussians.valid is not None else ''}; it needs the network's "
                         "unmerged output (net.voxel_size=None)")
    with torch.inference_mode(False), torch.enable_grad():  # Lightning evaluates and predicts under inference mode
        cams = w2c.detach().float().clone()
        inv = invert_rigid(cams)
        scenes = _frozen(gaussians, v)
        target = images.detach().float().reshape(b * v, 1, *images.shape[2:]).clone()
        z = transform_points(cams, scenes.means[::v].unflatten(1, (v, n // v)))[..., 2]  # [B, V, HW] camera z
        pivot = torch.eye(4, device=cams.device).repeat(b, v, 1, 1)
        pivot[..., 2, 3] = z.median(dim=-1).values
        first = torch.zeros(b, 1, 3, device=cams.device)

        def transforms(rot: Tensor, trans: Tensor) -> Tensor:  # [B, V, 4, 4] world transforms, view 0 fixed
            d = _se3(torch.cat([first, rot], 1), torch.cat([first, trans], 1))
            return inv @ pivot @ d @ invert_rigid(pivot) @ cams

        def loss(rot: Tensor, trans: Tensor) -> Tensor:
            A = transforms(rot, trans)
            # scene (b, i): view j's Gaussians moved by inv(A_i) A_j, seen through the predicted camera i, which is
            # the moved scene seen through the refined camera w2c_i inv(A_i)
            rel = (invert_rigid(A)[:, :, None] @ A[:, None]).flatten(0, 1)  # [B*V, V, 4, 4]
            moved = transform_gaussians(scenes, rel)
            err = (render_rgb(moved, cams.flatten(0, 1)[:, None]) - target).square()
            return err.reshape(b, -1).mean(1).sum()  # per sample, summed: as if alone in the batch

        rot, trans = _fit_deltas(loss, (b, v - 1), cams.device, steps, lr)
        A = transforms(rot, trans)
        out = cams @ invert_rigid(A)
    return out.to(w2c.dtype), A.to(w2c.dtype)


def _update_defined(metric: MeanMetric, values: Tensor) -> None:
    """Average the per-image values that are defined: NaN marks an image whose region is empty. A region rendered
    exactly (PSNR +inf) counts, as it does in the whole-image PSNR."""
    values = values[~torch.isnan(values)]
    if values.numel():
        metric.update(values)


def scored_targets(index: Tensor | None) -> Tensor | None:
    """``[B*T]`` bool: False for a target that repeats an earlier one of its sample (trajectory positions
    ``index [B, T]``). Evaluation pads a sample's last chunk of held-out views with its own views, so that batches
    stack; each held-out view is scored once. None when the views carry no positions."""
    if index is None:
        return None
    t = index.shape[1]
    earlier = torch.ones(t, t, dtype=torch.bool, device=index.device).tril(-1)  # [i, j]: j before i
    return ~((index[:, :, None] == index[:, None, :]) & earlier).any(-1).flatten()


PROTOCOL_SUFFIXES = ("", "_camrefine", "_targetalign", "_joint")  # feedforward first, unsuffixed
REGIONS = ("obs", "weak")


class EvalMetrics(nn.Module):
    """Per-image PSNR (torchmetrics) and SSIM (:func:`anycity.metrics.image.ssim`, skimage's default), their
    region-masked versions and depth / pose errors, for named variants under each evaluation protocol
    (:mod:`anycity.lit.protocols`).

    Names (``<v>`` a variant, ``<p>`` a protocol suffix: none for ``feedforward``, ``_camrefine``,
    ``_targetalign``, ``_joint``):
    ``psnr_<v><p>``, ``ssim_<v><p>``; ``psnr_obs_<v><p>``, ``psnr_weak_<v><p>``, ``ssim_obs_<v><p>``,
    ``ssim_weak_<v><p>`` (mean over images of the PSNR / SSIM inside the observation-supported / weak pixels of
    :func:`anycity.metrics.regions.region_masks`; images where a region is empty are skipped; SSIM as
    :mod:`anycity.metrics.image` defines it), ``lpips_<v><p>``, ``lpips_obs_*`` and ``lpips_weak_*`` when an
    offline LPIPS is given (one spatial map per image, :func:`anycity.metrics.regions.lpips_map`); ``region_obs``,
    ``region_weak`` (the regions' share of target pixels); ``psnr_baseline`` and ``psnr_nearest`` (+ ``_obs`` /
    ``_weak``) of the reference renders; ``abs_rel_<v>``, ``delta1_<v>`` (feed-forward depth); ``rre``, ``rte``,
    ``pose_auc30`` of the network's context cameras over all view pairs (degrees; AUC@30 in [0, 1]) and
    ``rre_<v>_camrefine`` etc. after the context-camera refinement; with ``scaffold_pose`` (Stage II re-places the
    cameras, ``net.refine_cameras``) also ``rre_scaffold`` etc. of the scaffold's own cameras.

    ``update(name, pred, target, regions)`` takes ``[M, 3, H, W]`` images (``name`` = ``<v><p>``, ``baseline`` or
    ``nearest``) and optionally the ``(observed, weak)`` masks ``[B, T, 1, H, W]``. ``items()`` yields the metrics
    that were updated, ready for ``LightningModule.log``.
    """

    def __init__(self, variants: tuple[str, ...], lpips=None, scaffold_pose: bool = False) -> None:
        super().__init__()
        self.variants = variants
        # torchmetrics LPIPS or None (:func:`anycity.metrics.regions.lpips_or_none`); not registered as a submodule, so
        # its backbone never enters checkpoints (which then load the same with or without LPIPS on the machine)
        object.__setattr__(self, "lpips", lpips)
        names = [f"{v}{p}" for v in variants for p in PROTOCOL_SUFFIXES] + ["baseline", "nearest"]
        m: dict[str, nn.Module] = {}
        for n in names:
            m[f"psnr_{n}"] = PeakSignalNoiseRatio(data_range=1.0, dim=(1, 2, 3), reduction="elementwise_mean")
            for r in REGIONS:
                m[f"psnr_{r}_{n}"] = MeanMetric()
            if n not in ("baseline", "nearest"):
                m[f"ssim_{n}"] = MeanMetric()
                if lpips is not None:
                    m[f"lpips_{n}"] = MeanMetric()
                for r in REGIONS:
                    m[f"ssim_{r}_{n}"] = MeanMetric()
                    if lpips is not None:
                        m[f"lpips_{r}_{n}"] = MeanMetric()
        for r in REGIONS:
            m[f"region_{r}"] = MeanMetric()
        for v in variants:
            m[f"abs_rel_{v}"] = MeanMetric()
            m[f"delta1_{v}"] = MeanMetric()
        for suffix in ("", *(f"_{v}_camrefine" for v in variants), *(("_scaffold",) if scaffold_pose else ())):
            for name in ("rre", "rte", "pose_auc30"):
                m[f"{name}{suffix}"] = MeanMetric()
        self.metrics = nn.ModuleDict(m)

    def update(self, name: str, pred: Tensor, target: Tensor, regions: tuple[Tensor, Tensor] | None = None,
               keep: Tensor | None = None) -> None:
        """Score ``pred``/``target [M, 3, H, W]`` (regions ``[B, T, 1, H, W]`` with ``M = B*T``); ``keep [M]`` bool
        (:func:`scored_targets`) leaves out the targets a batch repeats."""
        p, t = pred.float().clamp(0, 1), target.float()
        if keep is not None:
            p, t = p[keep], t[keep]
        from anycity.metrics.regions import lpips_map, masked_mean, masked_psnr, masked_ssim

        self.metrics[f"psnr_{name}"].update(p, t)
        has_ssim = f"ssim_{name}" in self.metrics
        if has_ssim:
            _update_defined(self.metrics[f"ssim_{name}"], ssim(p, t))
        lmap = None
        if has_ssim and self.lpips is not None:
            lmap = lpips_map(self.lpips.to(p.device), p, t)  # [M, 1, H, W], once for the image and its regions
            self.metrics[f"lpips_{name}"].update(lmap.mean(dim=(1, 2, 3)))
        if regions is None:
            return
        for r, mask in zip(REGIONS, regions):
            mk = mask.flatten(0, 1) if keep is None else mask.flatten(0, 1)[keep]
            _update_defined(self.metrics[f"psnr_{r}_{name}"], masked_psnr(p, t, mk))
            if has_ssim:
                _update_defined(self.metrics[f"ssim_{r}_{name}"], masked_ssim(p, t, mk))
            if lmap is not None:
                _update_defined(self.metrics[f"lpips_{r}_{name}"], masked_mean(lmap, mk))

    def update_regions(self, regions: tuple[Tensor, Tensor] | None, keep: Tensor | None = None) -> None:
        """The share of target pixels in each region, per image (``keep`` as in :meth:`update`)."""
        if regions is not None:
            for r, mask in zip(REGIONS, regions):
                share = mask.flatten(0, 1).float().mean(dim=(1, 2, 3))
                self.metrics[f"region_{r}"].update(share if keep is None else share[keep])

    def update_depth(self, variant: str, abs_rel: Tensor, delta1: Tensor, valid: Tensor) -> None:
        if bool(valid.any()):
            self.metrics[f"abs_rel_{variant}"].update(abs_rel[valid])
            self.metrics[f"delta1_{variant}"].update(delta1[valid])

    def update_pose(self, pred_w2c: Tensor, gt_w2c: Tensor, name: str | None = None) -> None:
        """Relative pose errors of every context view pair, ``[B, V, 4, 4]`` predicted and ground truth; under
        ``rre_<name>`` etc. when ``name`` is given (e.g. ``refined_camrefine``)."""
        if pred_w2c.shape[1] < 2:
            return
        suffix = f"_{name}" if name else ""
        rre, rte = relative_pose_errors(pred_w2c, gt_w2c)
        self.metrics[f"rre{suffix}"].update(rre)
        self.metrics[f"rte{suffix}"].update(rte)
        self.metrics[f"pose_auc30{suffix}"].update(pose_auc(rre, rte, 30))

    def items(self):
        return self.metrics.items()
