"""Our exported PLY looks the same in a viewer nobody here wrote: ``@mkkellogg/gaussian-splats-3d`` in headless
Chromium against ``anycity.render.render`` at the same camera (skipped without Chromium or without
``npm install`` in ``benchmarks/third_party_viewer``; CI has neither)."""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import pytest
import torch
from helpers.viewer_scenes import tiny_predict_folder

from anycity.export import load_ply, save_ply
from anycity.export.smoothing import smooth_3d
from anycity.viewer.scene import load_view_scene

HERE = Path(__file__).resolve().parents[2] / "benchmarks" / "third_party_viewer"
pytestmark = pytest.mark.skipif(
    not (shutil.which("chromium") and (HERE / "node_modules").is_dir() and importlib.util.find_spec("websockets")),
    reason="needs chromium, websockets and `npm install` in benchmarks/third_party_viewer")


def test_exported_ply_matches_our_render_in_a_third_party_viewer(tmp_path):
    sys.path.insert(0, str(HERE))
    from compare import compare

    folder = tiny_predict_folder(tmp_path / "scene")
    s = load_view_scene(folder)
    g = load_ply(folder / "scene.ply")
    # thin, sub-pixel splats as the network predicts them, then the export filter (what predict writes)
    g.scales[..., 2] = 1e-6
    save_ply(smooth_3d(g, s.w2c.float()[None], s.K.float()[None], s.width, s.height), folder / "scene.ply")
    r = compare(folder, camera=1, width=320, out=tmp_path / "cmp", settle=3.0)
    assert r["psnr"] > 35, r
    assert abs(r["mean_ours"] - r["mean_tp"]) < 3 and max(r["bands"]) < 4, r
    assert r["mean_ours"] > 20  # the scene is drawn, not two black frames
    assert torch.isfinite(torch.tensor(r["psnr"]))
