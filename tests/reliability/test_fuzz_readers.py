"""Fuzz every reader of camera files users hand us: mutate a valid file (truncate, flip/insert/delete bytes,
NaN/inf/huge/negative numbers, wrong JSON types, lens terms included); the outcome must be a parse whose cameras
are finite and rigid and stay so once the images are read and undistorted for the shards, or the project's one-line
``ValueError``/``FileNotFoundError`` -- never another exception or a hang.

``make test``: 50 examples per reader; ``-m slow``: 1000 per reader (counts in tests/reliability/README.md).
"""

import json
import struct

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from anycity.data.parsers import PARSERS
from anycity.data.parsers.base import GL_TO_CV, to_records
from anycity.data.parsers.guard import check_scene_cameras
from anycity.data.raycast import look_at
from anycity.geometry import camera_problem

W, H, N = 32, 24, 3
K = np.array([[30.0, 0, 16.0], [0, 31.0, 12.0], [0, 0, 1]])
GT = [look_at([10 * np.cos(a), 10 * np.sin(a), 8], [0, 0, 0]) for a in np.linspace(0, 1.5, N)]
CASES: dict[str, int] = {}


def _quat(R):  # wxyz of a rotation matrix (trace > 0 here)
    w = np.sqrt(max(1e-12, 1 + np.trace(R))) / 2
    return [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]


def _images(d, names):
    d.mkdir(parents=True, exist_ok=True)
    for n in names:
        cv2.imwrite(str(d / n), np.full((H, W, 3), 90, np.uint8))


def colmap_bin(root):
    src, d = root, root / "sparse" / "0"
    _images(src / "images", [f"v{i}.png" for i in range(N)])
    d.mkdir(parents=True)
    (d / "cameras.bin").write_bytes(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, W, H)
                                    + struct.pack("<4d", 30.0, 31.0, 16.0, 12.0))
    b = struct.pack("<Q", N)
    for i, g in enumerate(GT):
        b += struct.pack("<idddddddi", i + 1, *_quat(g[:3, :3]), *g[:3, 3], 1) + f"v{i}.png".encode() + b"\0"
        b += struct.pack("<Q", 1) + struct.pack("<ddq", 1.0, 2.0, 7)
    (d / "images.bin").write_bytes(b)
    (d / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    return src, d / "images.bin"


def colmap_txt(root):
    _images(root / "images", [f"v{i}.png" for i in range(N)])
    (root / "sparse").mkdir(parents=True)
    (root / "sparse" / "cameras.txt").write_text(f"# c\n1 PINHOLE {W} {H} 30 31 16 12\n")
    lines = []
    for i, g in enumerate(GT):
        lines += [" ".join(map(str, [i + 1, *_quat(g[:3, :3]), *g[:3, 3], 1, f"v{i}.png"])), "1.0 2.0 -1"]
    (root / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")
    return root, root / "sparse" / "images.txt"


def colmap_cameras_txt(root):
    src, _ = colmap_txt(root)
    return src, root / "sparse" / "cameras.txt"


def colmap_lens_txt(root):
    """An OPENCV camera: the fuzz reaches its lens terms (k1 k2 p1 p2), which the images are undistorted with."""
    src, _ = colmap_txt(root)
    (root / "sparse" / "cameras.txt").write_text(f"# c\n1 OPENCV {W} {H} 30 31 16 12 -0.25 0.05 0.002 -0.001\n")
    return src, root / "sparse" / "cameras.txt"


def colmap_cameras_bin(root):
    src, _ = colmap_bin(root)
    return src, root / "sparse" / "0" / "cameras.bin"


def _frames(prefix, scale=1.0):
    out = []
    for i, g in enumerate(GT):
        c2w = np.linalg.inv(g) @ GL_TO_CV
        c2w[:3, 3] *= scale
        out.append({"file_path": f"{prefix}{i}.png", "transform_matrix": c2w.tolist()})
    return out


def nerfstudio(root):
    _images(root / "images", [f"f{i}.png" for i in range(N)])
    (root / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                      "frames": _frames("images/f")}))
    return root, root / "transforms.json"


def nerfstudio_lens(root):
    _images(root / "images", [f"f{i}.png" for i in range(N)])
    (root / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                      "k1": -0.25, "k2": 0.05, "p1": 0.002, "p2": -0.001,
                                                      "frames": _frames("images/f")}))
    return root, root / "transforms.json"


def matrixcity(root):
    src = root / "pose" / "block_A"
    _images(root / "train" / "block_1", [f"{i}.png" for i in range(N)])
    src.mkdir(parents=True)
    (src / "transforms_train.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W,
                                                           "h": H, "frames": _frames("../../train/block_1/", 0.01)}))
    return src, src / "transforms_train.json"


def blendedmvs(root):
    src = root / "5a3ca9cb270f0e3f14d0eddb"
    _images(src / "blended_images", [f"{i:08d}.jpg" for i in range(N)])
    (src / "cams").mkdir()
    for i, g in enumerate(GT):
        rows = "\n".join(" ".join(map(str, r)) for r in g)
        krows = "\n".join(" ".join(map(str, r)) for r in K)
        (src / "cams" / f"{i:08d}_cam.txt").write_text(f"extrinsic\n{rows}\n\nintrinsic\n{krows}\n\n425 2.5\n")
    return src, src / "cams" / "00000001_cam.txt"


def _llff_rows(cols):
    rows = []
    for g in GT:
        c2w = np.linalg.inv(g)
        m = np.zeros((3, 5))
        for j, (i, s) in enumerate(cols):
            m[:, j] = s * c2w[:3, i]
        m[:, 3], m[:, 4] = c2w[:3, 3], [H, W, 30.0]
        rows.append(np.r_[m.reshape(-1), 1.0, 100.0])
    return np.array(rows)


def llff(root):
    _images(root / "images", [f"{i:03d}.png" for i in range(N)])
    np.save(root / "poses_bounds.npy", _llff_rows(((1, 1), (0, 1), (2, -1))))
    return root, root / "poses_bounds.npy"


def bungeenerf(root):
    _images(root / "images", [f"{i:03d}.png" for i in range(N)])
    rows = _llff_rows(((0, 1), (1, -1), (2, -1)))
    (root / "poses_enu.json").write_text(json.dumps({"poses": rows.tolist(), "scene_scale": 2.0}))
    return root, root / "poses_enu.json"


READERS = {"colmap_images_bin": ("colmap", colmap_bin), "colmap_cameras_bin": ("colmap", colmap_cameras_bin),
           "colmap_images_txt": ("colmap", colmap_txt), "colmap_cameras_txt": ("colmap", colmap_cameras_txt),
           "colmap_lens_txt": ("colmap", colmap_lens_txt), "transforms_json": ("nerfstudio", nerfstudio),
           "transforms_json_lens": ("nerfstudio", nerfstudio_lens), "matrixcity_json": ("matrixcity", matrixcity),
           "blendedmvs_cam": ("blendedmvs", blendedmvs), "llff_poses_bounds": ("llff", llff),
           "bungeenerf_json": ("bungeenerf", bungeenerf)}

SPECIAL = [b"nan", b"inf", b"-inf", b"1e308", b"-1", b"0", b"99999999999", b"\"x\"", b"null", b"[]", b"{}"]


@st.composite
def mutations(draw):
    ops = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "number", "json_type"]))
        ops.append((kind, draw(st.integers(0, 1 << 30)), draw(st.integers(0, 255)), draw(st.sampled_from(SPECIAL))))
    return ops


def mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for kind, pos, byte, special in ops:
        n = len(b)
        p = pos % max(1, n)
        if kind == "truncate":
            b = b[:p]
        elif kind == "flip" and n:
            b[p] ^= byte or 1
        elif kind == "insert":
            b[p:p] = bytes([byte]) * (1 + pos % 7)
        elif kind == "delete":
            del b[p:p + 1 + pos % 9]
        elif kind == "number":  # replace the k-th number token (text) or an 8-byte word (binary) by a special
            import re

            nums = list(re.finditer(rb"-?\d+(\.\d+)?(e-?\d+)?", bytes(b)))
            if nums:
                m = nums[pos % len(nums)]
                b[m.start():m.end()] = special.strip(b'"') if special[:1] != b'"' else special
            elif n >= 8:
                q = (p // 8) * 8
                b[q:q + 8] = struct.pack("<d", float(special) if special in (b"nan", b"inf", b"-inf", b"1e308")
                                         else 1e300)
        elif kind == "json_type":
            import re

            vals = list(re.finditer(rb"(?<=: )(-?[\d.e-]+|\[[^\[\]]*\]|\"[^\"]*\")", bytes(b)))
            if vals:
                m = vals[pos % len(vals)]
                b[m.start():m.end()] = special
    return bytes(b)


def _fuzz_one(reader, tmp_path_factory, ops):
    fmt, build = READERS[reader]
    root = tmp_path_factory.mktemp(reader)
    src, target = build(root)
    target.write_bytes(mutate(target.read_bytes(), ops))
    CASES[reader] = CASES.get(reader, 0) + 1
    try:
        scenes = PARSERS[fmt](src)
    except (ValueError, FileNotFoundError) as e:
        assert "\n" not in str(e), f"multi-line error: {e!r}"
        assert str(src) in str(e) or target.name in str(e) or str(target.parent) in str(e), \
            f"error does not name the file: {e!r}"
        return
    check_scene_cameras(scenes, src, fmt)  # a parse that succeeds returns only well-formed cameras
    _check_stored(scenes, root)


def _check_stored(scenes, root):
    """The cameras the shards would store (lens terms undone): sound, with a focal near the parsed one (NaN lens
    terms gave fx 4.6e-38 and black images), or a one-line error naming a file of the fixture."""
    for sc in scenes:
        try:
            records = [v for rec in to_records(sc) for v in rec.views]
        except (ValueError, FileNotFoundError) as e:
            assert "\n" not in str(e) and (str(root) in str(e) or f"scene {sc.name}:" in str(e)), \
                f"multi-line or unnamed error: {e!r}"
            continue
        for v, rec in zip(sc.views, records):
            assert camera_problem(rec.w2c, rec.K) is None, rec.K
            ratio = rec.K[0, 0] / v.K[0, 0] * (v.width / rec.width)
            assert 0.1 < ratio < 10, (v.K, rec.K)


def _make(n, deadline):
    @settings(max_examples=n, deadline=deadline, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(ops=mutations())
    def run(reader, tmp_path_factory, ops):
        _fuzz_one(reader, tmp_path_factory, ops)

    return run


_fast, _slow = _make(50, 10000), _make(1000, 10000)  # generous: the CI box is shared


# a hostile file gets one line, not numpy's overflow notes too; a mutated image list that leaves out photos is named
# in a warning (colmap._warn_unregistered), which is what it should do
@pytest.mark.filterwarnings("error::RuntimeWarning", "ignore:.*not in the COLMAP model")
@pytest.mark.parametrize("reader", sorted(READERS))
def test_fuzz_reader_fast(reader, tmp_path_factory):
    _fast(reader, tmp_path_factory)


@pytest.mark.slow
@pytest.mark.filterwarnings("error::RuntimeWarning", "ignore:.*not in the COLMAP model")
@pytest.mark.parametrize("reader", sorted(READERS))
def test_fuzz_reader_slow(reader, tmp_path_factory):
    _slow(reader, tmp_path_factory)
    print(f"\nfuzz {reader}: {CASES[reader]} cases")


def test_unmutated_fixtures_parse(tmp_path_factory):
    for reader in READERS:
        _fuzz_one(reader, tmp_path_factory, [])
        fmt, build = READERS[reader]
        src, _ = build(tmp_path_factory.mktemp(reader + "_ok"))
        assert len(PARSERS[fmt](src)[0].views) == N
