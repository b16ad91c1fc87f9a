"""``anycity view``: the viser page opens in headless Chromium and draws the splats (skipped without Chromium)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest
import torch
from PIL import Image

from anycity.export import save_cameras, save_ply
from anycity.structures import Gaussians

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--hide-scrollbars"]


def tiny_predict_folder(root, n: int = 3000, with_prov: bool = True):
    """A predict-like folder: a coloured cube of Gaussians seen by 3 cameras 4 units away, with input images."""
    gen = torch.Generator().manual_seed(0)
    means = torch.rand(1, n, 3, generator=gen) * 2 - 1
    g = Gaussians(means=means, quats=torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4).clone(),
                  scales=torch.full((1, n, 3), 0.06), opacities=torch.full((1, n), 0.9),
                  sh=((means.clamp(-1, 1) * 0.5 + 0.5 - 0.5) / 0.28209479177387814)[:, :, None, :])
    v = 3
    w2c = torch.eye(4).repeat(v, 1, 1)
    for i, x in enumerate((-1.0, 0.0, 1.0)):
        w2c[i, :3, 3] = torch.tensor([x, 0.0, 4.0])
    K = torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]).repeat(v, 1, 1)
    prov = {"obs_views": torch.randint(0, 4, (1, n), generator=gen).float(),
            "completion": torch.rand(1, n, generator=gen)} if with_prov else None
    save_ply(g, root / "scene.ply", extra=prov)
    save_cameras(root / "cameras.json", w2c, K, 48, 32)
    (root / "inputs").mkdir()
    for i in range(v):
        Image.fromarray(np.full((32, 48, 3), 60 * i, np.uint8)).save(root / "inputs" / f"{i:03d}.png")
    return root


def screenshot(url: str, out, budget_ms: int = 8000) -> np.ndarray:
    subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={out.parent / 'chrome_profile'}", f"--screenshot={out}",
                    "--window-size=1024,768", f"--virtual-time-budget={budget_ms}", url],
                   capture_output=True, timeout=180, check=False)
    return np.asarray(Image.open(out).convert("RGB")).astype(np.int16)


def drawn_share(img: np.ndarray) -> float:
    """Share of the central half of the frame that differs from the white background by > 30."""
    h, w = img.shape[:2]
    c = img[h // 4: 3 * h // 4, w // 8: 5 * w // 8]  # left of the GUI panel
    return float((np.abs(c - 255).max(-1) > 30).mean())


def test_build_server_loads_scene_and_provenance(tmp_path):
    pytest.importorskip("viser")
    from anycity.viewer.server import build_server

    server, scene = build_server(tiny_predict_folder(tmp_path), port=0)
    try:
        assert server.get_port() > 0 and scene.gaussians.num_gaussians == 3000
        assert set(scene.extras) == {"obs_views", "completion"} and len(scene.thumbs) == 3
    finally:
        server.stop()


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium installed (apt-get install chromium)")
def test_view_page_draws_splats_in_chromium(tmp_path):
    pytest.importorskip("viser")
    from anycity.viewer.server import build_server

    server, _ = build_server(tiny_predict_folder(tmp_path / "scene_dir" if (tmp_path / "scene_dir").mkdir() is None
                                                 else tmp_path), port=0)
    try:
        img = screenshot(f"http://127.0.0.1:{server.get_port()}", tmp_path / "shot.png")
    finally:
        server.stop()
    share = drawn_share(img)
    assert share > 0.05, f"viewer canvas looks blank: {share:.3f} of the centre drawn"
