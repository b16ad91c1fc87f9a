"""Rotations as unit quaternions in **wxyz** order and 3x3 matrices.

VGGT and AnySplat store quaternions xyzw; convert with :func:`xyzw_to_wxyz` at their boundary only.
"""

from __future__ import annotations

import torch
from torch import Tensor


def quat_to_rotmat(q: Tensor, eps: float = 1e-12) -> Tensor:
    """``[..., 4]`` wxyz quaternions (any norm > 0) -> ``[..., 3, 3]`` rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(eps)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    rows = (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def rotmat_to_quat(R: Tensor) -> Tensor:
    """``[..., 3, 3]`` rotation matrices -> ``[..., 4]`` unit wxyz quaternions with w >= 0.

    Uses the numerically stable branch per element (largest of w, x, y, z first).
    """
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    # 4 * squared components, each candidate's row is the full quaternion times 4*component.
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    cand = torch.stack([
        torch.stack([sq[:, 0], m21 - m12, m02 - m20, m10 - m01], -1),
        torch.stack([m21 - m12, sq[:, 1], m10 + m01, m02 + m20], -1),
        torch.stack([m02 - m20, m10 + m01, sq[:, 2], m12 + m21], -1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, sq[:, 3]], -1),
    ], 1)  # [M, 4 candidates, 4]
    best = sq.argmax(-1)
    q = cand[torch.arange(m.shape[0], device=R.device), best]
    q = q / (2 * sq.gather(-1, best[:, None]).clamp_min(1e-12).sqrt())
    q = torch.where(q[:, :1] < 0, -q, q)
    return (q / q.norm(dim=-1, keepdim=True)).reshape(*R.shape[:-2], 4)


def xyzw_to_wxyz(q: Tensor) -> Tensor:
    """``[..., 4]`` quaternions in VGGT/AnySplat's **xyzw** order -> the same quaternions in anycity's **wxyz**
    (a copy, norm unchanged); the inverse of :func:`wxyz_to_xyzw`."""
    return q[..., [3, 0, 1, 2]]


def wxyz_to_xyzw(q: Tensor) -> Tensor:
    """``[..., 4]`` quaternions in anycity's **wxyz** order -> VGGT/AnySplat's **xyzw** (the 9-D pose encoding's
    layout; a copy, norm unchanged); the inverse of :func:`xyzw_to_wxyz`."""
    return q[..., [1, 2, 3, 0]]


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of wxyz quaternions, ``[..., 4]``; rotation ``a`` applied after ``b``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)
