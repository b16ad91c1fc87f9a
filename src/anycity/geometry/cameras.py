"""Camera matrices: world-to-camera <-> camera-to-world, intrinsics under resize and crop.

Conventions: OpenCV camera frame (x right, y down, z forward), ``w2c``/``c2w`` are ``[..., 4, 4]``,
``K`` is ``[..., 3, 3]`` in pixels with pixel centres at +0.5 (the top-left pixel covers [0, 1)).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor


def invert_rigid(T: Tensor) -> Tensor:
    """Inverse of ``[..., 4, 4]`` rigid (or similarity-free) transforms via R^T, without a general inverse."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1
    return out


def w2c_to_c2w(w2c: Tensor) -> Tensor:
    """``[..., 4, 4]`` world-to-camera -> camera-to-world."""
    return invert_rigid(w2c)


def c2w_to_w2c(c2w: Tensor) -> Tensor:
    """``[..., 4, 4]`` camera-to-world -> world-to-camera."""
    return invert_rigid(c2w)


def to_homogeneous(Rt: Tensor) -> Tensor:
    """``[..., 3, 4]`` -> ``[..., 4, 4]`` by appending the row [0, 0, 0, 1]."""
    bottom = torch.zeros(*Rt.shape[:-2], 1, 4, dtype=Rt.dtype, device=Rt.device)
    bottom[..., 0, 3] = 1
    return torch.cat([Rt, bottom], dim=-2)


def camera_centers(w2c: Tensor) -> Tensor:
    """``[..., 4, 4]`` world-to-camera -> ``[..., 3]`` camera centres in world coordinates."""
    R, t = w2c[..., :3, :3], w2c[..., :3, 3:]
    return (-R.transpose(-1, -2) @ t)[..., 0]


def make_intrinsics(fx, fy, cx, cy) -> Tensor:
    """Scalars or broadcastable ``[...]`` tensors -> ``[..., 3, 3]`` pinhole K.

    K takes the promoted dtype of the floating-point tensor inputs (float32 when there are none: Python numbers,
    integer tensors) and the device of the first tensor input (CPU when there is none).
    """
    values = (fx, fy, cx, cy)
    tensors = [v for v in values if isinstance(v, Tensor)]
    dtypes = [t.dtype for t in tensors if t.is_floating_point()]
    dtype = functools.reduce(torch.promote_types, dtypes) if dtypes else torch.float32
    device = tensors[0].device if tensors else None
    fx, fy, cx, cy = torch.broadcast_tensors(*(torch.as_tensor(v, dtype=dtype, device=device) for v in values))
    K = torch.zeros(*fx.shape, 3, 3, dtype=dtype, device=device)
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = fx, fy, cx, cy, 1
    return K


def rescale_intrinsics(K: Tensor, sx: float | Tensor, sy: float | Tensor) -> Tensor:
    """K of an image resized by (sx, sy) = (new_w / old_w, new_h / old_h).

    With pixel centres at +0.5 the continuous image plane scales exactly: fx, cx scale by sx; fy, cy by sy.
    """
    S = torch.ones(*K.shape[:-2], 3, dtype=K.dtype, device=K.device)
    S[..., 0] = S[..., 0] * sx
    S[..., 1] = S[..., 1] * sy
    return S[..., :, None] * K


def crop_intrinsics(K: Tensor, x0: float | Tensor, y0: float | Tensor) -> Tensor:
    """K of the crop whose top-left corner is pixel (x0, y0) of the original image."""
    out = K.clone()
    out[..., 0, 2] = out[..., 0, 2] - x0
    out[..., 1, 2] = out[..., 1, 2] - y0
    return out


def focal_to_fov(focal: Tensor, size: float | Tensor) -> Tensor:
    """Focal length in pixels and image side in pixels -> full field of view in radians."""
    return 2 * torch.atan(size / (2 * focal))


def fov_to_focal(fov: Tensor, size: float | Tensor) -> Tensor:
    """Full field of view (radians) and image side in pixels -> focal length in pixels."""
    return size / (2 * torch.tan(fov / 2))


MAX_IMAGE_SIDE = 1 << 16  # image sides above this in a camera file are a corrupt header, not a photo
# the renderer refuses skew above 1e-3 px at every dtype (render.api._check_intrinsics), so a camera that passes
# here renders
MAX_SKEW = 1e-3


def camera_problem(w2c, K, tol: float = 1e-3) -> str | None:
    """What makes one pinhole camera unusable, or None when it is sound: a reader's check of cameras from a file.

    ``w2c [4, 4]`` must be finite and rigid (``R`` orthonormal with det +1 within ``tol``, last row 0 0 0 1);
    ``K [3, 3]`` finite with focal lengths > 0, last row 0 0 1 and skew ``|K[0, 1]|, |K[1, 0]|`` at most
    ``MAX_SKEW`` px. Array-likes (lists, arrays, CPU tensors).
    """
    try:
        w2c, K = np.asarray(w2c, dtype=np.float64), np.asarray(K, dtype=np.float64)
    except OverflowError:  # a JSON integer of hundreds of digits
        return "camera holds a number too large for a float"
    if w2c.shape != (4, 4) or K.shape != (3, 3):
        return f"expected w2c 4x4 and K 3x3, got {w2c.shape} and {K.shape}"
    if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
        return "camera holds NaN/inf"
    R = w2c[:3, :3]
    with np.errstate(all="ignore"):  # a damaged matrix overflows quietly here, then fails the test below
        ortho, det = np.abs(R @ R.T - np.eye(3)).max(), np.linalg.det(R)
    if not (ortho <= tol and abs(det - 1) <= tol and np.abs(w2c[3] - [0, 0, 0, 1]).max() <= 1e-6):
        return "camera pose is not a rigid rotation + translation"
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        return f"intrinsics need focal lengths > 0 (got fx={K[0, 0]:g}, fy={K[1, 1]:g})"
    if np.abs(K[2] - [0, 0, 1]).max() > 1e-6:
        row = ", ".join(f"{x:g}" for x in K[2])
        return f"K's last row must be [0, 0, 1], got [{row}] (divide a homogeneous K by K[2, 2])"
    skew = max(abs(K[0, 1]), abs(K[1, 0]))
    if skew > MAX_SKEW:
        return (f"intrinsics have skew {skew:.3g} px (K[0, 1] or K[1, 0]) that the renderer cannot draw "
                f"(at most {MAX_SKEW:g}); resample the image to a pinhole camera with zero skew")
    return None
