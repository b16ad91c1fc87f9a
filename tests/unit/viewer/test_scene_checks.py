"""What the viewer shows of unknown provenance (NaN completion), and the one-line refusals of ``view`` and
``render-video``: a scene with no Gaussians, a missing viewer extra."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch
from helpers.viewer_scenes import tiny_predict_folder

from anycity.export import save_ply
from anycity.structures import Gaussians
from anycity.viewer.scene import load_view_scene, ramp, splat_arrays
from anycity.viewer.server import COLOURINGS, _share_text, build_server
from anycity.viewer.video import render_video


def test_nan_completion_is_grey_not_the_colour_of_kept():
    col = ramp(np.array([0.0, np.nan, 1.0]))
    np.testing.assert_allclose(col[1], [0.5, 0.5, 0.5])
    assert not np.allclose(col[0], 0.5) and not np.allclose(col[2], 0.5)


def test_the_ramp_runs_from_blue_at_0_to_red_at_1():
    col = ramp(np.array([0.0, 1.0]))
    assert col[0, 2] > col[0, 0] and col[1, 0] > col[1, 2]


def test_a_splats_covariance_is_r_diag_s2_r_transposed():
    """One Gaussian stretched along its x axis (scales 1, .1, .1), turned 30 degrees about z: its long axis points at
    30 degrees in the world, covariance R diag(s^2) R^T (R^T diag(s^2) R turns it to -30 degrees)."""
    a = math.radians(30)
    q = torch.tensor([[[math.cos(a / 2), 0, 0, math.sin(a / 2)]]])
    g = Gaussians(torch.zeros(1, 1, 3), q, torch.tensor([[[1.0, 0.1, 0.1]]]), torch.ones(1, 1), torch.zeros(1, 1, 1, 3))
    c, s = math.cos(a), math.sin(a)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(splat_arrays(g)[1][0], R @ np.diag([1.0, 0.01, 0.01]) @ R.T, atol=1e-6)


def _with_completion(tmp_path, completion: torch.Tensor):
    folder = tiny_predict_folder(tmp_path, n=4)
    g = load_view_scene(folder).gaussians
    save_ply(g, folder / "scene.ply", extra={"obs_views": torch.full((1, 4), 2.0), "completion": completion[None]})
    return load_view_scene(folder)


def test_a_voxel_merged_scene_offers_no_completion_colouring(tmp_path):
    """All NaN (a voxel-merged prediction): the panel said "completed by Stage II: 0%" and the colouring drew every
    Gaussian as kept."""
    scene = _with_completion(tmp_path, torch.full((4,), float("nan")))
    assert "completion n/a (voxel-merged)" in _share_text(scene) and "completed by" not in _share_text(scene)
    from anycity.viewer.server import colourings

    assert colourings(scene.extras) == COLOURINGS[:2]


def test_a_partly_unknown_completion_is_shared_over_all_and_named(tmp_path):
    scene = _with_completion(tmp_path, torch.tensor([0.0, 0.9, float("nan"), 0.1]))
    assert "completed by Stage II (> 0.25): 25%, n/a for 25% (grey)" in _share_text(scene)
    from anycity.viewer.server import colourings

    assert colourings(scene.extras) == COLOURINGS


def test_the_share_seen_by_two_views_counts_two(tmp_path):
    folder = tiny_predict_folder(tmp_path, n=4)
    save_ply(load_view_scene(folder).gaussians, folder / "scene.ply",
             extra={"obs_views": torch.tensor([[2.0, 2, 1, 0]]), "completion": torch.zeros(1, 4)})
    assert "seen by >= 2 input views: 50%" in _share_text(load_view_scene(folder))


def test_a_scene_with_no_gaussians_is_one_line(tmp_path):
    """0 Gaussians (predict dropped every one as NaN): view and render-video ended in an IndexError traceback."""
    folder = tiny_predict_folder(tmp_path, n=10)
    n = 10
    save_ply(Gaussians(means=torch.full((1, n, 3), float("nan")), quats=torch.ones(1, n, 4), scales=torch.ones(1, n, 3),
                       opacities=torch.ones(1, n), sh=torch.zeros(1, n, 1, 3)), folder / "scene.ply")
    with pytest.raises(ValueError, match=r"scene.ply: 0 Gaussians .*; nothing to view"):
        load_view_scene(folder)


def test_without_the_viewer_extra_view_and_render_video_are_one_line(tmp_path, monkeypatch):
    """Without viser / imageio-ffmpeg: an uncaught ModuleNotFoundError."""
    monkeypatch.setitem(sys.modules, "viser", None)  # `import viser` raises ModuleNotFoundError
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    folder = tiny_predict_folder(tmp_path, n=10)
    with pytest.raises(ValueError, match=r"anycity view needs the viewer extra .*pip install -e '\.\[viewer\]'"):
        build_server(folder, port=0)
    with pytest.raises(ValueError, match=r"anycity render-video needs the viewer extra .*pip install -e "
                                         r"'\.\[viewer\]'"):
        render_video(folder, tmp_path / "v.mp4", progress=False)
    assert not (tmp_path / "v.mp4").exists()


def _rewrite_ply(ply, extra_fields: list[tuple], fill) -> None:
    """Rewrite ``ply`` with ``extra_fields`` (numpy dtype descriptors) appended, each column set by ``fill(name)``."""
    from plyfile import PlyData, PlyElement

    v = PlyData.read(str(ply))["vertex"].data
    data = np.empty(len(v), dtype=v.dtype.descr + extra_fields)
    for name in v.dtype.names:
        data[name] = v[name]
    for name, *_ in extra_fields:
        data[name] = fill(name)
    PlyData([PlyElement.describe(data, "vertex")]).write(str(ply))


def test_a_list_obs_views_column_is_ignored_with_one_warning(tmp_path):
    """Another tool's PLY with obs_views as a list property: colourings() raised a raw TypeError (np.isnan on
    objects)."""
    from anycity.viewer.server import colourings

    folder = tiny_predict_folder(tmp_path, n=4, with_prov=False)
    ply = folder / "scene.ply"
    _rewrite_ply(ply, [("obs_views", "O")], lambda _: [np.array([1.0, 2.0], np.float32)] * 4)
    with pytest.warns(UserWarning, match=r"scene\.ply: ignoring the list property obs_views") as rec:
        scene = load_view_scene(folder)
    assert len(rec) == 1 and "obs_views" not in scene.extras
    assert colourings(scene.extras) == COLOURINGS[:1] and "seen by" not in _share_text(scene)
    assert colourings({"obs_views": np.array([[1, 2]], dtype=object)[0]}) == COLOURINGS[:1]


def test_a_ply_of_sh_degree_5_is_one_line_naming_it(tmp_path):
    """105 f_rest (degree 5, more than a Gaussians holds) loaded, then failed later in one line without the file."""
    folder = tiny_predict_folder(tmp_path, n=4, with_prov=False)
    _rewrite_ply(folder / "scene.ply", [(f"f_rest_{i}", "<f4") for i in range(105)], lambda _: 0.0)
    with pytest.raises(ValueError, match=r"scene\.ply is not a readable 3DGS PLY .*105 f_rest_\* properties: SH "
                                         r"degree 5; anycity reads degree 0 to 4") as e:
        load_view_scene(folder)
    assert "\n" not in str(e.value)


def test_save_render_during_and_after_a_re_predict_saves_nowhere_and_says_so_in_the_panel(tmp_path, monkeypatch):
    """"Save render" wrote by path: while a re-predict had the folder moved aside it raised FileNotFoundError (a
    server traceback, nothing in the browser), and afterwards it saved the old scene's render into the new folder."""
    import os
    import re
    from types import SimpleNamespace

    import viser
    from viser._gui_handles import GuiButtonHandle

    clicks, panels, add_markdown = [], [], viser.GuiApi.add_markdown
    monkeypatch.setattr(GuiButtonHandle, "on_click", lambda self, f: clicks.append(f) or f)
    monkeypatch.setattr(viser.GuiApi, "add_markdown",
                        lambda self, *a, **k: panels.append(add_markdown(self, *a, **k)) or panels[-1])
    (tmp_path / "out").mkdir()
    folder = tmp_path / "out" / "scene"
    folder.mkdir()
    tiny_predict_folder(folder, n=50)
    server, scene = build_server(folder, port=0)
    try:
        (click,), (info,) = clicks, panels
        cam = SimpleNamespace(wxyz=np.array([1.0, 0, 0, 0]), position=np.array([0.0, 0, -4]), fov=1.0, aspect=1.0)
        click(SimpleNamespace(client=SimpleNamespace(camera=cam)))  # the scene as loaded: saved in its folder
        assert len(list((folder / "view_renders").glob("render_*.png"))) == 1 and "saved `" in info.content
        os.rename(folder, tmp_path / "out" / "scene.1")  # a re-predict moves the scene aside first
        click(SimpleNamespace(client=SimpleNamespace(camera=cam)))
        replaced = (rf"no render saved: {re.escape(str(folder))}: the scene was replaced on disk \(re-predicted\?\) "
                    rf"since this viewer loaded it; no render saved; restart anycity view {re.escape(str(folder))} to "
                    "load the new one$")
        assert re.search(replaced, info.content), info.content
        folder.mkdir()
        tiny_predict_folder(folder, n=60)  # ... and writes the new scene at the old path
        click(SimpleNamespace(client=SimpleNamespace(camera=cam)))
        assert re.search(replaced, info.content), info.content
        assert not (folder / "view_renders").exists()  # not the old scene's render in the new scene's folder
        assert len(list((tmp_path / "out" / "scene.1" / "view_renders").glob("*.png"))) == 1
    finally:
        server.stop()
