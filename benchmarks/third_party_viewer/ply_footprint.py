"""How a predicted PLY looks outside our renderer: sub-pixel splats, and what the baked 3-D filter changes.

For a predict scene folder written with ``--export.smooth_3d 0`` (raw Gaussians) this prints, at the first
predicted camera and widths 48 / 240 / 640 px:
- the share of splats whose projected 2-D footprint ``sqrt(det Σ2D)`` (no low-pass) is under 0.016 px² (what a
  viewer without our 0.3 px² low-pass drops), raw vs with :func:`anycity.export.smoothing.smooth_3d`;
- our own render at 640 px with the 2-D low-pass vs with a near-zero one (``EPS2D`` 1e-4, as a viewer without it
  draws): PSNR between them and the share of "hole" pixels (alpha < 0.5), raw vs smoothed;
- what the filter costs at the input resolution: PSNR of the smoothed render against the raw one at the input
  cameras, and the share of splats whose opacity an 8-bit viewer stores as 0 (below 1/510).

    python benchmarks/third_party_viewer/ply_footprint.py runs/mine_raw/my_photos
"""

from __future__ import annotations

import sys

import torch

import anycity.render.projection as proj
from anycity.export.smoothing import footprint_jacobian, smooth_3d
from anycity.geometry import quat_to_rotmat
from anycity.render import render
from anycity.viewer.scene import load_view_scene


def footprint(g, w2c, K) -> torch.Tensor:
    """``[N]`` sqrt(det) of the projected 2-D covariance in px² (EWA Jacobian, no low-pass)."""
    n = g.means.shape[1]
    T = footprint_jacobian(g.means[0], w2c.expand(n, 4, 4), K.expand(n, 3, 3))
    Rg = quat_to_rotmat(g.quats[0])
    cov = Rg @ torch.diag_embed(g.scales[0] ** 2) @ Rg.transpose(-1, -2)
    return torch.linalg.det(T @ cov @ T.transpose(-1, -2)).clamp_min(0).sqrt()


def main(folder: str) -> None:
    s = load_view_scene(folder)
    w2c, K = s.w2c.float(), s.K.float()
    smooth = smooth_3d(s.gaussians, w2c[None], K[None], s.width, s.height)
    print(f"{folder}: {s.gaussians.num_gaussians:,} Gaussians, input {s.width}x{s.height}")
    for width in (48, 240, 640):
        k = K[0].clone()
        k[:2] *= width / s.width
        shares = [(footprint(g, w2c[0], k) < 0.016).float().mean().item() for g in (s.gaussians, smooth)]
        print(f"  {width:4d} px: footprint < 0.016 px^2: raw {shares[0]:.1%}, smoothed {shares[1]:.1%}")
    raw_in = render(s.gaussians, w2c[None], K[None], s.width, s.height).rgb
    smooth_in = render(smooth, w2c[None], K[None], s.width, s.height).rgb
    mse = ((raw_in - smooth_in) ** 2).mean().clamp_min(1e-10)
    print(f"  input {s.width}x{s.height}, all {len(w2c)} cameras: smoothed vs raw PSNR "
          f"{-10 * torch.log10(mse).item():.2f} dB; opacity < 1/510: raw "
          f"{(s.gaussians.opacities < 1 / 510).float().mean().item():.1%}, "
          f"smoothed {(smooth.opacities < 1 / 510).float().mean().item():.1%}")
    width = 640
    height = round(width * s.height / s.width)
    k = K[0].clone()
    k[:2] *= width / s.width
    for name, g in (("raw", s.gaussians), ("smoothed", smooth)):
        ours = render(g, w2c[None, :1], k[None, None], width, height)
        saved, proj.EPS2D = proj.EPS2D, 1e-4
        try:
            bare = render(g, w2c[None, :1], k[None, None], width, height, backend="torch")
        finally:
            proj.EPS2D = saved
        mse = ((ours.rgb - bare.rgb) ** 2).mean().clamp_min(1e-10)
        print(f"  640 px {name:8s}: ours vs no-low-pass PSNR {-10 * torch.log10(mse).item():.2f} dB, holes "
              f"(alpha < 0.5) ours {(ours.alpha < 0.5).float().mean().item():.1%}, "
              f"no-low-pass {(bare.alpha < 0.5).float().mean().item():.1%}")


if __name__ == "__main__":
    main(sys.argv[1])
