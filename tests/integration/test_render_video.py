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
