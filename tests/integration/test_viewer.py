"""``anycity view``: the viser page opens in headless Chromium and draws the splats (skipped without Chromium)."""

from __future__ import annotations

import contextlib
import math
import shutil
import socket
import subprocess

import numpy as np
import pytest
import torch
from helpers.viewer_scenes import tiny_predict_folder
from PIL import Image

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", "--hide-scrollbars"]


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


def test_thumbnails_of_a_photo_folder_prediction(tmp_path):
    """cameras.json names the photos (img_1.jpg ...), the inputs are written as NNN.png: the frustums still get
    their photos."""
    from anycity.viewer.scene import load_view_scene

    scene = load_view_scene(tiny_predict_folder(tmp_path, names=["img_1.jpg", "img_2.jpg", "img_3.jpg"]))
    assert len(scene.thumbs) == 3 and scene.thumbs[2].mean() == 120


def test_save_render_button_writes_our_render_of_the_current_camera(tmp_path):
    """What the "Save render" button runs, at a predicted camera: our render of that view, and a second click never
    overwrites the first."""
    from anycity.geometry import rotmat_to_quat
    from anycity.viewer.scene import load_view_scene
    from anycity.viewer.server import camera_w2c, render_view, save_render

    scene = load_view_scene(tiny_predict_folder(tmp_path))
    c2w = torch.linalg.inv(scene.w2c[1]).double()
    wxyz, pos = rotmat_to_quat(c2w[:3, :3]).numpy(), c2w[:3, 3].numpy()
    fov = 2 * math.atan(0.5 * scene.height / float(scene.K[1, 1, 1]))
    first = save_render(scene, wxyz, pos, fov, scene.width / scene.height, height=64)
    second = save_render(scene, wxyz, pos, fov, scene.width / scene.height, height=64)
    assert first != second and first.parent == tmp_path / "view_renders" and second.is_file()
    img = np.asarray(Image.open(first))
    assert img.shape == (64, 96, 3) and img.std() > 5  # the cube, not an empty frame
    w2c, K = camera_w2c(wxyz, pos, fov, 96, 64)
    torch.testing.assert_close(w2c[0, 0], scene.w2c[1].float(), atol=1e-5, rtol=0)  # the viewer's camera round trip
    np.testing.assert_array_equal(img, render_view(scene, w2c, K, 96, 64))


def test_save_render_clicks_in_one_second_each_get_their_own_file(tmp_path, monkeypatch):
    import time

    from anycity.viewer.scene import load_view_scene
    from anycity.viewer.server import save_render

    scene = load_view_scene(tiny_predict_folder(tmp_path, n=50))
    monkeypatch.setattr(time, "strftime", lambda fmt, *a: "20250101_000000")
    files = [save_render(scene, [1.0, 0, 0, 0], [0.0, 0, -4], 1.0, 1.0, height=8) for _ in range(3)]
    assert [f.name for f in files] == ["render_20250101_000000.png", "render_20250101_000000_1.png",
                                       "render_20250101_000000_2.png"]
    assert len(list((tmp_path / "view_renders").iterdir())) == 3


def _server_with_spies(folder, monkeypatch, cameras=True):
    """build_server with its frustums, splat uploads and GUI callbacks recorded: ``(server, scene, spies)``; spies
    holds the frustums' keyword arguments, the splats' colours, the button's and the dropdown's callbacks and the
    panel."""
    import viser
    from viser._gui_handles import GuiButtonHandle, GuiDropdownHandle

    from anycity.viewer.server import build_server

    spies = {"frustums": [], "rgbs": [], "clicks": [], "dropdowns": [], "panels": []}
    frustum, splats = viser.SceneApi.add_camera_frustum, viser.SceneApi.add_gaussian_splats
    markdown = viser.GuiApi.add_markdown
    monkeypatch.setattr(viser.SceneApi, "add_camera_frustum",
                        lambda self, *a, **k: spies["frustums"].append(k) or frustum(self, *a, **k))
    monkeypatch.setattr(viser.SceneApi, "add_gaussian_splats",
                        lambda self, name, c, cov, rgbs, *a, **k: spies["rgbs"].append(rgbs)
                        or splats(self, name, c, cov, rgbs, *a, **k))
    monkeypatch.setattr(viser.GuiApi, "add_markdown",
                        lambda self, *a, **k: spies["panels"].append(markdown(self, *a, **k)) or spies["panels"][-1])
    monkeypatch.setattr(GuiButtonHandle, "on_click", lambda self, f: spies["clicks"].append(f) or f)
    monkeypatch.setattr(GuiDropdownHandle, "on_update", lambda self, f: spies["dropdowns"].append((self, f)) or f)
    server, scene = build_server(folder, port=0, cameras=cameras)
    return server, scene, spies


def test_frustums_sit_at_the_cameras_and_no_cameras_hides_them(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    from helpers.raycast_scenes import look_at

    from anycity.export import save_cameras
    from anycity.geometry import quat_to_rotmat

    folder = tiny_predict_folder(tmp_path, n=20)
    w2c = torch.stack([look_at((5.0 * math.cos(t), 5.0 * math.sin(t), 3.0), (0.0, 0, 0)) for t in (0.0, 0.5, 1.0)])
    save_cameras(folder / "cameras.json", w2c, torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]]).repeat(3, 1, 1),
                 48, 32)
    server, _, spies = _server_with_spies(folder, monkeypatch)
    server.stop()
    assert len(spies["frustums"]) == 3
    for v, k in enumerate(spies["frustums"]):
        c2w = torch.linalg.inv(w2c[v]).double()
        torch.testing.assert_close(quat_to_rotmat(torch.as_tensor(k["wxyz"])), c2w[:3, :3], atol=1e-5, rtol=0)
        np.testing.assert_allclose(k["position"], c2w[:3, 3].numpy(), atol=1e-5)
    server, _, spies = _server_with_spies(folder, monkeypatch, cameras=False)  # --no-cameras
    server.stop()
    assert spies["frustums"] == []


def test_colour_by_obs_views_ramps_to_red_at_4_views(tmp_path, monkeypatch):
    pytest.importorskip("viser")
    from anycity.viewer.scene import ramp

    server, scene, spies = _server_with_spies(tiny_predict_folder(tmp_path, n=20), monkeypatch)
    try:
        (dropdown, update), = spies["dropdowns"]
        dropdown.value = "obs_views (blue 0 -> red 4+ views)"
        update(None)
    finally:
        server.stop()
    np.testing.assert_allclose(spies["rgbs"][-1], ramp(scene.extras["obs_views"] / 4.0), atol=1e-6)


def test_save_render_into_an_unusable_folder_says_so_in_the_panel(tmp_path, monkeypatch):
    """view_renders is a file: the OSError (not a FileNotFoundError) was a server-side traceback, nothing shown."""
    from types import SimpleNamespace

    pytest.importorskip("viser")
    folder = tiny_predict_folder(tmp_path, n=20)
    (folder / "view_renders").write_text("a file where the folder goes")
    server, _, spies = _server_with_spies(folder, monkeypatch)
    try:
        (click,), (info,) = spies["clicks"], spies["panels"]
        cam = SimpleNamespace(wxyz=np.array([1.0, 0, 0, 0]), position=np.array([0.0, 0, -4]), fov=1.0, aspect=1.0)
        click(SimpleNamespace(client=SimpleNamespace(camera=cam)))
    finally:
        server.stop()
    assert "no render saved: " in info.content and "view_renders" in info.content


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

    server, _ = build_server(tiny_predict_folder(tmp_path), port=0, cameras=False)  # only splats can draw
    try:
        img = screenshot(f"http://127.0.0.1:{server.get_port()}", tmp_path / "shot.png")
    finally:
        server.stop()
    share = drawn_share(img)
    assert share > 0.05, f"viewer canvas looks blank: {share:.3f} of the centre drawn"


def test_view_refuses_an_empty_scene_and_a_missing_extra_in_one_line(tmp_path, capsys, monkeypatch):
    """0 Gaussians: an IndexError traceback; no viser: an uncaught ModuleNotFoundError. Both are one line now."""
    import sys

    from anycity.cli import main
    from anycity.export import save_ply
    from anycity.structures import Gaussians

    pytest.importorskip("viser")
    (tmp_path / "empty").mkdir()
    folder = tiny_predict_folder(tmp_path / "empty", n=10)
    save_ply(Gaussians(means=torch.full((1, 10, 3), float("nan")), quats=torch.ones(1, 10, 4),
                       scales=torch.ones(1, 10, 3), opacities=torch.ones(1, 10), sh=torch.zeros(1, 10, 1, 3)),
             folder / "scene.ply")
    assert main(["view", str(folder), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "scene.ply: 0 Gaussians" in err and len(err.splitlines()) == 1
    monkeypatch.setitem(sys.modules, "viser", None)
    (tmp_path / "full").mkdir()
    assert main(["view", str(tiny_predict_folder(tmp_path / "full", n=10)), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "anycity view needs the viewer extra" in err and len(err.splitlines()) == 1


_VIEW = "import sys; from anycity.cli import main; sys.exit(main(sys.argv[1:]))"


@pytest.mark.parametrize("host, why", [("nohost.invalid", "cannot resolve it"),
                                       ("203.0.113.7", "not an address of this machine")])
def test_a_host_the_viewer_cannot_listen_on_is_one_line_not_a_hang(tmp_path, host, why):
    """viser's server thread died (or tried 1000 ports) and `anycity view` waited for it forever, printing nothing."""
    import sys

    pytest.importorskip("viser")
    folder = tiny_predict_folder(tmp_path, n=10)
    try:
        child = subprocess.run([sys.executable, "-c", _VIEW, "view", str(folder), "--host", host, "--port", "0"],
                               capture_output=True, text=True, timeout=90)
    except subprocess.TimeoutExpired:
        pytest.fail(f"anycity view --host {host} hung")
    err = child.stderr.strip()
    assert child.returncode == 2 and len(err.splitlines()) == 1, err
    assert f"--host {host}: {why}" in err and "127.0.0.1" in err


def test_a_taken_port_moves_up_and_a_taken_65535_is_one_line(tmp_path):
    """--port 65535 taken: viser moved to 65536, its thread died on the OverflowError and view hung."""
    pytest.importorskip("viser")
    from anycity.viewer.server import build_server, listen_port

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert listen_port("127.0.0.1", port) > port
        assert listen_port("127.0.0.1", 0) == 0
    with _port_65535_or_skip() as top:
        top.listen()
        with pytest.raises(ValueError, match=r"--port 65535: it is taken on 127\.0\.0\.1; pass --port 0") as e:
            build_server(tiny_predict_folder(tmp_path, n=10), port=65535)
        assert "\n" not in str(e.value)


@contextlib.contextmanager
def _port_65535_or_skip():
    """A socket bound to 127.0.0.1:65535, closed on exit; the test is skipped where that port is in use."""
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", 65535))
        except OSError:
            pytest.skip("port 65535 is in use here")
        yield s


def test_a_free_port_65535_is_listened_on():
    from anycity.viewer.server import listen_port

    with _port_65535_or_skip():
        pass  # free a moment ago
    assert listen_port("127.0.0.1", 65535) == 65535
