"""Header checks before decoding: aerial survey frames pass, bombs are refused; JPEG walks as libjpeg reads."""

import io
import warnings

import cv2
import numpy as np
import pytest
from PIL import Image

from anycity.data.imagecheck import check_image_file, check_jpeg_complete


def _jpeg(h=16, w=16) -> bytearray:
    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(buf, "JPEG")
    return bytearray(buf.getvalue())


def _declaring(w: int, h: int) -> bytes:
    """An 8x8 JPEG whose start-of-frame header declares ``w`` x ``h`` (only the header is read)."""
    b = _jpeg(8, 8)
    i = b.find(b"\xff\xc0")
    b[i + 5:i + 7], b[i + 7:i + 9] = h.to_bytes(2, "big"), w.to_bytes(2, "big")
    return bytes(b)


@pytest.mark.parametrize("w,h", [(11664, 8750), (14204, 10652), (16384, 12288)])
def test_aerial_survey_frames_over_100_mp_pass_without_a_bomb_warning(tmp_path, w, h):
    """A Phase One iXM-100 frame (11664 x 8750 = 102 MP) was refused as a decompression bomb, and Pillow warned
    on it (its own limit is 89 MP: it warns above, and refuses over 179 MP)."""
    p = tmp_path / "ixm.jpg"
    p.write_bytes(_declaring(w, h))
    before = Image.MAX_IMAGE_PIXELS
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_image_file(p)
    assert Image.MAX_IMAGE_PIXELS == before  # raised while the header is read, then put back


def test_a_folder_of_survey_frames_is_planned_without_a_bomb_warning(tmp_path):
    """Predict's photo folder reads each header twice (size, capture time) with Pillow: never a warning."""
    from anycity.data.photos import PhotoFolder

    for name, tail in (("a.jpg", b""), ("b.jpg", b"\0")):  # two frames: not byte-for-byte copies
        (tmp_path / name).write_bytes(_declaring(11664, 8750) + tail)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        photos = PhotoFolder(tmp_path, (28, 42), patch=14)
    assert photos.hw == (28, 42) and photos.names == ["a.jpg", "b.jpg"]


@pytest.mark.parametrize("w,h,said", [(30000, 15000, "30000x15000 pixels"), (40000, 30000, "over 800 MP")])
def test_headers_over_400_mp_are_refused_in_one_line(tmp_path, w, h, said):
    p = tmp_path / "bomb.jpg"
    p.write_bytes(_declaring(w, h))
    with pytest.raises(ValueError, match=rf"^{p}: header declares {said}, over the 400 MP limit \(a decompression "
                                         r"bomb or a corrupt header\); downscale it or remove it$"):
        check_image_file(p)


def test_padding_bytes_between_jpeg_segments_are_skipped_as_libjpeg_does(tmp_path):
    """libjpeg decodes a JPEG with stray bytes between two header segments ("2 extraneous bytes before marker");
    the marker walk stopped at them and called the file truncated."""
    b = _jpeg()
    i = b.find(b"\xff\xdb")  # the first quantisation table, after APP0
    b[i:i] = b"\x00\x00"
    p = tmp_path / "padded.jpg"
    p.write_bytes(b)
    assert cv2.imdecode(np.frombuffer(bytes(b), np.uint8), cv2.IMREAD_COLOR).shape == (16, 16, 3)
    check_image_file(p)
    check_jpeg_complete(p)
    eoi = b.rfind(b"\xff\xd9")
    p.write_bytes(b[:eoi])  # cut short: still refused
    with pytest.raises(ValueError, match=r"truncated JPEG \(no end-of-image marker\)"):
        check_jpeg_complete(p)
    p.write_bytes(b[:i] + b"\x00" * 64)  # padding to the end: no scan at all
    with pytest.raises(ValueError, match=r"truncated JPEG"):
        check_jpeg_complete(p)
