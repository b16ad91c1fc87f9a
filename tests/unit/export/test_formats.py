"""Round trips of every export format, each read back by a parser that is not the writer."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import torch

from anycity.data.parsers import colmap as colmap_parser
from anycity.data.parsers import nerfstudio as ns_parser
from anycity.export import save_cameras, save_ply
from anycity.export.cli import export, export_main
from anycity.geometry import quat_to_rotmat
from anycity.structures import Gaussians

SH_C0 = 0.28209479177387814


def _scene(n: int = 50, v: int = 3, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians(means=torch.randn(1, n, 3, generator=gen), quats=torch.randn(1, n, 4, generator=gen),
                  scales=torch.rand(1, n, 3, generator=gen) * 0.1 + 0.01,
                  opacities=torch.rand(1, n, generator=gen) * 0.9 + 0.05,
                  sh=torch.randn(1, n, 4, 3, generator=gen) * 0.5)
    q = torch.nn.functional.normalize(torch.randn(v, 4, generator=gen), dim=-1)
    w2c = torch.eye(4).repeat(v, 1, 1).double()
    w2c[:, :3, :3] = quat_to_rotmat(q).double()
    w2c[:, :3, 3] = torch.randn(v, 3, generator=gen).double()
    K = torch.tensor([[40.0, 0, 24.5], [0, 41.0, 16.0], [0, 0, 1]]).repeat(v, 1, 1).double()
    return g, w2c, K


def _predict_dir(tmp_path, scale=None):
    g, w2c, K = _scene()
    d = tmp_path / "pred" / "sceneA"
    save_ply(g, d / "scene.ply")
    save_cameras(d / "cameras.json", w2c, K, 48, 32, scale=scale)
    return d, g, w2c, K


def _read_splat(path):
    """Independent reader: struct per record, as a web viewer does."""
    raw = path.read_bytes()
    assert len(raw) % 32 == 0
    out = []
    for i in range(len(raw) // 32):
        r = raw[32 * i: 32 * (i + 1)]
        pos, scale = struct.unpack("<3f", r[:12]), struct.unpack("<3f", r[12:24])
        rgba, rot = tuple(r[24:28]), tuple(r[28:32])
        out.append((pos, scale, rgba, [(b - 128) / 128 for b in rot]))
    return out


def test_splat_round_trip(tmp_path):
    d, g, _, _ = _predict_dir(tmp_path)
    target = export(d, "splat", tmp_path / "out")
    recs = _read_splat(target)
    assert len(recs) == g.num_gaussians
    means = g.means[0].numpy()
    for pos, scale, rgba, rot in recs:
        i = int(np.argmin(np.abs(means - np.array(pos)).sum(-1)))
        np.testing.assert_allclose(pos, means[i], atol=1e-6)
        np.testing.assert_allclose(scale, g.scales[0, i].numpy(), rtol=1e-5)
        assert abs(rgba[3] - g.opacities[0, i].item() * 255) <= 1.0
        rgb = np.clip(0.5 + SH_C0 * g.sh[0, i, 0].numpy(), 0, 1) * 255
        np.testing.assert_allclose(rgba[:3], rgb, atol=1.0)
        q = torch.nn.functional.normalize(g.quats[0, i], dim=0).numpy()
        assert min(np.abs(np.array(rot) - q).max(), np.abs(np.array(rot) + q).max()) <= 1.5 / 128
    # sorted by descending size x opacity, as antimatter15 does
    keys = [np.prod(s) * r[3] for _, s, r, _ in recs]
    assert all(a >= b - 1e-3 * max(keys) for a, b in zip(keys, keys[1:], strict=False))


def test_colmap_round_trip(tmp_path):
    d, g, w2c, K = _predict_dir(tmp_path)
    with pytest.warns(UserWarning, match="no inputs/ images for all 3 cameras"):  # predict saved no inputs here
        out = export(d, "colmap", tmp_path / "out")
    model = colmap_parser.read_model(tmp_path / "out")
    assert out == tmp_path / "out" / "sparse" / "0"
    assert len(model.images) == 3 and len(model.points) == g.num_gaussians
    for img in model.images.values():
        v = int(img["name"].split(".")[0])
        np.testing.assert_allclose(colmap_parser.w2c_of(img), w2c[v].numpy(), atol=1e-6)
        cam = model.cameras[img["camera_id"]]
        assert cam[1:3] == (48, 32)
        np.testing.assert_allclose(colmap_parser.intrinsics(cam[0], cam[3], "t")[0], K[v].numpy(), atol=1e-12)
    pts = np.stack([model.points[i + 1] for i in range(g.num_gaussians)])
    np.testing.assert_allclose(pts, g.means[0].numpy(), atol=1e-6)
    rgb = (tmp_path / "out" / "sparse" / "0" / "points3D.txt").read_text().splitlines()[1].split()[4:7]
    want = np.round(np.clip(0.5 + SH_C0 * g.sh[0, 0, 0].numpy(), 0, 1) * 255)
    np.testing.assert_allclose([int(x) for x in rgb], want, atol=1)


def test_nerfstudio_round_trip(tmp_path):
    d, g, w2c, K = _predict_dir(tmp_path, scale=2.5)
    with pytest.warns(UserWarning, match="names images/000.png etc. without writing them"):
        path = export(d, "nerfstudio", tmp_path / "out")
    scene = ns_parser.parse(path)[0]
    assert len(scene.views) == 3
    for v, view in enumerate(scene.views):
        np.testing.assert_allclose(view.w2c, w2c[v].numpy(), atol=1e-9)
        np.testing.assert_allclose(view.K, K[v].numpy(), atol=1e-12)
        assert (view.width, view.height) == (48, 32)
    meta = json.loads(path.read_text())
    assert (tmp_path / "out" / "scene.ply").is_file()
    # the seed nerfstudio reads (open3d: points and colours); graphdeco's fetchPly also requires nx ny nz (its
    # storePly writes zeros), and refused the file without them
    from plyfile import PlyData

    seed = PlyData.read(str(tmp_path / "out" / meta["ply_file_path"]))["vertex"]
    assert [p.name for p in seed.properties] == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert seed["red"].dtype == np.uint8 and not np.stack([seed[c] for c in ("nx", "ny", "nz")]).any()
    # the Gaussians beside it in the layout graphdeco's loader and SIBR read: SH degree 3 (45 f_rest), no extras
    names = [p.name for p in PlyData.read(str(tmp_path / "out" / "scene.ply"))["vertex"].properties]
    assert sum(n.startswith("f_rest_") for n in names) == 45 and names[-1] == "rot_3"
    np.testing.assert_allclose(np.stack([seed[c] for c in "xyz"], -1), g.means[0].numpy(), atol=1e-6)
    rgb = (0.5 + SH_C0 * g.sh[0, :, 0]).clamp(0, 1).numpy() * 255
    np.testing.assert_allclose(np.stack([seed[c] for c in ("red", "green", "blue")], -1), rgb, atol=0.51)
    assert json.loads((tmp_path / "out" / "scale.json").read_text())["metres_per_unit"] == 2.5


def test_exports_carry_a_photo_folders_input_images(tmp_path):
    """predict saves view v of a photo folder as inputs/NNN.png: the exports copy them under names the COLMAP model
    and transforms.json use (DJI_0001.jpg -> images/DJI_0001.png), so both convert back with their images."""
    from PIL import Image

    g, w2c, K = _scene()
    d = tmp_path / "pred" / "flight"
    names = ["DJI_0001.jpg", "DJI_0002.jpg", "DJI_0003.JPG"]
    save_ply(g, d / "scene.ply")
    save_cameras(d / "cameras.json", w2c, K, 48, 32, names)
    (d / "inputs").mkdir()
    for v in range(3):
        Image.new("RGB", (48, 32), (60 * v, 0, 0)).save(d / "inputs" / f"{v:03d}.png")
    for fmt in ("colmap", "nerfstudio"):
        export(d, fmt, tmp_path / fmt)
        assert sorted(p.name for p in (tmp_path / fmt / "images").iterdir()) == ["DJI_0001.png", "DJI_0002.png",
                                                                                 "DJI_0003.png"]
        src = tmp_path / fmt if fmt == "colmap" else tmp_path / fmt / "transforms.json"
        views = (colmap_parser if fmt == "colmap" else ns_parser).parse(src)[0].views
        assert [v.name for v in views] == ["DJI_0001.png", "DJI_0002.png", "DJI_0003.png"]
        for v, view in enumerate(views):  # each camera with its own input image
            assert np.asarray(Image.open(view.image_path))[0, 0, 0] == 60 * v
            np.testing.assert_allclose(view.w2c, w2c[v].numpy(), atol=1e-6)
    from anycity.export.cli import image_names

    assert image_names(["a.jpg", "a.png", "b"]) == ["000_a.png", "001_a.png", "002_b.png"]
    # COLMAP's images.txt is split on spaces: a photo named with one would lose the rest of its name there
    assert image_names(["DJI 0001.JPG", "DJI_0001.png"]) == ["000_DJI_0001.png", "001_DJI_0001.png"]
    assert image_names(["IMG 7 .jpg"]) == ["IMG_7.png"]
    # every suffix a photo folder reads (data.photos.PHOTO_SUFFIXES) is replaced, not kept inside the name
    from anycity.data.photos import PHOTO_SUFFIXES

    names = [f"p{i}{s}" for i, s in enumerate(PHOTO_SUFFIXES)]
    assert image_names(names) == [f"p{i}.png" for i in range(len(names))]


def test_ply_export_and_errors(tmp_path, capsys):
    d, g, _, _ = _predict_dir(tmp_path)
    assert export_main(["--from", str(d / "scene.ply"), "--format", "ply", "--out", str(tmp_path / "o")]) == 0
    from anycity.export import load_ply

    back = load_ply(tmp_path / "o" / "scene.ply")
    torch.testing.assert_close(back.means, g.means)
    # graphdeco's record, which fixed-record readers (SIBR's gaussianViewer: 62 floats) read without the header:
    # no provenance columns, SH zero-padded to degree 3
    from plyfile import PlyData

    names = [p.name for p in PlyData.read(str(tmp_path / "o" / "scene.ply"))["vertex"].properties]
    assert names == ["x", "y", "z", "nx", "ny", "nz", *(f"f_dc_{i}" for i in range(3)),
                     *(f"f_rest_{i}" for i in range(45)), "opacity", *(f"scale_{i}" for i in range(3)),
                     *(f"rot_{i}" for i in range(4))]
    k = (g.sh_degree + 1) ** 2
    assert g.sh_degree < 3 and back.sh_degree == 3
    torch.testing.assert_close(back.sh[..., :k, :], g.sh)
    assert (back.sh[..., k:, :] == 0).all()
    assert "scene.ply" in capsys.readouterr().out
    # never silently over an earlier export or the scene itself: --overwrite writes into a folder that is not empty
    with pytest.raises(FileExistsError, match="o exists and is not empty; pass --overwrite"):
        export_main(["--from", str(d / "scene.ply"), "--format", "ply", "--out", str(tmp_path / "o")])
    with pytest.raises(ValueError, match="is the scene folder --from reads"):  # not "pass --overwrite": that
        export(d, "ply", d)  # replaced the predict folder's scene.ply (with its provenance columns)
    assert export_main(["--from", str(d / "scene.ply"), "--format", "splat", "--out", str(tmp_path / "o"),
                        "--overwrite"]) == 0
    assert (tmp_path / "o" / "scene.splat").is_file() and (tmp_path / "o" / "scene.ply").is_file()
    (d / "cameras.json").unlink()
    for fmt in ("colmap", "nerfstudio"):
        with pytest.raises(ValueError, match=f"no cameras.json beside the scene; --format {fmt} needs") as e:
            export(d, fmt, tmp_path / "o2")
        assert "\n" not in str(e.value)
        assert not (tmp_path / "o2").exists()  # refused before writing anything
    with pytest.raises(FileNotFoundError, match="scene.ply"):
        export(tmp_path, "splat", tmp_path / "o3")


def test_an_out_folder_holding_one_file_is_not_written_into(tmp_path):
    d, _, _, _ = _predict_dir(tmp_path)
    out = tmp_path / "o"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="o exists and is not empty; pass --overwrite"):
        export(d, "splat", out)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_a_missing_input_image_is_warned_about_and_the_colmap_model_still_written(tmp_path):
    from PIL import Image

    d, _, _, _ = _predict_dir(tmp_path)
    (d / "inputs").mkdir()
    for v in (0, 1):  # view 2's image is missing
        Image.new("RGB", (48, 32)).save(d / "inputs" / f"{v:03d}.png")
    with pytest.warns(UserWarning, match="no inputs/ images for all 3 cameras"):
        out = export(d, "colmap", tmp_path / "o")
    assert out == tmp_path / "o" / "sparse" / "0" and (out / "images.txt").is_file()
    assert not (tmp_path / "o" / "images").exists()  # all or none: no model with some images missing


def test_flags_may_be_given_as_flag_equals_value(tmp_path):
    d, _, _, _ = _predict_dir(tmp_path)
    assert export_main([f"--from={d}", "--format=splat", f"--out={tmp_path / 'o'}"]) == 0
    assert (tmp_path / "o" / "scene.splat").is_file()


def test_the_default_out_is_export_format_inside_the_scene_folder(tmp_path, capsys):
    d, _, _, _ = _predict_dir(tmp_path)
    assert export_main(["--from", str(d), "--format", "splat"]) == 0
    assert (d / "export_splat" / "scene.splat").is_file()
    assert export_main(["--from", str(d / "scene.ply"), "--format", "ply"]) == 0  # beside a scene.ply given
    assert (d / "export_ply" / "scene.ply").is_file()
    assert sorted(p.name for p in d.parent.iterdir()) == ["sceneA"]  # nothing beside the scene folder
    assert f"wrote {d / 'export_splat' / 'scene.splat'}" in capsys.readouterr().out


@pytest.mark.parametrize("pad_degree", [None, 3])
def test_a_scene_with_no_gaussian_left_is_a_readable_empty_ply(tmp_path, pad_degree):
    from anycity.export import load_ply

    g, _, _ = _scene(4)
    g.opacities.fill_(float("nan"))  # every row dropped
    assert save_ply(g, tmp_path / "e.ply", pad_degree=pad_degree) == 4
    back = load_ply(tmp_path / "e.ply")
    assert back.means.shape == (1, 0, 3)
    assert back.sh.shape == (1, 0, ((pad_degree or g.sh_degree) + 1) ** 2, 3)


def test_a_malformed_cameras_json_is_one_line_naming_it(tmp_path):
    d, _, _, _ = _predict_dir(tmp_path)
    cams = json.loads((d / "cameras.json").read_text())
    for broken, what in (("garbage{", "not JSON"), ('{"views": []}', "no 'views' list"),
                         (json.dumps({"views": [{**cams["views"][0], "w2c": [[1, 0, 0]]}]}), "no 4x4 numeric 'w2c'"),
                         (json.dumps({"views": [{**cams["views"][0], "K": None}]}), "no 3x3 numeric 'K'"),
                         (json.dumps({"views": [{**cams["views"][0], "width": 0}]}), "positive integer 'width'"),
                         (json.dumps({"views": [{**cams["views"][0], "height": True}]}), "positive integer 'height'"),
                         (json.dumps({"views": [{**cams["views"][0], "w2c": [[float("nan")] * 4] * 4}]}),
                          "view 0: camera holds NaN/inf"),  # json writes and reads NaN
                         (json.dumps({"views": [{**cams["views"][0], "w2c": [[0, 0, 0, 1]] * 3 + [[0, 0, 0, 1]]}]}),
                          "view 0: camera pose is not a rigid"),  # a singular rotation: COLMAP's LinAlgError before
                         (json.dumps({"views": [{**cams["views"][0], "K": [[0, 0, 8], [0, 0, 8], [0, 0, 1]]}]}),
                          "view 0: intrinsics need focal lengths > 0"),
                         (json.dumps({"views": [cams["views"][0], {**cams["views"][1], "width": 47}]}),
                          "view 1 is 47x32, view 0 48x32"),
                         (json.dumps({"views": [{**cams["views"][0], "K": [[10 ** 400, 0, 8], [0, 1, 8], [0, 0, 1]]}]}),
                          "view 0: camera holds a number too large for a float"),  # was an OverflowError
                         (json.dumps({"views": [{**cams["views"][0], "width": 70000}]}),
                          r"positive integer 'width' \(at most 65536\)"),
                         (json.dumps({**cams, "metres_per_unit": "2"}), "'metres_per_unit' is '2', not a positive"),
                         (json.dumps({**cams, "metres_per_unit": 0}), "'metres_per_unit' is '0', not a positive"),
                         (json.dumps({**cams, "convention": "opengl_c2w"}), "'convention' is 'opengl_c2w', not"),
                         (json.dumps({**cams, "schema_version": 99}), "'schema_version' is '99'; this anycity reads "
                                                                      "up to 1"),
                         (json.dumps({"views": [{**cams["views"][0], "K": [[True, 0, 8], [0, 1, 8], [0, 0, 1]]}]}),
                          "no 3x3 numeric 'K'")):
        (d / "cameras.json").write_text(broken)
        with pytest.raises(ValueError, match=f"cameras.json: .*{what}.*not a cameras.json written by") as e:
            export(d, "colmap", tmp_path / "o")
        assert "\n" not in str(e.value)
    (d / "cameras.json").write_text(json.dumps({"views": [{k: x for k, x in v.items() if k != "name"}
                                                          for v in cams["views"]]}))  # names are optional
    with pytest.warns(UserWarning, match="no inputs/ images"):  # the fixture has none
        assert "IMAGE_ID" in (export(d, "colmap", tmp_path / "o") / "images.txt").read_text()


def test_every_format_keeps_the_rows_the_ply_keeps(tmp_path):
    """.splat and the point clouds kept rows with NaN/inf SH or a zero scale (the PLY writer drops them): a NaN
    colour became RGB 0 in .splat, a zero scale a splat no viewer draws."""
    from plyfile import PlyData

    from anycity.export.formats import save_colmap, save_points_ply, splat_bytes

    g, w2c, K = _scene(n=6)
    g.sh[0, 2, 0, 0] = float("nan")  # a NaN colour
    g.sh[0, 3, 1, 0] = float("inf")  # an inf higher band
    g.scales[0, 4] = 0.0  # a zero scale
    assert save_ply(g, tmp_path / "s.ply") == 3
    kept = PlyData.read(str(tmp_path / "s.ply"))["vertex"]["x"]
    assert len(splat_bytes(g)) // 32 == 3
    assert sorted(PlyData.read(str(save_points_ply(tmp_path / "p.ply", g)))["vertex"]["x"]) == sorted(kept)
    pts = (save_colmap(tmp_path / "c", w2c, K, 48, 32, ["a", "b", "c"], g) / "points3D.txt").read_text()
    assert len([line for line in pts.splitlines() if not line.startswith("#")]) == 3


def test_a_wrong_input_is_told_which_folder_or_file_to_pass_instead(tmp_path):
    from anycity.export.cli import load_scene

    d, _, _, _ = _predict_dir(tmp_path)
    # the predict's --export.out_dir itself: its scene folders are named (the hint said predictions/<scene>/)
    with pytest.raises(FileNotFoundError, match=rf"no scene.ply inside; it holds the scene folder\(s\) sceneA: pass "
                                                rf"one of them, e.g. {d}$"):
        load_scene(d.parent)
    with pytest.raises(FileNotFoundError, match=r"no scene.ply inside; pass a scene folder written by"):
        load_scene(tmp_path)  # no scene folder directly inside
    # one of the package's own exports, not damaged: named as the wrong kind of file, not "re-export it"
    assert export_main(["--from", str(d), "--format", "splat", "--out", str(tmp_path / "o")]) == 0
    for wrong in (tmp_path / "o" / "scene.splat", d / "cameras.json"):
        with pytest.raises(ValueError, match=r"not a \.(splat|json) file; pass .* or the scene.ply itself$"):
            load_scene(wrong)


@pytest.mark.parametrize("argv,typo,near", [
    (["export", "--from", "x", "--fromat", "splat"], "--fromat", "--format"),
    (["render-video", "x", "--widht", "64"], "--widht", "--width"),
    (["view", "x", "--prot", "8080"], "--prot", "--port"),
    (["export", "--bogus"], "--bogus", None)])
def test_a_mistyped_flag_is_named_with_the_nearest_one(argv, typo, near, capsys):
    # argparse called a mistyped required flag missing ("the following arguments are required: --format")
    from anycity.cli import main

    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and err.endswith(f"error: unrecognized argument {typo}" +
                                              (f"; did you mean {near}?" if near else ""))


@pytest.mark.parametrize("bad", ["../../../../ESCAPED_relative", "/ABS/ESCAPED_absolute", "sub\\ESCAPED.jpg",
                                 "..", ".", "", "a\0b.jpg"])
@pytest.mark.parametrize("fmt", ["colmap", "nerfstudio"])
def test_a_view_name_that_is_a_path_is_refused_and_nothing_escapes_out(tmp_path, bad, fmt):
    """cameras.json's view names became images/<name>.png: ../../x or an absolute path wrote the input images
    outside --out (and images.txt listed the absolute path)."""
    from PIL import Image

    g, w2c, K = _scene()
    d = tmp_path / "a" / "b" / "pred" / "flight"
    save_ply(g, d / "scene.ply")
    names = ["DJI_0001.jpg", bad.replace("/ABS", str(tmp_path)), "DJI_0003.jpg"]
    save_cameras(d / "cameras.json", w2c, K, 48, 32, names)
    (d / "inputs").mkdir()
    for v in range(3):
        Image.new("RGB", (48, 32)).save(d / "inputs" / f"{v:03d}.png")
    out = tmp_path / "a" / "b" / "out"
    with pytest.raises(ValueError, match=r"cameras\.json: view 1's 'name' .* is not a plain file name .*not a "
                                         r"cameras\.json written by") as e:
        export(d, fmt, out)
    assert "\n" not in str(e.value)
    assert not out.exists() and not [p for p in tmp_path.rglob("*ESCAPED*")]


def test_image_names_keep_only_a_names_last_component():
    """Defence in depth behind load_cameras: whatever reaches image_names stays a file name inside images/."""
    from anycity.export.cli import image_names

    got = image_names(["../../x/ESC.jpg", "/abs/dir/Y", "a\\b.JPG", "..", "c\0d"])
    assert got == ["ESC.png", "Y.png", "b.png", "view.png", "cd.png"]
    assert all("/" not in n and "\\" not in n and "\0" not in n for n in got)


def test_a_photo_name_that_is_not_utf8_is_written_to_images_txt_as_its_own_bytes(tmp_path):
    """A latin-1 ``caf\\xe9.jpg`` (held as a surrogate escape) loaded and predicted, then the COLMAP export stopped
    with "'utf-8' codec can't encode character '\\udce9'": the name is written as the file name's bytes."""
    import torch

    from anycity.export.formats import save_colmap

    w2c = torch.eye(4)[None].repeat(2, 1, 1)
    K = torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]])[None].repeat(2, 1, 1)
    name = b"caf\xe9.jpg".decode("utf-8", "surrogateescape")
    save_colmap(tmp_path / "c", w2c, K, 48, 32, ["a.jpg", name])
    lines = [ln for ln in (tmp_path / "c" / "images.txt").read_bytes().splitlines() if ln and ln[:1] != b"#"]
    assert lines[0].endswith(b" a.jpg") and lines[1].endswith(b" caf\xe9.jpg")
