import os

import cv2
import numpy as np
import pytest

from anycity.data.photos import load_photo_folder


def _write(folder, name, h, w, seed=0):
    img = np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8)
    folder.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(folder / name), img)
    return img


def test_folder_loads_sorted_resized_rgb(tmp_path):
    d = tmp_path / "my_roof"
    a = _write(d, "b.png", 40, 40, 1)
    _write(d, "a.jpg", 60, 80, 2)
    _write(d, "c.PNG", 50, 50, 3)
    (d / "notes.txt").write_text("ignored")
    out = load_photo_folder(d, (32, 32), mode="crop", patch=8)
    assert out["scene"] == "my_roof" and out["names"] == ["a.jpg", "b.png", "c.PNG"]
    assert out["images"].shape == (3, 3, 32, 32) and 0 <= out["images"].min() and out["images"].max() <= 1
    # b.png, area-resized 40 -> 32, keeps its mean colour in RGB order (cv2 reads BGR)
    mean_rgb = a[..., ::-1].reshape(-1, 3).mean(0) / 255
    np.testing.assert_allclose(out["images"][1].mean(dim=(1, 2)).numpy(), mean_rgb, atol=0.01)


def test_exif_orientation_is_applied(tmp_path):
    from PIL import Image

    d = tmp_path / "phone"
    d.mkdir()
    for name, red in (("a.jpg", 200), ("b.jpg", 180)):
        exif = Image.Exif()
        exif[0x0112] = 6  # stored landscape, shown rotated 90 degrees clockwise (portrait)
        Image.new("RGB", (64, 32), (red, 40, 40)).save(d / name, exif=exif)
    out = load_photo_folder(d, (32, 32), mode="keep", patch=8)
    h, w = out["images"].shape[-2:]
    assert h > w  # portrait, as the phone showed it


@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_is_shown_as_opencv_shows_a_jpeg(tmp_path, orientation):
    from PIL import Image

    from anycity.data.photos import load_photo, photo_size

    yy, xx = np.mgrid[0:24, 0:40]
    img = np.stack([xx * 6, yy * 10, (xx * yy) % 256], -1).astype(np.uint8)  # no symmetry
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(img).save(tmp_path / "a.jpg", quality=100, exif=exif)
    shown = cv2.imread(str(tmp_path / "a.jpg"))[..., ::-1]  # OpenCV applies a JPEG's orientation
    assert photo_size(tmp_path / "a.jpg") == shown.shape[:2]
    got = load_photo(tmp_path / "a.jpg", shown.shape[:2], mode="keep", patch=8)
    np.testing.assert_allclose(got.permute(1, 2, 0).numpy(), shown / 255, atol=1e-6)


def test_a_png_turned_by_an_imagemagick_exif_chunk_loads_upright_and_whole(tmp_path):
    """Pillow reads the orientation from a PNG's "Raw profile type exif" text chunk, OpenCV does not: the size came
    from one and the pixels from the other, and the photo loaded sideways with 44% cropped away."""
    from PIL import Image, PngImagePlugin

    from anycity.data.photos import load_photo, photo_size

    exif = Image.Exif()
    exif[0x0112] = 6
    raw = exif.tobytes().hex()
    text = f"\nexif\n{len(raw) // 2:8d}\n" + "\n".join(raw[i:i + 72] for i in range(0, len(raw), 72)) + "\n"
    info = PngImagePlugin.PngInfo()
    info.add_text("Raw profile type exif", text, zip=True)
    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :8] = 255  # a white left edge: the top edge once turned clockwise
    Image.fromarray(img).save(tmp_path / "p.png", pnginfo=info)
    assert photo_size(tmp_path / "p.png") == (64, 48)
    got = load_photo(tmp_path / "p.png", (64, 48), mode="keep", patch=8)
    assert got[:, :8].mean() > 0.99 and got[:, 8:].mean() < 0.01


def test_a_drone_photo_with_a_preview_is_refused_when_cut_short_and_read_with_data_after_it(tmp_path):
    """DJI photos are MPO (a JPEG with an embedded preview); the truncation check read "JPEG" only and let a cut one
    load with a grey half. A JPEG followed by other data (a motion photo's video) is whole, not truncated."""
    from PIL import Image

    from anycity.data.photos import load_photo, photo_size

    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (96, 128, 3), np.uint8)
    Image.fromarray(img).save(tmp_path / "m.jpg", "MPO", save_all=True, append_images=[Image.fromarray(img[::4, ::4])])
    data = (tmp_path / "m.jpg").read_bytes()
    assert Image.open(tmp_path / "m.jpg").format == "MPO"
    (tmp_path / "cut.jpg").write_bytes(data[: data.find(b"\xff\xd9") // 2])
    with pytest.raises(ValueError, match=r"cut\.jpg: truncated JPEG"):
        photo_size(tmp_path / "cut.jpg")
    Image.fromarray(img).save(tmp_path / "plain.jpg", quality=95)
    (tmp_path / "motion.jpg").write_bytes((tmp_path / "plain.jpg").read_bytes() + b"ftypmp42" + bytes(8000))
    assert photo_size(tmp_path / "motion.jpg") == (96, 128) == photo_size(tmp_path / "m.jpg")
    assert load_photo(tmp_path / "motion.jpg", (96, 128), patch=8).shape == (3, 96, 128)


def test_webp_and_16_bit_photos_load_upright(tmp_path):
    from PIL import Image

    d = tmp_path / "survey"
    d.mkdir()
    exif = Image.Exif()
    exif[0x0112] = 6  # stored landscape, shown portrait
    for name, blue in (("a.webp", 40), ("b.WEBP", 44)):
        Image.new("RGB", (64, 32), (200, 40, blue)).save(d / name, exif=exif)
    cv2.imwrite(str(d / "c.png"), np.full((64, 32), 40000, np.uint16))  # 16-bit grey: 40000 >> 8 = 156
    out = load_photo_folder(d, (32, 32), mode="keep", patch=8)
    assert out["names"] == ["a.webp", "b.WEBP", "c.png"]
    assert out["images"].shape[-2] > out["images"].shape[-1]  # portrait, as shown
    np.testing.assert_allclose(out["images"][:2].mean(dim=(2, 3)).numpy(), [[200 / 255, 40 / 255, 42 / 255]] * 2,
                               atol=0.02)
    assert abs(float(out["images"][2].mean()) - 156 / 255) < 0.01


def test_hidden_files_are_not_photos_and_raw_files_are_named(tmp_path):
    """A card copied from a Mac holds ``._NAME.JPG`` metadata beside each photo; camera raw and TIFF files are not
    read, and the warning says so."""
    d = tmp_path / "flight"
    _write(d, "DJI_0001.JPG", 32, 32, 1)
    _write(d, "DJI_0002.JPG", 32, 32, 2)
    (d / "._DJI_0001.JPG").write_bytes(b"\x00\x05\x16\x07Mac OS X")
    (d / "DJI_0001.DNG").write_bytes(b"raw")
    (d / "DJI_0002.tif").write_bytes(b"tiff")
    with pytest.warns(UserWarning, match=r"2 file\(s\) in .* are not read \(DJI_0001\.DNG, DJI_0002\.tif\): only "
                                         r"\.jpg/.*photos are; export them as JPEG"):
        out = load_photo_folder(d, (32, 32))
    assert out["names"] == ["DJI_0001.JPG", "DJI_0002.JPG"]


def test_jfif_and_jpe_are_photos_and_any_other_file_but_a_sidecar_is_named(tmp_path):
    """``.jfif`` / ``.jpe`` JPEGs, and BMP, AVIF, JPEG 2000 files, were dropped from a folder without a word."""
    import warnings

    from anycity.data.photos import list_photos

    d = tmp_path / "flight"
    d.mkdir()
    for i, name in enumerate(["DJI_0001.JPG", "DJI_0002.jfif", "DJI_0003.JPE"]):  # OpenCV writes no .jfif
        (d / name).write_bytes(cv2.imencode(".jpg", np.full((32, 32, 3), 60 * i, np.uint8))[1].tobytes())
    for name in ["DJI_0004.bmp", "DJI_0005.avif", "DJI_0006.jp2", "DJI_0007.MP4"]:
        (d / name).write_bytes(b"x")
    for suffix in (".xmp", ".aae", ".srt", ".mrk", ".txt", ".json", ".csv"):  # metadata, flight logs, notes: not named
        (d / f"DJI_0001{suffix.upper()}").write_bytes(b"x")
    (d / "images_2.bmp").mkdir()  # a folder is not a file left out
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        files = list_photos(d)
    assert [p.name for p in files] == ["DJI_0001.JPG", "DJI_0002.jfif", "DJI_0003.JPE"]
    assert [str(m.message) for m in w] == [
        f"predict_images: 4 file(s) in {d} are not read (DJI_0004.bmp, DJI_0005.avif, DJI_0006.jp2, DJI_0007.MP4): "
        "only .jpg/.jpeg/.jfif/.jpe/.png/.webp photos are; export them as JPEG to use them"]
    flags = []
    import anycity.data.photos as photos

    read = photos.read_image
    with pytest.MonkeyPatch.context() as mp, pytest.warns(UserWarning, match="4 file"):
        mp.setattr(photos, "read_image", lambda f, flag: flags.append(flag) or read(f, flag))
        out = load_photo_folder(d, (8, 8), mode="keep", patch=8)
    assert out["images"].shape == (3, 3, 8, 8)
    assert flags == [cv2.IMREAD_REDUCED_COLOR_4 | cv2.IMREAD_IGNORE_ORIENTATION] * 3  # each decoded as a JPEG


def test_a_photo_whose_file_name_is_not_utf8_loads(tmp_path, child, latin1_path):
    """A latin-1 ``caf\\xe9.jpg`` (an old card, a zip) is a surrogate-escaped str in Python, on which OpenCV 5's
    imread crashed the process (SIGSEGV)."""
    ok, jpg = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (48, 64, 3), dtype=np.uint8))
    (tmp_path / "flight").mkdir()
    (tmp_path / "flight" / "a.jpg").write_bytes(jpg.tobytes() + b"\0")  # the same pixels, not a byte-for-byte copy
    latin1_path(tmp_path / "flight", b"caf\xe9.jpg", jpg.tobytes())
    out = child("import sys; from anycity.data.photos import load_photo_folder\n"
                "out = load_photo_folder(sys.argv[1], (24, 32), mode='crop', patch=8)\n"
                "print([n.encode('utf-8', 'surrogateescape') for n in out['names']], tuple(out['images'].shape), "
                "bool((out['images'][0] == out['images'][1]).all()))", str(tmp_path / "flight"))
    assert out.split() == ["[b'a.jpg',", "b'caf\\xe9.jpg']", "(2,", "3,", "24,", "32)", "True"]


def test_large_jpegs_decode_at_a_fraction_of_their_size(tmp_path, monkeypatch):
    """A JPEG 8x larger than the model's input is decoded at 1/8 scale by libjpeg, upright, and matches decoding it
    in full and resizing."""
    from PIL import Image

    import anycity.data.photos as photos
    from anycity.data.views import resize_view

    yy, xx = np.mgrid[0:480, 0:640]
    img = np.stack([xx * 255 // 639, yy * 255 // 479, (xx + yy) % 256], -1).astype(np.uint8)  # smooth, no aliasing
    d = tmp_path / "drone"
    d.mkdir()
    exif = Image.Exif()
    exif[0x0112] = 6  # shown rotated: 480 wide, 640 high
    Image.fromarray(img).save(d / "a.jpg", quality=95, exif=exif)
    Image.fromarray(img).save(d / "b.JPG", quality=95, exif=exif)
    with open(d / "b.JPG", "ab") as f:  # the same pixels, not a byte-for-byte copy (left out)
        f.write(b"\0")
    flags = []
    read = photos.read_image
    monkeypatch.setattr(photos, "read_image", lambda f, flag: flags.append(flag) or read(f, flag))
    out = load_photo_folder(d, (64, 48), mode="keep", patch=8)
    assert flags == [cv2.IMREAD_REDUCED_COLOR_8 | cv2.IMREAD_IGNORE_ORIENTATION] * 2
    assert out["images"].shape == (2, 3, 64, 48)
    full = cv2.imread(str(d / "a.jpg"), cv2.IMREAD_COLOR)[..., ::-1]
    assert full.shape[:2] == (640, 480)  # upright
    ref, *_ = resize_view(np.ascontiguousarray(full), np.eye(3), (64, 48), "keep", 8)
    err = (out["images"][0].permute(1, 2, 0).numpy() - ref / 255).__abs__().mean()
    assert err < 0.01, err


def test_folder_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        load_photo_folder(tmp_path / "missing", (32, 32))
    one = tmp_path / "one"
    _write(one, "a.png", 32, 32)
    with pytest.raises(ValueError, match="holds 1 photo "):
        load_photo_folder(one, (32, 32))
    bad = tmp_path / "bad"
    _write(bad, "a.png", 32, 32)
    (bad / "b.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match=r"b\.jpg: not a readable image.*re-save it"):
        load_photo_folder(bad, (32, 32))
    (bad / "a.png").unlink()
    with pytest.raises(ValueError, match="holds 1 photo .only b.jpg.*add more"):
        load_photo_folder(bad, (32, 32))
    flights = tmp_path / "flights"  # the parent of two scenes' folders
    _write(flights / "north", "a.png", 32, 32)
    _write(flights / "south", "a.png", 32, 32)
    (flights / "west").mkdir()  # only a Mac's metadata of a photo: not a folder of photos
    (flights / "west" / "._a.jpg").write_bytes(b"\x00\x05\x16\x07Mac OS X")
    with pytest.raises(ValueError, match=r"holds no photos but sub-folders of photos \(north, south\); pass one"):
        load_photo_folder(flights, (32, 32))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes on this platform")
@pytest.mark.timeout(30, method="signal")  # the old loader waited forever on the pipe
def test_a_fifo_or_folder_with_a_photos_name_is_refused_in_one_line_not_waited_on(tmp_path):
    d = tmp_path / "flight"
    _write(d, "a.jpg", 32, 32)
    _write(d, "b.jpg", 32, 32, seed=1)
    os.symlink("b.jpg", d / "link.jpg")  # a symlink to a photo is read as the photo: here a copy of b.jpg
    with pytest.warns(UserWarning, match=r"byte-for-byte .* \(link.jpg = b.jpg\)"):
        assert load_photo_folder(d, (32, 32))["names"] == ["a.jpg", "b.jpg"]
    (d / "link.jpg").unlink()
    os.symlink(tmp_path / "elsewhere.jpg", d / "link.jpg")
    _write(tmp_path, "elsewhere.jpg", 32, 32, seed=2)
    assert load_photo_folder(d, (32, 32))["names"] == ["a.jpg", "b.jpg", "link.jpg"]
    os.mkfifo(d / "z.jpg")
    with pytest.raises(ValueError, match=r"predict_images: .*z\.jpg is a FIFO \(named pipe\), not a photo file; "
                                         "remove it"):
        load_photo_folder(d, (32, 32))
    (d / "z.jpg").unlink()
    (d / "c.png").mkdir()
    with pytest.raises(ValueError, match=r"c\.png is a folder, not a photo file"):
        load_photo_folder(d, (32, 32))


@pytest.mark.parametrize("odd_name", ["odd.png", "a_odd.png"])  # last or first in name order: the majority wins
def test_keep_aspect_no_crop_and_mixed_sizes_go_to_the_most_common(tmp_path, odd_name):
    d = tmp_path / "flight"
    for i in range(3):
        _write(d, f"img{i}.png", 60, 80, i)  # 4:3
    _write(d, odd_name, 32, 96, 9)  # 3:1
    with pytest.warns(UserWarning, match=rf"1 of 4 photos .*\({odd_name}\).*most common.* to 40x24 \(width x height\)"):
        out = load_photo_folder(d, (32, 32), mode="keep", patch=8)
    h, w = out["images"].shape[-2:]
    assert (h, w) == (24, 40) and out["images"].shape[0] == 4  # ~32*32 px at 4:3, sides multiples of 8
    assert sorted(out["names"]) == sorted(["img0.png", "img1.png", "img2.png", odd_name]) == out["names"]


def test_natural_order_and_capture_time(tmp_path):
    from PIL import Image

    from anycity.city.plan import order_photos

    d = tmp_path / "t"
    d.mkdir()
    for name, t in (("img10.jpg", "2024:05:01 10:00:02"), ("img2.jpg", "2024:05:01 10:00:03"),
                    ("img1.jpg", "2024:05:01 10:00:01")):
        exif = Image.Exif()
        exif[306] = t
        Image.new("RGB", (16, 16)).save(d / name, exif=exif)
    files = sorted(d.iterdir())
    order, by = order_photos(files)
    assert by == "time" and [files[i].name for i in order] == ["img1.jpg", "img10.jpg", "img2.jpg"]
    order, by = order_photos(files, "name")
    assert [files[i].name for i in order] == ["img1.jpg", "img2.jpg", "img10.jpg"]


def _exif_jpg(folder, name, original=None, changed=None, subsec=None):
    """A JPEG with EXIF DateTimeOriginal (36867), DateTime (306) and SubSecTimeOriginal (37521) as given."""
    from PIL import Image

    folder.mkdir(exist_ok=True)
    exif = Image.Exif()
    if changed:
        exif[306] = changed
    ifd = {}  # the Exif sub-IFD, set whole: Pillow 10.0 does not save edits made through get_ifd()
    if original:
        ifd[36867] = original
    if subsec:
        ifd[37521] = subsec
    if ifd:
        exif[0x8769] = ifd
    Image.new("RGB", (8, 8)).save(folder / name, exif=exif)
    return folder / name


def test_capture_order_is_date_time_original_not_the_edit_time(tmp_path):
    """An editor rewrites DateTime (306) on export; DateTimeOriginal (36867) is when the photo was taken."""
    from anycity.city.plan import order_photos

    d = tmp_path / "edited"
    files = [_exif_jpg(d, "c.jpg", "2024:05:01 10:00:00", "2024:06:01 09:00:09"),
             _exif_jpg(d, "b.jpg", "2024:05:01 10:00:02", "2024:06:01 09:00:05"),
             _exif_jpg(d, "a.jpg", "2024:05:01 10:00:04", "2024:06:01 09:00:01")]
    assert order_photos(files) == ([0, 1, 2], "time")  # c, b, a


def test_capture_order_within_one_second_uses_sub_seconds(tmp_path):
    """A burst: the same DateTimeOriginal, told apart by SubSecTimeOriginal (37521)."""
    from anycity.city.plan import order_photos

    d = tmp_path / "burst"
    files = [_exif_jpg(d, f"x{i}.jpg", "2024:05:01 10:00:00", subsec=sub) for i, sub in ((1, "70"), (2, "30"),
                                                                                       (3, "50"))]
    assert order_photos(files) == ([1, 2, 0], "time")  # x2, x3, x1


def test_name_order_ignores_case(tmp_path):
    from pathlib import Path

    from anycity.city.plan import order_photos

    files = [Path("a1.jpg"), Path("B2.jpg"), Path("c3.jpg")]
    assert order_photos(files, "name") == ([0, 1, 2], "name")


def test_scene_name_skips_generic_folder_names(tmp_path):
    from anycity.data.photos import scene_name

    assert scene_name(tmp_path / "boruszyn_kap" / "images") == "boruszyn_kap"  # COLMAP / nerfstudio layout
    assert scene_name(tmp_path / "my_flight") == "my_flight"
    assert scene_name(tmp_path / "roof" / "Images") == "roof"  # any case


def test_scene_name_of_the_current_folder_is_its_own_name(tmp_path, monkeypatch):
    """``--data.predict_images .`` names the scene after the folder it stands for, not ``""``."""
    from pathlib import Path

    from anycity.data.photos import scene_name

    (tmp_path / "my_flight").mkdir()
    monkeypatch.chdir(tmp_path / "my_flight")
    assert scene_name(Path(".")) == "my_flight"


def test_reorder_renames_the_photos_with_them(tmp_path):
    """``predict_order tokens`` loads by name, then reorders: the names (the outputs' labels) follow the files."""
    from anycity.data.photos import PhotoFolder

    d = tmp_path / "flight"
    for i in range(4):
        _write(d, f"p{i}.png", 32, 32, i)
    photos = PhotoFolder(d, (32, 32), "keep", 8, "name")
    photos.reorder([3, 0, 1, 2], "tokens")
    assert photos.names == [f.name for f in photos.files] == ["p3.png", "p0.png", "p1.png", "p2.png"]
    assert photos.ordered_by == "tokens"


def test_an_unreadable_photo_is_refused_naming_the_argument_and_the_fix(tmp_path):
    d = tmp_path / "bad"
    _write(d, "a.png", 32, 32)
    (d / "b.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError) as e:
        load_photo_folder(d, (32, 32))
    assert str(e.value) == (f"predict_images: cannot decode {d / 'b.jpg'}: not a readable image "
                            "(UnidentifiedImageError); re-save it as JPEG or PNG, or remove it")


def test_a_folder_of_only_unread_files_says_so_in_the_error_not_add_more_views(tmp_path):
    """A phone's folder of 40 HEIC photos failed with "holds no photos ... add more views of it"; only a separate
    warning said that they were not read. The error says how many were not read and to export them."""
    import warnings

    d = tmp_path / "iphone"
    d.mkdir()
    for i in range(40):
        (d / f"IMG_{i:04d}.HEIC").write_bytes(b"\x00\x00\x00\x18ftypheic")
    with warnings.catch_warnings(record=True) as w, pytest.raises(ValueError) as e:
        warnings.simplefilter("always")
        load_photo_folder(d, (32, 32))
    assert str(e.value) == (
        f"predict_images: {d} holds no photos (.jpg/.jpeg/.jfif/.jpe/.png/.webp) and 40 file(s) that are not read "
        "(IMG_0000.HEIC, IMG_0001.HEIC, IMG_0002.HEIC, IMG_0003.HEIC, IMG_0004.HEIC ...); export them as JPEG or "
        "PNG to use them: a scene needs at least 2 overlapping photos")
    assert not w  # said once, in the error
    _write(d, "a.jpg", 32, 32)
    with pytest.raises(ValueError, match=r"holds 1 photo \(only a\.jpg\) .* and 40 file\(s\) that are not read .*"
                                         "export them as JPEG or PNG"):
        load_photo_folder(d, (32, 32))


def test_byte_for_byte_copies_are_left_out_with_a_warning_naming_them(tmp_path):
    """Three copies of one photo went in as three views: cameras 19 deg apart and every Gaussian 'supported' by
    three views, without a word. Copies (same bytes; not merely the same size) are left out, the first by name
    kept."""
    import shutil

    from anycity.data.photos import PhotoFolder, list_photos

    d = tmp_path / "flight"
    _write(d, "p0.jpg", 32, 32, 0)
    _write(d, "p1.jpg", 32, 32, 1)
    shutil.copy(d / "p0.jpg", d / "p2.jpg")
    shutil.copy(d / "p0.jpg", d / "p3.jpg")
    same_size = bytearray((d / "p1.jpg").read_bytes())
    same_size[-3] ^= 1  # same size as p1, other bytes: not a copy
    (d / "p4.jpg").write_bytes(bytes(same_size))
    with pytest.warns(UserWarning, match=r"^predict_images: 2 photo\(s\) in .*flight are byte-for-byte copies of "
                                         r"another and are left out \(p2.jpg = p0.jpg, p3.jpg = p0.jpg\)"):
        files = list_photos(d)
    assert [f.name for f in files] == ["p0.jpg", "p1.jpg", "p4.jpg"]
    with pytest.warns(UserWarning, match="byte-for-byte copies"):
        assert PhotoFolder(d, (32, 32), "crop", 8).names == ["p0.jpg", "p1.jpg", "p4.jpg"]
    for p in ("p1.jpg", "p4.jpg"):
        (d / p).unlink()
    with pytest.warns(UserWarning, match="byte-for-byte"), \
            pytest.raises(ValueError, match=r"holds 1 photo \(only p0.jpg\)"):
        list_photos(d)  # copies of one photo are one view


def test_photos_with_transparency_are_named_in_a_warning(tmp_path):
    """An RGBA/LA PNG (or a palette with tRNS) went in as the colour under its transparent pixels, unannounced."""
    from PIL import Image

    from anycity.data.photos import PhotoFolder, photo_header

    d = tmp_path / "f"
    d.mkdir()
    Image.new("RGBA", (32, 32), (255, 0, 255, 0)).save(d / "a.png")
    Image.new("LA", (32, 32), (10, 0)).save(d / "b.png")
    Image.new("RGB", (32, 32)).save(d / "c.png")
    pal = Image.new("P", (32, 32))
    pal.info["transparency"] = 0
    pal.save(d / "d.png")
    assert [photo_header(d / n).alpha for n in ("a.png", "b.png", "c.png", "d.png")] == [True, True, False, True]
    with pytest.warns(UserWarning, match=r"^predict_images: 3 photo\(s\) in .* have transparency \(a.png, b.png, "
                                         r"d.png\); it is not read"):
        PhotoFolder(d, (32, 32), "crop", 8)


def test_a_png_folder_is_opened_once_per_photo_for_its_header(tmp_path, monkeypatch):
    """A PNG's EXIF can follow its pixels, so Pillow decodes it to read any tag: the size, the orientation and the
    capture time were read in three opens, each a full decode (3.4x OpenCV's decode time on 8000x6000)."""
    from PIL import PngImagePlugin

    from anycity.data.photos import PhotoFolder

    d = tmp_path / "f"
    for i in range(3):
        _write(d, f"{i}.png", 24, 32, i)
    loads = []
    real = PngImagePlugin.PngImageFile.load
    monkeypatch.setattr(PngImagePlugin.PngImageFile, "load", lambda self: loads.append(1) or real(self))
    photos = PhotoFolder(d, (32, 32), "keep", 8)
    assert len(loads) == 3
    photos.load()  # OpenCV decodes the pixels; the orientation comes from the headers read above
    assert len(loads) == 3


def test_a_placeholder_capture_time_is_no_capture_time(tmp_path):
    """A camera without a clock writes 0000:00:00 00:00:00 (or blanks); it sorted first under predict_order auto."""
    from anycity.city.plan import capture_time, order_photos

    d = tmp_path / "t"
    _exif_jpg(d, "a.jpg", original="2024:05:01 10:00:02")
    _exif_jpg(d, "b.jpg", original="2024:05:01 10:00:01")
    _exif_jpg(d, "c.jpg", original="0000:00:00 00:00:00")
    _exif_jpg(d, "d.jpg", original="    :  :     :  :  ")
    assert [capture_time(d / n) for n in ("c.jpg", "d.jpg")] == [None, None]
    assert order_photos(sorted(d.iterdir()))[1] == "name"
    with pytest.raises(ValueError, match="c.jpg has no EXIF capture time"):
        order_photos(sorted(d.iterdir()), "time")


def test_a_symlinked_folder_names_the_scene_after_the_link(tmp_path):
    """scene_name resolved links: two sites linked to folders both called 'timed' wrote one OUT_DIR/timed/."""
    from anycity.data.photos import scene_name

    (tmp_path / "dump" / "timed").mkdir(parents=True)
    (tmp_path / "site_A").symlink_to(tmp_path / "dump" / "timed")
    (tmp_path / "site_B").mkdir()
    (tmp_path / "site_B" / "images").symlink_to(tmp_path / "dump" / "timed")
    assert scene_name(tmp_path / "site_A") == "site_A"
    assert scene_name(tmp_path / "site_B" / "images") == "site_B"
    assert scene_name(tmp_path / "site_A" / ".." / "site_B") == "site_B"


def test_a_dangling_link_is_named_as_a_link(tmp_path):
    """It was 'not a readable image (FileNotFoundError); re-save it as JPEG or PNG': there is nothing to re-save."""
    from anycity.data.photos import PhotoFolder

    d = tmp_path / "f"
    _write(d, "a.jpg", 32, 32)
    _write(d, "b.jpg", 32, 32, 1)
    (d / "c.jpg").symlink_to(tmp_path / "gone.jpg")
    with pytest.raises(ValueError, match=r"^predict_images: .*c.jpg is a link to a file that does not exist; fix or "
                                         r"remove the link$"):
        PhotoFolder(d, (32, 32), "crop", 8)


def test_a_folder_name_too_long_for_the_outputs_is_shortened_with_a_hash(tmp_path):
    """A legal 246-byte folder name stopped predict with a traceback (OSError: File name too long) when its lock file
    .<name>.anycity-run.lock was made; names over 200 bytes are cut on a character and given a hash."""
    from anycity.data.photos import MAX_SCENE_NAME_BYTES, scene_name

    long = "flight_" * 35 + "x"
    with pytest.warns(UserWarning, match=r"^predict_images: the scene.s name \(flight_flight_.*246 bytes\) is too"):
        short = scene_name(tmp_path / long)
    assert len(short.encode()) <= MAX_SCENE_NAME_BYTES and short.startswith("flight_flight_")
    with pytest.warns(UserWarning, match="too long"):
        assert short != scene_name(tmp_path / (long + "y")) and short == scene_name(tmp_path / long / "images")
    cjk = "航拍" * 40  # 240 bytes in UTF-8: cut on a character, not inside one
    with pytest.warns(UserWarning, match="too long"):
        assert len(scene_name(tmp_path / cjk).encode()) <= MAX_SCENE_NAME_BYTES
    assert scene_name(tmp_path / ("a" * 200)) == "a" * 200  # at the limit: kept
    (tmp_path / f".{short}.anycity_city_work.partial.kept-123456-abcdef01").mkdir()  # the longest sibling fits


def _orbit_photos(d, views: int = 12):
    """The first ``views`` photos (48x48 JPEGs) of a 200-view synthetic orbit: consecutive views 1.8 degrees apart,
    as close as the closest pair of the 200 (rms of their thumbnails: 14.8 at the least, against 6 for a copy)."""
    import torch

    from anycity.data.raycast import SceneTensors, fov_intrinsics
    from anycity.data.synthetic import HFOV_DEG, make_city, render_view, trajectory

    rng = np.random.default_rng([1, 0])
    city = make_city(rng)
    w2c, _ = trajectory("orbit", 200, city, rng)
    K, scene = torch.as_tensor(fov_intrinsics(48, 48, HFOV_DEG), dtype=torch.float32), SceneTensors(city)
    d.mkdir()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # many small ops, as the synth command renders them: threads cost more than they give
    try:
        for i in range(views):
            rgb = render_view(scene, torch.as_tensor(w2c[i], dtype=torch.float32), K, 48, 48)["rgb"].numpy()
            cv2.imwrite(str(d / f"v{i:02d}.jpg"), (rgb[..., ::-1] * 255 + 0.5).astype(np.uint8))
    finally:
        torch.set_num_threads(threads)


def test_one_shot_saved_twice_is_named_in_a_warning_and_both_are_kept(tmp_path):
    """A JPEG re-saved at q80, or a .jpg and a .png export of one photo, went in as two views without a word (only
    byte-for-byte copies were caught): two views with no parallax. Consecutive views of an orbit are not named."""
    import warnings

    from PIL import Image

    from anycity.data.photos import PhotoFolder

    d = tmp_path / "orbit"
    _orbit_photos(d)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        assert len(PhotoFolder(d, (48, 48), patch=8)) == 12
    assert [str(m.message) for m in w] == []  # consecutive views are not copies
    Image.open(d / "v03.jpg").save(d / "v03_q80.jpg", quality=80)
    Image.open(d / "v07.jpg").save(d / "v07.png")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        photos = PhotoFolder(d, (48, 48), patch=8)
    assert [str(m.message) for m in w] == [
        f"predict_images: 2 pair(s) of photos in {d} look like one shot saved twice (v03.jpg ~ v03_q80.jpg, "
        "v07.jpg ~ v07.png); both are used, as two views with no parallax between them (read as a flat place): "
        "remove one of each pair if it is a copy"]
    assert len(photos) == 14 and {"v03_q80.jpg", "v07.png"} <= set(photos.names)


def test_the_near_copy_check_compares_thumbnails_of_one_size_all_at_once(tmp_path):
    """Photos of another size are not decoded for it, featureless ones (a damaged JPEG's grey) are not compared, and
    a shot turned by its EXIF orientation matches its upright export."""
    from PIL import Image

    import anycity.data.imagecheck as imagecheck
    from anycity.data.photos import near_copies, photo_header

    d = tmp_path / "f"
    img = cv2.resize(np.random.default_rng(0).integers(0, 255, (6, 8, 3), dtype=np.uint8), (64, 48),
                     interpolation=cv2.INTER_CUBIC)
    exif = Image.Exif()
    exif[0x0112] = 6  # stored 64 wide, shown 48 wide and 64 high
    d.mkdir()
    Image.fromarray(img).save(d / "turned.jpg", quality=95, exif=exif)
    Image.fromarray(np.rot90(img, -1)).save(d / "upright.png")
    Image.fromarray(np.full((64, 48, 3), 90, np.uint8)).save(d / "grey1.png")
    Image.fromarray(np.full((64, 48, 3), 90, np.uint8)).save(d / "grey2.jpg")
    _write(d, "other.jpg", 40, 40, 1)
    files = sorted(d.iterdir())
    decoded = []
    real = imagecheck.read_image
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(imagecheck, "read_image", lambda p, flag: decoded.append(p.name) or real(p, flag))
        pairs = near_copies(files, {f: photo_header(f) for f in files})
    assert [(a.name, b.name) for a, b in pairs] == [("turned.jpg", "upright.png")]
    assert sorted(decoded) == ["grey1.png", "grey2.jpg", "turned.jpg", "upright.png"]  # not other.jpg, alone
