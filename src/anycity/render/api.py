"""``render()``: differentiable rasterisation of 3D Gaussians into B x V pinhole cameras.

Backends share one contract (all inputs already validated, ``valid`` filled, ``background`` expanded)::

    fn(means [B,N,3], quats [B,N,4], scales [B,N,3], opacities [B,N], sh [B,N,K,3], valid [B,N] bool,
       w2c [B,V,4,4], K [B,V,3,3], width, height, background [B,V,3], near, far, render_normals)
       -> (rgb [B,V,3,H,W], depth [B,V,1,H,W], alpha [B,V,1,H,W], normal [B,V,3,H,W] or None)
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
from typing import Literal

import torch
from torch import Tensor

from anycity.structures import Gaussians, RenderOutput

Backend = Literal["auto", "torch", "gsplat", "cpu"]
NEAR_MIN = 1e-6  # smallest near plane: the EWA Jacobian's 1/z and 1/z² stay finite (and so do the gradients)

# name -> "module:function"; imported on first use so that optional dependencies stay optional.
_BACKENDS = {
    "torch": "anycity.render.torch_backend:render_torch",
    "gsplat": "anycity.render.gsplat_backend:render_gsplat",
    "cpu": "anycity.render.cpu_backend:render_cpu",
}


@functools.cache  # availability cannot change within a process; keep import probing off the per-call path
def _module_available(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """The backend ``render`` would use for ``dtype`` tensors on ``device``: "auto" -> gsplat for float32 CUDA
    tensors when installed, else the fused "cpu" kernels for float32 CPU tensors when numba is installed, else
    "torch"."""
    if backend not in ("auto", *_BACKENDS):
        raise ValueError(f"backend: expected one of {['auto', *_BACKENDS]}, got {backend!r}")
    if backend != "auto":
        return backend
    if dtype != torch.float32:  # gsplat and the fused kernels are float32-only
        return "torch"
    if device.type == "cuda":
        if _module_available("gsplat"):
            if _gsplat_kernels():
                return "gsplat"
            _warn_gsplat_without_kernels()
        else:
            _warn_no_gsplat()
    if device.type == "cpu" and _cpu_backend_available():
        return "cpu"
    return "torch"


@functools.cache  # once per process
def _warn_no_gsplat() -> None:
    import warnings

    warnings.warn("render_backend='auto' on CUDA without gsplat: FALLING BACK TO THE PURE-PYTORCH RENDERER, which is "
                  "many times slower and uses far more memory; install it (pip install 'anycity[gsplat]', see "
                  "docker/Dockerfile) or set render_backend: torch to silence this", RuntimeWarning, stacklevel=3)


@functools.cache  # once per process: gsplat may build its kernels on this import (minutes, the first time)
def _gsplat_kernels() -> bool:
    """Whether an installed gsplat has its CUDA kernels (``gsplat_backend.kernels_available``)."""
    from anycity.render.gsplat_backend import kernels_available

    return kernels_available()


@functools.cache  # once per process
def _warn_gsplat_without_kernels() -> None:
    import warnings

    warnings.warn("render_backend='auto' on CUDA: gsplat is installed without its CUDA kernels (no prebuilt wheel "
                  f"for torch {torch.__version__} and no CUDA toolkit (nvcc) to build them): FALLING BACK TO THE "
                  "PURE-PYTORCH RENDERER, which is many times slower; install the gsplat wheel built for this torch "
                  "and CUDA, or the CUDA toolkit (see docker/Dockerfile), or set render_backend: torch to silence "
                  "this", RuntimeWarning, stacklevel=3)


@functools.cache
def _cpu_backend_available() -> bool:
    return importlib.util.find_spec("anycity.render.cpu_backend") is not None and _module_available("numba")


def _load(backend: str):
    if backend == "gsplat" and _module_available("gsplat") and not _gsplat_kernels():
        raise ValueError(f"backend='gsplat': gsplat is installed without its CUDA kernels (no prebuilt wheel for torch "
                         f"{torch.__version__} and no CUDA toolkit (nvcc) to build them); install the gsplat wheel "
                         "built for this torch and CUDA, or the CUDA toolkit, or use backend='torch'")
    module, fn = _BACKENDS[backend].split(":")
    try:
        return getattr(importlib.import_module(module), fn)
    except ImportError as e:
        extra = {"gsplat": "pip install 'anycity[gsplat]' (needs CUDA)", "cpu": "pip install 'anycity[cpu]' (numba)"}
        raise ValueError(f"backend={backend!r} is not available ({e}); install it with {extra.get(backend, '')} "
                         "or use backend='torch'") from e


def _check_cameras(name: str, t: Tensor, shape: tuple, text: str, like: Tensor) -> None:
    if not isinstance(t, Tensor) or tuple(t.shape[-2:]) != shape[-2:] or t.dim() != 4 or t.shape[0] != shape[0]:
        got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
        raise ValueError(f"{name}: expected shape {text} with B={shape[0]} (the Gaussians' batch), got {got}")
    if t.device != like.device:
        raise ValueError(f"{name}: on {t.device}, but the Gaussians are on {like.device}; move both to one device")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or infinite values")


def _tolerance(dtype: torch.dtype, floor: float) -> float:
    """``floor``, or 4 machine epsilons of ``dtype`` when larger (a bfloat16 rotation is exact to about 4e-3 only)."""
    return max(floor, 4 * torch.finfo(dtype).eps) if dtype.is_floating_point else floor


def _check_rotation(w2c: Tensor, dtype: torch.dtype) -> None:
    """Refuse a ``w2c`` that is not a rigid transform: a 3x3 block that is not orthonormal (geometry would come out
    right, x/z and y/z being scale-invariant, but the SH view directions would use the wrong camera centre
    ``-Rᵀ t``), a reflection (det R = -1: a mirrored image), or a bottom row other than [0, 0, 0, 1] (the torch and cpu
    backends ignore it, but gsplat inverts the whole 4x4 for the SH camera centre)."""
    w2c = w2c.detach().double()
    R = w2c[..., :3, :3]
    err = (R @ R.mT - torch.eye(3, dtype=R.dtype, device=R.device)).abs().amax(dim=(-2, -1))
    row = (w2c[..., 3, :] - torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=R.dtype, device=R.device)).abs().amax(-1)
    tol = _tolerance(dtype, 1e-3)
    det = (R[..., 0, :] * torch.linalg.cross(R[..., 1, :], R[..., 2, :])).sum(-1)  # no LU: a few flops per camera
    bad = torch.stack([(err > tol).any(), (det < 0).any(),  # one host sync for the three checks
                       (row > _tolerance(dtype, 1e-6)).any()]).tolist()
    if bad[0]:
        raise ValueError(f"w2c: the rotation block w2c[..., :3, :3] is not orthonormal (max |R R^T - I| = "
                         f"{err.max().item():.3g} > {tol:.3g}); pass rigid world-to-camera transforms: put a scale "
                         "into the scene, not the camera, or orthonormalise R (U V^T of its SVD)")
    if bad[1]:
        raise ValueError("w2c: the rotation block w2c[..., :3, :3] has determinant -1 (a reflection: the image would "
                         "come out mirrored), it must be +1; a flipped axis: check the y-up/y-down convention (OpenCV: "
                         "x right, y down, z forward)")
    if bad[2]:
        raise ValueError(f"w2c: bottom row w2c[..., 3, :] must be [0, 0, 0, 1], got one off by {row.max().item():.3g}; "
                         "pass 4x4 world-to-camera transforms (append [0, 0, 0, 1] to a 3x4 [R|t], not zeros)")


NORMALISED_MAX_WIDTH = 8  # images this narrow may have pixel focals below 2 px (tests' tiny renders): not checked


def _check_intrinsics(K: Tensor, dtype: torch.dtype, width: int, height: int) -> None:
    """Refuse what the renderer would silently ignore: skew and a last row other than [0, 0, 1]; and a ``K`` that
    looks normalised (fx, fy < 2 and cx, cy <= 1 for an image wider than 8 px), which renders a near-empty image."""
    K = K.detach().double()
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    skew = torch.maximum(K[..., 0, 1].abs(), K[..., 1, 0].abs())
    row = (K[..., 2, :] - torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype, device=K.device)).abs().amax(-1)
    unit = (fx < 2) & (fy < 2) & (K[..., 0, 2] <= 1) & (K[..., 1, 2] <= 1)
    bad = torch.stack([((fx <= 0) | (fy <= 0)).any(),  # one host sync for the four checks
                       (skew > torch.clamp(_tolerance(dtype, 0.0) * torch.maximum(fx, fy), min=1e-3)).any(),
                       (row > _tolerance(dtype, 1e-6)).any(), unit.any()]).tolist()
    if bad[0]:
        raise ValueError("K: focal lengths K[...,0,0] and K[...,1,1] must be > 0 (intrinsics in pixels)")
    if bad[1]:
        raise ValueError(f"K: skew K[..., 0, 1] or K[..., 1, 0] up to {skew.max().item():.3g} px, but the renderer "
                         "reads fx, fy, cx, cy only; pass pinhole intrinsics with zero skew (resample the image)")
    if bad[2]:
        raise ValueError(f"K: last row must be [0, 0, 1], got one off by {row.max().item():.3g}; pass pinhole "
                         "intrinsics in pixels (divide a homogeneous K by K[2, 2])")
    if bad[3] and width > NORMALISED_MAX_WIDTH:
        i = unit.flatten().nonzero()[0, 0]
        raise ValueError(f"K looks normalised (fx {fx.flatten()[i]:.4g}, cx {K[..., 0, 2].flatten()[i]:.4g} for a "
                         f"{width}x{height} image); multiply rows 0 and 1 by W and H (K[..., 0, :] *= {width}; "
                         f"K[..., 1, :] *= {height}): the renderer takes intrinsics in pixels")


def render(
    gaussians: Gaussians,
    w2c: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    render_normals: bool = False,
    backend: Backend = "auto",
) -> RenderOutput:
    """Rasterise B Gaussian scenes into V cameras each.

    Semantics follow gsplat's ``rasterization`` (``rasterize_mode="classic"``, ``render_mode="RGB+ED"``):

    - EWA projection ``Σ2D = J W Σ Wᵀ Jᵀ`` with the Jacobian taken at x/z, y/z clamped to the image extent plus
      30 % of the half field of view (Inria's 1.3 × tan(fov/2) for a centred principal point), then a 0.3 px²
      low-pass added to both diagonal terms.
    - Footprint: per axis ``ceil(3.33 · sqrt(Σ2D[i,i]))`` pixels; Gaussians with camera z outside [near, far],
      a non-positive-definite Σ2D, or a footprint that misses the image are culled.
    - Pixel centres at (j + 0.5, i + 0.5); ``σ = ½ dᵀ Σ2D⁻¹ d``, ``α = min(0.99, o · e^(−σ))``; a Gaussian is skipped
      at a pixel when σ < 0 or α < 1/255. Front-to-back compositing by camera z stops *before* the Gaussian that
      would bring the transmittance T to ≤ 1e-4. α is capped at 0.99 as in Inria and gsplat ≥ 1.6 (1.5.x used 0.999).
    - Colour from SH (degree from K) evaluated with the view direction from the camera centre to the mean, plus
      0.5, clamped at 0. The background is composited with the final transmittance: ``rgb += T · bg``.
    - Depth is the alpha-normalised expected camera z, ``Σ wᵢ zᵢ / max(α, 1e-10)`` (0 where nothing is hit).
    - Normals (``render_normals=True``): each Gaussian's normal is the axis of its smallest scale, flipped to face
      the camera, in the camera frame, alpha-blended like colour (not renormalised).
    - ``valid=False`` Gaussians contribute nothing.

    Args:
        gaussians: B scenes of N Gaussians (``anycity.structures.Gaussians``).
        w2c: ``[B, V, 4, 4]`` world-to-camera (OpenCV: x right, y down, z forward), rigid: the 3x3 block a
            rotation (orthonormal to 1e-3, or 4 epsilons of a bfloat16/float16 dtype; det +1), bottom row
            [0, 0, 0, 1].
        K: ``[B, V, 3, 3]`` pinhole intrinsics in pixels of the rendered image: zero skew, last row [0, 0, 1];
            a normalised ``K`` (fx, fy < 2 and cx, cy <= 1, for an image wider than 8 px) is refused.
        width, height: image size in pixels.
        background: ``[3]``, ``[B, V, 3]`` or None (black); finite.
        near, far: culling planes on camera z (``1e-6 <= near < far``); a Gaussian at z == near or far is kept.
        render_normals: also return ``normal``.
        backend: "torch" (tiled pure PyTorch, CPU and CUDA, float32/float64), "gsplat" (CUDA float32, needs the
            ``gsplat`` extra; gsplat gives ``K`` no gradient, so a ``K`` that requires grad is refused rather than
            dropped), "cpu" (fused numba kernels, float32 CPU), or "auto" (gsplat for float32 CUDA tensors when
            installed; cpu for float32 CPU tensors when numba is installed; else torch).

    Returns:
        ``RenderOutput`` with rgb ``[B, V, 3, H, W]``, depth ``[B, V, 1, H, W]``, alpha ``[B, V, 1, H, W]``
        and normal ``[B, V, 3, H, W]`` or None, float32 when any Gaussian field is float16/bfloat16 (each such
        field is upcast). Differentiable w.r.t. means, quats, scales, opacities, sh, w2c (its top three rows),
        K (fx, fy, cx, cy; not on gsplat) and background, on every backend.

    Example::

        >>> import torch
        >>> from anycity.render import render
        >>> from anycity.structures import Gaussians
        >>> g = Gaussians(means=torch.tensor([[[0.0, 0.0, 3.0]]]), quats=torch.tensor([[[1.0, 0, 0, 0]]]),
        ...               scales=torch.full((1, 1, 3), 0.2), opacities=torch.ones(1, 1), sh=torch.ones(1, 1, 1, 3))
        >>> K = torch.tensor([[[[32.0, 0, 16], [0, 32.0, 16], [0, 0, 1]]]])
        >>> out = render(g, torch.eye(4)[None, None], K, 32, 32, backend="torch")
        >>> out.rgb.shape, round(out.alpha.max().item(), 2)
        (torch.Size([1, 1, 3, 32, 32]), 0.99)
    """
    if not isinstance(gaussians, Gaussians):
        raise ValueError(f"gaussians: expected anycity.structures.Gaussians, got {type(gaussians).__name__}")
    gaussians.validate()
    gaussians = _upcast_low_precision(gaussians)
    with torch.autocast(device_type=gaussians.means.device.type, enabled=False):
        return _render(gaussians, w2c, K, width, height, background, near, far, render_normals, backend)


def _upcast_low_precision(gaussians: Gaussians) -> Gaussians:
    """Cast every float16/bfloat16 field to float32 (geometry and rendering stay float32 under mixed precision);
    other fields are kept as they are."""
    low = {f.name: getattr(gaussians, f.name) for f in dataclasses.fields(gaussians)}
    low = {k: t.float() for k, t in low.items() if t is not None and t.dtype in (torch.float16, torch.bfloat16)}
    return dataclasses.replace(gaussians, **low) if low else gaussians


def _render(gaussians, w2c, K, width, height, background, near, far, render_normals, backend) -> RenderOutput:
    means = gaussians.means
    B = means.shape[0]
    for name, value in (("width", width), ("height", height)):
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"{name}: expected a positive int, got {value!r}")
    V = w2c.shape[1] if isinstance(w2c, Tensor) and w2c.dim() == 4 else -1
    _check_cameras("w2c", w2c, (B, V, 4, 4), "[B, V, 4, 4]", means)
    _check_cameras("K", K, (B, V, 3, 3), "[B, V, 3, 3]", means)
    if K.shape[1] != V:
        raise ValueError(f"K: expected V={V} cameras like w2c, got shape {tuple(K.shape)}")
    _check_rotation(w2c, w2c.dtype)  # tolerances from the dtypes given, before the cast below
    _check_intrinsics(K, K.dtype, width, height)
    w2c, K = w2c.to(means.dtype), K.to(means.dtype)
    if not (NEAR_MIN <= near < far):
        raise ValueError(f"near/far: expected {NEAR_MIN:g} <= near < far, got near={near}, far={far}; a near plane "
                         "at or too close to 0 makes the projection's 1/z overflow (pass e.g. near=0.01)")
    dtype = means.dtype
    if background is None:
        bg = torch.zeros(B, V, 3, dtype=dtype, device=means.device)
    else:
        bg = torch.as_tensor(background, dtype=dtype, device=means.device)
        if bg.shape not in ((3,), (B, V, 3)):
            raise ValueError(f"background: expected shape [3] or [B, V, 3] = {(B, V, 3)}, got {tuple(bg.shape)}")
        if not bool(torch.isfinite(bg).all()):
            raise ValueError("background: contains NaN or infinite values; pass colours in [0, 1] (or None: black)")
        bg = bg.expand(B, V, 3)
    valid = gaussians.valid
    if valid is None:
        valid = torch.ones(means.shape[:2], dtype=torch.bool, device=means.device)
    name = resolve_backend(backend, means.device, dtype)
    fn = _load(name)
    rgb, depth, alpha, normal = fn(
        means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.sh, valid,
        w2c, K, width, height, bg, float(near), float(far), render_normals,
    )
    return RenderOutput(rgb=rgb, depth=depth, alpha=alpha, normal=normal)
