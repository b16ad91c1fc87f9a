"""Our renderer vs a third-party viewer (``@mkkellogg/gaussian-splats-3d`` in headless Chromium) on one PLY.

Both render the PLY at one predicted camera, made browser-like (square pixels from the vertical focal length,
centred principal point, the predicted pose), at ``--width`` px over black. Prints PSNR, mean values, the share of
dark pixels and the mean absolute difference per eighth of the image height; writes ``OUT_{ours,tp,both}.png``.

    (cd benchmarks/third_party_viewer && npm install)        # once; Debian's chromium must be on PATH
    python benchmarks/third_party_viewer/compare.py runs/mine/my_photos [--ply other.ply] [--out /tmp/cmp]
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import http.server
import json
import math
import shutil
import sys
import threading
import urllib.parse
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from anycity.export.cli import load_scene
from anycity.render import render
from anycity.viewer.scene import load_view_scene

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from cdp_shot import shot  # noqa: E402


def browser_camera(w2c: torch.Tensor, K: torch.Tensor, in_w: int, in_h: int, width: int):
    """``(K' [3, 3], height, page camera dict)`` for a ``width`` px browser view from camera ``w2c``, ``K``."""
    height = round(width * in_h / in_w)
    f = float(K[1, 1]) * height / in_h
    Kb = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])
    c2w = torch.linalg.inv(w2c.double())
    pos, fwd, up = c2w[:3, 3], c2w[:3, 2], -c2w[:3, 1]
    cam = {"pos": pos.tolist(), "look": (pos + fwd).tolist(), "up": up.tolist(), "near": 0.01,
           "fov": math.degrees(2 * math.atan(height / 2 / f))}
    return Kb, height, cam


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="a predict output folder (scene.ply + cameras.json)")
    ap.add_argument("--ply", default=None, help="another PLY in that folder's frame (default: its scene.ply)")
    ap.add_argument("--camera", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--out", default="/tmp/third_party")
    ap.add_argument("--settle", type=float, default=8.0, help="seconds after load before the screenshot")
    a = ap.parse_args()
    if not (HERE / "node_modules").is_dir():
        sys.exit(f"compare.py: no {HERE / 'node_modules'}; run `npm install` in {HERE} first")
    scene = load_view_scene(a.folder)
    ply = Path(a.ply) if a.ply else Path(a.folder) / "scene.ply"
    g, _ = load_scene(ply)
    K, height, cam = browser_camera(scene.w2c[a.camera].float(), scene.K[a.camera].float(), scene.width,
                                    scene.height, a.width)
    ours = render(g, scene.w2c[a.camera].float()[None, None], K[None, None], a.width, height, near=cam["near"])
    o = (ours.rgb[0, 0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(o).save(f"{out}_ours.png")

    shutil.copy(ply, HERE / "_scene.ply")
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(HERE))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = (f"http://127.0.0.1:{server.server_address[1]}/index.html?url=_scene.ply"
               f"&cam={urllib.parse.quote(json.dumps(cam))}")
        asyncio.run(shot(url, f"{out}_tp.png", a.width, height, a.settle))
    finally:
        server.shutdown()
        (HERE / "_scene.ply").unlink(missing_ok=True)
    t = np.asarray(Image.open(f"{out}_tp.png").convert("RGB")).astype(np.float64)
    f = o.astype(np.float64)
    mse = ((f - t) ** 2).mean()
    band = [round(float(np.abs(f - t)[i: i + height // 8].mean()), 1) for i in range(0, height - height // 8 + 1,
                                                                                   height // 8)]
    print(f"{ply} at camera {a.camera}, {a.width}x{height}: PSNR ours vs third-party "
          f"{10 * math.log10(255 ** 2 / max(mse, 1e-9)):.2f} dB; mean value ours {f.mean():.1f}, third-party "
          f"{t.mean():.1f}; pixels < 10: ours {(f.max(-1) < 10).mean():.1%}, third-party {(t.max(-1) < 10).mean():.1%}")
    print(f"  mean |difference| per eighth of the height, top to bottom: {band}")
    Image.fromarray(np.concatenate([o, t.astype(np.uint8)], 1)).save(f"{out}_both.png")


if __name__ == "__main__":
    main()
