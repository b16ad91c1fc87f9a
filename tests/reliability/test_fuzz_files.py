"""Fuzz the other readers of files users hand us: ``load_ply``, a predict folder's ``cameras.json`` (through
``anycity export``), shard tars and their members, photo folders.

Outcome: a correct result or the project's one-line ``ValueError``/``FileNotFoundError`` naming the file.
"""

import io
import re
import struct
import warnings
import zlib

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from PIL import Image

from anycity.data.photos import load_photo_folder
from anycity.data.pipeline import SampleBuilder, make_pipeline
from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import ShardSetWriter, shard_urls
from anycity.export.cameras import load_cameras, save_cameras
from anycity.export.cli import export
from anycity.export.ply import load_ply, save_ply
from anycity.geometry import camera_problem
from anycity.structures import Gaussians

from .test_fuzz_readers import CASES, GT, K, mutate, mutations


def _gaussians(n=20):
    g = torch.Generator().manual_seed(0)
    return Gaussians(means=torch.randn(1, n, 3, generator=g), quats=torch.nn.functional.normalize(
        torch.randn(1, n, 4, generator=g), dim=-1), scales=torch.rand(1, n, 3, generator=g) * 0.1 + 0.01,
        opacities=torch.rand(1, n, generator=g), sh=torch.randn(1, n, 4, 3, generator=g))


def _one_line_naming(e, path):
    assert "\n" not in str(e) and path.name in str(e), repr(e)


def _fuzz_ply(tmp_path_factory, ops):
    d = tmp_path_factory.mktemp("ply")
    p = d / "scene.ply"
    save_ply(_gaussians(), p, max_degree=1)
    p.write_bytes(mutate(p.read_bytes(), ops))
    CASES["load_ply"] = CASES.get("load_ply", 0) + 1
    try:
        g = load_ply(p)
    except (ValueError, FileNotFoundError) as e:
        _one_line_naming(e, p)
        return
    assert torch.isfinite(g.means).all() and g.means.shape[-1] == 3


def _fuzz_cameras(tmp_path_factory, ops):
    d = tmp_path_factory.mktemp("pred")
    save_ply(_gaussians(), d / "scene.ply", max_degree=1)
    cams = d / "cameras.json"
    save_cameras(cams, torch.tensor(np.stack(GT)), torch.tensor(K).expand(len(GT), 3, 3), 32, 24, scale=2.0)
    cams.write_bytes(mutate(cams.read_bytes(), ops))
    CASES["cameras_json"] = CASES.get("cameras_json", 0) + 1
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*no inputs/ images")  # the fixture has no input images
            out = export(d, "colmap", d / "colmap")
    except (ValueError, FileNotFoundError) as e:
        _one_line_naming(e, cams)
        assert not (d / "colmap").exists()
        return
    views = load_cameras(cams)["views"]
    assert all(camera_problem(v["w2c"], v["K"]) is None for v in views)
    # the numbers of the model: a view's name is text, and a mutation may well name one "nan" (it did)
    rows = [ln.split() for f in ("images.txt", "cameras.txt") for ln in (out / f).read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]
    numbers = " ".join(t for r in rows for t in (r[1:8] if len(r) >= 10 else r[2:]))
    assert len(rows) == 2 * len(views) and not re.search(r"nan|inf", numbers, re.IGNORECASE), numbers[:300]


def _shard_dir(tmp_path_factory):
    d = tmp_path_factory.mktemp("shard")
    rng = np.random.default_rng(0)
    views = [ViewRecord(name=f"{i}.png", image=rng.integers(0, 255, (16, 16, 3), dtype=np.uint8),
                        w2c=np.eye(4), K=np.diag([16.0, 16.0, 1.0]), width=16, height=16,
                        depth=np.full((16, 16), 3.0, np.float32), ext="png") for i in range(3)]
    with ShardSetWriter(d) as w:
        w.write(SceneRecord(key="s0", views=views, source="t", units="metres", metres_per_unit=1.0), "test")
    return d


def _fuzz_shard(tmp_path_factory, ops):
    d = _shard_dir(tmp_path_factory)
    url = shard_urls(d, "test")[0]
    from pathlib import Path

    Path(url).write_bytes(mutate(Path(url).read_bytes(), ops))
    CASES["shard_tar"] = CASES.get("shard_tar", 0) + 1
    try:
        out = list(make_pipeline([url], SampleBuilder(2, 1, 0, (16, 16), train=False), train=False,
                                 skip_corrupt=False))
    except (ValueError, FileNotFoundError) as e:
        assert "\n" not in str(e).strip() or "test-000000.tar" in str(e).splitlines()[0], repr(e)
        assert "test-000000.tar" in str(e), repr(e)
        return
    for s in out:
        assert torch.isfinite(s["context"]["w2c"]).all() if isinstance(s.get("context"), dict) else True


def _fuzzer(fuzz_one, n):
    """``fuzz_one(tmp_path_factory, ops)`` over ``n`` derandomized mutation lists (as ``test_fuzz_readers._make``)."""
    @settings(max_examples=n, deadline=10000, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(ops=mutations())
    def run(tmp_path_factory, ops):
        fuzz_one(tmp_path_factory, ops)

    return run


_ply_fast, _ply_slow = _fuzzer(_fuzz_ply, 50), _fuzzer(_fuzz_ply, 1000)
_cameras_fast, _cameras_slow = _fuzzer(_fuzz_cameras, 50), _fuzzer(_fuzz_cameras, 1000)
_shard_fast, _shard_slow = _fuzzer(_fuzz_shard, 50), _fuzzer(_fuzz_shard, 1000)


def test_fuzz_load_ply(tmp_path_factory):
    _ply_fast(tmp_path_factory)


def test_fuzz_shard_tar(tmp_path_factory):
    _shard_fast(tmp_path_factory)


def test_fuzz_cameras_json_through_export(tmp_path_factory):
    _cameras_fast(tmp_path_factory)


@pytest.mark.slow
def test_fuzz_cameras_json_through_export_slow(tmp_path_factory):
    _cameras_slow(tmp_path_factory)
    print(f"\nfuzz cameras_json: {CASES['cameras_json']} cases")


@pytest.mark.slow
def test_fuzz_load_ply_slow(tmp_path_factory):
    _ply_slow(tmp_path_factory)
    print(f"\nfuzz load_ply: {CASES['load_ply']} cases")


@pytest.mark.slow
def test_fuzz_shard_tar_slow(tmp_path_factory):
    _shard_slow(tmp_path_factory)
    print(f"\nfuzz shard_tar: {CASES['shard_tar']} cases")


def _png_header_only(w, h):
    """A valid-looking PNG whose IHDR declares w x h but whose data is a few bytes (a decompression bomb)."""
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def _photo_bytes(kind, seed=0):
    rgb = np.random.default_rng(seed).integers(0, 255, (40, 56, 3), dtype=np.uint8)
    buf = io.BytesIO()
    if kind == "1x1":
        Image.fromarray(rgb[:1, :1]).save(buf, "PNG")
    elif kind == "png16":
        import cv2

        buf.write(cv2.imencode(".png", rgb.astype(np.uint16) * 257)[1].tobytes())  # 16-bit RGB PNG
    elif kind == "palette":
        Image.fromarray(rgb).convert("P").save(buf, "PNG")
    elif kind == "cmyk":
        Image.fromarray(rgb).convert("CMYK").save(buf, "JPEG")
    elif kind in ("jpeg", "truncated"):
        Image.fromarray(rgb).save(buf, "JPEG")
    elif kind == "bomb":
        return _png_header_only(30000, 30000)
    elif kind == "garbage":
        return b"\xff\xd8\xff\xe0 not really a jpeg"
    data = buf.getvalue()
    return data[: len(data) // 2] if kind == "truncated" else data


@pytest.mark.parametrize("kind,ok", [("1x1", True), ("png16", True), ("palette", True), ("cmyk", True),
                                     ("truncated", False), ("bomb", False), ("garbage", False)])
def test_photo_folder_hostile_images(tmp_path, kind, ok):
    import resource

    folder = tmp_path / "photos"
    folder.mkdir()
    for i in range(2):
        (folder / f"good{i}.jpg").write_bytes(_photo_bytes("jpeg", seed=1 + i))  # not copies of one another
    ext = "jpg" if kind in ("cmyk", "truncated", "garbage") else "png"
    bad = folder / f"x_{kind}.{ext}"
    bad.write_bytes(_photo_bytes(kind))
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if ok:
        out = load_photo_folder(folder, (32, 32), mode="crop")
        assert out["images"].shape == (3, 3, 32, 32) and torch.isfinite(out["images"]).all()
    else:
        with pytest.raises(ValueError) as e:
            load_photo_folder(folder, (32, 32), mode="crop")
        _one_line_naming(e.value, bad)
    grew_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024
    assert grew_mb < 500, f"{kind}: peak memory grew by {grew_mb:.0f} MB"  # the 30000^2 bomb was not allocated


@pytest.mark.parametrize("n_rest", [3, 6, 12, 27, 30, 46])
def test_a_ply_with_no_sh_degrees_f_rest_count_is_refused(tmp_path, n_rest):
    """6 f_rest (2 coefficients beyond DC: no SH degree has 3) loaded as a "degree" that the renderer's SH evaluation
    then read wrongly; a count that is no (d + 1)^2 - 1 per channel is refused in one line naming the file."""
    from plyfile import PlyData, PlyElement

    p = tmp_path / "scene.ply"
    save_ply(_gaussians(), p, max_degree=0)
    v = PlyData.read(str(p))["vertex"].data
    data = np.zeros(len(v), dtype=v.dtype.descr + [(f"f_rest_{i}", "<f4") for i in range(n_rest)])
    for name in v.dtype.names:
        data[name] = v[name]
    PlyData([PlyElement.describe(data, "vertex")]).write(str(p))
    with pytest.raises(ValueError, match=rf"scene\.ply .*{n_rest} f_rest_\* properties: no SH degree") as e:
        load_ply(p)
    _one_line_naming(e.value, p)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_a_ply_of_every_sh_degree_still_loads(tmp_path, degree):
    g = _gaussians()
    g = Gaussians(means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities,
                  sh=torch.randn(1, 20, 16, 3, generator=torch.Generator().manual_seed(1)))
    save_ply(g, tmp_path / "scene.ply", max_degree=degree)
    assert load_ply(tmp_path / "scene.ply").sh.shape == (1, 20, (degree + 1) ** 2, 3)
