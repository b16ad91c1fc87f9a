"""The input thumbnails the viewer shows on the camera frustums: a damaged one costs the thumbnails, not the
viewer; predict writes them so that a killed run leaves none cut short."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from helpers.faults import fail_writes_midway
from helpers.viewer_scenes import tiny_predict_folder
from PIL import Image

from anycity.export.views import save_view_pngs, view_png
from anycity.viewer.scene import load_view_scene


@pytest.mark.parametrize("keep", [60, 200])
def test_a_cut_thumbnail_warns_once_and_the_scene_shows_none(tmp_path, keep):
    """A truncated inputs/001.png (an interrupted copy) ended `anycity view` in an OSError traceback."""
    folder = tiny_predict_folder(tmp_path, n=50)
    png = view_png(folder, "inputs", 1)
    rng = np.random.default_rng(0)  # noise: a PNG large enough to cut inside its image data
    Image.fromarray(rng.integers(0, 255, (32, 48, 3), dtype=np.uint8)).save(png)
    png.write_bytes(png.read_bytes()[:keep])
    with pytest.warns(UserWarning, match=r"inputs/001\.png: unreadable input image .*no camera thumbnails") as rec:
        scene = load_view_scene(folder)
    assert len(rec) == 1 and scene.thumbs == [] and scene.gaussians.num_gaussians == 50 and scene.w2c is not None


def test_a_missing_first_thumbnail_shows_none_not_the_others_on_the_wrong_cameras(tmp_path):
    folder = tiny_predict_folder(tmp_path, n=50)
    view_png(folder, "inputs", 0).unlink()
    assert load_view_scene(folder).thumbs == []


def test_render_video_loads_no_thumbnails(tmp_path):
    folder = tiny_predict_folder(tmp_path, n=50)
    view_png(folder, "inputs", 0).write_bytes(b"not a png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_view_scene(folder, thumbs=False)
    assert scene.thumbs == [] and scene.w2c is not None
    assert len(load_view_scene(tiny_predict_folder(tmp_path / "ok", n=50)).thumbs) == 3  # the viewer's default


def test_a_png_write_that_fails_midway_leaves_no_cut_png(tmp_path, monkeypatch):
    """save_view_pngs wrote each PNG in place: a full disk (or a kill) left a truncated inputs/001.png that the viewer
    then failed to read."""
    images = torch.rand(3, 3, 32, 48, generator=torch.Generator().manual_seed(0))
    fail_writes_midway(monkeypatch, "001.png")
    with pytest.raises(OSError, match=r"disk full writing .*001\.png"):
        save_view_pngs(tmp_path, "inputs", images, range(3))
    monkeypatch.undo()
    assert sorted(p.name for p in (tmp_path / "inputs").iterdir()) == ["000.png"]  # no 001.png, no temp file
    save_view_pngs(tmp_path, "inputs", images, range(3))
    back = np.asarray(Image.open(view_png(tmp_path, "inputs", 2)))
    np.testing.assert_array_equal(back, (images[2].permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8))


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG of a few bytes whose header claims ``width x height`` RGB pixels (Pillow refuses it at open)."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def test_a_decompression_bomb_thumbnail_warns_once_and_the_scene_shows_none(tmp_path):
    """inputs/000.png whose header claims 60000x60000: Pillow's DecompressionBombError (an Exception, not an
    OSError) ended `anycity view` in a traceback."""
    folder = tiny_predict_folder(tmp_path, n=50)
    view_png(folder, "inputs", 0).write_bytes(_png_header_only(60000, 60000))
    with pytest.warns(UserWarning, match=r"inputs/000\.png: unreadable input image .*no camera thumbnails") as rec:
        scene = load_view_scene(folder)
    assert len(rec) == 1 and scene.thumbs == [] and scene.gaussians.num_gaussians == 50 and scene.w2c is not None
