"""``anycity render-video``: frame count of the interpolated path (+ orbit) and frames that move."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.viewer_scenes import tiny_predict_folder

from anycity.cli import main


def test_render_video_frames(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=400, with_prov=False)
    out = tmp_path / "fly.mp4"
    assert main(["render-video", str(folder), "--out", str(out), "--per-segment", "3", "--orbit", "4",
                 "--width", "48"]) == 0
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    assert meta["size"] == (48, 32)
    frames = [np.frombuffer(f, np.uint8).reshape(32, 48, 3).astype(int) for f in reader]
    assert len(frames) == 2 * 3 + 1 + 4  # 3 cameras: 2 segments of 3 + the last camera, then the orbit
    diffs = [np.abs(a - b).mean() for a, b in zip(frames, frames[1:], strict=False)]
    assert min(diffs) > 0.1, diffs


def test_render_video_says_its_frame_size_and_where_it_came_from(tmp_path, capsys):
    """The default width is the input's (tiny for the quickstart's model) and an odd --width is rounded down: both
    were silent, so a user got a 56 px video, or another width than asked, without a word."""
    pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=20, with_prov=False)
    assert main(["render-video", str(folder), "--out", str(tmp_path / "a.mp4"), "--per-segment", "1"]) == 0
    assert "frames of 48x32 (the input width; --width sets another)" in capsys.readouterr().out
    assert main(["render-video", str(folder), "--out", str(tmp_path / "b.mp4"), "--per-segment", "1",
                 "--width", "17"]) == 0
    assert "frames of 16x" in capsys.readouterr().out


def test_render_video_writes_at_the_fps_asked(tmp_path):
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    out = tmp_path / "fly.mp4"
    folder = tiny_predict_folder(tmp_path / "s", n=20, with_prov=False)
    assert main(["render-video", str(folder), "--out", str(out), "--per-segment", "1", "--width", "16",
                 "--fps", "10"]) == 0
    assert next(imageio_ffmpeg.read_frames(str(out)))["fps"] == 10


def test_a_nadir_flights_orbit_circles_above_the_ground(tmp_path, monkeypatch):
    """Straight-down cameras: render-video must orbit about the ground's normal (scene_up), not the cameras' mean
    "up", which lies on the ground and swings the orbit through it."""
    import torch
    from helpers.raycast_scenes import look_at

    from anycity.export import save_cameras, save_ply
    from anycity.structures import Gaussians
    from anycity.viewer import video

    pytest.importorskip("imageio_ffmpeg")
    g, n = torch.Generator().manual_seed(0), 2000
    means = torch.cat([torch.rand(n, 2, generator=g) * 20 - 10, torch.rand(n, 1, generator=g)], -1)[None]
    save_ply(Gaussians(means, torch.tensor([1.0, 0, 0, 0]).expand(1, n, 4).clone(), torch.full((1, n, 3), 0.05),
                       torch.full((1, n), 0.9), torch.zeros(1, n, 1, 3)), tmp_path / "scene.ply")
    w2c = torch.stack([look_at((x, y, 20.0), (x, y, 0.0), up=(0.0, 1.0, 0.0))
                       for x in (-6.0, 6.0) for y in (-6.0, 6.0)])
    save_cameras(tmp_path / "cameras.json", w2c, torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]]).repeat(4, 1, 1),
                 48, 32)
    seen = []

    def frames(scene, w2c, K, width, height, progress=True):
        seen.append(w2c)
        return iter([np.zeros((height, width, 3), np.uint8)] * len(w2c))

    monkeypatch.setattr(video, "render_frames", frames)
    assert video.render_video(tmp_path, tmp_path / "v.mp4", per_segment=1, orbit=6, width=16, progress=False) == 10
    eyes = torch.linalg.inv(seen[0][-6:])[:, :3, 3]
    assert (eyes[:, 2] > 15).all(), eyes  # at the flight's height, not through the ground


def _scene_and_an_earlier_video(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    out = tmp_path / "fly.mp4"
    out.write_bytes(b"an earlier video")
    return tiny_predict_folder(tmp_path / "s", n=50, with_prov=False), out


def test_render_video_keeps_an_existing_file(tmp_path, capsys):
    folder, out = _scene_and_an_earlier_video(tmp_path)
    args = ["render-video", str(folder), "--out", str(out), "--per-segment", "1", "--width", "16"]
    assert main(args) == 2
    assert f"{out} exists; pass --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"an earlier video"
    assert main([*args, "--overwrite"]) == 0 and out.stat().st_size > 100


def test_a_render_that_fails_midway_keeps_the_earlier_video_and_leaves_no_part(tmp_path, monkeypatch):
    """ffmpeg wrote straight to --out: a failed --overwrite run destroyed the old video and left a short one."""
    from anycity.viewer import video

    folder, out = _scene_and_an_earlier_video(tmp_path)
    frames = video.render_frames

    def fail_after_two(*args, **kwargs):
        for i, frame in enumerate(frames(*args, **kwargs)):
            if i == 2:
                raise RuntimeError("out of memory (simulated)")
            yield frame

    monkeypatch.setattr(video, "render_frames", fail_after_two)
    with pytest.raises(RuntimeError, match="simulated"):
        video.render_video(folder, out, per_segment=2, width=16, progress=False)
    assert out.read_bytes() == b"an earlier video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fly.mp4", "s"]
    monkeypatch.setattr(video, "render_frames", frames)
    assert video.render_video(folder, out, per_segment=2, width=16, progress=False) > 0
    assert out.stat().st_size > 100 and sorted(p.name for p in tmp_path.iterdir()) == ["fly.mp4", "s"]


def _empty_scene(tmp_path):
    """A predict folder whose scene.ply has 0 Gaussians (predict dropped every one as NaN)."""
    import torch

    from anycity.export import save_ply
    from anycity.structures import Gaussians

    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=10, with_prov=False)
    save_ply(Gaussians(means=torch.full((1, 10, 3), float("nan")), quats=torch.ones(1, 10, 4),
                       scales=torch.ones(1, 10, 3), opacities=torch.ones(1, 10), sh=torch.zeros(1, 10, 1, 3)),
             folder / "scene.ply")
    return folder


def test_an_empty_scene_is_one_line(tmp_path, capsys):
    """render-video --orbit on 0 Gaussians ended in an IndexError traceback (the median of nothing)."""
    pytest.importorskip("imageio_ffmpeg")
    folder = _empty_scene(tmp_path)
    out = tmp_path / "fly.mp4"
    assert main(["render-video", str(folder), "--out", str(out), "--orbit", "4", "--width", "16"]) == 2
    err = capsys.readouterr().err
    assert "scene.ply: 0 Gaussians" in err and "nothing to view" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_without_the_viewer_extra_render_video_is_one_line(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # `import imageio_ffmpeg` raises ModuleNotFoundError
    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=10, with_prov=False)
    assert main(["render-video", str(folder), "--out", str(tmp_path / "fly.mp4")]) == 2
    err = capsys.readouterr().err.strip()
    assert "render-video needs the viewer extra" in err and "pip install -e '.[viewer]'" in err
    assert len(err.splitlines()) == 1


_FFMPEG_CANNOT_FINISH = r"""
import resource, sys
from anycity.cli import main
folder, out, limit = sys.argv[1], sys.argv[2], int(sys.argv[3])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))  # ffmpeg inherits it: a disk or quota that fills up
sys.exit(main(["render-video", folder, "--out", out, "--per-segment", "4", "--width", "96", "--overwrite"]))
"""


def test_a_video_ffmpeg_cannot_finish_is_not_published_over_the_earlier_one(tmp_path):
    """imageio-ffmpeg ignores ffmpeg's exit status: ffmpeg failing at its last write (the mp4's index) left a cut,
    unplayable mp4 that was renamed over the good one under --overwrite, and render-video said "wrote"."""
    import subprocess
    import sys

    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=400, with_prov=False)
    out = tmp_path / "fly.mp4"
    assert main(["render-video", str(folder), "--out", str(out), "--per-segment", "4", "--width", "96"]) == 0
    good = out.read_bytes()
    assert imageio_ffmpeg.count_frames_and_secs(str(out))[0] == 9
    child = subprocess.run([sys.executable, "-c", _FFMPEG_CANNOT_FINISH, str(folder), str(out), str(len(good) // 2)],
                           capture_output=True, text=True, timeout=300)
    err = child.stderr.strip().splitlines()[-1]
    assert child.returncode == 2, child.stdout + child.stderr
    assert f"anycity: error: --out {out}: ffmpeg failed writing the video" in err and "wrote" not in child.stdout
    assert out.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fly.mp4", "s"]  # no temp file left


def test_ffmpeg_exiting_midway_is_one_line_naming_out(tmp_path, monkeypatch):
    """ffmpeg that dies while frames are sent (a broken pipe): imageio's OSError, with ffmpeg's whole command line,
    ended render-video in a traceback."""
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    from anycity.viewer import video

    folder, out = _scene_and_an_earlier_video(tmp_path)
    real = imageio_ffmpeg.write_frames

    def dies_after_two(path, *args, **kwargs):
        writer = real(path, *args, **kwargs)
        frame = yield
        writer.send(None)
        for _ in range(2):
            writer.send(frame)
            frame = yield
        writer.close()
        raise OSError("[Errno 32] Broken pipe\n\nFFMPEG COMMAND:\nffmpeg -y ...")

    monkeypatch.setattr(imageio_ffmpeg, "write_frames", dies_after_two)
    with pytest.raises(ValueError, match=r"--out .*fly\.mp4: ffmpeg failed writing the video \(it stopped after 2 "
                                         r"frames") as e:
        video.render_video(folder, out, per_segment=2, width=16, progress=False)
    assert "\n" not in str(e.value) and out.read_bytes() == b"an earlier video"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fly.mp4", "s"]


def test_a_damaged_input_image_does_not_stop_render_video(tmp_path):
    """render-video never shows the input images, yet loaded them: a cut inputs/001.png (an interrupted copy) ended
    it in an OSError traceback."""
    pytest.importorskip("imageio_ffmpeg")
    (tmp_path / "s").mkdir()
    folder = tiny_predict_folder(tmp_path / "s", n=50, with_prov=False)
    png = folder / "inputs" / "001.png"
    png.write_bytes(png.read_bytes()[:60])
    out = tmp_path / "fly.mp4"
    assert main(["render-video", str(folder), "--out", str(out), "--per-segment", "1", "--width", "16"]) == 0
    assert out.stat().st_size > 100
