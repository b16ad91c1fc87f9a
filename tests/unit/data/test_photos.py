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
    for name in ("a.jpg", "b.jpg"):
        exif = Image.Exif()
        exif[0x0112] = 6  # stored landscape, shown rotated 90 degrees clockwise (portrait)
        Image.new("RGB", (64, 32), (200, 40, 40)).save(d / name, exif=exif)
    out = load_photo_folder(d, (32, 32), mode="keep", patch=8)
    h, w = out["images"].shape[-2:]
    assert h > w  # portrait, as the phone showed it


def test_folder_errors_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        load_photo_folder(tmp_path / "missing", (32, 32))
    one = tmp_path / "one"
    _write(one, "a.png", 32, 32)
    with pytest.raises(ValueError, match="holds 1 photos"):
        load_photo_folder(one, (32, 32))
    bad = tmp_path / "bad"
    _write(bad, "a.png", 32, 32)
    (bad / "b.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(ValueError, match="cannot decode .*b.jpg"):
        load_photo_folder(bad, (32, 32))
    mixed = tmp_path / "mixed"
    _write(mixed, "a.png", 32, 32)
    _write(mixed, "b.png", 32, 96)
    with pytest.raises(ValueError, match="different sizes"):
        load_photo_folder(mixed, (32, 32), mode="keep", patch=8)
