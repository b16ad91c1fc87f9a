"""Stage I: the scaffold (AnySplat-style geometry path), completion branch off.

``L = L_rgb + w_depth * (L_z + L_xy) + w_normal * L_normal + w_cam * L_cam``; depth and normal terms start
after ``depth_warmup_steps``. ``L_rgb`` scores the renders of the target views (ground-truth cameras mapped
into the predicted frame) and of the context views (predicted cameras).
"""

from __future__ import annotations

from typing import Literal

from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor

from anycity.geometry.pose_encoding import extri_intri_to_pose_encoding
from anycity.lit.base import AnyCityModule, float32_outside_net
from anycity.lit.checkpoint_io import check_checkpoint_state
from anycity.losses import camera_loss, depth_z_loss, normal_loss, ray_anchor_loss, rgb_loss
from anycity.models.anycity import REFINEMENT_PREFIXES
from anycity.structures import ViewBatch

# NetConfig options of the completion branch and the priors it reads: Stage I builds none of them
STAGE2_NET_KEYS = ("completion_dim", "completion_tokens", "completion_heads", "inject_layers", "video_prior",
                   "prior_dim", "prior_depth", "prior_stride", "wan_dir", "wan_block", "wan_t_feat", "wan_lora_rank",
                   "wan_empty_prompt", "refine_depth", "refine_cameras", "camera_video", "pose_prior", "pose_prior_mix")


def stage2_net_keys(net: dict | None, preset: str) -> list[str]:
    """The keys of ``net`` (``model.net`` overrides) that set a :data:`STAGE2_NET_KEYS` option to other than
    ``preset``'s value: settings of the completion branch, which Stage I does not build."""
    from anycity.models.presets import PRESETS

    if not isinstance(net, dict) or preset not in PRESETS:
        return []  # the network's own construction reports an unknown preset
    norm = lambda v: tuple(v) if isinstance(v, list) else v  # noqa: E731  (YAML lists, stored tuples)
    return [k for k in STAGE2_NET_KEYS if k in net and norm(net[k]) != norm(getattr(PRESETS[preset], k))]


def check_no_stage2_net(init_args: dict) -> None:
    """Refuse, in one line, Stage II options in a Stage I ``model.net`` (``init_args["net"]``, as ``completion:
    true`` is): they would be stored and never used (``video_prior: wan2``, which Stage II refuses, was accepted). A
    value equal to the preset's is accepted (``configs/debug/cpu_ddp.yaml`` sets ``video_prior: small`` for either
    stage)."""
    net = init_args.get("net")
    keys = stage2_net_keys(net, init_args.get("preset", "tiny"))
    if keys:
        one = len(keys) == 1
        given = ", ".join(f"model.net.{k} {net[k]!r}" for k in keys)
        raise ValueError(f"{given}: {'a Stage II option' if one else 'Stage II options'} of the completion branch, "
                         f"which Stage I (ScaffoldModule) does not build; drop {'it' if one else 'them'} from the "
                         f"Stage I config (Stage II, RefinementModule, takes {'it' if one else 'them'})")


class ScaffoldModule(AnyCityModule):
    """Stage I training of the scaffold network.

    Args:
        depth_weight: weight of ``L_depth = L_z + L_xy`` (paper: 0.1).
        normal_weight: weight of ``L_normal`` (paper: 0.1).
        camera_weight: weight of the pose-encoding loss; 0 freezes ``net.camera_head.empty_pose_tokens``, which
            nothing else trains (:meth:`~anycity.lit.base.AnyCityModule.freeze_unsupervised_pose_token`).
        camera_loss_type: "l1" (VGGT's default) or "huber" on the pose encoding.
        ssim_weight: weight of ``1 - SSIM`` inside ``L_rgb`` (0 = MSE only).
        context_rgb_weight: weight of the context-view photometric term relative to the target views.
        depth_warmup_steps: optimiser steps before the depth and normal terms switch on (paper: 200).
        depth_grad_weight: weight of the gradient-matching part of ``L_z``.
        depth_abs_weight: weight of an extra unaligned log-depth L1 inside ``L_depth`` (pins the absolute scale of
            the normalised frame, which the affine-invariant ``L_z`` leaves free; 0 = paper).
        ray_weight: weight of the ray-anchoring term ``L_xy`` (mean reprojection L1 of the centres, pixels) inside
            ``L_depth``.
        depth_conf_threshold: ignore depth pixels whose predicted confidence is below this (None = keep all).
        flat_weight: weight ``lambda_flat`` of the flatness prior (smallest Gaussian scale) inside ``L_normal``,
            gated per pixel like the normal term (structure weight, valid ground truth, rendered coverage).
        **base: see :class:`anycity.lit.base.AnyCityModule` (preset, lr, schedule, renderer, ...).
    """

    variants = ("scaffold",)

    def __init__(
        self,
        depth_weight: float = 0.1,
        normal_weight: float = 0.1,
        camera_weight: float = 1.0,
        camera_loss_type: Literal["l1", "huber"] = "l1",
        ssim_weight: float = 0.0,
        context_rgb_weight: float = 1.0,
        depth_warmup_steps: int = 200,
        depth_grad_weight: float = 0.5,
        depth_abs_weight: float = 0.0,
        ray_weight: float = 1.0,
        depth_conf_threshold: float | None = None,
        flat_weight: float = 0.0,
        **base,
    ) -> None:
        # Stage I builds no completion branch: nothing unused in the DDP graph, nothing untrained in the checkpoint
        if (base.get("net") or {}).get("completion"):
            raise ValueError("model.net.completion: Stage I (ScaffoldModule) trains the scaffold only, got "
                             "completion=true; drop it (Stage II, RefinementModule, builds the completion branch)")
        check_no_stage2_net(base)  # (the whole dict: jsonargparse reads a base.get("preset") here as its type)
        base["net"] = {**(base.get("net") or {}), "completion": False}
        super().__init__(**base)  # also records every argument, these and the base's, as hparams
        self.freeze_unsupervised_pose_token(camera_weight)
        self._told_no_depth = False
        self._depth_kinds: set[bool] = set()  # whether batches seen so far had ground-truth depth

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        # Stage I checkpoints written before Stage I stopped building the completion branch carry its (untrained)
        # weights; this module has no place for them
        sd = checkpoint.get("state_dict", {})
        for k in [k for k in sd if k.startswith(tuple(f"net.{p}" for p in REFINEMENT_PREFIXES))]:
            del sd[k]
        check_checkpoint_state(self, checkpoint)  # one line for a damaged file, not Lightning's 50-line load error

    @float32_outside_net
    def training_step(self, batch: ViewBatch, batch_idx: int) -> Tensor:
        hp = self.hparams
        ctx, tgt = batch.context, batch.target
        out = self.forward_net(ctx.images, refine=False)
        if (bad := self.nonfinite_forward(out)) is not None:  # every DDP rank then skips the step (callbacks/nonfinite)
            return bad
        g = out.get("scaffold_gaussians") or out["gaussians"]
        geo_on = self.global_step >= hp.depth_warmup_steps
        terms: dict[str, Tensor] = {}

        w2c_t, _ = self.target_cameras(out["w2c"], ctx, tgt)
        r_tgt = self.render(g, w2c_t, tgt.K, tgt.hw, ctx.images)
        terms["rgb"] = rgb_loss(r_tgt.rgb, tgt.images, ssim_weight=hp.ssim_weight)["total"]
        loss = terms["rgb"]
        if hp.context_rgb_weight > 0 or (geo_on and hp.normal_weight > 0):
            r_ctx = self.render(g, out["w2c"], out["K"], ctx.hw, ctx.images, normals=geo_on and hp.normal_weight > 0)
            terms["rgb_ctx"] = rgb_loss(r_ctx.rgb, ctx.images, ssim_weight=hp.ssim_weight)["total"]
            loss = loss + hp.context_rgb_weight * terms["rgb_ctx"]
        if hp.camera_weight > 0:
            gt_enc = extri_intri_to_pose_encoding(ctx.w2c, ctx.K, ctx.hw, self.net.cfg.focal_decode)
            terms["cam"] = camera_loss(out["pose_enc_list"], gt_enc, loss_type=hp.camera_loss_type)["total"]
            loss = loss + hp.camera_weight * terms["cam"]
        if len(self._depth_kinds) < 2:
            self._depth_kinds.add(ctx.depth is not None)
            if len(self._depth_kinds) == 2:
                rank_zero_warn("training mixes scenes with ground-truth depth and scenes without (e.g. synthetic and "
                               "COLMAP shards): a sample's frame is scaled by its context's median depth, or without "
                               "depth by its context cameras' spread, so the camera head is taught translations in "
                               "two units; convert the depth-free scenes with depth, or train on one kind")
        if geo_on and hp.depth_weight > 0 and ctx.depth is None and not self._told_no_depth:
            self._told_no_depth = True  # shards converted without depth (e.g. COLMAP): a data matter, said once
            rank_zero_warn(f"model.depth_weight is {hp.depth_weight}, but a batch has no ground-truth depth (its "
                           "shards hold none); the depth term is skipped for such batches")
        if geo_on and hp.depth_weight > 0 and ctx.depth is not None:
            dz = depth_z_loss(out["depth"], ctx.depth, ctx.mask, out.get("depth_conf"), hp.depth_conf_threshold,
                              grad_weight=hp.depth_grad_weight)["total"]
            if hp.depth_abs_weight > 0:
                dz = dz + hp.depth_abs_weight * depth_z_loss(out["depth"], ctx.depth, ctx.mask, grad_weight=0.0,
                                                             align=False)["total"]
            dxy = ray_anchor_loss(out["pixel_means"], out["w2c"], out["K"], ctx.mask)
            terms["depth"] = dz + hp.ray_weight * dxy
            loss = loss + hp.depth_weight * terms["depth"]
        if geo_on and hp.normal_weight > 0:
            n = normal_loss(r_ctx.depth, r_ctx.normal, out["K"], image=ctx.images, alpha=r_ctx.alpha,
                            scales=g.scales, flat_weight=hp.flat_weight, scales_valid=g.valid, mask=ctx.mask)
            terms["normal"] = n["total"]
            loss = loss + hp.normal_weight * terms["normal"]
        terms["loss"] = loss
        self.log_terms(terms, batch.batch_size, prog_bar=("loss", "rgb", "depth", "cam"))
        return loss
