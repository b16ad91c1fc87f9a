"""Cheap checks of an image file before decoding it: refuse decompression bombs and truncated JPEGs; its size as
stored or as shown (:func:`image_size`). The converters, which decode with OpenCV, check JPEGs for truncation only
(:func:`check_jpeg_complete`). :func:`read_image` decodes a file with OpenCV from its bytes.

The header is read without decoding pixels (PIL opens lazily), so a 30000 x 30000 header costs nothing. Pillow's
own decompression-bomb limit (89 MP: it warns on a 102 MP aerial survey frame and refuses one over 179 MP) is
raised to :data:`MAX_PIXELS` while this module opens a file (:func:`pil_pixel_limit`).
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

MAX_PIXELS = 400_000_000
"""400 MP: above the largest aerial survey frames (Phase One iXM-100: 11664 x 8750 = 102 MP; 150 MP cameras exist),
which :func:`anycity.data.photos.load_photo` decodes at 1/8 of their size, far below a decompression bomb's."""
_PIL_LIMIT = threading.RLock()


@contextmanager
def pil_pixel_limit(max_pixels: int = MAX_PIXELS) -> Iterator[None]:
    """Pillow's ``Image.MAX_IMAGE_PIXELS`` raised to at least ``max_pixels`` while the block runs, then put back.

    Pillow has no per-call limit, only that module global: the lock keeps two threads from restoring each other's
    value. Open headers only inside (decoding is OpenCV's, after :func:`check_image_file`)."""
    from PIL import Image

    with _PIL_LIMIT:
        old = Image.MAX_IMAGE_PIXELS
        Image.MAX_IMAGE_PIXELS = None if old is None else max(old, max_pixels)
        try:
            yield
        finally:
            Image.MAX_IMAGE_PIXELS = old


def read_image(path: str | Path, flags: int):
    """``cv2.imread(path, flags)`` decoded from the file's bytes (``[H, W, C]`` or ``[H, W]``), None when OpenCV
    cannot decode them. OpenCV 5's path-taking calls crash the process (SIGSEGV) on a file name that is not UTF-8
    (a latin-1 ``caf\\xe9.jpg`` from an old card or zip), so no path is handed to OpenCV."""
    import cv2
    import numpy as np

    data = np.fromfile(path, np.uint8)
    if data.size == 0:  # imdecode asserts on an empty buffer
        return None
    try:
        return cv2.imdecode(data, flags)
    except cv2.error:
        return None


def check_image_file(path: str | Path, max_pixels: int = MAX_PIXELS) -> None:
    """Raise a one-line ``ValueError`` naming ``path`` if its header declares more than ``max_pixels`` pixels,
    it cannot be identified as an image, or it is a JPEG cut short (no end-of-image marker)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with pil_pixel_limit(max_pixels), warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # refused below, in one line
            with Image.open(path) as im:  # header only
                w, h = im.size
                fmt = im.format
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ValueError(f"cannot decode {path}: not a readable image ({type(e).__name__}); re-save it as JPEG "
                         "or PNG, or remove it") from None
    except Image.DecompressionBombError:  # over twice Pillow's limit: the size is not given
        w, h, fmt = -1, -1, None
    if w < 0 or w * h > max_pixels:
        size = f"{w}x{h} pixels" if w >= 0 else f"over {2 * max_pixels // 10**6} MP"
        raise ValueError(f"{path}: header declares {size}, over the {max_pixels // 10**6} MP limit "
                         "(a decompression bomb or a corrupt header); downscale it or remove it")
    if fmt in ("JPEG", "MPO"):  # MPO: a drone's JPEG with an embedded preview
        check_jpeg_complete(path)


def check_jpeg_complete(path: str | Path) -> None:
    """Raise a one-line ``ValueError`` naming ``path`` if it is a JPEG (by its start-of-image bytes) cut short.
    Any other file passes: decoders stop with a libjpeg warning and fill the rest grey (OpenCV 4.x), so a cut
    copy would otherwise be decoded without a word."""
    path = Path(path)
    with open(path, "rb") as f:
        is_jpeg = f.read(3) == b"\xff\xd8\xff"
    if is_jpeg and not _jpeg_complete(path):
        raise ValueError(f"{path}: truncated JPEG (no end-of-image marker); re-copy or re-save it, or remove it")


def _jpeg_complete(path: Path) -> bool:
    """Whether the primary image of a JPEG has its end-of-image marker: walked from the start past the header
    segments (an EXIF thumbnail inside APP1 holds one of its own) to the first scan, then searched after it. Data
    after the marker (a phone's motion-photo video, an MPO's preview) is allowed; so are stray bytes between two
    segments, which libjpeg skips ("extraneous bytes before marker") as the walk does."""
    import mmap

    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        i, n = 2, len(data)
        while i + 4 <= n:
            if data[i] != 0xFF:  # not a marker: resync at the next 0xFF, as libjpeg's next_marker does
                i = data.find(b"\xff", i)
                if i == -1:
                    return False
                continue
            marker = data[i + 1]
            if marker == 0xDA:  # start of scan: entropy-coded data follows, where 0xFF is always stuffed
                return data.find(b"\xff\xd9", i) != -1
            if marker in (0xFF, 0x00):  # a fill byte; 0xFF 0x00 is no marker (libjpeg skips both)
                i += 1 if marker == 0xFF else 2
                continue
            i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
        return False


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation (1..8; 1 when absent or out of range) Pillow reads from any image's header."""
    from PIL import Image

    with pil_pixel_limit(), Image.open(path) as im:
        return _orientation(im)


def _orientation(im) -> int:
    return exif_orientation_of(im.getexif())


def exif_orientation_of(exif) -> int:
    """The orientation tag (1..8) of a Pillow ``Exif``; 1 when absent or out of range."""
    o = exif.get(0x0112, 1)
    return o if o in range(1, 9) else 1


def image_size(path: str | Path, *, as_shown: bool) -> tuple[int, int]:
    """``(h, w)`` from the header only: as stored, or ``as_shown`` with the EXIF orientation applied (as
    :func:`anycity.data.photos.load_photo` applies it). Posed datasets describe the stored pixels (COLMAP ignores
    the orientation); a photo folder without cameras is read as shown. Raises what Pillow raises on an unreadable
    file; callers name the file and the fix."""
    from PIL import Image

    with pil_pixel_limit(), Image.open(path) as im:
        w, h = im.size
        if as_shown and _orientation(im) in (5, 6, 7, 8):  # rotated by 90 degrees when shown
            w, h = h, w
    return h, w
