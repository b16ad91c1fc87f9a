"""Mip-Splatting's 3D smoothing filter, baked into exported scales and opacities.

Most predicted Gaussians are far below a pixel; our renderer shows them only through its 0.3 px² 2-D low-pass
(:data:`anycity.render.projection.EPS2D`). Viewers with a smaller or no low-pass drop them and show holes, and
so does our own renderer as soon as one zooms in. The 3-D filter gives each Gaussian a minimum size from the
highest sampling rate at which an input camera saw it: ``Σ' = Σ + (variance_px / ν²) I`` with ``ν = f / z``
(pixels per world unit).

The opacity is scaled so the Gaussian keeps its 2-D mass (peak alpha × footprint area) in that camera,
``o' = o · sqrt(det(Σ₂ + ε I) / det(Σ₂' + ε I))`` with Σ₂ the projected covariance and ε the 0.3 px² low-pass,
rather than its 3-D density as Mip-Splatting does (``sqrt(det Σ / det Σ')``). Our splats are thin and far below a
pixel; the 3-D rule multiplies their opacity by ~0.01 (median, ``boruszyn_kap``) and leaves 59 % of them below
1/255, so the exported scene renders dark and full of holes in any renderer (43.6 % of pixels below 10/255 at
640 px, against 2.7 % with the 2-D rule). The 2-D rule keeps what the input cameras saw (36.8 dB against the raw
render there): a sub-pixel splat becomes a ``variance_px + ε`` px² splat of peak ``ε / (variance_px + ε)`` of its
opacity.
"""

from __future__ import annotations

import torch
from torch import Tensor

from anycity.geometry import quat_to_rotmat
from anycity.render.projection import EPS2D
from anycity.structures import Gaussians

VARIANCE_PX = 0.2  # Mip-Splatting's 3D filter variance in pixels² of the input cameras
CHUNK = 1 << 16  # Gaussians per step: ~10 [B, V, CHUNK] float32 tensors, ~0.2 GB at 64 views


def _best_camera(means: Tensor, w2c: Tensor, K: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """``(ν [B, N], camera [B, N])``: the highest ``f / z`` over the cameras that frame each centre (else over those
    it is in front of; ν = 0 when behind all of them) and the index of that camera."""
    p = torch.einsum("bvij,bnj->bvni", w2c[..., :3, :3], means) + w2c[..., None, :3, 3]
    z = p[..., 2]
    front = z > 1e-6
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[..., 0, 0, None] * p[..., 0] / zs + K[..., 0, 2, None]
    v = K[..., 1, 1, None] * p[..., 1] / zs + K[..., 1, 2, None]
    inside = front & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
    nu = torch.maximum(K[..., 0, 0, None], K[..., 1, 1, None]) / zs  # [B, V, N]
    zero = torch.zeros_like(nu)
    best, cam = torch.where(inside, nu, zero).max(1)
    best_front, cam_front = torch.where(front, nu, zero).max(1)
    framed = best > 0
    return torch.where(framed, best, best_front), torch.where(framed, cam, cam_front)


def best_camera(means: Tensor, w2c: Tensor, K: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """:func:`_best_camera` over slices of :data:`CHUNK` Gaussians, so its ``[B, V, N]`` intermediates stay
    ``[B, V, CHUNK]`` (a 64-view scene of millions of Gaussians would otherwise need gigabytes)."""
    parts = [_best_camera(means[:, s:s + CHUNK], w2c, K, width, height) for s in range(0, means.shape[1], CHUNK)]
    if not parts:
        return _best_camera(means, w2c, K, width, height)
    return torch.cat([p[0] for p in parts], 1), torch.cat([p[1] for p in parts], 1)


def sampling_rate(means: Tensor, w2c: Tensor, K: Tensor, width: int, height: int) -> Tensor:
    """``[B, N]`` highest ``f / z`` (pixels per world unit) over the cameras that see each centre in frame; for a
    centre no camera frames, the highest over the cameras it is in front of; 0 when behind all of them.
    ``means [B, N, 3]``, ``w2c [B, V, 4, 4]``, ``K [B, V, 3, 3]`` for ``width x height`` images."""
    return best_camera(means, w2c, K, width, height)[0]


def footprint_jacobian(means: Tensor, w2c: Tensor, K: Tensor) -> Tensor:
    """``[..., 2, 3]`` EWA Jacobian times rotation, world -> pixels, of each centre ``means [..., 3]`` in its camera
    (``w2c [..., 4, 4]``, ``K [..., 3, 3]``: one camera per Gaussian; ``T Σ Tᵀ`` is its 2-D covariance)."""
    R = w2c[..., :3, :3]
    p = (R @ means[..., None])[..., 0] + w2c[..., :3, 3]
    z = p[..., 2].clamp_min(1e-6)
    fx, fy = K[..., 0, 0], K[..., 1, 1]
    J = torch.zeros(*means.shape[:-1], 2, 3, dtype=means.dtype, device=means.device)
    J[..., 0, 0], J[..., 0, 2] = fx / z, -fx * p[..., 0] / z ** 2
    J[..., 1, 1], J[..., 1, 2] = fy / z, -fy * p[..., 1] / z ** 2
    return J @ R


def smooth_3d(g: Gaussians, w2c: Tensor, K: Tensor, width: int, height: int,
              variance_px: float = VARIANCE_PX) -> Gaussians:
    """``g`` with the 3-D filter baked in (a new object; Gaussians no camera sees in front are kept as is).

    ``g`` holds B scenes of N Gaussians, ``w2c [B, V, 4, 4]`` and ``K [B, V, 3, 3]`` their input cameras for
    ``width x height`` images; ``variance_px`` is the filter in px² of those images."""
    # float64: the gain's determinants of a long thin footprint cancel in float32 (a 3000 px needle's opacity was
    # exported at the 0.9 clamp instead of 0.70)
    means, w2c, K = g.means.double(), w2c.double(), K.double()
    var = g.scales.double() ** 2
    eye = torch.eye(2, dtype=means.dtype, device=means.device)
    filts, gains = [], []
    for s in range(0, means.shape[1], CHUNK):  # [B, V, CHUNK] and a few 3x3 matrices per Gaussian at a time
        sl = slice(s, s + CHUNK)
        nu, cam = _best_camera(means[:, sl], w2c, K, width, height)
        filt = torch.where(nu > 0, variance_px / nu.clamp_min(1e-12) ** 2, torch.zeros_like(nu))  # [B, n] world²
        take = cam[..., None, None].expand(-1, -1, 4, 4)
        T = footprint_jacobian(means[:, sl], w2c.gather(1, take), K.gather(1, take[..., :3, :3]))
        R = quat_to_rotmat(g.quats[:, sl].double())
        before = T @ (R * var[:, sl, None, :]) @ R.transpose(-1, -2) @ T.transpose(-1, -2) + EPS2D * eye
        after = before + filt[..., None, None] * (T @ T.transpose(-1, -2))
        gain = torch.sqrt(torch.linalg.det(before) / torch.linalg.det(after)).clamp(max=1.0)
        filts.append(filt)
        gains.append(torch.where(nu > 0, gain, 1.0))  # behind every camera: no footprint, no filter (inf/inf)
    filt = torch.cat(filts, 1) if filts else var[..., 0]
    gain = torch.cat(gains, 1) if gains else var[..., 0]
    return Gaussians(means=g.means, quats=g.quats, scales=(var + filt[..., None]).sqrt().to(g.scales.dtype),
                     opacities=(g.opacities * gain.to(g.opacities.dtype)), sh=g.sh, valid=g.valid)
