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


def compare(folder: str | Path, ply: str | Path | None = None, camera: int = 0, width: int = 640,
            out: str | Path = "/tmp/third_party", settle: float = 8.0) -> dict:
    """Render ``ply`` (default ``folder/scene.ply``) in both at camera ``camera`` of ``folder``; returns PSNR (dB),
    mean values, dark-pixel shares and the mean absolute difference per eighth of the height, and writes
    ``{out}_{ours,tp,both}.png``."""
    if not (HERE / "node_modules").is_dir():
        raise FileNotFoundError(f"compare.py: no {HERE / 'node_modules'}; run `npm install` in {HERE} first")
    scene = load_view_scene(folder)
    ply = Path(ply) if ply else Path(folder) / "scene.ply"
    g, _ = load_scene(ply)
    K, height, cam = browser_camera(scene.w2c[camera].float(), scene.K[camera].float(), scene.width,
                                    scene.height, width)
    ours = render(g, scene.w2c[camera].float()[None, None], K[None, None], width, height, near=cam["near"])
    o = (ours.rgb[0, 0].clamp(0, 1).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(o).save(f"{out}_ours.png")

    name = f"_scene_{threading.get_ident()}.ply"
    shutil.copy(ply, HERE / name)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(HERE))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = (f"http://127.0.0.1:{server.server_address[1]}/index.html?url={name}"
               f"&cam={urllib.parse.quote(json.dumps(cam))}")
        asyncio.run(shot(url, f"{out}_tp.png", width, height, settle))
    finally:
        server.shutdown()
        (HERE / name).unlink(missing_ok=True)
    t = np.asarray(Image.open(f"{out}_tp.png").convert("RGB")).astype(np.float64)
    f = o.astype(np.float64)
    mse = ((f - t) ** 2).mean()
    step = max(height // 8, 1)
    Image.fromarray(np.concatenate([o, t.astype(np.uint8)], 1)).save(f"{out}_both.png")
    return {"ply": str(ply), "camera": camera, "width": width, "height": height,
            "psnr": 10 * math.log10(255 ** 2 / max(mse, 1e-9)), "mean_ours": f.mean(), "mean_tp": t.mean(),
            "dark_ours": (f.max(-1) < 10).mean(), "dark_tp": (t.max(-1) < 10).mean(),
            "bands": [float(np.abs(f - t)[i: i + step].mean()) for i in range(0, step * 8, step)]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", help="a predict output folder (scene.ply + cameras.json)")
    ap.add_argument("--ply", default=None, help="another PLY in that folder's frame (default: its scene.ply)")
    ap.add_argument("--camera", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--out", default="/tmp/third_party")
    ap.add_argument("--settle", type=float, default=8.0, help="seconds after load before the screenshot")
    a = ap.parse_args()
    try:
        r = compare(a.folder, a.ply, a.camera, a.width, a.out, a.settle)
    except FileNotFoundError as e:
        sys.exit(str(e))
    print(f"{r['ply']} at camera {r['camera']}, {r['width']}x{r['height']}: PSNR ours vs third-party "
          f"{r['psnr']:.2f} dB; mean value ours {r['mean_ours']:.1f}, third-party {r['mean_tp']:.1f}; pixels < 10: "
          f"ours {r['dark_ours']:.1%}, third-party {r['dark_tp']:.1%}")
    print(f"  mean |difference| per eighth of the height, top to bottom: {[round(b, 1) for b in r['bands']]}")


if __name__ == "__main__":
    main()
