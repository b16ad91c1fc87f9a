"""``anycity view``'s Save render with what a browser may send (huge or odd cameras, two clicks at once), the URL
it prints and its ``--port`` message. The render itself is stubbed: these check sizes, names and messages."""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from anycity.viewer import server
from anycity.viewer.server import MAX_RENDER_WIDTH, save_click, save_render, view_main, view_url

CAM = dict(wxyz=[1.0, 0, 0, 0], position=[0.0, 0, -4], fov_y=1.0)


@pytest.fixture
def sizes(monkeypatch):
    """The ``(width, height)`` of each render asked for; the stub returns a 2 x 2 image (never the size asked)."""
    asked = []
    monkeypatch.setattr(
        server, "render_view", lambda scene, w2c, K, w, h: asked.append((w, h)) or np.zeros((2, 2, 3), np.uint8)
    )
    return asked


@pytest.mark.parametrize("aspect", [100.0, 1e6])
def test_save_render_bounds_the_width_a_browser_asks_for(tmp_path, sizes, aspect):
    """aspect=100 rendered 48000 x 480, aspect=1e6 about 480 Mpx: the width is at most MAX_RENDER_WIDTH now."""
    save_render(SimpleNamespace(folder=tmp_path), **CAM, aspect=aspect)
    ((w, h),) = sizes
    assert h == 480 and w <= MAX_RENDER_WIDTH


def test_save_render_keeps_an_ordinary_aspect(tmp_path, sizes):
    save_render(SimpleNamespace(folder=tmp_path), **CAM, aspect=640 / 480)
    assert sizes == [(640, 480)]


@pytest.mark.parametrize(
    "change, named",
    [
        (dict(aspect=float("nan")), "aspect"),
        (dict(aspect=0.0), "aspect"),
        (dict(aspect=-640 / 480), "aspect"),
        (dict(aspect=math.inf), "aspect"),
        (dict(fov_y=0.0), "field of view 0.0"),
        (dict(fov_y=float("nan")), "field of view nan"),
        (dict(fov_y=math.pi), "field of view"),
        (dict(position=[math.nan, 0, 0]), "camera position"),
        (dict(wxyz=[0.0, 0, 0, 0]), "rotation"),
        (dict(wxyz=[math.inf, 0, 0, 0]), "rotation"),
        (dict(height=0), "image height 0"),
    ],
)
def test_an_odd_camera_is_a_one_line_value_error(tmp_path, sizes, change, named):
    """fov 0 was a ZeroDivisionError, NaN a renderer's ValueError or a NaN image, a negative width a 1 px PNG."""
    with pytest.raises(ValueError, match=named) as e:
        save_render(SimpleNamespace(folder=tmp_path), **{**CAM, "aspect": 1.0, **change})
    assert "\n" not in str(e.value) and sizes == []
    assert not (tmp_path / "view_renders").exists() or not any((tmp_path / "view_renders").iterdir())


class _ZeroHighCamera:
    """viser's CameraHandle of a browser reporting a 0 px tall view: its ``aspect`` divides by 0."""

    wxyz, position, fov, image_width, image_height = np.array([1.0, 0, 0, 0]), np.zeros(3), 1.0, 640, 0

    @property
    def aspect(self) -> float:
        return self.image_width / self.image_height


def test_the_button_says_no_render_saved_in_the_panel_for_an_odd_camera(tmp_path, sizes):
    """The click handler caught only OSError: these were tracebacks on the server's terminal, nothing in the panel."""
    scene = SimpleNamespace(folder=tmp_path)
    assert save_click(scene, _ZeroHighCamera(), None) == "no render saved: the browser's view is 640 x 0 px"
    nan_fov = SimpleNamespace(wxyz=[1.0, 0, 0, 0], position=[0.0, 0, -4], fov=math.nan, aspect=1.0)
    assert save_click(scene, nan_fov, None).startswith("no render saved: field of view nan")
    ok = SimpleNamespace(wxyz=[1.0, 0, 0, 0], position=[0.0, 0, -4], fov=1.0, aspect=1.0)
    line = save_click(scene, ok, None)
    assert line.startswith("saved `") and (tmp_path / "view_renders").is_dir() and sizes == [(480, 480)]


def test_two_clicks_at_once_in_one_second_each_get_their_own_file(tmp_path, monkeypatch):
    """Both renders run at once (viser's thread pool) and end in the same second: each used to take the same free
    name after its own exists() check, and one render overwrote the other."""
    barrier = threading.Barrier(2, timeout=5)

    def render(scene, w2c, K, w, h):
        barrier.wait()  # both have started (and, before the fix, both had picked their name)
        return np.full((2, 2, 3), 100 if float(w2c[0, 0, 2, 3]) > 3.5 else 200, np.uint8)

    monkeypatch.setattr(server, "render_view", render)
    monkeypatch.setattr(time, "strftime", lambda fmt, *a: "20250101_000000")
    files = []
    threads = [
        threading.Thread(
            target=lambda z=z: files.append(
                save_render(SimpleNamespace(folder=tmp_path), [1.0, 0, 0, 0], [0.0, 0, z], 1.0, 1.0, height=8)
            )
        )
        for z in (-3.0, -4.0)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert sorted(f.name for f in files) == ["render_20250101_000000.png", "render_20250101_000000_1.png"]
    assert sorted(p.name for p in (tmp_path / "view_renders").iterdir()) == sorted(f.name for f in files)
    assert sorted(int(np.asarray(Image.open(f))[0, 0, 0]) for f in files) == [100, 200]


def test_a_name_taken_meanwhile_is_skipped_and_kept(tmp_path, sizes, monkeypatch):
    monkeypatch.setattr(time, "strftime", lambda fmt, *a: "20250101_000000")
    (tmp_path / "view_renders").mkdir()
    (tmp_path / "view_renders" / "render_20250101_000000.png").write_bytes(b"earlier")
    f = save_render(SimpleNamespace(folder=tmp_path), **CAM, aspect=1.0, height=8)
    assert f.name == "render_20250101_000000_1.png" and Image.open(f).size == (2, 2)
    assert (tmp_path / "view_renders" / "render_20250101_000000.png").read_bytes() == b"earlier"


@pytest.mark.parametrize(
    "host, url, every",
    [
        ("127.0.0.1", "http://127.0.0.1:8080", False),
        ("localhost", "http://localhost:8080", False),
        ("::1", "http://[::1]:8080", False),
        ("fe80::1%eth0", "http://[fe80::1%25eth0]:8080", False),
        ("", "http://127.0.0.1:8080", True),
        ("0.0.0.0", "http://127.0.0.1:8080", True),
        ("::", "http://[::1]:8080", True),
    ],
)
def test_the_printed_url_opens_for_ipv6_and_wildcard_hosts(host, url, every):
    """--host ::1 printed http://::1:8080, --host '' http://:8080 and 0.0.0.0 an address no browser opens."""
    assert view_url(host, 8080) == (url, every)


def test_a_port_that_is_not_a_number_is_an_invalid_int(capsys):
    """argparse named the type function: "invalid _port value: 'abc'"."""
    with pytest.raises(SystemExit) as e:
        view_main(["some_scene", "--port", "abc"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "argument --port: invalid int value: 'abc'" in err and "_port" not in err
