"""Network sizes. ``build_network(preset, **overrides)`` is the public entry point.

* ``tiny``: CPU tests and the quickstart (conv patch 8 so 64x64 and 112x112 work, 4 layer pairs, 1.58M params).
* ``small``: a laptop-GPU model (conv patch 14, 8 pairs of 256-d blocks).
* ``base``: DINOv2-B/14 patch embed, 12 pairs of 768-d blocks.
* ``vggt-1b``: VGGT-1B exactly (aggregator 909.1M, camera head 216.2M, depth head 32.7M) + AnySplat's Gaussian
  head (SH degree 4) + the completion branch. Its video prior defaults to the small built-in one; pass
  ``video_prior="wan", wan_dir=...`` for Wan 2.2 (the paper's prior).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from numbers import Integral

from anycity.models.completion import scale_layers

VGGT_HEAD_LAYERS = (4, 11, 17, 23)
PAPER_INJECT_LAYERS = (4, 7, 11, 23)
# integer options: (lowest, highest or None, what the bound means)
INT_RANGES: dict[str, tuple[int, int | None, str]] = {
    "sh_degree": (0, 4, "the renderer's SH degrees; AnySplat's weights use 4"),
    "camera_iterations": (1, None, "the camera head's refinement steps; VGGT uses 4"),
    **{name: (1, None, "a size") for name in ("embed_dim", "num_heads", "patch_size", "img_size", "camera_num_heads",
                                              "dpt_features", "completion_dim", "completion_tokens",
                                              "completion_heads", "prior_dim")},
    **{name: (0, None, "a count; 0 = none") for name in ("num_register_tokens", "camera_trunk_depth", "prior_depth",
                                                        "wan_lora_rank")},
}


@dataclass(frozen=True)
class NetConfig:
    # aggregator
    embed_dim: int = 1024
    depth: int = 24
    num_heads: int = 16
    patch_size: int = 14
    patch_embed: str = "dinov2_vitl14_reg"
    img_size: int = 518
    num_register_tokens: int = 4
    # heads
    head_layers: tuple[int, ...] | None = None  # None: VGGT's (4, 11, 17, 23) scaled to depth
    camera_trunk_depth: int = 4
    camera_num_heads: int = 16
    camera_iterations: int = 4
    dpt_features: int = 256
    dpt_out_channels: tuple[int, ...] = (256, 512, 1024, 1024)
    sh_degree: int = 4
    # slope of the Gaussian head's last hidden activation: 0 = ReLU (AnySplat, for its weights); > 0 a leaky ReLU for
    # models trained from scratch, whose ReLU layer dies (constant opacity/scale/colour that Stage II cannot change)
    gaussian_head_slope: float = 0.0
    voxel_size: float | None = None  # None: pixel-aligned Gaussians, no merge
    # "head": the Gaussian head predicts the full SH (AnySplat); "pixel": SH DC = the input pixel's colour plus the
    # head's residual (the head's SH outputs start near zero at random init)
    color_mode: str = "head"
    # "absolute": scale = 0.001 * softplus (AnySplat); "pixel": scale = (depth / focal) * softplus, i.e. relative to
    # the pixel's footprint in its own view
    scale_mode: str = "absolute"
    # random init only: bias the camera head to an identity rotation and this field of view (radians); None keeps
    # VGGT's init (whose ReLU FoV starts at 0, which the pose decode clamps to 1e-4 rad: a huge focal length, no
    # gradient). Pretrained weights override it.
    camera_init_fov: float | None = None
    # focal length from the predicted FoV: "vggt" or "anysplat" (AnySplat's +1e-3; load_pretrained(kind="anysplat")
    # sets it, and it travels in the hyperparameters and the Stage I -> Stage II hand-over)
    focal_decode: str = "vggt"
    # completion branch + video prior
    completion: bool = True
    completion_dim: int = 1024
    completion_tokens: int = 256
    completion_heads: int = 16
    # None: the paper's (4, 7, 11, 23) scaled to depth by completion.scale_layers, which merges layers that land on
    # the same one: tiny (depth 4) gets 3 injection stages (0, 1, 3), small (8) (1, 2, 3, 7), base (12) (1, 3, 5, 11)
    inject_layers: tuple[int, ...] | None = None
    video_prior: str = "small"  # small | wan | wan-tiny | none
    prior_dim: int = 256
    prior_depth: int = 2
    prior_stride: int = 16
    wan_dir: str | None = None
    # Wan block whose output feeds the completion branch; None = the middle one (14 of TI2V-5B's 30): block 0 is
    # little more than the patchified VAE latent, and diffusion-feature studies find mid-depth features carry the
    # most correspondence/semantic signal; later blocks cost more (all kept blocks run, LoRA backprops through them)
    wan_block: int | None = None
    wan_t_feat: float = 0.0
    wan_lora_rank: int = 16  # LoRA (float32) on attn1 q/k/v/out of the kept blocks; 0 = frozen prior
    # umT5 embedding of "" as a [1, L, 4096] tensor (torch.save); None: <wan_dir>/empty_prompt.pt if present, else zeros
    wan_empty_prompt: str | None = None
    # Stage II: the depth head also decodes Z_final = Z_geo + dZ (else only the Gaussian head does, centre offsets
    # included); measured on the quickstart, see docs/stage2.md "Levers tried"
    refine_depth: bool = True
    # Beyond the paper (whose cameras stay the scaffold's): the completion residual also reaches the camera token the
    # frozen camera head reads, so Stage II can re-place the views; train it with RefinementModule(camera_weight>0).
    # Measured on the quickstart in docs/stage2.md
    refine_cameras: bool = False
    # Beyond the paper, with refine_cameras: the camera residual of each view also reads that view's own video-prior
    # features, which know the frame's place in the clip (the scaffold is equivariant over views 1..V-1)
    camera_video: bool = False
    # Beyond the paper, with refine_cameras: a frozen pretrained pose prior (models/pose_prior.py; the .pt that
    # scripts/pose_prior.py writes, or "random" for tests) whose per-view pose each camera residual also reads.
    # Content-based and order-free, it stands in for the camera motion a pretrained video model knows
    pose_prior: str | None = None
    # Beyond the paper, with pose_prior: each re-placed pose also moves towards the prior's own, by per-view amounts
    # (translation, rotation) a zero-initialised linear of the camera residual's features gives; docs/stage2.md
    pose_prior_mix: bool = False

    def resolved_head_layers(self) -> tuple[int, ...]:
        return tuple(self.head_layers) if self.head_layers else scale_layers(VGGT_HEAD_LAYERS, self.depth)

    def resolved_inject_layers(self) -> tuple[int, ...]:
        return tuple(self.inject_layers) if self.inject_layers else scale_layers(PAPER_INJECT_LAYERS, self.depth)


PRESETS: dict[str, NetConfig] = {
    "tiny": NetConfig(embed_dim=64, depth=4, num_heads=4, patch_size=8, patch_embed="conv", camera_trunk_depth=1,
                      camera_num_heads=4, dpt_features=32, dpt_out_channels=(16, 32, 64, 64), sh_degree=1,
                      completion_dim=64, completion_tokens=16, completion_heads=4, prior_dim=64, prior_depth=1,
                      color_mode="pixel", scale_mode="pixel", camera_init_fov=1.0, gaussian_head_slope=0.1),
    "small": NetConfig(embed_dim=256, depth=8, num_heads=8, patch_size=14, patch_embed="conv", camera_trunk_depth=2,
                       camera_num_heads=8, dpt_features=128, dpt_out_channels=(64, 128, 256, 256), sh_degree=2,
                       completion_dim=256, completion_tokens=64, completion_heads=8, prior_dim=128,
                       camera_init_fov=1.0, gaussian_head_slope=0.1),
    "base": NetConfig(embed_dim=768, depth=12, num_heads=12, patch_embed="dinov2_vitb14_reg", camera_trunk_depth=2,
                      camera_num_heads=12, dpt_features=256, dpt_out_channels=(128, 256, 512, 512), sh_degree=3,
                      completion_dim=512, completion_tokens=128, completion_heads=8, prior_dim=256,
                      camera_init_fov=1.0, gaussian_head_slope=0.1),
    "vggt-1b": NetConfig(),
}


def preset_config(preset: str, **overrides) -> NetConfig:
    if preset not in PRESETS:
        raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got {preset!r}")
    names = {f.name for f in fields(NetConfig)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ValueError(f"build_network: unknown option(s) {unknown}; valid options are {sorted(names)}")
    cfg = replace(PRESETS[preset], **overrides)
    check_int_options(cfg)
    check_widths(cfg)
    for name, allowed in (("color_mode", ("head", "pixel")), ("scale_mode", ("absolute", "pixel"))):
        if getattr(cfg, name) not in allowed:
            raise ValueError(f"{name}: expected one of {list(allowed)}, got {getattr(cfg, name)!r}")
    layers = cfg.resolved_head_layers()
    if len(layers) != 4 or not all(0 <= i < cfg.depth for i in layers):
        raise ValueError(f"head_layers: the DPT heads read 4 aggregator layers of 0..{cfg.depth - 1}, got "
                         f"{list(layers)} (depth {cfg.depth}); use depth >= 4 or give head_layers 4 indices")
    inject = cfg.resolved_inject_layers()
    if cfg.completion and not all(0 <= i < cfg.depth for i in inject):
        raise ValueError(f"inject_layers: the completion branch reads aggregator layers 0..{cfg.depth - 1} of this "
                         f"preset (depth {cfg.depth}), got {list(inject)}; set net.inject_layers: null (the paper's "
                         f"{list(PAPER_INJECT_LAYERS)} scaled to the depth) or give indices below {cfg.depth}")
    return cfg


def check_int_options(cfg: NetConfig) -> None:
    """One line naming ``net.<option>`` for an integer option out of its range (:data:`INT_RANGES`)."""
    for name, (lo, hi, why) in INT_RANGES.items():
        v = getattr(cfg, name)
        if not isinstance(v, Integral) or isinstance(v, bool) or v < lo or (hi is not None and v > hi):
            span = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            raise ValueError(f"net.{name}: expected an integer {span} ({why}), got {v!r}")


def check_widths(cfg: NetConfig) -> None:
    """One line naming ``net.<option>`` for a width the layers cannot split: the aggregator's 2D RoPE needs a head
    width ``embed_dim / num_heads`` that is a multiple of 4, the camera head and the completion branch whole heads,
    the DPT heads' UV embedding a multiple of 4 for each of the 4 ``dpt_out_channels`` and for
    ``dpt_features / 2``."""
    dim, heads = cfg.embed_dim, cfg.num_heads
    if dim % (4 * heads):
        fits = [n for n in range(1, heads + 1) if dim % (4 * n) == 0]
        fix = f"use num_heads {fits[-1]}" if fits else "use an embed_dim that is a multiple of 4 * num_heads"
        raise ValueError(f"net.num_heads: expected a divisor of embed_dim {dim} that leaves a head width divisible "
                         f"by 4 (the aggregator's 2D RoPE), got {heads} (head width {dim / heads:g}); {fix}")
    for name, width, what in (("camera_num_heads", 2 * dim, "the camera head's width, 2 * embed_dim"),
                              ("completion_heads", cfg.completion_dim, "completion_dim")):
        n = getattr(cfg, name)
        if width % n:
            fits = [k for k in range(1, n + 1) if width % k == 0]
            raise ValueError(f"net.{name}: expected a divisor of {what} ({width}), got {n}; use {name} {fits[-1]}")
    f = cfg.dpt_features
    if f % 8:
        raise ValueError(f"net.dpt_features: expected a multiple of 8 (the DPT heads halve it and their UV embedding "
                         f"needs a multiple of 4), got {f}; use {f + (-f) % 8}")
    oc = cfg.dpt_out_channels
    ok = isinstance(oc, (tuple, list)) and len(oc) == 4 and all(
        isinstance(c, Integral) and not isinstance(c, bool) and c > 0 and c % 4 == 0 for c in oc)
    if not ok:
        raise ValueError(f"net.dpt_out_channels: expected 4 positive multiples of 4 (one width per DPT layer; the UV "
                         f"embedding needs a multiple of 4), got {list(oc) if isinstance(oc, (tuple, list)) else oc!r}"
                         f"; e.g. {list(PRESETS['tiny'].dpt_out_channels)}")


def build_network(preset: str = "tiny", **overrides):
    """A new :class:`anycity.models.anycity.AnyCityNet` of ``preset`` with random weights (train mode).

    ``preset``: ``"tiny"`` (CPU, quickstart; patch 8), ``"small"`` (laptop GPU; patch 14), ``"base"`` (DINOv2-B/14),
    ``"vggt-1b"`` (VGGT-1B's architecture and parameter names); see :data:`PRESETS` and this module's docstring.
    ``overrides``: any :class:`NetConfig` field, e.g. ``sh_degree=0``, ``completion=False`` (scaffold only, as
    Stage I), ``video_prior="wan", wan_dir=...``, ``voxel_size=0.01``, ``camera_trunk_depth=2``; an unknown name or
    an out-of-range value is a one-line ``ValueError`` listing the valid ones.

    Weights: :func:`anycity.models.load_checkpoint` rebuilds and loads the network an ``anycity fit`` checkpoint
    trained (preset and overrides included); :func:`anycity.models.pretrained.load_pretrained` copies VGGT-1B or
    AnySplat weights into a network built here. For inference, switch to eval mode and drop autograd (a fraction of
    the memory)::

        net = build_network("tiny").eval()
        with torch.inference_mode():
            out = net(images)  # images [B, V, 3, H, W] in [0, 1], H and W multiples of net.cfg.patch_size
    """
    from anycity.models.anycity import AnyCityNet

    return AnyCityNet(preset_config(preset, **overrides))


__all__ = ["NetConfig", "PRESETS", "build_network", "preset_config"]
