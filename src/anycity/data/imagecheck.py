"""Cheap checks of an image file before decoding it: refuse decompression bombs and truncated JPEGs; its size as
stored or as shown (:func:`image_size`). The converters, which decode with OpenCV, check JPEGs for truncation only
(:func:`check_jpeg_complete`).

The header is read without decoding pixels (PIL opens lazily), so a 30000 x 30000 header costs nothing.
"""

from __future__ import annotations

from pathlib import Path

MAX_PIXELS = 100_000_000  # 100 MP: larger than any aerial photo we resize to a few hundred pixels


def check_image_file(path: str | Path, max_pixels: int = MAX_PIXELS) -> None:
    """Raise a one-line ``ValueError`` naming ``path`` if its header declares more than ``max_pixels`` pixels,
    it cannot be identified as an image, or it is a JPEG cut short (no end-of-image marker)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:  # header only
            w, h = im.size
            fmt = im.format
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise ValueError(f"cannot decode {path}: not a readable image ({type(e).__name__}); re-save it as JPEG "
                         "or PNG, or remove it") from None
    except Image.DecompressionBombError:
        w, h, fmt = -1, -1, None
    if w < 0 or w * h > max_pixels:
        raise ValueError(f"{path}: header declares {w}x{h} pixels, over the {max_pixels // 10**6} MP limit "
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
    after the marker (a phone's motion-photo video, an MPO's preview) is allowed."""
    import mmap

    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        i, n = 2, len(data)
        while i + 4 <= n and data[i] == 0xFF:
            marker = data[i + 1]
            if marker == 0xDA:  # start of scan: entropy-coded data follows, where 0xFF is always stuffed
                return data.find(b"\xff\xd9", i) != -1
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
        return False


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation (1..8; 1 when absent or out of range) Pillow reads from any image's header."""
    from PIL import Image

    with Image.open(path) as im:
        return _orientation(im)


def _orientation(im) -> int:
    o = im.getexif().get(0x0112, 1)
    return o if o in range(1, 9) else 1


def image_size(path: str | Path, *, as_shown: bool) -> tuple[int, int]:
    """``(h, w)`` from the header only: as stored, or ``as_shown`` with the EXIF orientation applied (as
    :func:`anycity.data.photos.load_photo` applies it). Posed datasets describe the stored pixels (COLMAP ignores
    the orientation); a photo folder without cameras is read as shown. Raises what Pillow raises on an unreadable
    file; callers name the file and the fix."""
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
        if as_shown and _orientation(im) in (5, 6, 7, 8):  # rotated by 90 degrees when shown
            w, h = h, w
    return h, w
