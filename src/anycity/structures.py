"""Data containers shared by every package: Gaussians, renders, cameras and training batches.

Dim glossary (see ``docs/design.md``): B batch, V views, T targets, N Gaussians, K SH coefficients,
H/W image height/width in pixels. Cameras follow OpenCV (x right, y down, z forward); ``w2c`` is the
world-to-camera 4x4 matrix and ``K`` the 3x3 pinhole intrinsics in pixels of the image they travel with.

Every container has ``validate()``, which raises ``ValueError`` naming the field, the expected shape and
what was given. Containers are dataclasses, so Lightning moves them between devices as a whole.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814  # Y_0^0, so that colour = SH_C0 * sh_dc + 0.5
IMAGE_MIN, IMAGE_MAX = -1e-3, 1.0 + 1e-3  # [0, 1] images, with room for a resize's rounding


def image_range(images: Tensor) -> tuple[float, float, str | None]:
    """``(min, max, fault)`` of images meant to hold [0, 1] values (one reduction, one host sync). ``fault`` says
    what they look like instead, for the caller's fix: None (fine), "nonfinite" (NaN or inf), "signed" ([-1, 1]),
    "normalised" (mean/std, e.g. ImageNet), "0-255", or "over" (a little above 1)."""
    lo, hi = torch.stack(torch.aminmax(images.detach())).tolist()
    if not (math.isfinite(lo) and math.isfinite(hi)):  # aminmax spreads a NaN to both
        return lo, hi, "nonfinite"
    if lo < IMAGE_MIN:
        return lo, hi, "signed" if lo >= -1 + IMAGE_MIN and hi <= IMAGE_MAX else "normalised"
    if hi > IMAGE_MAX:
        return lo, hi, "0-255" if hi > 2 else "over"
    return lo, hi, None


def _shape_error(name: str, expected: str, t: Tensor) -> ValueError:
    return ValueError(f"{name}: expected shape {expected}, got {tuple(t.shape)}")


def _check_finite(name: str, t: Tensor) -> None:
    # A sum is NaN or inf when any element is, and costs a fifth of an elementwise test (renders validate their
    # Gaussians on every call); only a non-finite sum, which finite elements can also give by overflowing, is
    # tested element by element.
    if t.is_floating_point() and not bool(t.detach().sum().isfinite()) and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or infinite values; check the upstream computation")


def _render_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype a Gaussian field renders in: ``render()`` upcasts float16/bfloat16 fields to float32."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def sh_degree_from_k(k: int) -> int:
    """Number of SH coefficients ``K = (degree + 1)**2`` -> degree; raises for other K."""
    d = math.isqrt(k) - 1
    if d < 0 or (d + 1) ** 2 != k or d > 4:
        raise ValueError(f"sh: expected K = (degree+1)^2 coefficients with degree 0..4, got K={k}")
    return d


@dataclass
class Gaussians:
    """A batch of 3D Gaussian scenes.

    Attributes:
        means: ``[B, N, 3]`` centres in world units.
        quats: ``[B, N, 4]`` rotations, **wxyz**, need not be normalised (a zero-norm one renders, but
            ``anycity.export`` drops it).
        scales: ``[B, N, 3]`` standard deviations along the rotated axes, in world units (activated: ``validate``
            refuses negative values, e.g. log-scales; a zero renders as the renderer's 0.3 px low-pass, but
            ``anycity.export`` drops it).
        opacities: ``[B, N]`` in [0, 1] (activated: ``validate`` refuses other values).
        sh: ``[B, N, K, 3]`` spherical-harmonic coefficients, K = (degree+1)^2; degree 0 gives
            colour = 0.282095 * sh + 0.5.
        valid: ``[B, N]`` bool, or None (all valid). Invalid Gaussians contribute nothing; ragged
            batches pad with invalid entries instead of huge values.

    Every field but ``valid`` is floating point with the dtype of ``means``; float16/bfloat16 fields count as
    float32 (``render()`` upcasts them), so a mixed-precision head's output validates.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    valid: Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[1]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_k(self.sh.shape[2])

    def validate(self) -> Gaussians:
        m = self.means
        if m.dim() != 3 or m.shape[-1] != 3:
            raise _shape_error("gaussians.means", "[B, N, 3]", m)
        if not m.is_floating_point():
            raise ValueError(f"gaussians.means: expected a floating-point dtype, got {m.dtype}; cast every field "
                             "with gaussians.to(dtype=torch.float32)")
        for name in ("quats", "scales", "opacities", "sh"):
            t = getattr(self, name)
            if not t.is_floating_point() or _render_dtype(t.dtype) != _render_dtype(m.dtype):
                raise ValueError(f"gaussians.{name}: expected dtype {m.dtype} like means, got {t.dtype}; cast every "
                                 "field to one dtype with gaussians.to(dtype=...)")
        b, n = m.shape[:2]
        expect = {
            "quats": (self.quats, (b, n, 4), "[B, N, 4]"),
            "scales": (self.scales, (b, n, 3), "[B, N, 3]"),
            "opacities": (self.opacities, (b, n), "[B, N]"),
        }
        for name, (t, shape, text) in expect.items():
            if tuple(t.shape) != shape:
                raise _shape_error(f"gaussians.{name}", f"{text} = {shape}", t)
        if self.sh.dim() != 4 or self.sh.shape[:2] != (b, n) or self.sh.shape[3] != 3:
            raise _shape_error("gaussians.sh", f"[B, N, K, 3] with B={b}, N={n}", self.sh)
        sh_degree_from_k(self.sh.shape[2])
        if self.valid is not None:
            if tuple(self.valid.shape) != (b, n):
                raise _shape_error("gaussians.valid", f"[B, N] = {(b, n)}", self.valid)
            if self.valid.dtype != torch.bool:
                raise ValueError(f"gaussians.valid: expected dtype bool, got {self.valid.dtype}")
        floats = []
        for f in fields(self):
            t = getattr(self, f.name)
            if t is not None:
                if t.device != m.device:
                    raise ValueError(f"gaussians.{f.name}: on {t.device}, but means are on {m.device}")
                if f.name != "opacities" and t.is_floating_point():  # checked below
                    floats.append((f.name, t))
        # one host sync for every field (a render validates on each call; on a GPU each sync waits for the queued
        # work): a sum is NaN or inf when any element is and costs a fifth of an elementwise test; min and max are
        # NaN when any element is, so opacities in [0, 1] are finite too. A non-finite sum, which finite elements can
        # also give by overflowing, or opacities out of [0, 1], are looked at closely.
        stats = [t.detach().sum().float() for _, t in floats]
        if self.opacities.numel():
            lo, hi = torch.aminmax(self.opacities.detach())
            stats += [lo.float(), hi.float(), self.scales.detach().amin().float()]
        values = torch.stack(stats).tolist() if stats else []
        for (name, t), total in zip(floats, values):
            if not math.isfinite(total):
                _check_finite(f"gaussians.{name}", t)
        if self.opacities.numel():
            lo, hi, smin = values[len(floats):]
            if not (lo >= 0 and hi <= 1):
                _check_finite("gaussians.opacities", self.opacities)
                raise ValueError(f"gaussians.opacities: expected values in [0, 1], got [{lo:.4g}, {hi:.4g}]; apply "
                                 "sigmoid to opacity logits (the backends disagree outside [0, 1])")
            # zero scales (and zero-norm quaternions) are left alone: the network's softplus can underflow to them,
            # and every render validates; they render as the 0.3 px low-pass, and export drops them with a warning
            if smin < 0:
                raise ValueError(f"gaussians.scales: expected standard deviations >= 0, got a minimum of {smin:.4g}; "
                                 "these look like log-scales (graphdeco's raw scales): pass scales.exp()")
        return self

    def detach(self) -> Gaussians:
        return Gaussians(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name).detach()
                            for f in fields(self)})

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Gaussians:
        """Move to ``device``; cast floating fields to ``dtype`` (``valid`` stays bool)."""
        out = {}
        for f in fields(self):
            t = getattr(self, f.name)
            out[f.name] = None if t is None else t.to(device=device, dtype=dtype if t.is_floating_point() else None)
        return Gaussians(**out)

    def float(self) -> Gaussians:
        return self.to(dtype=torch.float32)


@dataclass
class RenderOutput:
    """What ``anycity.render.render`` returns for B scenes seen from V cameras each.

    Attributes:
        rgb: ``[B, V, 3, H, W]`` in [0, +inf) (background composited with the final transmittance).
        depth: ``[B, V, 1, H, W]`` alpha-normalised expected camera z (0 where alpha is 0).
        alpha: ``[B, V, 1, H, W]`` accumulated opacity 1 - T_final.
        normal: ``[B, V, 3, H, W]`` alpha-blended per-Gaussian normals in the camera frame, or None.
    """

    rgb: Tensor
    depth: Tensor
    alpha: Tensor
    normal: Tensor | None = None

    def validate(self) -> RenderOutput:
        if self.rgb.dim() != 5 or self.rgb.shape[2] != 3:
            raise _shape_error("render.rgb", "[B, V, 3, H, W]", self.rgb)
        b, v, _, h, w = self.rgb.shape
        for name, c in (("depth", 1), ("alpha", 1), ("normal", 3)):
            t = getattr(self, name)
            if t is None:
                continue
            if tuple(t.shape) != (b, v, c, h, w):
                raise _shape_error(f"render.{name}", f"[B, V, {c}, H, W] = {(b, v, c, h, w)}", t)
        return self


@dataclass
class Views:
    """A set of posed views of B scenes, V views each.

    Attributes:
        images: ``[B, V, 3, H, W]`` float in [0, 1].
        w2c: ``[B, V, 4, 4]`` world-to-camera (OpenCV).
        K: ``[B, V, 3, 3]`` intrinsics in pixels of ``images``.
        depth: ``[B, V, 1, H, W]`` z-depth in the sample's normalised world units, or None.
        mask: ``[B, V, 1, H, W]`` bool, True where depth/normal are valid (not sky), or None.
        normal: ``[B, V, 3, H, W]`` unit normals in the camera frame, or None.
        index: ``[B, V]`` long, each view's position in its trajectory, or None.

    ``validate(compact=True)`` also accepts the data loader's compact form (uint8 images in [0, 255]; see
    ``anycity.data.pipeline.to_float32``).
    """

    images: Tensor
    w2c: Tensor
    K: Tensor
    depth: Tensor | None = None
    mask: Tensor | None = None
    normal: Tensor | None = None
    index: Tensor | None = None

    @property
    def num_views(self) -> int:
        return self.images.shape[1]

    @property
    def hw(self) -> tuple[int, int]:
        return int(self.images.shape[-2]), int(self.images.shape[-1])

    def validate(self, name: str = "views", compact: bool = False) -> Views:
        """Shapes, dtypes and devices only (no pass over the pixels); ``compact``: uint8 images are accepted."""
        img = self.images
        if img.dim() != 5 or img.shape[2] != 3:
            raise _shape_error(f"{name}.images", "[B, V, 3, H, W]", img)
        if not (img.is_floating_point() or (compact and img.dtype == torch.uint8)):
            raise ValueError(f"{name}.images: expected float in [0, 1]{' (or compact uint8)' if compact else ''}, got "
                             f"{img.dtype}; convert with images.float() / 255 (anycity.data.pipeline.to_float32)")
        b, v, _, h, w = img.shape
        if tuple(self.w2c.shape) != (b, v, 4, 4):
            raise _shape_error(f"{name}.w2c", f"[B, V, 4, 4] = {(b, v, 4, 4)}", self.w2c)
        if tuple(self.K.shape) != (b, v, 3, 3):
            raise _shape_error(f"{name}.K", f"[B, V, 3, 3] = {(b, v, 3, 3)}", self.K)
        for attr, c in (("depth", 1), ("mask", 1), ("normal", 3)):
            t = getattr(self, attr)
            if t is not None and tuple(t.shape) != (b, v, c, h, w):
                raise _shape_error(f"{name}.{attr}", f"[B, V, {c}, H, W] = {(b, v, c, h, w)}", t)
        if self.index is not None and tuple(self.index.shape) != (b, v):
            raise _shape_error(f"{name}.index", f"[B, V] = {(b, v)}", self.index)
        for attr in ("w2c", "K", "depth", "normal"):
            t = getattr(self, attr)
            if t is not None and not t.is_floating_point():
                raise ValueError(f"{name}.{attr}: expected a floating-point dtype, got {t.dtype}; cast it with "
                                 ".float()")
        if self.mask is not None and self.mask.dtype != torch.bool:
            raise ValueError(f"{name}.mask: expected dtype bool (True where depth is valid), got {self.mask.dtype}; "
                             "pass mask > 0.5")
        if self.index is not None and (self.index.is_floating_point() or self.index.is_complex()
                                       or self.index.dtype == torch.bool):
            raise ValueError(f"{name}.index: expected an integer dtype (long), got {self.index.dtype}; cast it with "
                             ".long()")
        for f in fields(self):
            t = getattr(self, f.name)
            if t is not None and t.device != img.device:
                raise ValueError(f"{name}.{f.name}: on {t.device}, but images are on {img.device}; move the views "
                                 "together")
        return self


@dataclass
class ViewBatch:
    """One training/evaluation batch: B scene windows.

    Attributes:
        context: the sparse input views the network sees (V = 2..64, default 4).
        target: held-out views to render and score (T views).
        dense: the dense teacher set for Stage II distillation (default 12 views), or None.
        scene: B scene identifiers.
        scale: ``[B]`` metres per normalised world unit (multiply to get back to the source units).
        world_from_source: ``[B, 4, 4]`` the similarity applied to the source world frame
            (p_norm = world_from_source @ p_src, scale included), so outputs map back to the source.
    """

    context: Views
    target: Views
    dense: Views | None = None
    scene: list[str] | None = None
    scale: Tensor | None = None
    world_from_source: Tensor | None = None

    @property
    def batch_size(self) -> int:
        return self.context.images.shape[0]

    def validate(self, compact: bool = False) -> ViewBatch:
        """Shapes, dtypes and devices only (cheap enough for every batch); every group has the context's B.
        ``compact``: also accept the data loader's compact form (uint8 images)."""
        self.context.validate("batch.context", compact)
        b = self.batch_size
        for name in ("target", "dense"):
            views = getattr(self, name)
            if views is None:
                continue
            views.validate(f"batch.{name}", compact)
            if views.images.shape[0] != b:
                raise ValueError(f"batch.{name}: expected B={b} scenes like batch.context, got "
                                 f"{views.images.shape[0]}; build every view group from the same samples")
        if self.scene is not None and len(self.scene) != b:
            raise ValueError(f"batch.scene: expected {b} scene names (one per sample), got {len(self.scene)}")
        if self.scale is not None:
            if tuple(self.scale.shape) != (b,):
                raise _shape_error("batch.scale", f"[B] = {(b,)}", self.scale)
            if not self.scale.is_floating_point():
                raise ValueError(f"batch.scale: expected a floating-point dtype, got {self.scale.dtype}")
        if self.world_from_source is not None:
            if tuple(self.world_from_source.shape) != (b, 4, 4):
                raise _shape_error("batch.world_from_source", f"[B, 4, 4] = {(b, 4, 4)}", self.world_from_source)
            if not self.world_from_source.is_floating_point():
                raise ValueError(f"batch.world_from_source: expected a floating-point dtype, got "
                                 f"{self.world_from_source.dtype}")
        return self
