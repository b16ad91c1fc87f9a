"""Cheap checks of an image file before decoding it: refuse decompression bombs and truncated JPEGs; its size as
stored or as shown (:func:`image_size`).

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
    if fmt == "JPEG":
        with open(path, "rb") as f:
            f.seek(max(0, path.stat().st_size - 4096))
            tail = f.read().rstrip(b"\x00")
        if not tail.endswith(b"\xff\xd9"):
            raise ValueError(f"{path}: truncated JPEG (no end-of-image marker); re-copy or re-save it, or remove it")


def image_size(path: str | Path, *, as_shown: bool) -> tuple[int, int]:
    """``(h, w)`` from the header only: as stored, or ``as_shown`` with the EXIF orientation applied as OpenCV's
    decoders apply it. Posed datasets describe the stored pixels (COLMAP ignores the orientation); a photo folder
    without cameras is read as shown. Raises what Pillow raises on an unreadable file; callers name the file and the
    fix."""
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
        if as_shown and im.getexif().get(0x0112, 1) in (5, 6, 7, 8):  # rotated by 90 degrees when shown
            w, h = h, w
    return h, w
