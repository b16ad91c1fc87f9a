"""Shared LightningModule machinery for both stages: the network, rendering, optimiser and schedule,
evaluation on held-out target views and prediction.

Stage-specific training lives in :mod:`anycity.lit.scaffold` (Stage I) and :mod:`anycity.lit.refinement`
(Stage II). Only this package, ``callbacks`` and ``cli`` import Lightning.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
import typing
from collections.abc import Iterator
from dataclasses import fields
from fnmatch import fnmatchcase
from typing import Any, Literal, TypedDict

import lightning.pytorch as pl
import torch
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from torch import Tensor

from anycity.callbacks.nonfinite import all_finite
from anycity.lit.distributed import log_eval_metrics, union_over_ranks
from anycity.lit.evaluation import (
    AlignMode,
    EvalMetrics,
    align_target_poses,
    cameras_in_pred_frame,
    fit_gt_to_pred,
    refine_context_cameras,
    scored_targets,
    transform_gaussians,
)
from anycity.metrics import depth_metrics, mean_colour_baseline, nearest_view_reference
from anycity.models.presets import NetConfig
from anycity.structures import Gaussians, RenderOutput, ViewBatch, Views

Preset = Literal["tiny", "small", "base", "vggt-1b"]
RenderBackend = Literal["auto", "torch", "cpu", "gsplat"]
BackgroundMode = Literal["fixed", "context_mean"]
PretrainedKind = Literal["vggt", "anysplat"]


def float32_outside_net(step):
    """Run a LightningModule step with autocast off, except in :meth:`AnyCityModule.forward_net`, which keeps the
    trainer's precision (``bf16-mixed``) for the network's trunk. Lightning runs every step under autocast; left on,
    the losses', metrics' and test-time fits' matmuls and convolutions (SSIM, reprojection, Sim(3) transfers) would
    run in bf16: SSIM reads about 0.02 high and ray anchoring gets a 0.2 px noise floor."""

    @functools.wraps(step)
    def wrapped(self, *args, **kwargs):
        dev, outer = self.device.type, getattr(self, "_net_autocast", None)
        self._net_autocast = (dev, torch.is_autocast_enabled(dev), torch.get_autocast_dtype(dev))
        try:
            with torch.autocast(dev, enabled=False):
                return step(self, *args, **kwargs)
        finally:
            self._net_autocast = outer

    return wrapped


_NET_HINTS = typing.get_type_hints(NetConfig)
# Overrides of a preset's NetConfig fields; a TypedDict so that a misspelt key fails when the config is parsed.
NetOverrides = TypedDict("NetOverrides", {f.name: _NET_HINTS[f.name] for f in fields(NetConfig)}, total=False)


# Lightning refuses gradient clipping under mixed precision with an optimiser that unscales inside its own step, as
# torch's fused AdamW does: those runs keep foreach
FUSED_ADAMW_PRECISIONS = ("32-true",)


def check_precision(precision: str) -> None:
    """Refuse a ``trainer.precision`` that casts the whole module (``64-true``, ``bf16-true``, ``16-true``): the
    heads, losses and renderer run in float32, so those fail with a dtype error in the first step."""
    if precision.endswith("-true") and precision != "32-true":
        raise ValueError(f"trainer.precision {precision}: the heads, losses and renderer run in float32; use "
                         "bf16-mixed (GPU) or 32-true")


def make_adamw(param_groups: list[dict], lr: float, fused: bool) -> torch.optim.AdamW:
    """AdamW with betas (0.9, 0.95). ``fused``: torch's one-kernel step over all tensors (on 2 CPU cores 7.9 ms a
    step for the tiny preset's 512 tensors, against 28 ms for foreach; the same update up to float rounding); else
    foreach, torch's CUDA default (on CPU torch would otherwise loop per tensor: the same bits, 30 % slower)."""
    kernel = {"fused": True} if fused else {"foreach": True}
    return torch.optim.AdamW(param_groups, lr=lr, betas=(0.9, 0.95), **kernel)


def warmup_cosine(step: int, warmup: int, total: int, min_ratio: float) -> float:
    """LR multiplier: linear warm-up over ``warmup`` steps, then cosine from 1 to ``min_ratio`` at ``total``."""
    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def schedule_steps(trainer: pl.Trainer) -> int:
    """The optimiser steps an LR schedule spans: ``trainer.max_steps`` (with ``accumulate_grad_batches`` too, a
    step is one optimiser step). Not Lightning's ``estimated_stepping_batches``: for the shard stream, which has no
    length, that is ``max_steps`` anyway, or -1 / inf when only ``max_epochs`` ends the run; and with
    ``max_epochs`` set, reading it builds the training loader before a resumed run's batch count is restored, so
    the resumed run trained again on the samples it had already seen."""
    steps = trainer.max_steps
    if steps is None or steps <= 0:
        raise ValueError(f"trainer.max_steps is {steps}: the LR schedule is sized by it (the shard stream has no "
                         "length, so max_epochs cannot size it); set --trainer.max_steps N")
    return int(steps)


_RESUMING = contextvars.ContextVar("anycity_resuming", default=False)


@contextlib.contextmanager
def resuming() -> Iterator[None]:
    """Modules built in this block are for a ``fit`` that resumes from a checkpoint file: its weights replace the
    pretrained ones, so ``pretrained`` (kept in the hyperparameters: it says what the run started from) is not read;
    the machine that resumes may not have that file."""
    token = _RESUMING.set(True)
    try:
        yield
    finally:
        _RESUMING.reset(token)


class AnyCityModule(pl.LightningModule):
    """Base of :class:`ScaffoldModule` and :class:`RefinementModule` (not used directly).

    Args:
        preset: network size preset (``anycity.models.build_network``).
        net: keyword overrides of the preset (e.g. ``{"sh_degree": 1}``); unknown keys fail at construction.
        pretrained: local VGGT / AnySplat checkpoint loaded into the scaffold, or None (random init).
        pretrained_kind: layout of ``pretrained`` ("vggt" model.pt or "anysplat").
        lr: peak learning rate of AdamW.
        weight_decay: AdamW weight decay (not applied to biases and norms).
        pretrained_lr_scale: LR multiplier of parameters matching ``pretrained_patterns`` (with ``pretrained``
            weights only: from random init they train at the full rate).
        pretrained_patterns: glob patterns (over ``net.`` parameter names) of pretrained layers.
        warmup_steps: linear LR warm-up steps; the cosine decay spans the rest of the run.
        min_lr_ratio: final LR as a fraction of ``lr``.
        render_backend: renderer backend ("auto" picks gsplat on CUDA, the fused CPU kernels on CPU).
        render_pose_grad: the render losses reach the predicted poses (``w2c``) they render with, as in AnySplat;
            False renders at detached poses (the poses then learn only from the camera loss and from placing the
            Gaussians). Either way the intrinsics render detached (gsplat gives them no gradient), and every
            backend trains the same way.
        background: RGB background of the renders (``background_mode="fixed"``).
        background_mode: "fixed" uses ``background``; "context_mean" fills pixels no Gaussian covers with the
            mean colour of the scene's context images (a prediction from the inputs alone).
        eval_align: how target cameras enter the predicted frame at evaluation (and when rendering targets in
            training): "sim3" fits the predicted context cameras to the ground truth; "none" uses the shared
            convention, unscaled: the targets' ground-truth poses relative to the first context camera, applied
            to the network's first camera as predicted (at evaluation) or to the origin, where training pins it.
        eval_pose_align_steps: ``test`` only, the ``targetalign`` protocol (:mod:`anycity.lit.protocols`): each
            placed target camera refined photometrically against its own target image before it is scored (Adam
            steps on a rotation and translation delta with the Gaussians frozen, AnySplat's ``test.align_pose``,
            which uses 100 steps), logged as ``*_targetalign``; 0 = off. It starts from the ``camrefine`` cameras
            when ``camera_refine_steps > 0``.
        eval_pose_align_lr: Adam learning rate of that alignment (AnySplat: 0.005; radians and scene units).
        eval_joint: ``test`` only, the ``joint`` protocol (AnySplat / WorldMirror): context and target images through
            the network together, targets rendered at the network's own target cameras; logged as ``*_joint``.
        camera_refine_steps: test-time refinement of the predicted context cameras from the context images alone, in
            ``test`` (the ``camrefine`` protocol, logged as ``*_camrefine``) and ``predict`` (the exported cameras
            and Gaussians): Adam steps fitting a rigid delta per view so that all views' Gaussians reproduce the
            context images (:func:`~anycity.lit.evaluation.refine_context_cameras`); 0 = off. Each step renders
            all V views' Gaussians into every context camera (cost grows as V^2): meant for a sparse context.
        camera_refine_lr: Adam learning rate of that refinement (radians and scene units).
        gradient_checkpointing: recompute transformer blocks in backward (passed to the network).
    """

    variants: tuple[str, ...] = ("scaffold",)

    def __init__(
        self,
        preset: Preset = "tiny",
        net: NetOverrides | None = None,
        pretrained: str | None = None,
        pretrained_kind: PretrainedKind = "vggt",
        lr: float = 2e-4,
        weight_decay: float = 0.05,
        pretrained_lr_scale: float = 0.1,
        pretrained_patterns: list[str] | None = None,
        warmup_steps: int = 100,
        min_lr_ratio: float = 0.1,
        render_backend: RenderBackend = "auto",
        render_pose_grad: bool = True,
        background: tuple[float, float, float] = (0.0, 0.0, 0.0),
        background_mode: BackgroundMode = "fixed",
        eval_align: AlignMode = "sim3",
        eval_pose_align_steps: int = 0,
        eval_pose_align_lr: float = 0.005,
        eval_joint: bool = False,
        camera_refine_steps: int = 0,
        camera_refine_lr: float = 0.01,
        gradient_checkpointing: bool = False,
    ) -> None:
        super().__init__()
        from anycity.models import build_network

        self.net = build_network(preset, **dict(net or {}))
        if gradient_checkpointing:
            self.net.set_gradient_checkpointing(True)
        if pretrained and _RESUMING.get():
            rank_zero_info(f"model.pretrained {pretrained}: not read, the fit resumes from a checkpoint whose "
                           "weights replace it")
        elif pretrained:
            from anycity.models.pretrained import load_pretrained

            report = load_pretrained(self.net, pretrained, kind=pretrained_kind)
            report.require_backbone(pretrained)
            rank_zero_info(f"model.pretrained {pretrained}: {report}")
        from anycity.metrics.regions import lpips_or_none

        lpips, self.lpips_status = lpips_or_none()  # one line, printed when testing starts
        moved = "refined" in self.variants and self.net.cfg.refine_cameras  # the scaffold's cameras are scored too
        self.val_metrics = EvalMetrics(self.variants, scaffold_pose=moved)
        self.test_metrics = EvalMetrics(self.variants, lpips, scaffold_pose=moved)
        # Called here, Lightning collects the arguments of every __init__ on the stack: the subclass's own and
        # those it passes on in **base, so checkpoints and LightningCLI see one flat set of hyperparameters.
        self.save_hyperparameters()
        if self.net.cfg.focal_decode != (net or {}).get("focal_decode", "vggt"):  # set by an AnySplat checkpoint
            self.hparams.net = {**(net or {}), "focal_decode": self.net.cfg.focal_decode}

    def setup(self, stage: str) -> None:
        # here, before the strategy casts the module to the precision's dtype
        precision = getattr(self._trainer, "precision", None)
        if precision is not None:
            check_precision(str(precision))

    def freeze_unsupervised_pose_token(self, camera_weight: float) -> None:
        """Freeze ``net.camera_head.empty_pose_tokens`` when ``camera_weight`` is 0: it feeds only the camera head's
        first iteration, whose encoding only the camera loss reads (later iterations detach it), so it would get no
        gradient, and DDP with ``find_unused_parameters: false`` stops at the second step. With one iteration the
        final cameras read it, and it trains through them."""
        if camera_weight == 0 and self.net.cfg.camera_iterations > 1:
            self.net.camera_head.empty_pose_tokens.requires_grad_(False)

    # ----------------------------------------------------------------------------------------- rendering
    def render(self, gaussians: Gaussians, w2c: Tensor, K: Tensor, hw: tuple[int, int], context: Tensor,
               normals: bool = False) -> RenderOutput:
        """Render ``gaussians`` into cameras ``w2c [B, V, 4, 4]``, ``K`` (``anycity.render.render`` itself runs in
        float32 outside autocast); ``context [B, V', 3, H', W']`` are the input images (for
        ``background_mode="context_mean"``)."""
        from anycity.render import render

        # Never the intrinsics: gsplat, the training backend on GPUs, gives K no gradient, and CPU training should
        # train the same way.
        K = K.detach()
        if not self.hparams.render_pose_grad:
            w2c = w2c.detach()
        if self.hparams.background_mode == "context_mean":
            bg = context.detach().float().mean(dim=(1, 3, 4))[:, None].expand(-1, w2c.shape[1], -1).contiguous()
        else:
            bg = torch.tensor(self.hparams.background, device=w2c.device, dtype=torch.float32)
        return render(gaussians, w2c, K, hw[1], hw[0], background=bg, render_normals=normals,
                      backend=self.hparams.render_backend)

    def target_cameras(self, pred_w2c: Tensor, context: Views, query: Views,
                       anchor_first: bool = False) -> tuple[Tensor, Tensor]:
        """Ground-truth ``query`` cameras in the predicted frame and the depth scale ``s [B]`` (pred = s * gt);
        ``anchor_first``: see :func:`~anycity.lit.evaluation.fit_gt_to_pred` (evaluation's placement)."""
        s, R, t = fit_gt_to_pred(pred_w2c.detach(), context.w2c, self.hparams.eval_align, anchor_first)
        return cameras_in_pred_frame(query.w2c, s, R, t), s

    # ----------------------------------------------------------------------------------------- optimiser
    def configure_optimizers(self) -> dict[str, Any]:
        hp = self.hparams
        patterns = [p if p.startswith("net.") else f"net.{p}" for p in (hp.pretrained_patterns or [])]
        from anycity.callbacks.freeze import require_matches

        require_matches(self, patterns, "model.pretrained_patterns:")  # a typo: pretrained layers at the full rate
        # the groups are the same with or without weights (so a resumed run's optimiser state fits), but layers
        # trained from random init are not slowed down as pretrained ones
        scale = hp.pretrained_lr_scale if hp.pretrained else 1.0
        groups: dict[tuple[bool, bool], list[Tensor]] = {}
        for name, p in self.named_parameters():
            if not p.requires_grad:
                continue
            pretrained = any(fnmatchcase(name, pat) for pat in patterns)
            no_decay = p.ndim < 2 or "norm" in name or name.endswith(".bias")
            groups.setdefault((pretrained, no_decay), []).append(p)
        if not groups:
            raise ValueError("configure_optimizers: no trainable parameters; check the freeze patterns")
        param_groups = [{"params": ps, "lr": hp.lr * (scale if pre else 1.0),
                         "weight_decay": 0.0 if nd else hp.weight_decay} for (pre, nd), ps in groups.items()]
        opt = make_adamw(param_groups, hp.lr, fused=self.fused_adamw_allowed())
        total = schedule_steps(self.trainer)
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda s: warmup_cosine(s, hp.warmup_steps, total, hp.min_lr_ratio))
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def fused_adamw_allowed(self) -> bool:
        """Full precision (:data:`FUSED_ADAMW_PRECISIONS`) and every trainable tensor on a CPU or CUDA device."""
        precision = str(getattr(self._trainer, "precision", ""))
        return precision in FUSED_ADAMW_PRECISIONS and all(
            p.device.type in ("cpu", "cuda") for p in self.parameters() if p.requires_grad)

    def on_train_start(self) -> None:
        # a resumed optimiser takes its kernel flags from the checkpoint: one saved by a full-precision run is
        # fused, which a mixed-precision run with gradient clipping cannot step
        if not self.fused_adamw_allowed():
            for opt in self.trainer.optimizers:
                for group in opt.param_groups:
                    if group.get("fused"):
                        group["fused"], group["foreach"] = False, True

    def nonfinite_forward(self, out: dict) -> Tensor | None:
        """None when the network's Gaussians and cameras are finite; else a NaN loss wired to every trainable
        parameter. Rendering a NaN scene raises (on this rank alone, while the other DDP ranks wait in backward);
        this loss lets backward run on every rank and the ``nonfinite`` callback skip the step everywhere."""
        g = out["gaussians"]
        parts = [g.means, g.quats, g.scales, g.opacities, g.sh, out["w2c"], out["K"]]
        if all_finite(parts):
            return None
        return sum(p.sum() for p in self.parameters() if p.requires_grad) * float("nan")

    # ----------------------------------------------------------------------------------------- logging
    def log_terms(self, terms: dict[str, Tensor], batch_size: int, prog_bar: tuple[str, ...] = ()) -> None:
        for k, v in terms.items():
            self.log(f"train/{k}", v.detach(), batch_size=batch_size, prog_bar=k in prog_bar)

    # ----------------------------------------------------------------------------------------- evaluation
    def forward(self, images: Tensor, **kwargs) -> dict[str, Any]:
        """``module(images)``: the network's forward (:meth:`anycity.models.AnyCityNet.forward`; ``images``
        ``[B, V, 3, H, W]`` in [0, 1]), so a module loaded with ``load_from_checkpoint`` runs like its ``net``."""
        return self.forward_net(images, **kwargs)

    def forward_net(self, images: Tensor, **kwargs) -> dict[str, Any]:
        """``self.net(images, **kwargs)`` under the autocast the running step was entered with (see
        :func:`float32_outside_net`; the network keeps its heads in float32 itself)."""
        if getattr(self, "_net_autocast", None) is None:  # called outside a step: the caller's autocast holds
            return self.net(images, **kwargs)
        dev, enabled, dtype = self._net_autocast
        with torch.autocast(dev, dtype=dtype, enabled=enabled):
            return self.net(images, **kwargs)

    def predict_variants(self, images: Tensor) -> tuple[dict[str, Any], dict[str, Gaussians]]:
        """Network outputs and the Gaussians to score: ``{"scaffold"}`` (+ ``"refined"`` in Stage II)."""
        out = self.forward_net(images, refine="refined" in self.variants)
        scaffold = out.get("scaffold_gaussians") or out["gaussians"]
        variants = {"scaffold": scaffold}
        if "refined" in self.variants:
            variants["refined"] = out["gaussians"]
        return out, variants

    @staticmethod
    def variant_cameras(out: dict[str, Any], name: str) -> tuple[Tensor, Tensor]:
        """``(w2c, K)`` that variant ``name``'s Gaussians were placed with: the scaffold's cameras for
        ``"scaffold"``, the network's final ones (re-placed in Stage II with ``net.refine_cameras``) otherwise."""
        if name == "scaffold":
            return out.get("scaffold_w2c", out["w2c"]), out.get("scaffold_K", out["K"])
        return out["w2c"], out["K"]

    def _warn_unscaled_placement(self, ctx: Views) -> None:
        """Once: ``eval_align none`` takes the ground truth's scale as the network's, which holds for a frame scaled
        by its context's median depth (as the network is trained), not for one scaled by its cameras' spread (a
        sample with no ground-truth depth, e.g. COLMAP)."""
        if self.hparams.eval_align != "none" or ctx.depth is not None or getattr(self, "_told_unscaled", False):
            return
        self._told_unscaled = True
        rank_zero_warn("eval_align none: a batch has no ground-truth depth, so its frame is scaled by its context "
                       "cameras' spread, not by the median depth the network learns, and its targets are placed at a "
                       "scale the network does not share; pass --model.init_args.eval_align sim3 (a fit to the "
                       "context cameras only) to place them at the network's scale")

    @torch.no_grad()
    @float32_outside_net
    def evaluate(self, batch: ViewBatch, metrics: EvalMetrics, want_preview: bool, protocols: tuple[str, ...] = (
            "feedforward",)) -> dict[str, Any] | None:
        """Score every variant on the batch's targets under each of ``protocols`` (see :mod:`anycity.lit.protocols`,
        which says which images each reads). ``feedforward`` always runs and is logged without a suffix
        (``psnr_<variant>``); the others add ``_camrefine``, ``_targetalign`` and ``_joint``. ``targetalign`` starts
        from the ``camrefine`` cameras when that protocol runs too. Region-masked figures (``psnr_obs_*``,
        ``psnr_weak_*``) come from :func:`anycity.metrics.regions.region_masks` on the ground truth."""
        from anycity.lit import protocols as P

        ctx, tgt = batch.context, batch.target
        self._warn_unscaled_placement(ctx)
        cams = P.TargetCameras.of(tgt)
        out, variants = self.predict_variants(ctx.images)
        gt = tgt.images.flatten(0, 1)
        regions = self.region_masks(ctx, tgt)
        keep = scored_targets(tgt.index)  # a padded chunk's repeated targets are scored once
        metrics.update_regions(regions, keep)
        metrics.update("baseline", mean_colour_baseline(ctx.images, tuple(tgt.images.shape)).flatten(0, 1), gt,
                       regions, keep)
        metrics.update_pose(out["w2c"], ctx.w2c)
        if out.get("scaffold_w2c") is not None and out["scaffold_w2c"] is not out["w2c"]:
            metrics.update_pose(out["scaffold_w2c"], ctx.w2c, "scaffold")
        if ctx.index is not None and tgt.index is not None and ctx.hw == tgt.hw:
            metrics.update("nearest", nearest_view_reference(ctx.images, ctx.index, tgt.index).flatten(0, 1), gt,
                           regions, keep)
        preview = {"context": ctx.images[0, :1].expand(tgt.num_views, -1, -1, -1), "target": tgt.images[0]}
        hp = self.hparams
        joint = P.joint(self, ctx, tgt)[0] if "joint" in protocols else None
        for name, g in variants.items():
            scene = P.Scene(g, *self.variant_cameras(out, name))
            r, s = P.feedforward(self, scene, ctx, cams)
            metrics.update(name, r.rgb.flatten(0, 1), gt, regions, keep)
            if tgt.depth is not None:
                d = depth_metrics(r.depth / s[:, None, None, None, None], tgt.depth, tgt.mask)
                metrics.update_depth(name, d["abs_rel"], d["delta1"], d["valid"] if keep is None else d["valid"] & keep)
            preview[name] = r.rgb[0]
            preview[f"{name}_depth"] = r.depth[0]
            if "camrefine" in protocols and hp.camera_refine_steps > 0:
                r_ref, _, scene = P.camrefine(self, scene, ctx, cams, hp.camera_refine_steps)
                metrics.update(f"{name}_camrefine", r_ref.rgb.flatten(0, 1), gt, regions, keep)
                metrics.update_pose(scene.w2c, ctx.w2c, f"{name}_camrefine")
            if "targetalign" in protocols and hp.eval_pose_align_steps > 0:
                r_al, _ = P.targetalign(self, scene, ctx, tgt, hp.eval_pose_align_steps)
                metrics.update(f"{name}_targetalign", r_al.rgb.flatten(0, 1), gt, regions, keep)
            if joint is not None:
                metrics.update(f"{name}_joint", joint[name].rgb.flatten(0, 1), gt, regions, keep)
        if not want_preview:
            return None
        from anycity.callbacks.previews import depth_to_rgb, region_colours

        last = list(variants)[-1]
        preview[f"{last}_depth"] = depth_to_rgb(preview[f"{last}_depth"])
        for name in variants:
            if name != last:
                preview.pop(f"{name}_depth")
        if regions is not None:
            preview["regions"] = region_colours(regions[0][0], regions[1][0])
        return {"preview": {k: v.detach().float().cpu() for k, v in preview.items()}}

    def region_masks(self, context: Views, target: Views) -> tuple[Tensor, Tensor] | None:
        """Observation-supported and weak target pixels ``[B, T, 1, H, W]`` from the ground-truth depth and cameras
        (:func:`anycity.metrics.regions.region_masks`), or None when the targets or the context have no depth."""
        if target.depth is None or context.depth is None:
            return None
        from anycity.metrics.regions import region_masks

        return region_masks(target.depth, target.w2c, target.K, context.depth, context.w2c, context.K,
                            target_valid=target.mask, context_valid=context.mask)

    def _camera_renderer(self, K: Tensor, hw: tuple[int, int], context: Tensor):
        """``f(scenes [B*N], w2c [B*N, 1, 4, 4]) -> rgb [B*N, 1, 3, H, W]`` rendering scene ``b*N + i`` into camera
        ``i`` of scene ``b`` (``K [B, N, 3, 3]``; ``context [B, V, 3, H', W']`` for the background), the form the
        test-time pose fits take; its tensors are made outside inference mode, so autograd can run through it."""
        n = K.shape[1]
        with torch.inference_mode(False):  # the fits need autograd; Lightning tests and predicts under inference mode
            Ks = K.float().reshape(-1, 1, 3, 3).clone()
            ctx = context.repeat_interleave(n, dim=0).clone()
        return lambda scenes, cams: self.render(scenes, cams, Ks, hw, ctx).rgb

    def align_targets(self, g: Gaussians, w2c: Tensor, tgt: Views, context: Tensor, steps: int) -> Tensor:
        """``w2c [B, T, 4, 4]`` target cameras refined photometrically against ``tgt.images`` (see
        :func:`anycity.lit.evaluation.align_target_poses`)."""
        return align_target_poses(self._camera_renderer(tgt.K, tgt.hw, context), g, w2c, tgt.images, steps,
                                  self.hparams.eval_pose_align_lr)

    def refine_cameras(self, g: Gaussians, w2c: Tensor, K: Tensor, images: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        """Context cameras ``w2c [B, V, 4, 4]`` (intrinsics ``K``) refined against their own ``images`` and the
        per-view Gaussian transforms that go with them (see
        :func:`anycity.lit.evaluation.refine_context_cameras`)."""
        hw = (int(images.shape[-2]), int(images.shape[-1]))
        return refine_context_cameras(self._camera_renderer(K, hw, images), g, w2c, images, steps,
                                      self.hparams.camera_refine_lr)

    def _log_metrics(self, metrics: EvalMetrics, split: str) -> None:
        # at epoch end on every rank: a rank without samples must still join the metric syncs (lit/distributed.py)
        logged = log_eval_metrics(self, metrics, split)
        skipped = self._report_skips(split)
        if not logged:  # no rank scored a sample (the ranks agree on it: log_eval_metrics gathered the flags)
            raise ValueError(f"{split}: no sample was scored on any rank ({skipped} corrupt sample(s) or shard(s) "
                             f"skipped, skip_corrupt: true); fix or re-create the {split} shards")

    def _report_skips(self, split: str) -> int:
        """Say, at the end of every evaluation, how many distinct corrupt samples (or shards) ``skip_corrupt``
        skipped so far on all ranks (the union of the ranks' lists, so that a shard every rank reads counts once):
        the figures leave them out, held-out targets included. Every rank calls it (a collective); returns the
        count."""
        dm = getattr(self.trainer, "datamodule", None)
        if dm is None or not hasattr(dm, "skip_counter"):
            return 0
        n = len(union_over_ranks(self, {r.get("what", r["where"]) for r in dm.skip_counter.records()}))
        if n:
            rank_zero_warn(f"{split}: {n} corrupt sample(s) skipped so far on all ranks (skip_corrupt: true); these "
                           f"figures leave them out. Rank 0's list: {dm.skip_counter.directory}")
        return n

    def on_validation_epoch_end(self) -> None:
        self._log_metrics(self.val_metrics, "val")

    def on_test_epoch_end(self) -> None:
        self._log_metrics(self.test_metrics, "test")

    def validation_step(self, batch: ViewBatch, batch_idx: int) -> dict[str, Any] | None:
        return self.evaluate(batch, self.val_metrics, batch_idx == 0)

    def on_test_start(self) -> None:
        if self.trainer.is_global_zero:
            print(self.lpips_status, flush=True)

    def test_step(self, batch: ViewBatch, batch_idx: int) -> dict[str, Any] | None:
        res = self.evaluate(batch, self.test_metrics, batch_idx == 0, self.test_protocols())
        return res

    def test_protocols(self) -> tuple[str, ...]:
        """The protocols ``anycity test`` scores: feed-forward always, then those switched on in the hparams."""
        hp = self.hparams
        on = {"camrefine": hp.camera_refine_steps > 0, "targetalign": hp.eval_pose_align_steps > 0,
              "joint": hp.eval_joint}
        return ("feedforward", *(p for p, enabled in on.items() if enabled))

    # ----------------------------------------------------------------------------------------- prediction
    @torch.no_grad()
    @float32_outside_net
    def predict_step(self, batch: ViewBatch | Views | Tensor | dict, batch_idx: int) -> dict[str, Any]:
        """Reconstruct from context images (a batch of shards, of :class:`Views`, images ``[B, V, 3, H, W]`` or a
        photo-folder dict ``{"images", "scene"}``); returns Gaussians, predicted cameras and context re-renders."""
        if isinstance(batch, dict):
            images, scene = batch["images"], batch.get("scene")
        else:
            ctx = batch.context if isinstance(batch, ViewBatch) else batch
            images, scene = (ctx.images if isinstance(ctx, Views) else ctx), getattr(batch, "scene", None)
        out, variants = self.predict_variants(images)
        final, scaffold, w2c = variants[list(variants)[-1]], variants["scaffold"], out["w2c"]
        if final is not scaffold and out["scaffold_w2c"] is not w2c:
            # net.refine_cameras re-placed the views: the provenance compares content, so the scaffold's decoding
            # goes at the same cameras, or every Gaussian would count as completed for the camera move alone
            scaffold = self.net.place_gaussians(out["scaffold_raw_gaussians"], out["scaffold_depth"],
                                                out["scaffold_offset"], w2c, out["K"], images)
        if self.hparams.camera_refine_steps > 0:
            w2c, A = self.refine_cameras(final, w2c, out["K"], images, self.hparams.camera_refine_steps)
            final, scaffold = transform_gaussians(final, A), transform_gaussians(scaffold, A)
        hw = (int(images.shape[-2]), int(images.shape[-1]))
        renders = self.render(final, w2c, out["K"], hw, images)
        return {"gaussians": final.detach(), "w2c": w2c.detach(), "K": out["K"].detach(),
                "images": images, "renders": renders, "scene": scene, "scaffold": scaffold.detach(),
                "depth": out["depth"].detach(),
                "batch_idx": batch_idx}
