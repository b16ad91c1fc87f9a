"""Is the third-party viewer's difference its 8-bit blending? Re-composite one crop of ``compare.py``'s frame.

The splats our renderer draws in the crop are composited back-to-front per pixel: (a) with our cut-offs in float,
(b) with the viewer's cut-offs (√8 σ, no 0.99 clamp) in float, (c) the same with the colour stored in 8 bits and
every blend rounded to 8 bits, as WebGL does. Each is compared with our render and with the viewer's screenshot.

    python benchmarks/third_party_viewer/blend_crop.py FOLDER --shots /tmp/third_party [--crop 0 40 0 200]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from anycity.export.cli import load_scene
from anycity.render.projection import project_gaussians
from anycity.viewer.scene import load_view_scene

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare import browser_camera  # noqa: E402


def blend(alpha: torch.Tensor, colour: torch.Tensor, eight_bit: bool) -> torch.Tensor:
    """Back-to-front ``C = c·a + C·(1 - a)`` over ``alpha [P, n]`` (far to near), ``colour [n, 3]`` -> ``[P, 3]``."""
    out = torch.zeros(alpha.shape[0], 3, dtype=torch.float64)
    for i in range(alpha.shape[1]):
        a = alpha[:, i:i + 1].double()
        out = colour[i][None].double() * a + out * (1 - a)
        if eight_bit:
            out = (out * 255).round() / 255
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--ply", default=None)
    ap.add_argument("--shots", required=True, help="compare.py's --out prefix (its _ours.png and _tp.png)")
    ap.add_argument("--crop", type=int, nargs=4, default=[0, 40, 0, 200], metavar=("Y0", "Y1", "X0", "X1"))
    ap.add_argument("--width", type=int, default=640)
    a = ap.parse_args()
    scene = load_view_scene(a.folder)
    g, _ = load_scene(Path(a.ply) if a.ply else Path(a.folder) / "scene.ply")
    K, height, cam = browser_camera(scene.w2c[0].float(), scene.K[0].float(), scene.width, scene.height, a.width)
    n = g.means.shape[1]
    P = project_gaussians(g.means, g.quats, g.scales, g.opacities, g.sh, torch.ones(1, n, dtype=torch.bool),
                          scene.w2c[0].float()[None, None], K[None, None], a.width, height, cam["near"], 1e10, False)
    m, con, op, feat, vis = P.mean2d[0], P.conic[0], P.opacity[0], P.features[0], P.visible[0]
    y0, y1, x0, x1 = a.crop
    r = P.radius[0].float().amax(-1)
    sel = vis & (m[:, 0] + r > x0) & (m[:, 0] - r < x1) & (m[:, 1] + r > y0) & (m[:, 1] - r < y1)
    idx = sel.nonzero()[:, 0]
    order = idx[torch.argsort(feat[idx, 3], descending=True)]  # far to near
    ys, xs = torch.meshgrid(torch.arange(y0, y1) + 0.5, torch.arange(x0, x1) + 0.5, indexing="ij")
    d = torch.stack([xs.flatten(), ys.flatten()], -1)[:, None] - m[order][None]
    c = con[order]
    power = -0.5 * (c[:, 0] * d[..., 0] ** 2 + c[:, 2] * d[..., 1] ** 2) - c[:, 1] * d[..., 0] * d[..., 1]
    raw = op[order][None] * torch.exp(power)
    ours_a = raw.clamp(max=0.99)
    ours_a = torch.where(ours_a < 1 / 255, torch.zeros_like(ours_a), ours_a)
    viewer_a = torch.where(power < -4, torch.zeros_like(raw), raw)
    col = feat[order, :3].clamp(0, 1)
    col8 = (col * 255).round() / 255
    shots = {k: np.asarray(Image.open(f"{a.shots}_{k}.png").convert("RGB")).astype(float)[y0:y1, x0:x1].reshape(-1, 3)
             for k in ("ours", "tp")}

    def psnr(x, y):
        return 10 * math.log10(255 ** 2 / max(((x - y) ** 2).mean(), 1e-9))

    print(f"crop rows {y0}:{y1}, cols {x0}:{x1}: {len(order)} splats; our render vs third-party "
          f"{psnr(shots['ours'], shots['tp']):.2f} dB, mean {shots['ours'].mean():.1f} / {shots['tp'].mean():.1f}")
    for name, b in (("our cut-offs, float", blend(ours_a, col, False)),
                    ("viewer cut-offs, float", blend(viewer_a, col8, False)),
                    ("viewer cut-offs, 8-bit blending", blend(viewer_a, col8, True))):
        x = b.numpy() * 255
        print(f"  {name:32s}: vs our render {psnr(x, shots['ours']):.2f} dB, vs third-party "
              f"{psnr(x, shots['tp']):.2f} dB, mean {x.mean():.1f}")


if __name__ == "__main__":
    main()
