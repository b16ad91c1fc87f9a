"""Each converter on a tiny fixture written here: cameras come back as the OpenCV ground truth."""

import io
import json
import shutil
import struct

import cv2
import numpy as np
import pytest
import torch
import webdataset as wds

from anycity.data.parsers import convert
from anycity.data.parsers.base import GL_TO_CV
from anycity.data.raycast import look_at
from anycity.data.schema import read_meta
from anycity.geometry import rotmat_to_quat

W, H, N = 32, 24, 3
K = np.array([[30.0, 0, 16.0], [0, 31.0, 12.0], [0, 0, 1]])


def _gt():
    return [look_at([10 * np.cos(a), 10 * np.sin(a), 8], [0, 0, 0]) for a in np.linspace(0, 1.5, N)]


def _images(d, names, ext=".png"):
    d.mkdir(parents=True, exist_ok=True)
    for i, n in enumerate(names):
        cv2.imwrite(str(d / n), np.full((H, W, 3), 40 * i + 20, np.uint8))


def _read(out):
    metas = []
    for p in sorted(out.glob("*.tar")):
        metas += [read_meta(s) for s in wds.WebDataset(str(p), shardshuffle=False)]
    return metas


def _check(out, gt, scale=1.0):
    meta = _read(out)[0]
    assert len(meta["views"]) == len(gt)
    for v, g in zip(meta["views"], gt):
        w2c = np.array(v["w2c"])
        g = g.copy()
        g[:3, 3] *= scale
        assert np.allclose(w2c, g, atol=1e-6), (w2c, g)
        assert np.allclose(v["K"], K, atol=1e-6)
    return meta


def _write_colmap_bin(d, gt, model_id=1, params=(30.0, 31.0, 16.0, 12.0)):
    d.mkdir(parents=True)
    with open(d / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, model_id, W, H))
        f.write(struct.pack(f"<{len(params)}d", *params))
    with open(d / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", N))
        for i, g in enumerate(gt):
            q = rotmat_to_quat(torch.tensor(g[:3, :3])).tolist()
            f.write(struct.pack("<idddddddi", i + 1, *q, *g[:3, 3], 1) + f"v{i}.png".encode() + b"\x00")
            f.write(struct.pack("<Q", 1) + struct.pack("<ddq", 1.0, 2.0, 7))
    with open(d / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", 1) + struct.pack("<QdddBBBdQ", 7, 0, 0, 0, 1, 2, 3, 0.1, 1))
        f.write(struct.pack("<ii", 1, 0))


def test_colmap_binary_and_text(tmp_path):
    gt = _gt()
    src = tmp_path / "scene"
    _images(src / "images", [f"v{i}.png" for i in range(N)])
    _write_colmap_bin(src / "sparse" / "0", gt)
    meta = _check_convert("colmap", src, tmp_path / "out", gt)
    assert meta["units"] == "sfm" and np.allclose(meta["world_from_source"], np.eye(4))
    # text model
    txt = tmp_path / "scene_txt"
    _images(txt / "images", [f"v{i}.png" for i in range(N)])
    (txt / "sparse").mkdir(parents=True)
    (txt / "sparse" / "cameras.txt").write_text(f"# c\n1 PINHOLE {W} {H} 30 31 16 12\n")
    lines = []
    for i, g in enumerate(gt):
        q = rotmat_to_quat(torch.tensor(g[:3, :3])).tolist()
        lines += [" ".join(map(str, [i + 1, *q, *g[:3, 3], 1, f"v{i}.png"])), "1.0 2.0 -1"]
    (txt / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")
    _check_convert("colmap", txt, tmp_path / "out_txt", gt)
    # the last image has no 2-D points and the file ends right after its line (trailing blank line trimmed): it
    # was silently dropped
    (txt / "sparse" / "images.txt").write_text("\n".join(lines[:-1]) + "\n")
    _check_convert("colmap", txt, tmp_path / "out_txt_trimmed", gt)


def _check_convert(fmt, src, out, gt, scale=1.0):
    convert(fmt, src, out)
    return _check(out, gt, scale)


def test_a_camera_for_another_size_is_rescaled_and_one_for_another_aspect_is_refused(tmp_path):
    gt = _gt()
    src = tmp_path / "scene"
    (src / "images").mkdir(parents=True)
    for i in range(N):  # stored at twice the camera's resolution: K follows
        cv2.imwrite(str(src / "images" / f"v{i}.png"), np.zeros((2 * H, 2 * W, 3), np.uint8))
    _write_colmap_bin(src / "sparse" / "0", gt)
    convert("colmap", src, tmp_path / "out")
    assert np.allclose(_read(tmp_path / "out")[0]["views"][0]["K"], np.diag([2.0, 2.0, 1.0]) @ K)
    for i in range(N):  # saved again rotated (an EXIF orientation applied): stretching K would be wrong
        cv2.imwrite(str(src / "images" / f"v{i}.png"), np.zeros((W, H, 3), np.uint8))
    with pytest.raises(ValueError, match=rf"v0\.png: the image is {H}x{W} but its camera is for {W}x{H}, another "
                                         "aspect ratio"):
        convert("colmap", src, tmp_path / "out2")


def _blobs(K, dist, pts, h, w):
    """``[h, w, 3]`` uint8: a Gaussian blob (sigma 1.5 px) where each normalised point ``pts [P, 2]`` lands through
    the camera ``K`` (pixel centres at +0.5) with OpenCV distortion ``dist``."""
    K_cv = K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    uv = cv2.projectPoints(np.c_[pts, np.ones(len(pts))], np.zeros(3), np.zeros(3), K_cv, dist)[0][:, 0]
    ii, jj = np.mgrid[0:h, 0:w]
    img = sum(np.exp(-((jj - u) ** 2 + (ii - v) ** 2) / (2 * 1.5 ** 2)) for u, v in uv)
    return np.repeat(np.round(255 * img).astype(np.uint8)[..., None], 3, -1), uv + 0.5


def _centroids(img, near, r=4):
    """Intensity centroids (pixel centres at +0.5) of the blobs within ``r`` px of each ``near [P, 2]``."""
    g = img[..., 0].astype(float)
    out = []
    for u, v in near:
        i0, j0 = int(v), int(u)
        ii, jj = np.mgrid[i0 - r:i0 + r + 1, j0 - r:j0 + r + 1]
        win = g[i0 - r:i0 + r + 1, j0 - r:j0 + r + 1]
        out.append([(win * (jj + 0.5)).sum() / win.sum(), (win * (ii + 0.5)).sum() / win.sum()])
    return np.array(out)


@pytest.mark.parametrize("fmt,model", [("colmap", "OPENCV"), ("colmap", "FULL_OPENCV"), ("nerfstudio", "OPENCV"),
                                       ("colmap", "SIMPLE_RADIAL"), ("colmap", "RADIAL"), ("nerfstudio", "OPENCV+k3")])
def test_a_distorted_camera_is_stored_undistorted_with_its_pinhole_k(tmp_path, fmt, model):
    """Each point of the scene is where the stored pinhole K puts it: COLMAP's OPENCV and FULL_OPENCV (OpenCV's
    rational model: k1 k2 p1 p2 k3 k4 k5 k6, once refused as "a fisheye or thin-prism lens") models, SIMPLE_RADIAL
    (f cx cy k) and RADIAL (f cx cy k1 k2), and DL3DV's layout (a json for the full resolution with k1 k2 p1 p2,
    or also k3, the images in ``images_4``); a lens term read into the wrong slot moves the points."""
    gt, w, h = _gt(), 64, 48
    K_img = np.array([[40.0, 0, 32.0], [0, 41.0, 24.0], [0, 0, 1]])  # at the images' 64x48
    dist = np.array([-0.25, 0.05, 0.002, -0.001])  # k1 k2 p1 p2: a wide drone lens
    if model == "FULL_OPENCV":
        dist = np.r_[dist, 0.01, 0.15, -0.02, 0.01]  # k3, and the rational denominator's k4 k5 k6
    if model in ("SIMPLE_RADIAL", "RADIAL"):  # one focal; RADIAL's k2 differs from its k1
        K_img[1, 1] = 40.0
        dist = np.array([0.3, 0, 0, 0]) if model == "SIMPLE_RADIAL" else np.array([-0.25, 0.05, 0, 0])
    if model == "OPENCV+k3":  # OpenCV's order k1 k2 p1 p2 k3; tangential terms that move points past the tolerance
        dist = np.array([-0.35, 0.05, 0.01, -0.008, 0.1])
    pts = np.array([[0.0, 0.0], [0.35, 0.25], [-0.4, -0.3], [0.45, -0.2]])
    img, seen = _blobs(K_img, dist, pts, h, w)
    src = tmp_path / "scene"
    folder = src / "images" if fmt == "colmap" else src / "images_4"
    folder.mkdir(parents=True)
    for i in range(N):
        cv2.imwrite(str(folder / f"v{i}.png"), img)
    if fmt == "colmap":  # its camera is for 32x24: rescaled to the images first
        # COLMAP's documented parameter order (src/colmap/sensor/models.h)
        params = {"SIMPLE_RADIAL": (20.0, 16.0, 12.0, dist[0]), "RADIAL": (20.0, 16.0, 12.0, dist[0], dist[1])}.get(
            model, (20.0, 20.5, 16.0, 12.0, *dist))
        _write_colmap_bin(src / "sparse" / "0", gt, params=params,
                          model_id={"SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "FULL_OPENCV": 6}[model])
    else:
        frames = [{"file_path": f"images/v{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
                  for i, g in enumerate(gt)]
        terms = {"k1": dist[0], "k2": dist[1], "p1": dist[2], "p2": dist[3]}  # nerfstudio's keys, by name
        if len(dist) == 5:
            terms["k3"] = dist[4]
        (src / "transforms.json").write_text(json.dumps({
            "camera_model": "OPENCV", "fl_x": 160.0, "fl_y": 164.0, "cx": 128.0, "cy": 96.0, "w": 4 * w, "h": 4 * h,
            **{k: float(v) for k, v in terms.items()}, "frames": frames}))
    convert(fmt, src, tmp_path / "out")
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    meta = read_meta(sample)
    K_new = np.array(meta["views"][0]["K"])
    for v, g in zip(meta["views"], gt):
        np.testing.assert_allclose(np.array(v["w2c"]), g, atol=1e-6)  # undistortion leaves the pose alone
    stored = cv2.imdecode(np.frombuffer(sample["000.png"], np.uint8), cv2.IMREAD_COLOR)
    assert stored.shape[:2] == (h, w)
    want = (np.c_[pts, np.ones(len(pts))] @ K_new.T)[:, :2]
    assert np.abs(want - seen).max() > 2  # the distortion moves these points by more than the tolerance below
    np.testing.assert_allclose(_centroids(stored, want), want, atol=0.25)


def test_photos_colmap_did_not_register_are_named_not_dropped_silently(tmp_path):
    src = tmp_path / "scene"
    _images(src / "images", [f"v{i}.png" for i in range(N)] + ["stray.jpg", "blurred.png"])
    (src / "images" / "notes.txt").write_text("not a photo")
    _write_colmap_bin(src / "sparse" / "0", _gt())
    with pytest.warns(UserWarning, match=r"images: 2 image\(s\) are not in the COLMAP model \(not registered\) and "
                                         r"are left out: blurred\.png, stray\.jpg$"):
        convert("colmap", src, tmp_path / "out")
    assert len(_read(tmp_path / "out")[0]["views"]) == N


def test_colmap_distorted_and_missing(tmp_path):
    src = tmp_path / "scene"
    _images(src / "images", [f"v{i}.png" for i in range(N)])
    _write_colmap_bin(src / "sparse" / "0", _gt(), model_id=5, params=(30, 31, 16, 12, 0.1, 0, 0, 0))
    with pytest.raises(ValueError, match="OPENCV_FISHEYE .*; undistort first"):
        convert("colmap", src, tmp_path / "o")
    # a refused model is named for what it is (FOV was called "a fisheye or thin-prism lens")
    _write_colmap_bin(tmp_path / "fov" / "sparse" / "0", _gt(), model_id=7, params=(30, 31, 16, 12, 0.9))
    with pytest.raises(ValueError, match=r"camera model FOV \(the FOV \(arctan\) lens model\) is not read here; "
                                         "undistort first"):
        convert("colmap", tmp_path / "fov", tmp_path / "o_fov")
    with pytest.raises(FileNotFoundError, match="COLMAP"):
        convert("colmap", tmp_path / "scene" / "images", tmp_path / "o2")
    with pytest.raises(FileNotFoundError):
        convert("colmap", tmp_path / "nothing", tmp_path / "o3")
    # the model folder instead of the scene's converts that model, with the scene's images/ and name (it was
    # refused, and before that said "images/v0.png: not found")
    ok = tmp_path / "ok"
    _images(ok / "images", [f"v{i}.png" for i in range(N)])
    _write_colmap_bin(ok / "sparse" / "0", _gt())
    meta = _check_convert("colmap", ok / "sparse" / "0", tmp_path / "o4", _gt())
    assert meta["extra"]["scene"] == "ok"


def _colmap_models(scene, models):
    """COLMAP models of ``_gt()`` at ``scene``'s ``models`` (folders relative to it: binary; text for ``sparse``
    itself, holding the first two images only) and its ``images/``."""
    _images(scene / "images", [f"v{i}.png" for i in range(N)])
    for m in models:
        if m == "sparse":
            (scene / "sparse").mkdir(exist_ok=True)
            (scene / "sparse" / "cameras.txt").write_text(f"1 PINHOLE {W} {H} 30 31 16 12\n")
            (scene / "sparse" / "images.txt").write_text("".join(_image_blocks(_gt()[:2])))
        else:
            _write_colmap_bin(scene / m, _gt())


@pytest.mark.parametrize("models", [["sparse/0", "sparse/1"], ["sparse", "sparse/0", "sparse/1"]])
def test_a_colmap_scene_with_several_models_is_refused_naming_each(tmp_path, models):
    """The mapper writes sparse/0, sparse/1, ... for disconnected parts, and a merge script writes sparse/ beside
    them: only the first of sparse/0, sparse was read, the other model's images warned of as "not registered"."""
    _colmap_models(tmp_path / "scene", models)
    counts = {"sparse": 2, "sparse/0": N, "sparse/1": N}
    listed = ", ".join(f"{m} \\({counts[m]} images\\)" for m in models)
    with pytest.raises(ValueError, match=rf"^{tmp_path}/scene: {len(models)} COLMAP models, {listed}; pass --src "
                                         rf"{tmp_path}/scene/sparse/N \(one model\), or merge them \(colmap "
                                         r"model_merger\) into one$"):
        convert("colmap", tmp_path / "scene", tmp_path / "out")


def test_the_one_model_of_a_colmap_scene_is_read_whatever_its_number(tmp_path):
    _colmap_models(tmp_path / "scene", ["sparse/1"])
    _check_convert("colmap", tmp_path / "scene", tmp_path / "out", _gt())


def test_src_one_model_of_a_scene_converts_it_and_names_that_model_in_the_warning(tmp_path):
    scene = tmp_path / "scene"
    _colmap_models(scene, ["sparse", "sparse/0", "sparse/1"])
    _images(scene / "images", ["v0.png", "v1.png", "v2.png", "stray.png"])
    with pytest.warns(UserWarning, match=rf"images: 2 image\(s\) are not in the COLMAP model {scene}/sparse and are "
                                         r"left out: stray\.png, v2\.png$"):
        meta = _check_convert("colmap", scene / "sparse", tmp_path / "out", _gt()[:2])
    assert meta["extra"]["scene"] == "scene"
    with pytest.warns(UserWarning, match=rf"not in the COLMAP model {scene}/sparse/1 and are left out: stray\.png$"):
        meta = _check_convert("colmap", scene / "sparse" / "1", tmp_path / "out1", _gt())
    assert meta["extra"]["scene"] == "scene"


def test_a_folder_of_colmap_scenes_skips_those_without_a_model_with_one_warning(tmp_path):
    """A scene whose SfM failed (images/ only, or an empty sparse/) was passed over silently, or stopped the run."""
    for name in ("a", "b"):
        _colmap_scene(tmp_path / "src" / name, [f"v{i}.png" for i in range(N)])
    _images(tmp_path / "src" / "failed" / "images", ["v0.png"])
    _images(tmp_path / "src" / "empty" / "images", ["v0.png"])
    (tmp_path / "src" / "empty" / "sparse").mkdir()
    with pytest.warns(UserWarning, match=rf"^{tmp_path}/src: skipped 2 sub-folder\(s\), no COLMAP model in sparse/: "
                                         r"empty, failed$"):
        convert("colmap", tmp_path / "src", tmp_path / "out", split="train")
    assert sorted(m["extra"]["scene"] for m in _read(tmp_path / "out")) == ["a", "b"]
    for name in ("a", "b"):
        shutil.rmtree(tmp_path / "src" / name)
    with pytest.raises(FileNotFoundError, match=r"src: no COLMAP model"):
        convert("colmap", tmp_path / "src", tmp_path / "out2")


def test_a_camera_model_id_a_newer_colmap_added_is_named_as_such(tmp_path):
    """COLMAP 4.x's ids 12+ (SIMPLE_DIVISION, ..., EQUIRECTANGULAR) were called "the file is corrupt"."""
    _images(tmp_path / "scene" / "images", [f"v{i}.png" for i in range(N)])
    _write_colmap_bin(tmp_path / "scene" / "sparse" / "0", _gt(), model_id=12, params=(30.0, 16.0, 12.0, -1e-7))
    with pytest.raises(ValueError, match=r"cameras\.bin: camera model id 12 is not one this reader knows \(a newer "
                                         r"COLMAP's lens model, or a damaged file\); undistort first \(colmap "
                                         r"image_undistorter\) so the model is PINHOLE, or export the model as text to "
                                         r"see its name$"):
        convert("colmap", tmp_path / "scene", tmp_path / "out")


@pytest.mark.parametrize("kind", ["bin", "txt"])
def test_converting_reads_neither_the_2d_observations_nor_the_3d_points(tmp_path, kind):
    """They were parsed and held (a city model: minutes and GB) though converting never uses them: a damaged
    points3D file or POINTS2D line does not stop it, and read_model(points=False) leaves them empty."""
    from anycity.data.parsers.colmap import read_model

    scene = tmp_path / "scene"
    if kind == "bin":
        _images(scene / "images", [f"v{i}.png" for i in range(N)])
        _write_colmap_bin(scene / "sparse" / "0", _gt())  # one observation per image
        model = read_model(scene)  # the default still reads them
        assert list(model.points) == [7] and all(im["point3D_ids"].tolist() == [7] for im in model.images.values())
        (scene / "sparse" / "0" / "points3D.bin").write_bytes(b"garbage")
    else:
        _colmap_scene(scene, [f"v{i}.png" for i in range(N)])
        (scene / "sparse" / "images.txt").write_text("".join(_image_blocks(_gt(), points="1.0 2.0 x")))
        (scene / "sparse" / "points3D.txt").write_text("garbage\n")
    _check_convert("colmap", scene, tmp_path / "out", _gt())
    model = read_model(scene, points=False)
    assert len(model.images) == N and not model.points
    assert all(im["xys"].shape == (0, 2) and im["point3D_ids"].shape == (0,) for im in model.images.values())


def _dl3dv(scene, gt):
    """A DL3DV scene as shipped: ``scene/nerfstudio/{transforms.json, images/}``; returns its nerfstudio folder."""
    src = scene / "nerfstudio"
    _images(src / "images", [f"f{i}.png" for i in range(N)])
    frames = [{"file_path": f"images/f{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
              for i, g in enumerate(gt)]
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                     "frames": frames}))
    return src


def test_dl3dv_scenes_are_named_after_their_scene_folder_not_nerfstudio(tmp_path):
    """``--src HASH/nerfstudio`` named every DL3DV scene "nerfstudio": two scenes collided in one index."""
    from anycity.data.parsers.nerfstudio import parse

    gt = _gt()
    for h in ("0a1b2c", "9f8e7d"):
        assert parse(_dl3dv(tmp_path / h, gt))[0].name == h
        assert parse(_dl3dv(tmp_path / h, gt) / "transforms.json")[0].name == h
    (tmp_path / "0a1b2c" / "nerfstudio").rename(tmp_path / "0a1b2c" / "garden")
    assert parse(tmp_path / "0a1b2c" / "garden")[0].name == "garden"  # a folder of its own name keeps it


def test_a_360_equirectangular_nerfstudio_camera_is_refused_as_such(tmp_path):
    """It was called "(k4: a fisheye lens)", with the advice to undistort it, which no 360 image can be."""
    src = _dl3dv(tmp_path / "scene", _gt())
    meta = json.loads((src / "transforms.json").read_text())
    (src / "transforms.json").write_text(json.dumps({**meta, "camera_model": "EQUIRECTANGULAR"}))
    with pytest.raises(ValueError, match=r"frame 0: camera model EQUIRECTANGULAR \(360 equirectangular images\) is "
                                         r"not read here; these images cannot be converted, cut perspective crops "
                                         r"from them \(e\.g\. ns-process-data images --camera-type equirectangular\) "
                                         r"and convert those$"):
        convert("nerfstudio", src, tmp_path / "out")
    (src / "transforms.json").write_text(json.dumps({**meta, "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(ValueError, match=r"camera model OPENCV_FISHEYE \(a fisheye lens\) is not read here; "
                                         "undistort the images first"):
        convert("nerfstudio", src, tmp_path / "out")


def test_nerfstudio(tmp_path):
    gt = _gt()
    src = tmp_path / "ns"
    _images(src / "images", [f"f{i}.png" for i in range(N)])
    frames = [{"file_path": f"images/f{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
              for i, g in enumerate(gt)]
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                     "frames": frames, "applied_scale": 1.0}))
    meta = _check_convert("nerfstudio", src, tmp_path / "out", gt)
    assert meta["extra"]["applied_scale"] == 1.0
    # frames listed out of file-name order (ns-process-data writes COLMAP's image ids) come back in file-name order
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                     "frames": frames[::-1]}))
    _check_convert("nerfstudio", src, tmp_path / "out_reversed", gt)
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "w": W, "h": H, "k4": 0.1, "frames": frames}))
    with pytest.raises(ValueError, match="fisheye lens.*undistort the images first"):
        convert("nerfstudio", src, tmp_path / "o2")
    # depth PNGs are read while the shards are written: a damaged one is named in one line, and no shard set is left
    (src / "depth").mkdir()
    for i, fr in enumerate(frames):
        fr["depth_file_path"] = f"depth/f{i}.png"
        cv2.imwrite(str(src / fr["depth_file_path"]), np.full((H, W), 1000, np.uint16))
    (src / "depth" / "f1.png").write_bytes(b"not a png")
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                     "frames": frames}))
    with pytest.raises(ValueError, match=r"depth/f1\.png: not a one-channel depth png; re-export it"):
        convert("nerfstudio", src, tmp_path / "o3")
    assert not (tmp_path / "o3" / "index.json").exists()



def test_nerfstudio_without_cx_cy_puts_the_principal_point_at_the_image_centre(tmp_path):
    """transforms.json may leave out cx/cy: the principal point is then (w/2, h/2) of a w x h image; taking w/2 for
    cy on a non-square image shifts every ray of the scene vertically."""
    gt = _gt()
    src = tmp_path / "ns"
    _images(src / "images", [f"f{i}.png" for i in range(N)])
    frames = [{"file_path": f"images/f{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
              for i, g in enumerate(gt)]
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "w": W, "h": H, "frames": frames}))
    meta = _check_convert("nerfstudio", src, tmp_path / "out", gt)
    assert W != H
    for v in meta["views"]:
        np.testing.assert_allclose(np.array(v["K"])[:2, 2], [W / 2, H / 2])


def test_a_scene_over_max_views_is_cut_into_windows_that_keep_every_view(tmp_path):
    """70 views with max_views 64: windows of consecutive views that hold every view once, in order; dropping the
    last window would lose views from the shards without a word."""
    from anycity.data.parsers.base import ParsedScene, ParsedView, to_records

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((8, 8, 3), np.uint8))
    Kv = np.array([[8.0, 0, 4], [0, 8, 4], [0, 0, 1]])
    views = [ParsedView(f"v{i:02d}", tmp_path / "a.png", np.eye(4), Kv, 8, 8) for i in range(70)]
    recs = list(to_records(ParsedScene("s", views, "colmap", "sfm"), max_views=64))
    assert [v.name for r in recs for v in r.views] == [f"v{i:02d}" for i in range(70)]
    assert len(recs) > 1 and all(2 <= len(r.views) <= 64 for r in recs)
    assert [r.first_index for r in recs] == [sum(len(q.views) for q in recs[:k]) for k in range(len(recs))]
    assert all(r.scene_views == 70 for r in recs)
    assert len({r.key for r in recs}) == len(recs)


def _split_frames(gt, folder, last=1.0):
    """MatrixCity split-file frames of ``gt``: OpenGL c2w in 100 m units (``c2w[3][3] = last``, as released)."""
    frames = []
    for i, g in enumerate(gt):
        c2w = np.linalg.inv(g) @ GL_TO_CV
        c2w[:3, 3] /= 100.0  # MatrixCity split files store 100 m units
        c2w[3, 3] = last
        frames.append({"file_path": f"../../{folder}/{i:04d}.png", "transform_matrix": c2w.tolist()})
    return frames


def test_matrixcity_split_file_with_depth(tmp_path):
    gt = _gt()
    src = tmp_path / "pose" / "block_A"
    img_dir = tmp_path / "train" / "block_1"
    _images(img_dir, [f"{i:04d}.png" for i in range(N)])
    (img_dir / "depth").mkdir()
    for i in range(N):
        np.save(img_dir / "depth" / f"{i:04d}.npy", np.full((H, W), 1234.0, np.float32))  # centimetres
    frames = _split_frames(gt, "train/block_1")
    src.mkdir(parents=True)
    (src / "transforms_train.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                          "frames": frames}))
    convert("matrixcity", src, tmp_path / "out")
    meta = _check(tmp_path / "out", gt)
    assert meta["units"] == "metres" and np.allclose(np.diag(meta["world_from_source"]), [100, 100, 100, 1])
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    import io
    assert np.allclose(np.load(io.BytesIO(sample["000.depth.npy"])), 12.34)


@pytest.mark.parametrize("rotation_scale", [0.01, 1.0])
def test_matrixcity_raw_block_and_split_files_as_released(tmp_path, rotation_scale):
    """The released pose files carry the rotation's scale in c2w[3][3] too (MatrixCity's own loaders reset it to 1);
    the raw block json stores the rotation scaled by 0.01 in most blocks, unscaled in some."""
    gt = _gt()
    raw = tmp_path / "aerial" / "block_1"
    _images(raw, [f"{i:04d}.png" for i in range(N)])
    frames = []
    for i, g in enumerate(gt):
        c2w = np.linalg.inv(g) @ GL_TO_CV
        c2w[:3, :3] *= rotation_scale
        c2w[3, 3] = rotation_scale
        frames.append({"frame_index": i, "rot_mat": c2w.tolist()})
    (raw / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                    "frames": frames}))
    convert("matrixcity", raw, tmp_path / "out_raw")
    _check(tmp_path / "out_raw", gt)
    split = tmp_path / "pose" / "block_A"
    split.mkdir(parents=True)
    frames = _split_frames(gt, "aerial/block_1", last=0.01)
    (split / "transforms_train.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W,
                                                            "h": H, "frames": frames}))
    convert("matrixcity", split, tmp_path / "out_split")
    _check(tmp_path / "out_split", gt)


def test_a_raw_matrixcity_block_takes_its_image_size_from_its_images(tmp_path):
    """Raw block files give only ``camera_angle_x``: street renders (1000x1000) are not aerial ones (1920x1080)."""
    gt = _gt()
    raw = tmp_path / "street" / "small_city_road_down"
    _images(raw, [f"{i:04d}.png" for i in range(N)])
    frames = [{"frame_index": i, "rot_mat": (np.linalg.inv(g) @ GL_TO_CV).tolist()} for i, g in enumerate(gt)]
    (raw / "transforms.json").write_text(json.dumps({"camera_angle_x": 2 * np.arctan(0.5 * W / 30.0),
                                                    "frames": frames}))
    convert("matrixcity", raw, tmp_path / "out")
    assert np.allclose(_read(tmp_path / "out")[0]["views"][0]["K"], [[30, 0, W / 2], [0, 30, H / 2], [0, 0, 1]])


def test_matrixcity_depth_drops_its_sentinels_and_keeps_far_pixels():
    from anycity.data.parsers.matrixcity import depth_metres

    cm = np.array([[1234.0, 80000.0, 65504.0, 65535.0], [np.inf, np.nan, 0.0, -5.0]], np.float32)
    np.testing.assert_allclose(depth_metres(cm), [[12.34, 800.0, 0, 0], [0, 0, 0, 0]], rtol=1e-6)


def test_matrixcity_pose_files_name_their_split(tmp_path):
    gt = _gt()
    img_dir = tmp_path / "aerial" / "block_1"
    _images(img_dir, [f"{i:04d}.png" for i in range(N)])
    pose = tmp_path / "pose" / "block_A"
    pose.mkdir(parents=True)
    frames = _split_frames(gt, "aerial/block_1")
    for name in ("train", "train_dense", "test"):  # three files: an 8:1:1 split by scene would make one val
        (pose / f"transforms_{name}.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12,
                                                                  "w": W, "h": H, "frames": frames}))
    convert("matrixcity", pose, tmp_path / "out")
    shards = sorted(p.name.split("-")[0] for p in (tmp_path / "out").glob("*.tar"))
    counts = {sp: sum(1 for p in (tmp_path / "out").glob(f"{sp}-*.tar")
                      for _ in wds.WebDataset(str(p), shardshuffle=False)) for sp in set(shards)}
    assert counts == {"train": 2, "test": 1}


def test_blendedmvs_with_pfm(tmp_path):
    gt = _gt()
    src = tmp_path / "5a3ca9cb270f0e3f14d0eddb"
    _images(src / "blended_images", [f"{i:08d}.jpg" for i in range(N)])
    (src / "cams").mkdir()
    (src / "rendered_depth_maps").mkdir()
    for i, g in enumerate(gt):
        rows = "\n".join(" ".join(map(str, r)) for r in g)
        krows = "\n".join(" ".join(map(str, r)) for r in K)
        (src / "cams" / f"{i:08d}_cam.txt").write_text(f"extrinsic\n{rows}\n\nintrinsic\n{krows}\n\n425 2.5\n")
        d = np.arange(H * W, dtype=np.float32).reshape(H, W) + 1
        with open(src / "rendered_depth_maps" / f"{i:08d}.pfm", "wb") as f:
            f.write(f"Pf\n{W} {H}\n-1.0\n".encode() + np.flipud(d).astype("<f4").tobytes())
    (src / "cams" / "._00000000_cam.txt").write_bytes(b"\x00\x05\x16\x07Mac OS X")  # a Mac-copied drive's metadata
    convert("blendedmvs", src, tmp_path / "out")
    _check(tmp_path / "out", gt)
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    import io
    depth = np.load(io.BytesIO(sample["000.depth.npy"]))
    assert depth[0, 0] == 1 and depth[0, 1] == 2  # top row first after the PFM flip
    (src / "blended_images" / "00000001.jpg").write_bytes(b"not a jpeg")  # a damaged download: named in one line
    with pytest.raises(ValueError, match=r"00000001\.jpg: not a readable image .* remove 00000001_cam\.txt"):
        convert("blendedmvs", src, tmp_path / "out2")
    (src / "blended_images" / "00000001.jpg").unlink()  # a missing one: named as missing, not as unreadable
    with pytest.raises(FileNotFoundError, match=r"00000001\.jpg: not found; expected the image of 00000001_cam\.txt"):
        convert("blendedmvs", src, tmp_path / "out3")
    # a skewed camera (the 3x3 K is read whole) is refused at conversion, not at fit by the renderer; its message
    # carries its own fix, not "damaged, re-export"
    _images(src / "blended_images", ["00000001.jpg"])
    skewed = np.array(K, float)
    skewed[0, 1] = 2.0
    krows = "\n".join(" ".join(map(str, r)) for r in skewed)
    (src / "cams" / "00000000_cam.txt").write_text(f"extrinsic\n{rows}\n\nintrinsic\n{krows}\n\n425 2.5\n")
    with pytest.raises(ValueError, match=r"00000000.*skew 2 px .*zero skew$") as e:
        convert("blendedmvs", src, tmp_path / "out4")
    assert "damaged" not in str(e.value)


def test_blendedmvs_image_size_is_the_size_stored(tmp_path):
    """The size the cameras describe: the stored pixels, whatever a JPEG's EXIF orientation says (the converters
    decode them unrotated), so the intrinsics are not rescaled across the axes."""
    from PIL import Image

    from anycity.data.parsers.blendedmvs import _image_size

    exif = Image.Exif()
    exif[0x0112] = 6  # stored 64 wide and 32 high, shown rotated by 90 degrees
    Image.new("RGB", (64, 32)).save(tmp_path / "a.jpg", exif=exif)
    Image.new("RGB", (64, 32)).save(tmp_path / "b.jpg")
    assert _image_size(tmp_path / "a.jpg", tmp_path / "a_cam.txt") == (32, 64)
    assert _image_size(tmp_path / "b.jpg", tmp_path / "b_cam.txt") == (32, 64)


@pytest.mark.parametrize("orientation", [3, 6])
def test_exif_rotated_jpegs_keep_the_cameras_and_the_stored_pixels(tmp_path, orientation):
    """COLMAP (and every posed dataset) describes the stored pixels: a JPEG's EXIF orientation (a phone held upright,
    a gimbal's flag) must neither rescale K across the axes (90 degrees) nor rotate the image under its pose (180)."""
    from PIL import Image

    from anycity.data.schema import decode_image, member

    gt = _gt()
    src = tmp_path / "scene"
    (src / "images").mkdir(parents=True)
    exif = Image.Exif()
    exif[0x0112] = orientation
    stored = np.zeros((H, W, 3), np.uint8)
    stored[: H // 2, : W // 2] = 255  # bright top-left quadrant: any rotation moves it
    for i in range(N):
        Image.fromarray(stored).save(src / "images" / f"v{i}.jpg", exif=exif, quality=100)
    _write_colmap_bin(src / "sparse" / "0", gt)
    model = src / "sparse" / "0" / "images.bin"  # the model names v{i}.png; these photos are JPEGs
    model.write_bytes(model.read_bytes().replace(b".png", b".jpg"))
    _check_convert("colmap", src, tmp_path / "out", gt)  # K exactly the camera's, not rescaled
    sample = next(iter(wds.WebDataset(str(sorted((tmp_path / "out").glob("*.tar"))[0]), shardshuffle=False)))
    img = decode_image(member(sample, read_meta(sample)["views"][0]["image"]))
    assert img.shape == (H, W, 3)
    assert img[: H // 2, : W // 2].mean() > 200 and img[H // 2 :, W // 2 :].mean() < 50


def _llff_rows(gt, cols):
    rows = []
    for g in gt:
        c2w = np.linalg.inv(g)
        R = c2w[:3, :3]
        m = np.zeros((3, 5))
        for j, (i, s) in enumerate(cols):
            m[:, j] = s * R[:, i]
        m[:, 3] = c2w[:3, 3]
        m[:, 4] = [H, W, 30.0]
        rows.append(np.r_[m.reshape(-1), 1.0, 100.0])
    return np.array(rows)


def test_llff_and_bungeenerf(tmp_path):
    gt = _gt()
    Kf = np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]])
    for fmt, cols in (("llff", ((1, 1), (0, 1), (2, -1))), ("bungeenerf", ((0, 1), (1, -1), (2, -1)))):
        src = tmp_path / fmt
        _images(src / "images", [f"{i:03d}.png" for i in range(N)])
        (src / "images" / "._000.png").write_bytes(b"\x00\x05\x16\x07Mac OS X")  # not an image: passed over
        rows = _llff_rows(gt, cols)
        if fmt == "llff":
            np.save(src / "poses_bounds.npy", rows)
        else:
            (src / "poses_enu.json").write_text(json.dumps({"poses": rows.tolist(), "scene_scale": 2.0}))
        convert(fmt, src, tmp_path / f"out_{fmt}")
        meta = _read(tmp_path / f"out_{fmt}")[0]
        for v, g in zip(meta["views"], gt):
            assert np.allclose(v["w2c"], g, atol=1e-6) and np.allclose(v["K"], Kf)
    with pytest.raises(FileNotFoundError, match="poses_bounds.npy"):
        convert("llff", tmp_path / "bungeenerf", tmp_path / "o")


@pytest.mark.parametrize("fmt,cols,pose_file", [("llff", ((1, 1), (0, 1), (2, -1)), "poses_bounds.npy"),
                                               ("bungeenerf", ((0, 1), (1, -1), (2, -1)), "poses_enu.json")])
def test_llff_and_bungeenerf_take_the_pose_file_as_src(tmp_path, fmt, cols, pose_file):
    """``--src`` is "the source dataset folder (or pose file)": the pose file itself was looked for inside itself
    ("poses_bounds.npy/poses_bounds.npy: not found")."""
    src = tmp_path / "scene"
    _images(src / "images", [f"{i:03d}.png" for i in range(N)])
    rows = _llff_rows(_gt(), cols)
    if fmt == "llff":
        np.save(src / pose_file, rows)
    else:
        (src / pose_file).write_text(json.dumps({"poses": rows.tolist()}))
    convert(fmt, src / pose_file, tmp_path / "out")
    meta = _read(tmp_path / "out")[0]
    assert meta["extra"]["scene"] == "scene"
    np.testing.assert_allclose([v["w2c"] for v in meta["views"]], _gt(), atol=1e-6)
    with pytest.raises(ValueError, match=rf"000\.png: a file, not .*{pose_file}; pass --src the scene folder that "
                                         rf"holds {pose_file} and images/$"):
        convert(fmt, src / "images" / "000.png", tmp_path / "out2")


def test_blendedmvs_refuses_a_file_naming_the_scene_folder_to_pass(tmp_path):
    """A cam.txt as ``--src`` failed as "cannot parse ... NotADirectoryError; the file is truncated or damaged"."""
    src = tmp_path / "5a3ca9cb270f0e3f14d0eddb"
    _images(src / "blended_images", ["00000000.jpg"])
    (src / "cams").mkdir()
    (src / "cams" / "00000000_cam.txt").write_text("extrinsic\n")
    for f in (src / "cams" / "00000000_cam.txt", src / "blended_images" / "00000000.jpg"):
        with pytest.raises(ValueError, match=rf"^{f}: a file, not a BlendedMVS scene; pass --src the scene \(PID\) "
                                             rf"folder that holds cams/ and blended_images/: {src}$"):
            convert("blendedmvs", f, tmp_path / "out")


@pytest.mark.parametrize("depth_hw,max_side", [((24, 32), 12), ((18, 24), None)])
def test_converted_depth_is_resampled_under_the_pixel_centres_of_the_stored_image(tmp_path, depth_hw, max_side):
    """Depth given at another size, or downscaled with ``max_side``, takes the source pixel under each stored pixel's
    centre (cv2.INTER_NEAREST_EXACT), as K is rescaled; plain INTER_NEAREST takes pixel floor(x * scale)."""
    from anycity.data.parsers.base import ParsedView, _load_view

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((H, W, 3), np.uint8))
    dh, dw = depth_hw
    v, u = np.mgrid[0:dh, 0:dw]
    ramp = (100 * v + u + 1).astype(np.float32)  # encodes the depth pixel
    rec = _load_view(ParsedView("a", tmp_path / "a.png", np.eye(4), K, W, H, depth=lambda: ramp), max_side)
    oh, ow = rec.depth.shape
    assert (ow, oh) == (rec.width, rec.height) and (max_side is None or max(oh, ow) == max_side)
    # depth pixel coordinates under each stored pixel centre: stored K -> source K -> depth-map pixels
    us = ((np.arange(ow) + 0.5) - rec.K[0, 2]) / rec.K[0, 0] * K[0, 0] + K[0, 2]
    vs = ((np.arange(oh) + 0.5) - rec.K[1, 2]) / rec.K[1, 1] * K[1, 1] + K[1, 2]
    err_u = (rec.depth - 1) % 100 + 0.5 - us[None] * dw / W
    err_v = (rec.depth - 1) // 100 + 0.5 - vs[:, None] * dh / H
    assert np.abs(err_u).max() <= 0.5 + 1e-6 and np.abs(err_v).max() <= 0.5 + 1e-6


def _colmap_scene(src, names, ids=None):
    """A COLMAP text scene at ``src`` whose images ``names`` (N of them, ``_gt()`` poses) are written here; ``ids``:
    their COLMAP image ids (default 1..N), listed in images.txt in id order."""
    (src / "images").mkdir(parents=True)
    for i, n in enumerate(names):
        cv2.imwrite(str(src / "images" / n), np.full((H, W, 3), 40 * i + 20, np.uint8))
    (src / "sparse").mkdir()
    (src / "sparse" / "cameras.txt").write_text(f"1 PINHOLE {W} {H} 30 31 16 12\n")
    lines = []
    ids = ids or list(range(1, len(names) + 1))
    for i, g, n in sorted(zip(ids, _gt(), names)):
        q = rotmat_to_quat(torch.tensor(g[:3, :3])).tolist()
        lines += [" ".join(map(str, [i, *q, *g[:3, 3], 1, n])), ""]
    (src / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")


def test_a_truncated_jpeg_is_refused_in_one_line(tmp_path):
    """A half-copied JPEG: OpenCV 4.x decodes it with the missing rows grey, and it was stored so; OpenCV 5 refused
    it only as "not a readable image"."""
    src = tmp_path / "scene"
    _colmap_scene(src, [f"v{i}.jpg" for i in range(N)])
    yy, xx = np.mgrid[0 : 8 * H, 0 : 8 * W]  # big enough that OpenCV 4.8 decodes its first half and fills the rest
    cv2.imwrite(str(src / "images" / "v1.jpg"), np.dstack([xx, yy, (xx // 16 + yy // 16) % 2 * 255]).astype(np.uint8))
    raw = (src / "images" / "v1.jpg").read_bytes()
    (src / "images" / "v1.jpg").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ValueError, match=r"v1\.jpg: truncated JPEG \(no end-of-image marker\); re-copy or re-save "
                                         r"it, or remove it$"):
        convert("colmap", src, tmp_path / "out")
    assert not (tmp_path / "out" / "index.json").exists()


def test_scenes_whose_names_sanitise_alike_keep_their_own_keys(tmp_path):
    """'東京' and '大阪' both sanitised to 'colmap_', 'block 1' to 'block-1': one scene was lost."""
    names = ["東京", "大阪", "block 1", "block-1"]
    for name in names:
        _colmap_scene(tmp_path / "src" / name, [f"v{j}.png" for j in range(N)])
    convert("colmap", tmp_path / "src", tmp_path / "out", split="train")
    index = json.loads((tmp_path / "out" / "index.json").read_text())
    keys = [s["key"] for s in index["samples"]]
    assert len(set(keys)) == len(names) and len({s["key"] for s in index["scenes"]}) == len(names)
    assert "colmap_block-1" in keys  # a name sanitising leaves alone keeps its plain key
    metas = _read(tmp_path / "out")
    assert sorted(m["extra"]["scene"] for m in metas) == sorted(names)
    assert all(len(m["views"]) == N for m in metas)


def _raw_block(folder, n=N, pose_file="transforms.json"):
    """A raw MatrixCity block (``rot_mat`` scaled by 0.01, images NNNN.png) of the first ``n`` of ``_gt()``."""
    _images(folder, [f"{i:04d}.png" for i in range(n)])
    frames = []
    for i, g in enumerate((_gt() * 2)[:n]):
        c2w = np.linalg.inv(g) @ GL_TO_CV
        c2w[:3, :3] *= 0.01
        frames.append({"frame_index": i, "rot_mat": c2w.tolist()})
    (folder / pose_file).write_text(json.dumps({"camera_angle_x": 2 * np.arctan(0.5 * W / 30.0), "frames": frames}))


def test_a_raw_matrixcity_block_reads_its_curated_poses_not_the_pre_culling_ones(tmp_path):
    """As released, a block holds transforms.json beside transforms_origin.json (every pose collected, views off
    the map included); the glob ``transforms_*.json`` picked the latter."""
    block = tmp_path / "aerial" / "block_1"
    _raw_block(block, n=5, pose_file="transforms_origin.json")
    _raw_block(block, n=N)
    convert("matrixcity", block, tmp_path / "out")
    meta = _read(tmp_path / "out")[0]
    assert meta["extra"]["pose_file"] == "transforms.json" and len(meta["views"]) == N
    np.testing.assert_allclose([v["w2c"] for v in meta["views"]], _gt(), atol=1e-6)
    (block / "transforms.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"no MatrixCity transforms\.json .* \(transforms_origin\.json, the "
                                                r"poses before culling, is not read\)"):
        convert("matrixcity", block, tmp_path / "out2")


@pytest.mark.parametrize("folder,split", [("aerial/test/block_1_test", "test"), ("block_2_test", "test"),
                                          ("street/test/small_city_road_down", "test"),
                                          ("aerial/train/block_1", "train")])
def test_a_matrixcity_test_block_goes_to_the_test_split(tmp_path, folder, split):
    _raw_block(tmp_path / folder)
    convert("matrixcity", tmp_path / folder, tmp_path / "out")
    assert [p.name.split("-")[0] for p in (tmp_path / "out").glob("*.tar")] == [split]


def test_matrixcity_depth_is_found_in_the_released_tree_and_its_absence_named(tmp_path):
    """small_city/aerial/train/block_1 and its depth archive extracted where it lies,
    small_city_depth*/aerial/train/block_1_depth (the float32 release preferred); none found: one warning naming
    the folders searched (the depth was dropped without a word)."""
    block = tmp_path / "small_city" / "aerial" / "train" / "block_1"
    _raw_block(block)
    for tree, cm in (("small_city_depth", 1000.0), ("small_city_depth_float32", 1234.0)):
        (tmp_path / tree / "aerial" / "train" / "block_1_depth").mkdir(parents=True)
        for i in range(N):
            np.save(tmp_path / tree / "aerial" / "train" / "block_1_depth" / f"{i:04d}.npy",
                    np.full((H, W), cm, np.float32))
    convert("matrixcity", block, tmp_path / "out")
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    assert np.allclose(np.load(io.BytesIO(sample["002.depth.npy"])), 12.34)
    for tree in ("small_city_depth", "small_city_depth_float32"):
        shutil.rmtree(tmp_path / tree)
    with pytest.warns(UserWarning, match=rf"no depth for {N} of {N} views .*searched {block / 'depth'}, "
                                         rf"{block}_depth, .*small_city_depth\*/aerial/train/block_1_depth"):
        convert("matrixcity", block, tmp_path / "out2")


def _exr_block(tmp_path):
    block = tmp_path / "aerial" / "train" / "block_1"
    _raw_block(block)
    (block.parent / "block_1_depth").mkdir()
    return block, [block.parent / "block_1_depth" / f"{i:04d}.exr" for i in range(N)]


@pytest.mark.parametrize("reader", ["OpenEXR", "opencv"])
def test_matrixcity_exr_depth_is_read_with_or_without_opencv_s_exr_codec(tmp_path, monkeypatch, reader):
    """OpenCV wheels without the OpenEXR codec (5.0's) gave None, and the error told the user to set an
    environment variable that changes nothing there; the OpenEXR package reads it instead."""
    import OpenEXR

    block, exrs = _exr_block(tmp_path)
    cm = np.array([[1234.0, 65504.0, 80000.0, 250.5]], np.float32).repeat(H, 0).repeat(W // 4, 1)  # [H, W]
    for p in exrs:
        OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                     {"R": cm, "G": cm, "B": cm}).write(str(p))
    from anycity.data.parsers import matrixcity

    if reader == "opencv":
        monkeypatch.setenv("OPENCV_IO_ENABLE_OPENEXR", "1")  # before OpenCV 4.x first looks (it reads it once)
        if not matrixcity.opencv_reads_exr():
            pytest.skip("this OpenCV build has no OpenEXR codec")
    else:
        monkeypatch.setattr(matrixcity, "opencv_reads_exr", lambda: False)
    convert("matrixcity", block, tmp_path / "out")
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    want = np.array([[12.34, 0, 800.0, 2.505]], np.float32).repeat(H, 0).repeat(W // 4, 1)
    np.testing.assert_allclose(np.load(io.BytesIO(sample["001.depth.npy"])), want, rtol=1e-6)


def test_exr_depth_without_a_reader_is_refused_naming_what_to_install(tmp_path, monkeypatch):
    import sys

    block, exrs = _exr_block(tmp_path)
    for p in exrs:
        p.write_bytes(b"v/1\x01" + bytes(60))
    from anycity.data.parsers import matrixcity

    monkeypatch.setattr(matrixcity, "opencv_reads_exr", lambda: False)
    monkeypatch.setitem(sys.modules, "OpenEXR", None)  # not installed
    with pytest.raises(ValueError, match=r"0000\.exr: cannot read EXR depth: this OpenCV build has no OpenEXR codec "
                                         r"and the OpenEXR package is not installed; pip install 'anycity\[exr\]' "
                                         r"\(or OpenEXR\)$"):
        convert("matrixcity", block, tmp_path / "out")


@pytest.mark.parametrize("fmt", ["nerfstudio", "matrixcity"])
def test_depth_in_a_folder_whose_name_is_not_utf8_is_read(tmp_path, child, latin1_path, fmt):
    """A dataset in a folder with a latin-1 name (``caf\\xe9``, a surrogate-escaped str in Python): OpenCV 5's
    imread (nerfstudio's depth PNGs) and haveImageReader (MatrixCity's EXR depth) crashed the process (SIGSEGV)."""
    import os

    import OpenEXR

    made = tmp_path / "made"  # written under a plain name (cv2.imwrite would crash too), then renamed
    if fmt == "nerfstudio":
        _images(made / "images", [f"f{i}.png" for i in range(N)])
        (made / "depth").mkdir()
        frames = [{"file_path": f"images/f{i}.png", "depth_file_path": f"depth/f{i}.png",
                   "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()} for i, g in enumerate(_gt())]
        for fr in frames:
            cv2.imwrite(str(made / fr["depth_file_path"]), np.full((H, W), 2500, np.uint16))  # mm
        (made / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W,
                                                          "h": H, "frames": frames}))
        sub = ""
    else:
        _, exrs = _exr_block(made)
        cm = np.full((H, W), 250.0, np.float32)
        for p in exrs:
            OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                         {"R": cm, "G": cm, "B": cm}).write(str(p))
        sub = "/aerial/train/block_1"
    src = latin1_path(tmp_path, b"caf\xe9")
    os.rmdir(src)
    os.rename(made, src)
    child("import sys; from anycity.data.parsers import convert; convert(sys.argv[1], sys.argv[2], sys.argv[3])",
          fmt, src + sub, str(tmp_path / "out"))
    sample = next(iter(wds.WebDataset(str(next((tmp_path / "out").glob("*.tar"))), shardshuffle=False)))
    np.testing.assert_allclose(np.load(io.BytesIO(sample["001.depth.npy"])), 2.5)


@pytest.mark.parametrize("max_side", [-5, 0, 7])
def test_max_side_below_8_is_refused_in_one_line(tmp_path, max_side):
    """-5 crashed in OpenCV's resize, 0 meant no resize without a word."""
    _colmap_scene(tmp_path / "scene", [f"v{i}.png" for i in range(N)])
    with pytest.raises(ValueError, match=rf"^max_side: expected the longer stored side in pixels, >= 8, got "
                                         rf"{max_side}; leave it out to keep the images' size$"):
        convert("colmap", tmp_path / "scene", tmp_path / "out", max_side=max_side)


@pytest.mark.parametrize("ext,dist,max_side", [(".png", (-0.2, 0.05, 0.0, 0.0), None),
                                               (".jpg", (-0.2, 0.05, 0.001, 0.0), None),
                                               (".jpg", None, 20), (".bmp", None, None)])
def test_a_view_comes_back_encoded_as_the_shard_stores_it(tmp_path, ext, dist, max_side):
    """Undistorted (or resized, or re-coded) views were held as decoded arrays for a whole sample (48 MB per 12 MP
    view); they come back as the bytes the shard stores, the same bytes as encoding the array there gave."""
    from anycity.data.parsers.base import ParsedView, _load_view, undistort
    from anycity.data.schema import encode_image

    rng = np.random.default_rng(0)
    cv2.imwrite(str(tmp_path / f"a{ext}"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    view = ParsedView("a", tmp_path / f"a{ext}", np.eye(4), K, W, H, dist=None if dist is None else np.array(dist))
    rec = _load_view(view, max_side)
    assert isinstance(rec.image, bytes)
    img = cv2.imread(str(tmp_path / f"a{ext}"))
    if dist is not None:
        img = undistort(img, None, K, np.array(dist))[0]
    if max_side:
        img = cv2.resize(img, (rec.width, rec.height), interpolation=cv2.INTER_AREA)
    assert rec.image == encode_image(img[..., ::-1], rec.ext)


@pytest.mark.parametrize("ext", [".jfif", ".jpe", ".JPG"])
def test_every_jpeg_suffix_a_photo_folder_reads_is_stored_as_its_own_jpeg_bytes(tmp_path, ext):
    """A .jfif or .jpe photo (Windows' names for saved JPEGs) is a JPEG: the shard keeps its bytes, not a PNG copy."""
    from anycity.data.parsers.base import ParsedView, _load_view

    rng = np.random.default_rng(0)
    ok, buf = cv2.imencode(".jpg", rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
    (tmp_path / f"a{ext}").write_bytes(buf.tobytes())
    rec = _load_view(ParsedView("a", tmp_path / f"a{ext}", np.eye(4), K, W, H), None)
    assert rec.ext == "jpg" and rec.image == buf.tobytes()


def test_an_image_name_that_names_the_images_folder_is_one_line(tmp_path):
    """A damaged images.bin whose image name came out empty put ``images/`` itself as the image: a raw
    IsADirectoryError (found by the slow fuzz of images.bin)."""
    from anycity.data.parsers.base import ParsedView, _load_view

    (tmp_path / "images").mkdir()
    view = ParsedView("", tmp_path / "images" / "", np.eye(4), K, W, H)
    with pytest.raises(ValueError, match=r"images: a folder, not the image of view ''; the camera file's image name "
                                         r"is damaged"):
        _load_view(view, None)


def _image_blocks(gt, points="1.0 2.0 -1"):
    """``images.txt`` blocks: per image its line and its POINTS2D line ``points``, each ending in a newline."""
    blocks = []
    for i, g in enumerate(gt):
        q = rotmat_to_quat(torch.tensor(g[:3, :3])).tolist()
        blocks.append(" ".join(map(str, [i + 1, *q, *g[:3, 3], 1, f"v{i}.png"])) + "\n" + points + "\n")
    return blocks


@pytest.mark.parametrize("case", ["blank_between", "blank_between_no_points", "indented_comment", "comment_between",
                                  "no_points", "points", "no_points_trimmed"])
def test_colmap_images_txt_is_read_as_colmap_reads_it(tmp_path, case):
    """Blank and comment lines are skipped before an image line only; the line after it is its POINTS2D, maybe
    empty (COLMAP's ReadImagesText). Pairing lines two by two lost every other image when a blank line separated
    the blocks, with a warning that they were not registered; an indented comment was an error."""
    gt = [look_at([10 * np.cos(a), 10 * np.sin(a), 8], [0, 0, 0]) for a in np.linspace(0, 1.5, 6)]
    blocks, empty = _image_blocks(gt), _image_blocks(gt, points="")
    text = {"blank_between": "\n".join(blocks), "blank_between_no_points": "\n".join(empty),
            "indented_comment": "  # Image list\n\t#   IMAGE_ID, QW, ...\n" + "".join(blocks),
            "comment_between": "".join(blocks[:3]) + "# more images\n\n" + "".join(blocks[3:]),
            "no_points": "".join(empty),  # anycity export's and the common known-pose layout
            "points": "".join(blocks), "no_points_trimmed": "".join(empty).rstrip("\n") + "\n"}[case]
    src = tmp_path / "scene"
    _images(src / "images", [f"v{i}.png" for i in range(len(gt))])
    (src / "sparse").mkdir()
    comment = "  # Camera list" if case == "indented_comment" else "# Camera list"
    (src / "sparse" / "cameras.txt").write_text(f"{comment}\n1 PINHOLE {W} {H} 30 31 16 12\n")
    (src / "sparse" / "images.txt").write_text(text)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no image named as not registered
        convert("colmap", src, tmp_path / "out")
    _check(tmp_path / "out", gt)


@pytest.mark.parametrize("model,params", [("OPENCV", "30 31 16 12 0.1"), ("OPENCV", "30 31 16 12 0.1 0.01 0.001"),
                                          ("FULL_OPENCV", "30 31 16 12 0.1 0.01 0 0 0.001"),
                                          ("PINHOLE", "30 31 16 12 0.5"), ("SIMPLE_RADIAL", "30 16 12")])
def test_a_cameras_txt_line_whose_parameter_count_does_not_fit_its_model_is_refused(tmp_path, model, params):
    """A short OPENCV line crashed the conversion with OpenCV's assertion; a short FULL_OPENCV one was read."""
    _colmap_scene(tmp_path / "scene", [f"v{i}.png" for i in range(N)])
    (tmp_path / "scene" / "sparse" / "cameras.txt").write_text(f"# c\n1 {model} {W} {H} {params}\n")
    want = {"OPENCV": 8, "FULL_OPENCV": 12, "PINHOLE": 4, "SIMPLE_RADIAL": 4}[model]
    with pytest.raises(ValueError, match=rf"^{tmp_path}/scene/sparse/cameras\.txt: camera 1 \({model}\) has "
                                         rf"{len(params.split())} parameters, {model} takes {want}; fix the line"):
        convert("colmap", tmp_path / "scene", tmp_path / "out")


def test_cameras_bin_reads_as_many_parameters_as_its_model_takes(tmp_path):
    """The binary model has no count of its own: an OPENCV camera with 5 parameters written is a truncated file."""
    src = tmp_path / "scene"
    _images(src / "images", [f"v{i}.png" for i in range(N)])
    _write_colmap_bin(src / "sparse" / "0", _gt(), model_id=4, params=(30.0, 31.0, 16.0, 12.0, 0.1))
    (src / "sparse" / "0" / "images.bin").unlink()  # cameras.bin alone: its 5 doubles read as 8
    (src / "sparse" / "0" / "images.bin").write_bytes(struct.pack("<Q", 0))
    with pytest.raises(ValueError, match=r"scene: cannot parse as colmap: error: unpack requires a buffer of 64 "
                                         r"bytes; the file is truncated or damaged"):
        convert("colmap", src, tmp_path / "out")


@pytest.mark.parametrize("fmt,lens,match", [
    ("colmap", "OPENCV 30 31 16 12 nan 0 0 0", r"view 'v0\.png' of scene 'scene': lens distortion terms \[nan, 0\.0, "
                                               r"0\.0, 0\.0\] are not finite; the camera file is damaged"),
    ("colmap", "SIMPLE_RADIAL 30 16 12 inf", r"view 'v0\.png' .*lens distortion terms \[inf, 0\.0, 0\.0, 0\.0\] are "
                                             "not finite"),
    ("colmap", "OPENCV 30 31 16 12 1e30 0 0 0", r"images/v0\.png \(view v0\.png\): lens terms \[1e\+30, 0\.0, 0\.0, "
                                                r"0\.0\] are not a lens: undistorting them takes the focal from 30, 31 "
                                                r"px to 1\.214e\+31, 1\.254e\+31 px, over 10x; check the camera"),
    ("colmap", "OPENCV 30 31 16 12 -1e30 0 0 0", r"images/v0\.png \(view v0\.png\): lens terms .* are not a lens: "
                                                 r"undistorting them takes 100% of the pixels from outside the image"),
    ("nerfstudio", {"k1": float("nan")}, r"view 'v0\.png' of scene 'scene': lens distortion terms \[nan, 0\.0, 0\.0, "
                                         r"0\.0, 0\.0\] are not finite"),
    ("nerfstudio", {"k1": 1e30}, r"images/v0\.png \(view v0\.png\): lens terms .* are not a lens: undistorting them "
                                 "takes the focal from"),
])
def test_lens_terms_no_lens_has_are_refused_naming_the_view(tmp_path, fmt, lens, match):
    """NaN/inf or absurd distortion was converted without a word: every image black and fx 4.6e-38 (NaN), or fx
    1.2e31 (k1 = 1e30); k1 = -1e30 kept K and filled every image with its border."""
    src = tmp_path / "scene"
    if fmt == "colmap":
        _colmap_scene(src, [f"v{i}.png" for i in range(N)])
        (src / "sparse" / "cameras.txt").write_text(f"1 {lens.split()[0]} {W} {H} {lens.split(' ', 1)[1]}\n")
    else:
        _images(src / "images", [f"v{i}.png" for i in range(N)])
        frames = [{"file_path": f"images/v{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
                  for i, g in enumerate(_gt())]
        (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                         **lens, "frames": frames}))
    with pytest.raises(ValueError, match=match) as e:
        convert(fmt, src, tmp_path / "out")
    assert "\n" not in str(e.value) and str(src) in str(e.value)
    assert not (tmp_path / "out" / "index.json").exists()


def test_undistort_keeps_a_real_lens_and_names_where_it_refuses(tmp_path):
    """A strong but real lens (a wide drone lens; OpenCV's rational model) still converts; an absurd one is named."""
    from anycity.data.parsers.base import undistort

    img = np.full((H, W, 3), 90, np.uint8)
    for dist in ((-0.25, 0.05, 0.002, -0.001), (-0.25, 0.05, 0.002, -0.001, 0.01, 0.15, -0.02, 0.01), (2.0, 0, 0, 0)):
        out, _, K_new = undistort(img, None, K, np.array(dist))
        assert (out == 90).all() and 0.5 < K_new[0, 0] / K[0, 0] < 2
    with pytest.raises(ValueError, match=r"^a\.png: lens terms \[0\.0, 0\.0, 0\.5, 0\.0\] are not a lens: undistorting "
                                         r"them takes .*; check the camera file's distortion parameters"):
        undistort(img, None, K, np.array([0.0, 0.0, 0.5, 0.0]), "a.png")
    # non-finite terms get their own reason (OpenCV gave fx 4.6e-38 for NaN, a black image), not the focal's
    for dist in ((float("nan"), 0, 0, 0), (0.0, float("inf"), 0, 0)):
        with pytest.raises(ValueError, match=r"^a\.png: lens terms \[.*\] are not a lens \(not finite\); check the "
                                             r"camera file's distortion parameters, or re-export it$"):
            undistort(img, None, K, np.array(dist), "a.png")


def test_colmap_views_come_in_image_name_order_not_image_id_order(tmp_path):
    _colmap_scene(tmp_path / "scene", [f"v{i}.png" for i in range(N)], ids=[3, 1, 2])  # listed v1, v2, v0
    convert("colmap", tmp_path / "scene", tmp_path / "out")
    meta = _check(tmp_path / "out", _gt())  # each name keeps its own w2c
    assert [v["name"] for v in meta["views"]] == [f"v{i}.png" for i in range(N)]


def test_llff_with_an_image_more_than_poses_is_refused(tmp_path):
    src = tmp_path / "llff"
    _images(src / "images", [f"{i:03d}.png" for i in range(N + 1)])
    np.save(src / "poses_bounds.npy", _llff_rows(_gt(), ((1, 1), (0, 1), (2, -1))))
    with pytest.raises(ValueError, match=rf"{N} poses but {N + 1} images .*they must match 1:1"):
        convert("llff", src, tmp_path / "out")


def test_llff_bounds_keep_near_and_far(tmp_path):
    from anycity.data.parsers.llff import parse_llff

    _images(tmp_path / "images", [f"{i:03d}.png" for i in range(N)])
    np.save(tmp_path / "poses_bounds.npy", _llff_rows(_gt(), ((1, 1), (0, 1), (2, -1))))  # near 1, far 100
    assert parse_llff(tmp_path)[0].extra["bounds"] == [[1.0, 100.0]] * N


def test_write_scenes_splits_by_its_seed(tmp_path):
    from anycity.data.parsers.base import ParsedScene, ParsedView, write_scenes
    from anycity.data.writer import split_scenes

    assert split_scenes(10, 1) != split_scenes(10, 0)  # else the seed could not show
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((H, W, 3), np.uint8))
    scenes = [ParsedScene(name=f"s{i}", views=[ParsedView("a.png", tmp_path / "a.png", np.eye(4), K, W, H)],
                          source="colmap", units="sfm") for i in range(10)]
    index = write_scenes(scenes, tmp_path / "out", seed=1)
    assert [s["split"] for s in sorted(index["scenes"], key=lambda s: int(s["key"].removeprefix("colmap_s")))] \
        == split_scenes(10, 1)


def test_nerfstudio_without_images_reads_the_largest_downscaled_copy(tmp_path):
    gt = _gt()
    src = tmp_path / "ns"
    for n in (2, 8):  # images_2 at 16x12, images_8 at 4x3
        (src / f"images_{n}").mkdir(parents=True)
        for i in range(N):
            cv2.imwrite(str(src / f"images_{n}" / f"f{i}.png"), np.zeros((H // n, W // n, 3), np.uint8))
    frames = [{"file_path": f"images/f{i}.png", "transform_matrix": (np.linalg.inv(g) @ GL_TO_CV).tolist()}
              for i, g in enumerate(gt)]
    (src / "transforms.json").write_text(json.dumps({"fl_x": 30, "fl_y": 31, "cx": 16, "cy": 12, "w": W, "h": H,
                                                     "frames": frames}))
    convert("nerfstudio", src, tmp_path / "out")
    for v in _read(tmp_path / "out")[0]["views"]:
        assert (v["width"], v["height"]) == (W // 2, H // 2)
        np.testing.assert_allclose(v["K"], np.diag([0.5, 0.5, 1.0]) @ K)


def _pfm(path, d, header, dtype):
    """A one-channel PFM of ``d [H, W]`` (bottom row first) after ``header`` bytes, its floats as ``dtype``."""
    path.write_bytes(header + np.flipud(d).astype(dtype).tobytes())


def test_a_big_endian_pfm_and_one_with_a_blank_header_line_read(tmp_path):
    from anycity.data.parsers.blendedmvs import read_pfm

    d = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.float32)
    _pfm(tmp_path / "be.pfm", d, b"Pf\n3 2\n1.0\n", ">f4")  # a positive scale: big-endian
    np.testing.assert_array_equal(read_pfm(tmp_path / "be.pfm"), d)
    _pfm(tmp_path / "blank.pfm", d, b"Pf\n\n3 2\n-1.0\n", "<f4")
    np.testing.assert_array_equal(read_pfm(tmp_path / "blank.pfm"), d)


def test_negative_depth_is_masked_out_and_stored_as_zero(tmp_path):
    from anycity.data.parsers.base import ParsedView, _load_view

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((H, W, 3), np.uint8))
    depth = np.full((H, W), 5.0, np.float32)
    depth[0, :4] = -1.0  # the invalid marker
    rec = _load_view(ParsedView("a", tmp_path / "a.png", np.eye(4), K, W, H, depth=lambda: depth), None)
    assert not rec.mask[0, :4].any() and rec.mask[1:].all() and rec.mask[0, 4:].all()
    assert (rec.depth[0, :4] == 0).all() and (rec.depth[rec.mask] == 5.0).all()


def test_max_side_scales_the_rows_of_k_by_the_height_ratio(tmp_path):
    from anycity.data.parsers.base import ParsedView, _load_view

    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((24, 33, 3), np.uint8))
    Ka = np.array([[30.0, 0, 16.5], [0, 30.0, 12.0], [0, 0, 1]])
    rec = _load_view(ParsedView("a", tmp_path / "a.png", np.eye(4), Ka, 33, 24), 16)
    assert (rec.width, rec.height) == (16, 12)  # 16/33 across, 12/24 down
    np.testing.assert_allclose(rec.K[1], [0, 15.0, 6.0])
    np.testing.assert_allclose(rec.K[0], [30.0 * 16 / 33, 0, 8.0])


def test_three_scenes_of_one_name_get_three_keys():
    from anycity.data.parsers.base import ParsedScene, scene_keys

    scenes = [ParsedScene(name="a", views=[], source="colmap", units="sfm") for _ in range(3)]
    assert scene_keys(scenes) == ["colmap_a", "colmap_a-2", "colmap_a-3"]


def test_a_matrixcity_name_saying_train_and_test_is_test():
    from anycity.data.parsers.matrixcity import _split_of

    assert _split_of("block_train_test") == "test"
