"""AnyCityNet: the composition root. Scaffold (VGGT + Gaussian head) and the Stage II completion branch."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
from torch import Tensor, nn

from anycity.geometry.pose_encoding import blend_pose_encoding, pose_encoding_to_extri_intri
from anycity.models.aggregator import Aggregator
from anycity.models.completion import CompletionBranch
from anycity.models.gaussians import pixel_centres, pixel_footprint, raw_to_gaussians
from anycity.models.heads import CameraHead, DepthHead, GaussianHead
from anycity.models.pose_prior import load_pose_prior, pose_features
from anycity.models.presets import NetConfig
from anycity.models.video_prior import WanVideoPrior, build_video_prior
from anycity.structures import image_range

SCAFFOLD_PREFIXES = ("aggregator.", "camera_head.", "depth_head.", "gaussian_head.")
REFINEMENT_PREFIXES = ("completion.", "video_prior.")
IMAGE_DTYPES = (torch.float32, torch.bfloat16, torch.float16)


def _float32_region(device: torch.device) -> contextlib.AbstractContextManager:
    """Autocast off on ``device`` (heads and geometry run in float32); nothing to switch off where the device has no
    autocast (``meta``, whose ``torch.autocast`` raises)."""
    available = getattr(torch.amp, "is_autocast_available", None)  # torch >= 2.4
    if available(device.type) if available is not None else device.type != "meta":
        return torch.autocast(device.type, enabled=False)
    return contextlib.nullcontext()


def _check_range(images: Tensor) -> None:
    """One-line error for ``images`` with values outside [0, 1] (a resize's rounding allowed) or NaN/inf, with the
    fix that fits what they look like: [-1, 1], mean/std-normalised (ImageNet), 0-255."""
    lo, hi, fault = image_range(images)  # one reduction, one host sync
    if fault == "nonfinite":
        got = "NaN" if math.isnan(lo) else f"a minimum of {lo:.4g} and a maximum of {hi:.4g}"
        raise ValueError(f"images: expected finite values in [0, 1], got {got}; find the non-finite pixels "
                         "(~torch.isfinite(images)) and fix the loading or preprocessing that made them")
    if fault in ("signed", "normalised"):
        fix = {"signed": "they look like [-1, 1]; use (x + 1) / 2",
               "normalised": "they look mean/std-normalised (e.g. ImageNet); undo the normalisation: x * std + mean"}
        raise ValueError(f"images: expected values in [0, 1], got a minimum of {lo:.4g} (maximum {hi:.4g}); "
                         f"{fix[fault]}")
    if fault in ("0-255", "over"):
        fix = {"0-255": "images look like 0-255; divide by 255", "over": "clamp them to [0, 1]"}
        raise ValueError(f"images: expected values in [0, 1], got a maximum of {hi:.4g}; {fix[fault]}")


def _layout_fix(images) -> str:
    """The fix for ``images`` that are not ``[B, V, 3, H, W]``: the permute for channels-last ``[..., H, W, 3]``,
    the missing leading dims for ``[V, 3, H, W]`` / ``[3, H, W]``, else a general hint."""
    if not isinstance(images, Tensor):
        if type(images).__name__ == "ndarray":
            return "pass a torch tensor: torch.from_numpy(images), [H, W, 3] arrays permuted to [3, H, W]"
        return "pass a torch tensor (torch.stack(views)[None] for a list of [3, H, W] views)"
    shape, n = images.shape, images.dim()
    scale = "" if images.is_floating_point() else ", then .float() / 255"
    if 3 <= n <= 5 and shape[-1] == 3 and shape[-3] != 3:
        order = {3: "(2, 0, 1)[None, None]", 4: "(0, 3, 1, 2)[None]", 5: "(0, 1, 4, 2, 3)"}[n]
        return f"they are channels-last: permute to [..., 3, H, W] with images.permute{order}{scale}"
    if n in (3, 4) and shape[-3] == 3:
        lead = {3: "[None, None] (one image)", 4: "[None] (V views of one sample)"}[n]
        return f"add the missing leading dims with images{lead}"
    return "stack the views on dim 1 and the samples on dim 0"


class AnyCityNet(nn.Module):
    """``net(images [B, V, 3, H, W] in [0, 1], refine=True) -> dict``; H, W multiples of ``patch_size``.

    Output keys (world frame = first camera, OpenCV, normalised scene units):
        ``pose_enc [B, V, 9]`` (t, quat xyzw, fov_h, fov_w) and ``pose_enc_list`` (one per camera iteration);
        ``w2c [B, V, 4, 4]``, ``K [B, V, 3, 3]`` (pixels of the input images): the final cameras, re-placed by
        Stage II with ``cfg.refine_cameras``; ``scaffold_w2c``, ``scaffold_K``: the scaffold's (the same tensors
        otherwise);
        ``depth [B, V, 1, H, W]`` (z-depth), ``depth_conf [B, V, 1, H, W]`` (>= 1): decoded from Z_final when
        ``refine_depth`` and refining, else the scaffold's; ``scaffold_depth``: the scaffold's depth;
        ``offset [B, V, 3, H, W]``: the final centre offsets (depth units, camera frame);
        ``pixel_means [B, V, H, W, 3]``: final pixel-aligned Gaussian centres (depth unprojected + offset) before
        any voxel merge; ``scaffold_pixel_means``: the scaffold's;
        ``scaffold_gaussians``: :class:`Gaussians` decoded from the geometry tokens alone;
        ``gaussians``: final Gaussians (Z_geo + ΔZ through the Gaussian head, centre offsets included, and with
        ``cfg.refine_depth`` the depth head; the same object as ``scaffold_gaussians`` when
        ``refine=False`` or the net has no completion branch). N = V*H*W unless ``voxel_size`` merges, in which
        case ``valid [B, N]`` masks padding;
        ``raw_gaussians [B, V, C_raw, H, W]``: the final head output before activation;
        ``delta``: list of ``[B, V, P, 2C]`` residuals ΔZ (one per Gaussian-head layer) or None;
        ``gates``: list of ``[B, M, 1]`` video gates (one per injection layer) or None.
    """

    def __init__(self, cfg: NetConfig):
        super().__init__()
        self.cfg = cfg
        self.head_layers = cfg.resolved_head_layers()
        self.aggregator = Aggregator(cfg.img_size, cfg.patch_size, cfg.embed_dim, cfg.depth, cfg.num_heads,
                                     num_register_tokens=cfg.num_register_tokens, patch_embed=cfg.patch_embed)
        dim2 = 2 * cfg.embed_dim
        dpt = dict(patch_size=cfg.patch_size, features=cfg.dpt_features, out_channels=cfg.dpt_out_channels,
                   layers=self.head_layers)
        self.camera_head = CameraHead(dim2, cfg.camera_trunk_depth, cfg.camera_num_heads)
        self.depth_head = DepthHead(dim2, **dpt)
        self.gaussian_head = GaussianHead(dim2, sh_degree=cfg.sh_degree, hidden_slope=cfg.gaussian_head_slope, **dpt)
        if cfg.camera_init_fov is not None:
            self.camera_head.init_pose_bias(cfg.camera_init_fov, cfg.camera_iterations)
        if cfg.color_mode == "pixel":
            self.gaussian_head.init_sh_residual()
        self.video_prior = None
        self.completion = None
        self.pose_prior = None
        if cfg.completion:
            self.video_prior = build_video_prior(
                cfg.video_prior, cfg.prior_dim, cfg.prior_depth, max(1, cfg.prior_dim // 64), cfg.prior_stride,
                wan_dir=cfg.wan_dir, **({"block": cfg.wan_block, "t_feat": cfg.wan_t_feat}
                                        if cfg.video_prior.startswith("wan") else {}),
                **({"empty_prompt_path": cfg.wan_empty_prompt} if cfg.video_prior == "wan" else {}))
            if isinstance(self.video_prior, WanVideoPrior) and cfg.wan_lora_rank > 0:
                self.video_prior.add_lora(cfg.wan_lora_rank)
            self.completion = CompletionBranch(
                dim2, cfg.completion_dim, cfg.completion_tokens, cfg.completion_heads, cfg.resolved_inject_layers(),
                self.head_layers, self.video_prior.out_dim if self.video_prior is not None else None,
                camera=cfg.refine_cameras, camera_video=cfg.camera_video, camera_pose=cfg.pose_prior is not None,
                camera_mix=cfg.pose_prior_mix)
            if cfg.pose_prior is not None:  # frozen; built after the branch so its random init does not shift
                self.pose_prior = load_pose_prior(cfg.pose_prior)

    # -- parameter groups ------------------------------------------------------------------------------------
    def scaffold_parameters(self) -> Iterator[nn.Parameter]:
        """Stage I parameters: ``aggregator.*``, ``camera_head.*``, ``depth_head.*``, ``gaussian_head.*``."""
        return (p for n, p in self.named_parameters() if n.startswith(SCAFFOLD_PREFIXES))

    def refinement_parameters(self) -> Iterator[nn.Parameter]:
        """Stage II trainables: ``completion.*`` and the prior's trainable params (LoRA ``lora_`` only for Wan)."""
        return (p for n, p in self.named_parameters() if n.startswith(REFINEMENT_PREFIXES) and p.requires_grad)

    def freeze_scaffold(self, frozen: bool = True) -> None:
        for p in self.scaffold_parameters():
            p.requires_grad_(not frozen)

    def set_gradient_checkpointing(self, enabled: bool = True) -> None:
        self.aggregator.gradient_checkpointing = enabled
        if hasattr(self.aggregator.patch_embed, "gradient_checkpointing"):
            self.aggregator.patch_embed.gradient_checkpointing = enabled
        if isinstance(self.video_prior, WanVideoPrior):
            tr = self.video_prior.transformer
            tr.enable_gradient_checkpointing() if enabled else tr.disable_gradient_checkpointing()

    # -- forward ---------------------------------------------------------------------------------------------
    def check_images(self, images: Tensor) -> None:
        """One-line errors for what the network cannot read: ``images`` not ``[B, V, 3, H, W]`` float32/bf16/fp16
        in [0, 1] (finite) with H, W multiples of the patch size, or the network's weights cast away from float32."""
        p = self.cfg.patch_size
        if not isinstance(images, Tensor) or images.dim() != 5 or images.shape[2] != 3:
            got = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
            raise ValueError(f"images: expected [B, V, 3, H, W] float in [0, 1], got {got}; {_layout_fix(images)}")
        b, v, _, h, w = images.shape
        if b == 0 or v == 0:
            raise ValueError(f"images: expected at least 1 sample and 1 view, got B={b}, V={v}")
        if h == 0 or w == 0 or h % p or w % p:
            raise ValueError(f"images: H and W must be positive multiples of the patch size {p} (e.g. {8 * p}x"
                             f"{14 * p}), got {h}x{w}; resize or crop the views to a multiple of {p}")
        if not images.is_floating_point():
            raise ValueError(f"images: expected a float tensor in [0, 1], got {images.dtype}; divide uint8 by 255")
        if images.dtype not in IMAGE_DTYPES:
            raise ValueError(f"images: {str(images.dtype).removeprefix('torch.')}; pass images.float()")
        weights = self.aggregator.camera_token.dtype
        if weights != torch.float32:  # the float32 heads and geometry would meet bf16/fp16/fp64 weights
            name = str(weights).removeprefix("torch.")
            if weights in (torch.bfloat16, torch.float16):
                cast = "net.bfloat16()" if weights == torch.bfloat16 else "net.half()"
                raise ValueError(f"network: weights are {name} ({cast}); keep float32 weights and run under "
                                 "torch.autocast (Lightning: trainer.precision bf16-mixed, not bf16-true)")
            raise ValueError(f"network: weights are {name}, expected float32; cast them back with net.float()")
        if not images.is_meta:
            _check_range(images)  # one reduction: cheap next to the network

    def forward(self, images: Tensor, refine: bool = True) -> dict:
        self.check_images(images)
        h, w = images.shape[-2:]
        psi = self.aggregator.patch_start_idx
        layers = set(self.head_layers) | {self.cfg.depth - 1}
        refine = refine and self.completion is not None
        if refine:
            layers |= set(self.completion.inject_layers)
        tokens = self.aggregator(images, keep=layers)
        with _float32_region(images.device):  # heads and geometry in float32
            tokens = [None if t is None else t.float() for t in tokens]
            images = images.float()
            pose_enc_list = self.camera_head(tokens, self.cfg.camera_iterations)
            w2c, K = pose_encoding_to_extri_intri(pose_enc_list[-1], (h, w), self.cfg.focal_decode)
            depth, depth_conf = self.depth_head(tokens, images, psi)
            raw, offset = self.gaussian_head(tokens, images, psi)
            means = pixel_centres(depth, K, w2c, offset)
            scaffold = self._gaussians(raw, means, depth, K, images)
            final = dict(gaussians=scaffold, delta=None, gates=None, depth=depth, depth_conf=depth_conf, raw=raw,
                         offset=offset, pixel_means=means, pose_enc_list=pose_enc_list, w2c=w2c, K=K)
            if refine:
                # Z_final = Z_geo + dZ goes through the whole decoder: the Gaussian head (attributes and centre
                # offsets) and, with cfg.refine_depth, the depth head, so Stage II can move geometry
                vid = self.video_prior(images) if self.video_prior is not None else None
                prior_w2c = pose = None
                if self.pose_prior is not None:
                    with torch.no_grad():
                        prior_w2c = self.pose_prior(images)
                        pose = pose_features(prior_w2c)
                delta, gates, camera_delta, camera_mix = self.completion(tokens, psi, vid, pose)
                pel, w2c_f, K_f = pose_enc_list, w2c, K
                if camera_delta is not None:  # cfg.refine_cameras: the camera head re-reads the last layer
                    last = tokens[-1]
                    last = torch.cat([last[:, :, :1] + camera_delta[:, :, None], last[:, :, 1:]], dim=2)
                    pel = self.camera_head([*tokens[:-1], last], self.cfg.camera_iterations)
                    if camera_mix is not None:  # cfg.pose_prior_mix: one more step, towards the prior's pose
                        pel = [*pel, blend_pose_encoding(pel[-1], prior_w2c, camera_mix)]
                    w2c_f, K_f = pose_encoding_to_extri_intri(pel[-1], (h, w), self.cfg.focal_decode)
                d, dc = depth, depth_conf
                if self.cfg.refine_depth:
                    d, dc = self.depth_head(tokens, images, psi, delta=delta)
                r, o = self.gaussian_head(tokens, images, psi, delta=delta)
                m = pixel_centres(d, K_f, w2c_f, o)
                final = dict(gaussians=self._gaussians(r, m, d, K_f, images), delta=delta, gates=gates, depth=d,
                             depth_conf=dc, raw=r, offset=o, pixel_means=m, pose_enc_list=pel, w2c=w2c_f, K=K_f)
        return {"pose_enc": final["pose_enc_list"][-1], "pose_enc_list": final["pose_enc_list"], "w2c": final["w2c"],
                "K": final["K"], "scaffold_w2c": w2c, "scaffold_K": K,
                "depth": final["depth"], "depth_conf": final["depth_conf"], "scaffold_depth": depth,
                "offset": final["offset"], "pixel_means": final["pixel_means"], "scaffold_pixel_means": means,
                "scaffold_offset": offset, "gaussians": final["gaussians"], "scaffold_gaussians": scaffold,
                "raw_gaussians": final["raw"], "scaffold_raw_gaussians": raw, "delta": final["delta"],
                "gates": final["gates"]}

    def place_gaussians(self, raw: Tensor, depth: Tensor, offset: Tensor | None, w2c: Tensor, K: Tensor,
                        images: Tensor):
        """The Gaussians of one decoding (``raw`` from the Gaussian head, ``depth [B, V, 1, H, W]``, ``offset``)
        placed with the cameras ``w2c [B, V, 4, 4]``, ``K [B, V, 3, 3]``: e.g. the scaffold's decoding at Stage
        II's re-placed cameras, so the two differ only by what Stage II changed in the content."""
        with _float32_region(images.device):  # float32, as in forward
            return self._gaussians(raw.float(), pixel_centres(depth, K, w2c, offset), depth.float(), K.float(),
                                   images.float())

    def _gaussians(self, raw: Tensor, means: Tensor, depth: Tensor, K: Tensor, images: Tensor):
        aux = {"rgb": images if self.cfg.color_mode == "pixel" else None,
               "footprint": pixel_footprint(depth, K) if self.cfg.scale_mode == "pixel" else None}
        return raw_to_gaussians(raw, means, self.cfg.sh_degree, self.cfg.voxel_size, **aux)
