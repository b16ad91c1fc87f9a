"""VGGT's 9-D camera encoding ``absT_quaR_FoV`` <-> ``w2c`` / ``K``.

Layout of the last dim: ``[t (3), quaternion (4, **xyzw**, VGGT's order), fov_h, fov_w]`` where ``[R|t]`` is
the OpenCV world-to-camera transform and the fields of view are full angles in radians. The principal point
is the image centre ``(W/2, H/2)`` in pixel units (pixel centres at +0.5, so this is the geometric centre).
The quaternion is xyzw, as in VGGT: the camera head emits this encoding and ``losses/camera.py`` compares it;
everywhere else the package uses wxyz.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from anycity.geometry.cameras import focal_to_fov, fov_to_focal, to_homogeneous
from anycity.geometry.rotations import quat_to_rotmat, rotmat_to_quat, wxyz_to_xyzw, xyzw_to_wxyz

POSE_ENCODING_DIM = 9
# "vggt": f = size / (2 tan(fov/2)) (upstream VGGT, ours); "anysplat": AnySplat's copy of VGGT decodes
# f = (size/2) / (tan(fov/2) + 1e-3), about 2e-3 relative in K; an AnySplat checkpoint reproduces its cameras only
# with its own decode (NetConfig.focal_decode, set by load_pretrained(kind="anysplat")).
FOCAL_DECODES = ("vggt", "anysplat")
ANYSPLAT_TAN_EPS = 1e-3
# The decode clamps a predicted field of view to [FOV_MIN, FOV_MAX] radians: the camera head's FoV activation is a
# ReLU, so 0 (an infinite focal length, -inf gradient) is reachable, and FoV >= pi gives a focal length <= 0, which
# render() refuses. Values inside the range pass bit for bit (VGGT's cameras are unchanged).
FOV_MIN, FOV_MAX = 1e-4, math.pi - 1e-3


def _fov_to_focal(fov: Tensor, size: float, mode: str) -> Tensor:
    fov = fov.clamp(FOV_MIN, FOV_MAX)
    if mode == "anysplat":
        return (size / 2) / (torch.tan(fov / 2) + ANYSPLAT_TAN_EPS)
    if mode != "vggt":
        raise ValueError(f"focal_decode: expected one of {FOCAL_DECODES}, got {mode!r}")
    return fov_to_focal(fov, size)


def _focal_to_fov(focal: Tensor, size: float, mode: str) -> Tensor:
    if mode == "anysplat":  # the exact inverse of the decode above
        return 2 * torch.atan(size / (2 * focal) - ANYSPLAT_TAN_EPS)
    if mode != "vggt":
        raise ValueError(f"focal_decode: expected one of {FOCAL_DECODES}, got {mode!r}")
    return focal_to_fov(focal, size)


def _check_hw(image_size_hw) -> tuple[int, int]:
    if len(image_size_hw) != 2 or min(image_size_hw) <= 0:
        raise ValueError(f"image_size_hw: expected (H, W) with positive sides, got {tuple(image_size_hw)}")
    return int(image_size_hw[0]), int(image_size_hw[1])


def extri_intri_to_pose_encoding(w2c: Tensor, K: Tensor, image_size_hw: tuple[int, int],
                                 focal_decode: str = "vggt") -> Tensor:
    """``w2c [..., 4, 4]`` (or ``[..., 3, 4]``) and pixel ``K [..., 3, 3]`` -> ``[..., 9]`` encoding.

    Only fx, fy of ``K`` are used; a principal point off the centre is not representable. ``focal_decode``: the
    inverse of which decode (see ``FOCAL_DECODES``).
    """
    h, w = _check_hw(image_size_hw)
    if w2c.shape[-1] != 4 or w2c.shape[-2] not in (3, 4):
        raise ValueError(f"w2c: expected [..., 4, 4] or [..., 3, 4], got {tuple(w2c.shape)}")
    quat = wxyz_to_xyzw(rotmat_to_quat(w2c[..., :3, :3]))
    fov_h = _focal_to_fov(K[..., 1, 1], h, focal_decode)
    fov_w = _focal_to_fov(K[..., 0, 0], w, focal_decode)
    return torch.cat([w2c[..., :3, 3], quat, fov_h[..., None], fov_w[..., None]], dim=-1).float()


def pose_encoding_to_extri_intri(enc: Tensor, image_size_hw: tuple[int, int],
                                 focal_decode: str = "vggt") -> tuple[Tensor, Tensor]:
    """``[..., 9]`` encoding -> ``w2c [..., 4, 4]`` and ``K [..., 3, 3]`` in pixels of an ``(H, W)`` image.

    The quaternion need not be unit norm (the camera head does not normalise it). The fields of view are clamped
    to ``[FOV_MIN, FOV_MAX]`` (1e-4 .. pi - 1e-3 radians; no gradient outside), so the focal lengths are finite
    and positive. ``focal_decode``: "vggt" or "anysplat" (see ``FOCAL_DECODES``).
    """
    h, w = _check_hw(image_size_hw)
    if enc.shape[-1] != POSE_ENCODING_DIM:
        raise ValueError(f"pose encoding: expected last dim 9 (t, quat xyzw, fov_h, fov_w), got {tuple(enc.shape)}")
    R = quat_to_rotmat(xyzw_to_wxyz(enc[..., 3:7]))
    w2c = to_homogeneous(torch.cat([R, enc[..., :3, None]], dim=-1))
    fy = _fov_to_focal(enc[..., 7], h, focal_decode)
    fx = _fov_to_focal(enc[..., 8], w, focal_decode)
    zero, one = torch.zeros_like(fx), torch.ones_like(fx)
    K = torch.stack([fx, zero, zero + w / 2, zero, fy, zero + h / 2, zero, zero, one], dim=-1)
    return w2c, K.unflatten(-1, (3, 3))


def blend_pose_encoding(enc: Tensor, w2c: Tensor, weight: Tensor) -> Tensor:
    """Move an encoding's translation and rotation towards another pose's, per view.

    ``enc [..., 9]``; ``w2c [..., 4, 4]``: the pose moved towards; ``weight [..., 2]``: how far, for the
    translation and the rotation (0 keeps ``enc`` exactly, 1 reaches ``w2c``; neither is clamped). The rotation is
    blended linearly on the quaternion, after ``w2c``'s is given ``enc``'s sign and norm; the fields of view are
    kept. Gradients reach ``enc`` and ``weight`` (and ``w2c``).
    """
    if enc.shape[-1] != POSE_ENCODING_DIM or weight.shape[-1] != 2:
        raise ValueError(f"blend_pose_encoding: expected enc [..., 9] and weight [..., 2], got "
                         f"{tuple(enc.shape)} and {tuple(weight.shape)}")
    t, q = enc[..., :3], enc[..., 3:7]
    qp = wxyz_to_xyzw(rotmat_to_quat(w2c[..., :3, :3].float()))
    sign = torch.where((q * qp).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    qp = qp * sign * q.norm(dim=-1, keepdim=True)
    a_t, a_r = weight[..., :1], weight[..., 1:]
    return torch.cat([t + a_t * (w2c[..., :3, 3] - t), q + a_r * (qp - q), enc[..., 7:]], dim=-1)
