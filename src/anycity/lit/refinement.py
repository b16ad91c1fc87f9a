"""Stage II: completion branch + video prior on a frozen scaffold, distilled from a dense-view teacher.

``L = L_rgb + w_d2s * L_d2s + w_pres * L_pres + w_reg * L_reg``. The teacher is the same network's scaffold
path run on the dense views under ``no_grad``; teacher and student render the same (ground-truth) dense
cameras, each mapped into its own predicted frame, and depths are compared up to a per-scene scale
(``d2s_depth_scale``).
"""

from __future__ import annotations

import json
import shlex
from dataclasses import fields, replace
from typing import Literal

import torch
from torch import Tensor, nn

from anycity.geometry import camera_centers
from anycity.geometry.pose_encoding import extri_intri_to_pose_encoding
from anycity.lit.base import AnyCityModule, float32_outside_net
from anycity.losses import camera_loss, d2s_loss, preservation_loss, regularizer_loss, rgb_loss
from anycity.models.anycity import SCAFFOLD_PREFIXES
from anycity.safe_load import missing_reason, safe_torch_load, user_path
from anycity.structures import RenderOutput, ViewBatch, Views

# scaffold weights a Stage I checkpoint may lack: the centre offset came later, and its zero init is what an older
# Stage I decoded
OPTIONAL_SCAFFOLD_PREFIXES = ("gaussian_head.offset_conv.",)
# scaffold settings that change what its weights decode but not their shapes: Stage II must use Stage I's
DECODE_KEYS = ("scale_mode", "color_mode", "gaussian_head_slope", "head_layers", "camera_iterations", "camera_init_fov")


def stage1_net_flags(stage1: dict, stage2_net: dict | None) -> str:
    """The command-line overrides, to follow the Stage II config, that rebuild the scaffold of a Stage I checkpoint
    (``stage1``: its ``hyper_parameters``): its preset, and one ``net`` dict holding this Stage II ``net``
    (``stage2_net``) with the Stage I keys laid over it (``completion`` excepted). One dict, as a later ``-c`` file's
    ``net`` replaces the whole dict, and a dotted ``net.KEY null`` does not parse. A generic hint without a preset."""
    if not stage1.get("preset"):
        return ("--model.init_args.preset PRESET and --model.init_args.net.KEY VALUE for each key of the Stage I "
                "config's model.net (a later -c file's net replaces the whole dict)")
    net = {**(stage2_net or {}), **{k: v for k, v in (stage1.get("net") or {}).items() if k != "completion"}}
    return (f"--model.init_args.preset {shlex.quote(str(stage1['preset']))} "
            f"--model.init_args.net {shlex.quote(json.dumps(net))}")


def decode_mismatch(stage1: dict, cfg) -> list[str]:
    """``"KEY: A there, B here"`` for each of :data:`DECODE_KEYS` on which the network of a Stage I checkpoint
    (``stage1``: its ``hyper_parameters``) and ``cfg`` (this network's ``NetConfig``) differ; empty when they agree or
    the checkpoint stores no preset to rebuild its settings from."""
    from anycity.models.presets import preset_config

    if not stage1.get("preset"):
        return []
    net = {k: v for k, v in (stage1.get("net") or {}).items() if k in (*DECODE_KEYS, "depth")}  # depth: head layers
    theirs = preset_config(stage1["preset"], **net)

    def value(c, key):
        return c.resolved_head_layers() if key == "head_layers" else getattr(c, key)

    return [f"net.{k}: {value(theirs, k)} there, {value(cfg, k)} here" for k in DECODE_KEYS
            if value(theirs, k) != value(cfg, k)]


def pretrained_scaffold_gaps(net: nn.Module, path: str, kind: str) -> list[str]:
    """Scaffold weights of ``net`` that the pretrained file ``path`` (layout ``kind``) does not fill: absent or of
    another shape (the zero-initialised centre offset excepted). Reads names and shapes only; an unreadable file
    (a corrupt safetensors one included) is the one-line ``ValueError`` of :func:`read_state_dict`."""
    from anycity.models.pretrained import read_shapes, remap_keys

    shapes = remap_keys(read_shapes(path), kind)  # a folder, or a sharded checkpoint: every file it names
    return sorted(k for k, v in net.state_dict().items() if k.startswith(SCAFFOLD_PREFIXES)
                  and not k.startswith(OPTIONAL_SCAFFOLD_PREFIXES) and shapes.get(k) != tuple(v.shape))


def _refuse_other_stage(path: str, hp: dict) -> None:
    """Refuse, as ``init_from``, a checkpoint whose ``hyper_parameters`` say it is not Stage I's: LightningCLI records
    the module class as ``_class_path``; without it, a Stage II module's own arguments (``init_from``, ``d2s_weight``)
    give it away. A Stage II checkpoint's scaffold fits, and its trained completion branch would be thrown away."""
    name = str(hp.get("_class_path") or "").rpartition(".")[2]
    if not name and ("init_from" in hp or "d2s_weight" in hp):
        name = "RefinementModule"
    if not name or name == "ScaffoldModule":
        return
    stage1 = hp.get("init_from") if isinstance(hp.get("init_from"), str) else None
    fix = f"its own was {stage1}" if stage1 else "e.g. runs/stage1/checkpoints/last.ckpt"
    if name == "RefinementModule":
        raise ValueError(f"model.init_from: {path} is a Stage II (RefinementModule) checkpoint, not a Stage I one; to "
                         f"continue that run pass it as --ckpt_path {path} (without init_from), or start Stage II "
                         f"anew from the Stage I checkpoint ({fix})")
    raise ValueError(f"model.init_from: {path} is a {name} checkpoint, not a Stage I (ScaffoldModule) one; pass the "
                     f"Stage I checkpoint ({fix})")


def far_index(views: Views, context: Views, k: int | None) -> Tensor | None:
    """Positions ``[B, k]`` of the ``k`` views of ``views`` whose camera centres are farthest from their nearest
    context camera (per scene, ground-truth cameras), in their original order; None (all) when ``k`` is None or
    not smaller."""
    if k is None or k >= views.num_views:
        return None
    if k <= 0:
        raise ValueError(f"model.d2s_views: expected a positive number of dense views or None, got {k}")
    c, cc = camera_centers(views.w2c.float()), camera_centers(context.w2c.float())
    dist = torch.cdist(c, cc).amin(-1)  # [B, D]
    return dist.topk(k, dim=1).indices.sort(dim=1).values


def _take(x: Tensor | None, idx: Tensor | None) -> Tensor | None:
    """``x [B, D, ...]`` at the positions ``idx [B, k]`` of dim 1 (all when ``idx`` is None)."""
    if x is None or idx is None:
        return x
    return torch.gather(x, 1, idx.view(*idx.shape, *([1] * (x.dim() - 2))).expand(-1, -1, *x.shape[2:]))


def far_views(views: Views, context: Views, k: int | None) -> Views:
    """The views of :func:`far_index`; ``views`` itself when that is all of them."""
    return _take_views(views, far_index(views, context, k))


def _take_views(views: Views, idx: Tensor | None) -> Views:
    return views if idx is None else Views(*(_take(getattr(views, f.name), idx) for f in fields(Views)))


def _scaled(r: RenderOutput, s: Tensor) -> RenderOutput:
    """Render with depth divided by the per-scene scale ``s [B]`` (predicted units -> ground-truth units)."""
    return RenderOutput(rgb=r.rgb, depth=r.depth / s[:, None, None, None, None], alpha=r.alpha, normal=r.normal)


class RefinementModule(AnyCityModule):
    """Stage II training: scaffold frozen; completion tokens, gates, projections and LoRA train.

    Args:
        lr: peak learning rate of AdamW (Stage II: 1e-4, the paper's).
        init_from: Stage I checkpoint (``.ckpt``) whose ``net.*`` weights initialise the network; loaded when
            training starts from scratch (not when resuming, testing or predicting from a Stage II checkpoint).
        d2s_weight: weight of ``L_d2s`` (paper: 1.0).
        pres_weight: weight of ``L_pres`` (paper: 0.1; 0 = the "w/o L_pres" ablation).
        reg_weight: weight of ``L_reg`` (paper: 0.01).
        ssim_weight: weight of ``1 - SSIM`` inside ``L_rgb``.
        context_rgb_weight: weight of the context-view photometric term.
        gate_mode: gate regulariser, "entropy" or "mean".
        d2s_views: beyond the paper (which renders all 12): how many of the dense cameras ``L_d2s`` renders, those
            farthest from every context camera (weak content lives in views far from the context); None = all.
        d2s_depth_scale: how ``L_d2s`` reconciles the teacher's and the student's depth scales (the paper does not
            say): "median" rescales the teacher's depth per scene by the median student/teacher ratio, so the term
            teaches shape only; "cameras" converts each to ground-truth units by the scale of its own camera fit
            (``eval_align``), which with ``sim3`` pulls the student's depth off its cameras (docs/stage2.md).
        camera_weight: beyond the paper (whose Stage II keeps the scaffold's cameras): weight of Stage I's
            pose-encoding loss on the cameras Stage II re-places (``net.refine_cameras``); 0 = off, the paper's.
        camera_loss_type: "l1" or "huber", as in Stage I.
        freeze_scaffold: freeze ``net.scaffold_parameters()`` (Stage II default); without it, ``camera_weight: 0``
            still freezes ``net.camera_head.empty_pose_tokens``, which only the camera loss trains.
        **base: see :class:`anycity.lit.base.AnyCityModule`.
    """

    variants = ("scaffold", "refined")

    def __init__(
        self,
        lr: float = 1e-4,
        init_from: str | None = None,
        d2s_weight: float = 1.0,
        pres_weight: float = 0.1,
        reg_weight: float = 0.01,
        ssim_weight: float = 0.0,
        context_rgb_weight: float = 1.0,
        gate_mode: str = "entropy",
        d2s_views: int | None = None,
        d2s_depth_scale: Literal["median", "cameras"] = "median",
        camera_weight: float = 0.0,
        camera_loss_type: Literal["l1", "huber"] = "l1",
        freeze_scaffold: bool = True,
        **base,
    ) -> None:
        super().__init__(lr=lr, **base)  # also records every argument, these and the base's, as hparams
        if gate_mode not in ("entropy", "mean"):
            raise ValueError(f"model.gate_mode: expected 'entropy' or 'mean', got {gate_mode!r}")
        if d2s_depth_scale not in ("median", "cameras"):
            raise ValueError(f"model.d2s_depth_scale: expected 'median' or 'cameras', got {d2s_depth_scale!r}")
        if camera_weight > 0 and not self.net.cfg.refine_cameras:
            raise ValueError("model.camera_weight: Stage II keeps the scaffold's cameras unless "
                             "model.net.refine_cameras is true; set it, or camera_weight: 0")
        if freeze_scaffold:
            for p in self.net.scaffold_parameters():
                p.requires_grad_(False)
        self.freeze_unsupervised_pose_token(camera_weight)  # matters with freeze_scaffold: false

    # ----------------------------------------------------------------------------------------- init
    def setup(self, stage: str) -> None:
        super().setup(stage)
        # A resumed fit (--ckpt_path) needs neither the Stage I file nor the pose prior's: its checkpoint holds both.
        # Lightning restores it after this hook and says so (trainer.ckpt_path) only then, so a missing file is
        # reported in _check_fresh_fit, once it is known whether this fit resumes. test/predict never need them.
        self._fresh_fit_problems: list[Exception] = []
        if stage != "fit":
            return
        # training only: test/predict may merge voxels (net.voxel_size is a test-time key, cli.NET_TEST_TIME_KEYS)
        if self.hparams.reg_weight > 0 and self.net.cfg.voxel_size is not None:
            raise ValueError("model.reg_weight: the stability term compares the scaffold's and the final Gaussians one "
                             "to one, which a voxel merge (model.net.voxel_size) pairs arbitrarily; train with "
                             "net.voxel_size: null, or set reg_weight: 0")
        try:
            if self.net.pose_prior is not None:
                self.net.pose_prior.check_loaded()
        except FileNotFoundError as e:
            self._fresh_fit_problems.append(e)
        if not self.hparams.init_from:
            if self.hparams.freeze_scaffold and (problem := self._random_scaffold()) is not None:
                self._fresh_fit_problems.append(problem)
        elif not user_path(self.hparams.init_from).is_file():
            why = missing_reason(user_path(self.hparams.init_from)) or "is not a file"
            self._fresh_fit_problems.append(FileNotFoundError(
                f"model.init_from: {self.hparams.init_from} {why}; pass the Stage I checkpoint (e.g. "
                "runs/stage1/checkpoints/last.ckpt)"))
        else:  # loaded here, before the strategy wraps the model; a resumed fit's checkpoint then replaces it
            try:
                self.load_stage1(self.hparams.init_from)
            except ValueError as e:  # unreadable, or another network's scaffold: a resumed fit does not need it
                self._fresh_fit_problems.append(e)

    def _random_scaffold(self) -> Exception | None:
        """Without ``init_from``: the error if the frozen scaffold would keep random weights, i.e. no ``pretrained``
        file, or one that does not fill every scaffold weight (a VGGT file has no Gaussian head); else None."""
        fix = "pass the Stage I checkpoint, e.g. --model.init_args.init_from runs/stage1/checkpoints/last.ckpt"
        if not self.hparams.pretrained:
            return ValueError("model.init_from: Stage II freezes the scaffold, and none was given (no init_from, no "
                              f"pretrained), so it would train on a random one; {fix}")
        try:
            gaps = pretrained_scaffold_gaps(self.net, self.hparams.pretrained, self.hparams.pretrained_kind)
        except (FileNotFoundError, ValueError) as e:  # a resumed fit may lack the file: reported on a fresh fit only
            return e
        if not gaps:
            return None
        why = ("a VGGT file has no Gaussian head" if self.hparams.pretrained_kind == "vggt" else
               "weights made for another network, e.g. another net.sh_degree")
        return ValueError(f"model.init_from: Stage II freezes the scaffold, and model.pretrained "
                          f"{self.hparams.pretrained} leaves {len(gaps)} of its weights random (e.g. {gaps[0]}: "
                          f"{why}); {fix}, or an AnySplat file that fits (model.pretrained_kind: anysplat)")

    def on_fit_start(self) -> None:
        if not self.trainer.strategy.restore_checkpoint_after_setup:
            self._check_fresh_fit()

    def on_train_start(self) -> None:
        super().on_train_start()
        if self.trainer.strategy.restore_checkpoint_after_setup:  # FSDP, DeepSpeed: restored after on_fit_start
            self._check_fresh_fit()

    def _check_fresh_fit(self) -> None:
        """Raise the first thing :meth:`setup` found missing, unless this fit resumed from a checkpoint."""
        problems = getattr(self, "_fresh_fit_problems", [])
        if self.trainer.ckpt_path is None and problems:
            raise problems[0]

    def load_stage1(self, path: str) -> None:
        """Copy the scaffold weights (``net.{aggregator,camera_head,depth_head,gaussian_head}.*``) of a Stage I
        checkpoint. They must fit this network's scaffold key for key and shape for shape: a scaffold built with
        other options (a deeper trunk, another SH degree) would otherwise keep random, frozen blocks. The one
        exception is the zero-initialised centre offset, which Stage I checkpoints from before it lack. A completion
        branch an older Stage I checkpoint may hold (untrained) is not copied, so Stage II may use another video
        prior, or none."""
        from anycity.models.pretrained import first_non_tensor, first_nonfinite

        # memory-mapped, tensors only: the weights are read on use and the optimiser state (2x the weights) never is
        ckpt = safe_torch_load(path, mmap=True, what="model.init_from")
        if not isinstance(ckpt, dict):
            raise ValueError(f"model.init_from: {path} holds a {type(ckpt).__name__}, not a checkpoint; pass the "
                             "Stage I checkpoint (e.g. runs/stage1/checkpoints/last.ckpt)")
        state = ckpt.get("state_dict", ckpt)
        stage1_hp = ckpt.get("hyper_parameters") or {}
        del ckpt
        if not isinstance(state, dict) or not isinstance(stage1_hp, dict):
            raise ValueError(f"model.init_from: {path} is damaged (its state_dict or hyper_parameters is not a dict); "
                             "pass the Stage I checkpoint (e.g. runs/stage1/checkpoints/last.ckpt)")
        _refuse_other_stage(path, stage1_hp)
        if (bad := first_non_tensor(state)) is not None:
            raise ValueError(f"model.init_from: {path} holds a {bad[1]} under the key {bad[0]!r}, not a tensor; the "
                             "file is damaged: pass the Stage I checkpoint a fit wrote")
        decode = (stage1_hp.get("net") or {}).get("focal_decode", "vggt")
        if decode != self.net.cfg.focal_decode:  # e.g. Stage I started from AnySplat: keep its camera decode
            self.net.cfg = replace(self.net.cfg, focal_decode=decode)
            self.hparams.net = {**(self.hparams.net or {}), "focal_decode": decode}
        own = self.net.state_dict()
        theirs = {k[len("net."):]: v for k, v in state.items()
                  if k.startswith("net.") and k[len("net."):].startswith(SCAFFOLD_PREFIXES)}
        if not theirs:
            raise ValueError(f"model.init_from: {path} holds no 'net.*' scaffold weights; pass a ScaffoldModule "
                             "checkpoint")
        problems = []
        unexpected = sorted(k for k in theirs if k not in own)
        if unexpected:
            problems.append(f"{len(unexpected)} of its keys are not in this network (e.g. {unexpected[0]})")
        missing = sorted(k for k in own if k.startswith(SCAFFOLD_PREFIXES) and k not in theirs
                         and not k.startswith(OPTIONAL_SCAFFOLD_PREFIXES))
        if missing:
            problems.append(f"{len(missing)} scaffold weights of this network are not in it (e.g. {missing[0]})")
        shapes = [k for k in theirs if k in own and theirs[k].shape != own[k].shape]
        if shapes:
            k = shapes[0]
            problems.append(f"{len(shapes)} shapes differ (e.g. {k}: {list(theirs[k].shape)} there, "
                            f"{list(own[k].shape)} here)")
        decode_problems = decode_mismatch(stage1_hp, self.net.cfg)
        if decode_problems:  # same shapes, other Gaussians: the frozen scaffold would not be the one Stage I trained
            problems.append(f"it decodes its weights with other settings ({', '.join(decode_problems)})")
        if problems:
            raise ValueError(f"model.init_from: {path} does not fit this network's scaffold: {'; '.join(problems)}; "
                             "give Stage II the Stage I network after its config: "
                             f"{stage1_net_flags(stage1_hp, self.hparams.net)}")
        if (bad := first_nonfinite(theirs)) is not None:  # a frozen NaN scaffold: every Stage II step NaN
            raise ValueError(f"model.init_from: {path} holds non-finite values (NaN or Inf) in net.{bad}; Stage I "
                             "diverged before it was saved: pass an earlier Stage I checkpoint")
        self.net.load_state_dict(theirs, strict=False)

    # ----------------------------------------------------------------------------------------- checkpoints
    def on_save_checkpoint(self, checkpoint: dict) -> None:
        from anycity.lit.prior_ckpt import drop_frozen_prior, save_pose_prior_meta

        drop_frozen_prior(self.net, checkpoint)
        save_pose_prior_meta(self.net, checkpoint)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Put back the frozen prior's weights and rebuild the pose prior, then check every weight (keys, shapes,
        tensors, finite) in one line naming the file, before Lightning's strict load."""
        from anycity.lit.checkpoint_io import check_checkpoint_state, checkpoint_source, checkpoint_state
        from anycity.lit.prior_ckpt import restore_frozen_prior, restore_pose_prior

        source = checkpoint_source(self)
        provided = list(checkpoint_state(checkpoint, source))  # the file's own; the frozen prior's are this net's
        restore_frozen_prior(self.net, checkpoint, source)
        restore_pose_prior(self.net, checkpoint)
        check_checkpoint_state(self, checkpoint, finite_keys=provided)

    # ----------------------------------------------------------------------------------------- training
    @float32_outside_net
    def training_step(self, batch: ViewBatch, batch_idx: int) -> Tensor:
        hp = self.hparams
        ctx, tgt, dense = batch.context, batch.target, batch.dense
        out = self.forward_net(ctx.images, refine=True)
        if (bad := self.nonfinite_forward(out)) is not None:  # every DDP rank then skips the step (callbacks/nonfinite)
            return bad
        final, scaffold = out["gaussians"], out["scaffold_gaussians"]
        terms: dict[str, Tensor] = {}

        w2c_t, _ = self.target_cameras(out["w2c"], ctx, tgt)
        r_tgt = self.render(final, w2c_t, tgt.K, tgt.hw, ctx.images)
        terms["rgb"] = rgb_loss(r_tgt.rgb, tgt.images, ssim_weight=hp.ssim_weight)["total"]
        loss = terms["rgb"]
        if hp.context_rgb_weight > 0 or hp.pres_weight > 0:
            r_ctx = self.render(final, out["w2c"], out["K"], ctx.hw, ctx.images)
            if hp.context_rgb_weight > 0:
                terms["rgb_ctx"] = rgb_loss(r_ctx.rgb, ctx.images, ssim_weight=hp.ssim_weight)["total"]
                loss = loss + hp.context_rgb_weight * terms["rgb_ctx"]
            if hp.pres_weight > 0:
                with torch.no_grad():  # each at its own cameras: both are renders of the context views
                    r_scaf = self.render(scaffold.detach(), *self.variant_cameras(out, "scaffold"), ctx.hw,
                                         ctx.images)
                terms["pres"] = preservation_loss(r_ctx, r_scaf)["total"]
                loss = loss + hp.pres_weight * terms["pres"]
        if hp.camera_weight > 0:
            gt_enc = extri_intri_to_pose_encoding(ctx.w2c, ctx.K, ctx.hw, self.net.cfg.focal_decode)
            terms["cam"] = camera_loss(out["pose_enc_list"], gt_enc, loss_type=hp.camera_loss_type)["total"]
            loss = loss + hp.camera_weight * terms["cam"]
        if hp.d2s_weight > 0 and dense is None:  # a contradiction between the configs, not a data matter
            raise ValueError(f"model.d2s_weight is {hp.d2s_weight}, but the batches hold no dense views "
                             "(data.num_dense: 0); set data.num_dense (the paper: 12) or model.d2s_weight: 0")
        if hp.d2s_weight > 0:
            idx = far_index(dense, ctx, hp.d2s_views)  # the cameras rendered; the teacher reads every dense view
            shown = _take_views(dense, idx)
            with torch.no_grad():
                t_out = self.forward_net(dense.images, refine=False)
                t_out = {**t_out, "gaussians": t_out.get("scaffold_gaussians") or t_out["gaussians"]}
            # the teacher reads other views than the student and can overflow alone: skip the step on every DDP rank
            # as for the student (the NaN loss is built here, outside no_grad, so backward reaches every parameter)
            if (bad := self.nonfinite_forward(t_out)) is not None:
                return bad
            with torch.no_grad():
                t_g = t_out["gaussians"]
                w2c_td, s_t = self.target_cameras(t_out["w2c"], dense, dense)  # its frame: dense view 0's
                teacher = _scaled(self.render(t_g, _take(w2c_td, idx), shown.K, shown.hw, ctx.images), s_t)
            w2c_sd, s_s = self.target_cameras(out["w2c"], ctx, shown)
            student = _scaled(self.render(final, w2c_sd, shown.K, shown.hw, ctx.images), s_s)
            terms["d2s"] = d2s_loss(student, teacher, scale_align=hp.d2s_depth_scale == "median")["total"]
            loss = loss + hp.d2s_weight * terms["d2s"]
        if hp.reg_weight > 0:
            terms["reg"] = regularizer_loss(out.get("delta"), out.get("gates"), final, scaffold,
                                            gate_mode=hp.gate_mode)["total"]
            loss = loss + hp.reg_weight * terms["reg"]
        terms["loss"] = loss
        self.log_terms(terms, batch.batch_size, prog_bar=("loss", "rgb", "d2s", "pres"))
        return loss
