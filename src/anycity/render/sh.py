"""Real spherical harmonics up to degree 4, in the basis order and sign convention of Inria 3DGS and gsplat.

Colour of a Gaussian seen along unit direction d (from the camera centre to the Gaussian's mean):
``c = max(sum_k sh[k] * Y_k(d) + 0.5, 0)``. Degree 0 gives ``c = 0.282095 * sh[0] + 0.5``.
"""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
C4 = (2.5033429417967046, -1.7701307697799304, 0.9461746957575601, -0.6690465435572892, 0.10578554691520431,
      -0.6690465435572892, 0.47308734787878004, -1.7701307697799304, 0.6258357354491761)


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Unit directions ``[..., 3]`` -> SH basis values ``[..., (degree+1)**2]``."""
    if not 0 <= degree <= 4:
        raise ValueError(f"sh degree: expected 0..4, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy), C3[1] * xy * z, C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    if degree >= 4:
        out += [
            C4[0] * xy * (xx - yy), C4[1] * yz * (3 * xx - yy), C4[2] * xy * (7 * zz - 1), C4[3] * yz * (7 * zz - 3),
            C4[4] * (zz * (35 * zz - 30) + 3), C4[5] * xz * (7 * zz - 3), C4[6] * (xx - yy) * (7 * zz - 1),
            C4[7] * xz * (xx - 3 * yy), C4[8] * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
        ]
    return torch.stack(out, dim=-1)


def sh_rotation(R: Tensor, degree: int) -> Tensor:
    """``[..., K, K]`` (K = (degree+1)**2) matrices ``D`` that turn SH coefficients ``sh [..., K, 3]`` into
    ``D @ sh`` when the scene is rotated by ``R [..., 3, 3]``: ``sh_basis(R d) @ (D @ sh) == sh_basis(d) @ sh`` for
    every unit ``d``, so each Gaussian keeps its view-dependent colour. Every band is closed under rotation, so the
    least-squares fit on 64 spread directions (float64) is exact and block-diagonal. Differentiable in ``R``; same
    device and dtype as ``R``."""
    i = torch.arange(64, dtype=torch.float64, device=R.device) + 0.5
    polar, azimuth = torch.acos(1 - i / 32), torch.pi * (1 + 5**0.5) * i  # a Fibonacci sphere
    d = torch.stack([azimuth.cos() * polar.sin(), azimuth.sin() * polar.sin(), polar.cos()], -1)
    rotated = sh_basis(torch.einsum("...ij,pj->...pi", R.double(), d), degree)  # [..., 64, K]
    At = rotated.transpose(-1, -2)  # normal equations: well conditioned (the basis is orthogonal on the sphere)
    return torch.linalg.solve(At @ rotated, At @ sh_basis(d, degree)).to(R.dtype)


def eval_sh(sh: Tensor, dirs: Tensor | None) -> Tensor:
    """SH coefficients ``[..., K, 3]`` and unit view directions ``[..., 3]`` -> colours ``[..., 3]`` >= 0.

    ``dirs`` may be None for degree 0 (view-independent). Adds 0.5 and clamps at 0, as gsplat and Inria do.
    """
    k = sh.shape[-2]
    if k == 1:
        return (C0 * sh[..., 0, :] + 0.5).clamp_min(0.0)
    degree = int(round(k**0.5)) - 1
    basis = sh_basis(dirs, degree)  # [..., K]
    return ((basis[..., None, :] @ sh)[..., 0, :] + 0.5).clamp_min(0.0)
