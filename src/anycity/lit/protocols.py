"""Evaluation protocols: how the held-out target views are rendered, one function per protocol, each named for
the images it reads. Scoring (PSNR, SSIM, regions, depth) happens in the caller; a protocol only renders.

=====================  ==========================================================  ===============================
protocol               what it does                                                images it reads
=====================  ==========================================================  ===============================
``feedforward``        the network's Gaussians rendered at the targets' ground-    context images (through the
                       truth poses, placed in the predicted frame by the context   network) only
                       cameras (``eval_align``: Sim(3) fit of the context poses,
                       or the first-camera convention)
``camrefine``          the predicted context cameras refined photometrically       context images only
                       against the context images (Gaussians frozen), then the
                       targets placed as above
``targetalign``        each placed target camera refined against its own target    context images and the
                       image (AnySplat ``test.align_pose``, NoPoSplat protocol)    target image
``joint``              context and target images through the network together;     context and target images
                       the targets rendered at the network's own target cameras    (both through the network)
                       from the context views' Gaussians (AnySplat / WorldMirror);
                       a padded chunk's repeated targets are not fed again
=====================  ==========================================================  ===============================

``feedforward`` and ``camrefine`` receive target *cameras* (:class:`TargetCameras`) and never a target image, so
they cannot read one; ``targetalign`` and ``joint`` receive the target :class:`Views`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

from anycity.geometry import camera_centers
from anycity.lit.evaluation import scored_targets, transform_gaussians
from anycity.structures import Gaussians, RenderOutput, Views

PROTOCOLS = ("feedforward", "camrefine", "targetalign", "joint")


@dataclass
class TargetCameras:
    """Ground-truth target cameras without their images: ``w2c [B, T, 4, 4]``, ``K [B, T, 3, 3]``, ``hw``."""

    w2c: Tensor
    K: Tensor
    hw: tuple[int, int]

    @classmethod
    def of(cls, views: Views) -> TargetCameras:
        return cls(views.w2c, views.K, views.hw)


@dataclass
class Scene:
    """What the network (or a test-time step) made of the context: Gaussians of B scenes, context cameras
    ``w2c [B, V, 4, 4]`` and ``K [B, V, 3, 3]`` in the predicted frame."""

    gaussians: Gaussians
    w2c: Tensor
    K: Tensor


def place(module, scene: Scene, context: Views, targets: TargetCameras) -> tuple[Tensor, Tensor]:
    """Ground-truth target cameras in the scene's predicted frame (``module.target_cameras``: the Sim(3) fit of
    the predicted to the ground-truth context poses, or the first-camera convention anchored at the scene's first
    camera as predicted) and the depth scale ``s [B]``."""
    return module.target_cameras(scene.w2c, context, Views(context.images, targets.w2c, targets.K), anchor_first=True)


def feedforward(module, scene: Scene, context: Views, targets: TargetCameras) -> tuple[RenderOutput, Tensor]:
    """Render the network's Gaussians at the placed target cameras. Reads no target image.
    Returns the render ``[B, T, ...]`` and the depth scale ``s [B]`` (pred = s * ground truth)."""
    w2c, s = place(module, scene, context, targets)
    return module.render(scene.gaussians, w2c, targets.K, targets.hw, context.images), s


def camrefine(module, scene: Scene, context: Views, targets: TargetCameras,
              steps: int) -> tuple[RenderOutput, Tensor, Scene]:
    """Refine the context cameras from the context images alone (:meth:`AnyCityModule.refine_cameras`), move each
    view's Gaussians with its camera, then render as :func:`feedforward`. Reads no target image.
    Returns the render, the depth scale and the refined scene (for the pose metrics and later protocols)."""
    w2c, A = module.refine_cameras(scene.gaussians, scene.w2c, scene.K, context.images, steps)
    refined = Scene(transform_gaussians(scene.gaussians, A), w2c, scene.K)
    render, s = feedforward(module, refined, context, targets)
    return render, s, refined


def targetalign(module, scene: Scene, context: Views, target: Views, steps: int) -> tuple[RenderOutput, Tensor]:
    """Place the targets as :func:`feedforward`, then refine each target camera against its own image (Gaussians
    frozen) before rendering. Reads the target images."""
    w2c, s = place(module, scene, context, TargetCameras.of(target))
    w2c = module.align_targets(scene.gaussians, w2c, target, context.images, steps)
    return module.render(scene.gaussians, w2c, target.K, target.hw, context.images), s


def joint(module, context: Views, target: Views) -> tuple[dict[str, RenderOutput], Tensor]:
    """AnySplat / WorldMirror protocol: the V context and T target images go through the network together; the
    Gaussians of the V context views are rendered at the network's own T target cameras (no pose fit, no
    optimisation). AnySplat rescales the target translations by the ratio of the context translations to put
    them in ground-truth units; rendering in the predicted frame with the predicted target cameras is the same
    picture (Gaussians and cameras scaled together), so that ratio is used only as the depth scale.
    Reads the target images (through the network). Needs targets of the context's size and pixel-aligned Gaussians.
    A sample whose chunk evaluation padded with repeats of its own targets (:func:`scored_targets`) feeds only its
    distinct targets to the network (the network sees every input image, so repeats would change the scene); each
    repeat gets the render of its first occurrence.
    Returns the renders of every variant (``{name: RenderOutput}``, ``[B, T, ...]``) and the depth scale ``s [B]``
    (mean context camera distance from the first camera, predicted over ground truth)."""
    if target.hw != context.hw:
        raise ValueError(f"joint protocol: targets {target.hw} must have the context size {context.hw}")
    keep = scored_targets(target.index)
    if keep is None or bool(keep.all()):
        return _joint(module, context.images, context.w2c, target.images)
    b, t = target.index.shape
    keep = keep.view(b, t)
    first = (target.index[:, :, None] == target.index[:, None, :]) & keep[:, None, :]  # [B, T, T]: one True a row
    slot = (first * (keep.cumsum(1) - 1)[:, None, :]).sum(-1)  # [B, T]: the first occurrence among the distinct
    parts = []
    for i in range(b):  # samples may have different numbers of distinct targets
        renders, s = _joint(module, context.images[i:i + 1], context.w2c[i:i + 1], target.images[i:i + 1, keep[i]])
        parts.append(({name: _views_of(r, slot[i]) for name, r in renders.items()}, s))
    renders = {name: _cat([p[0][name] for p in parts]) for name in parts[0][0]}
    return renders, torch.cat([p[1] for p in parts])


def _joint(module, context_images: Tensor, context_w2c: Tensor,
           target_images: Tensor) -> tuple[dict[str, RenderOutput], Tensor]:
    """:func:`joint` on ``context_images [B, V, 3, H, W]`` (ground-truth ``context_w2c [B, V, 4, 4]``) and
    ``target_images [B, T, 3, H, W]``, every target fed to the network."""
    v, hw = context_images.shape[1], tuple(context_images.shape[-2:])
    out, variants = module.predict_variants(torch.cat([context_images, target_images], dim=1))
    renders = {}
    for name, g in variants.items():
        w2c, K = module.variant_cameras(out, name)
        w2c_t, K_t = w2c[:, v:], K[:, v:]
        if g.valid is not None:
            raise ValueError("joint protocol: needs the network's pixel-aligned Gaussians (net.voxel_size=None) to "
                             "tell the context views' Gaussians from the targets'")
        n = g.means.shape[1] // out["w2c"].shape[1] * v  # the context views' pixel-aligned Gaussians come first
        ctx_g = Gaussians(g.means[:, :n], g.quats[:, :n], g.scales[:, :n], g.opacities[:, :n], g.sh[:, :n])
        renders[name] = module.render(ctx_g, w2c_t, K_t, hw, context_images)
    pred_d = _mean_distance_from_first(camera_centers(out["w2c"][:, :v]))  # the head does not pin view 0 at 0
    gt_d = _mean_distance_from_first(camera_centers(context_w2c.float()))
    s = torch.where(gt_d > 1e-8, pred_d / gt_d.clamp_min(1e-8), torch.ones_like(gt_d))
    return renders, s


def _views_of(r: RenderOutput, views: Tensor) -> RenderOutput:
    """``r`` at the views ``views [T']`` (indices into dim 1, repeats allowed)."""
    return RenderOutput(**{f.name: None if (x := getattr(r, f.name)) is None else x[:, views] for f in fields(r)})


def _cat(rs: list[RenderOutput]) -> RenderOutput:
    """Renders of single samples stacked on the batch dim."""
    parts = {f.name: [getattr(r, f.name) for r in rs] for f in fields(RenderOutput)}
    return RenderOutput(**{k: None if xs[0] is None else torch.cat(xs) for k, xs in parts.items()})


def _mean_distance_from_first(centers: Tensor) -> Tensor:
    """Mean distance ``[B]`` of the camera centres ``[B, V, 3]`` from the first one."""
    return (centers - centers[:, :1]).norm(dim=-1).mean(1)
