"""A folder of one scene's own photos (no poses) -> the network's input, for ``anycity predict``.

Predict keeps each photo's aspect ratio (``mode="keep"``: about H*W pixels, both sides multiples of the patch, the
photo scaled uniformly and centre-cropped by under one patch, so pixels stay square). A folder of mixed aspect
ratios is resized to the most common one (the others are scaled to cover it and centre-cropped), with a warning
naming them. Any number of photos loads lazily, chunk by chunk (:class:`PhotoFolder`); ``anycity.city`` plans the
chunks.
"""

from __future__ import annotations

import hashlib
import os
import stat
import warnings
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch

from anycity.data import imagecheck
from anycity.data.imagecheck import (
    check_image_file,
    exif_orientation,
    exif_orientation_of,
    pil_pixel_limit,
    read_image,
)
from anycity.data.views import jpeg_reduction, resize_plan, resize_view

JPEG_SUFFIXES = (".jpg", ".jpeg", ".jfif", ".jpe")
PHOTO_SUFFIXES = (*JPEG_SUFFIXES, ".png", ".webp")
# Every other visible file of a photo folder is named in a warning as not read, except these sidecars that sit
# beside drone and phone photos: metadata (.xmp, Apple's .aae), DJI's flight logs and RTK timestamps (.srt, .mrk),
# notes and tables (.txt, .json, .csv). Camera raw and HEIF have no decoder here; TIFF is not read either, as where
# its orientation tag is applied differs between OpenCV and Pillow versions (OpenCV 5.0 refuses an oriented TIFF).
SIDECAR_SUFFIXES = (".xmp", ".aae", ".srt", ".mrk", ".txt", ".json", ".csv")
MAX_VIEWS = 64  # views of one forward pass; more photos are reconstructed in chunks (anycity.city)
# Near-copies (one shot saved twice: a JPEG re-saved at q80, a .jpg and a .png export) are told by the rms difference
# of 32x32 greyscale thumbnails (0..255) of photos of one size. Measured (stop 58): one shot re-encoded gives at most
# 3.04 (48x48 synthetic photos re-saved at JPEG q80; q60 4.68; WebP q80 2.36; a .png of a .jpg 0.77, the .jpg
# decoded at 1/8 by libjpeg), 0.8 on real 960-px photos at any quality down to q40; consecutive photos give at least
# 12.68 (a 200-view synthetic orbit, 1.8 degrees apart; 14.77 on its first 40), 32.8 on real_aerial's two scenes (45.6
# on boruszyn_kap). The threshold sits 2x above the first and 2.1x below the second.
# A featureless thumbnail (standard deviation under NEAR_COPY_FLAT: blank sky, a lens cap, or the grey libjpeg fills
# a damaged JPEG's missing data with) is not compared: two of one colour are not told apart from a copy.
NEAR_COPY_SIDE = 32
NEAR_COPY_RMS = 6.0
NEAR_COPY_FLAT = 1.0


def _is_photo(path: Path) -> bool:
    return path.suffix.lower() in PHOTO_SUFFIXES and not path.name.startswith(".")  # not a Mac's ._x.jpg


def check_photo_folder(folder: str | Path) -> Path:
    """``folder`` as a Path, or a one-line error when it is not a folder (``data.predict_images``)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"predict_images: {folder} is not a folder; pass a folder holding one scene's photos")
    return folder


def list_photos(folder: str | Path) -> list[Path]:
    """The photos of ``folder`` (:data:`PHOTO_SUFFIXES`, any case; at least 2), sorted by name.

    Hidden files are not photos: a card copied from a Mac holds a ``._DJI_0001.JPG`` metadata file beside each
    photo. Any other file (camera raw, HEIF, TIFF, BMP, a video, ...) but the sidecars of :data:`SIDECAR_SUFFIXES` is
    named in a warning, as it is not read (in the error, when that leaves under 2 photos). A photo's name on
    anything but a regular file (a FIFO, a device, a folder) is refused in one line. A byte-for-byte copy of an
    earlier photo (by name) is left out with a warning: two copies of one view would be read as two views of the
    place with no parallax between them, as if it were flat.
    """
    folder = check_photo_folder(folder)
    visible = sorted(p for p in folder.iterdir() if not p.name.startswith("."))
    files = [p for p in visible if _is_photo(p)]
    for p in files:
        _check_regular(p)
    copies = _copies(files)
    if copies:
        files = [p for p in files if p not in copies]
        shown = ", ".join(f"{c.name} = {o.name}" for c, o in list(copies.items())[:5]) + (" ..." if len(copies) > 5
                                                                                         else "")
        warnings.warn(f"predict_images: {len(copies)} photo(s) in {folder} are byte-for-byte copies of another and "
                      f"are left out ({shown}): a copy would be read as a second view with no parallax",
                      stacklevel=2)
    unread = [p.name for p in visible
              if p.suffix.lower() not in (*PHOTO_SUFFIXES, *SIDECAR_SUFFIXES) and not p.is_dir()]
    unread_shown = ", ".join(unread[:5]) + (" ..." if len(unread) > 5 else "")
    scenes = [d.name for d in visible if d.is_dir() and any(map(_is_photo, d.iterdir()))] if len(files) < 2 else []
    if unread and (len(files) >= 2 or scenes):  # else the error below names them
        warnings.warn(f"predict_images: {len(unread)} file(s) in {folder} are not read ({unread_shown}): only "
                      f"{'/'.join(PHOTO_SUFFIXES)} photos are; export them as JPEG to use them", stacklevel=2)
    if len(files) < 2:
        only = f" (only {files[0].name})" if files else ""
        only += f" and {len(copies)} byte-for-byte cop{'y' if len(copies) == 1 else 'ies'} of it" if copies else ""
        photos = "1 photo" if files else "no photos"
        if scenes:  # the parent of several scenes' folders
            shown = ", ".join(scenes[:5]) + (" ..." if len(scenes) > 5 else "")
            raise ValueError(f"predict_images: {folder} holds {photos}{only} but sub-folders of photos "
                             f"({shown}); pass one of them: a predict reconstructs one scene")
        if unread:  # a phone's HEIC photos, a camera's raw files: the views are there, in a format not read
            raise ValueError(f"predict_images: {folder} holds {photos}{only} ({'/'.join(PHOTO_SUFFIXES)}) and "
                             f"{len(unread)} file(s) that are not read ({unread_shown}); export them as JPEG or PNG "
                             "to use them: a scene needs at least 2 overlapping photos")
        raise ValueError(f"predict_images: {folder} holds {photos}{only} ({'/'.join(PHOTO_SUFFIXES)}); "
                         "a scene needs at least 2 overlapping photos, so add more views of it")
    return files


def _copies(files: list[Path]) -> dict[Path, Path]:
    """``{copy: original}`` for each of ``files`` with the same bytes as an earlier one; only files of equal size
    are hashed, so a folder of distinct photos is not read here."""
    by_size: dict[int, list[Path]] = {}
    for p in files:
        try:
            by_size.setdefault(p.stat().st_size, []).append(p)
        except OSError:  # a dangling symlink: "cannot decode ..." when it is read
            continue
    copies: dict[Path, Path] = {}
    for size, same in by_size.items():
        if len(same) < 2 or size == 0:  # empty files are refused as undecodable, each by name
            continue
        first: dict[str, Path] = {}
        for p in same:
            h = hashlib.sha1()
            with open(p, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            original = first.setdefault(h.hexdigest(), p)
            if original is not p:
                copies[p] = original
    return copies


def _check_regular(path: Path) -> None:
    """A one-line ``ValueError`` if ``path`` (symlinks followed) is there but is not a regular file: opening a FIFO
    named ``x.jpg`` would wait for a writer forever. A missing one is refused where it is read."""
    try:
        mode = path.stat().st_mode
    except OSError:  # a dangling symlink or a loop: "cannot decode ..." when it is read
        return
    if not stat.S_ISREG(mode):
        kind = "folder" if stat.S_ISDIR(mode) else "FIFO (named pipe)" if stat.S_ISFIFO(mode) else "special file"
        raise ValueError(f"predict_images: {path} is a {kind}, not a photo file; remove it from the folder or rename "
                         "it so that it does not end like a photo")


def near_copies(files: list[Path], headers: dict[Path, PhotoHeader], block: int = 1024) -> list[tuple[Path, Path]]:
    """Pairs of ``files`` that look like one shot saved twice: of one size as shown (``headers``, see
    :func:`photo_header`), with :data:`NEAR_COPY_SIDE`-px greyscale thumbnails less than :data:`NEAR_COPY_RMS` apart
    (rms, 0..255); featureless ones (:data:`NEAR_COPY_FLAT`) are not compared. Each photo of a size shared with
    another is decoded once, a JPEG at up to 1/8 of its size by libjpeg, over threads; the thumbnails are compared
    all at once, ``block`` rows per matrix product. A photo that does not decode is passed over (its loading says
    so, naming it)."""
    by_size: dict[tuple[int, int], list[Path]] = {}
    for p in files:
        by_size.setdefault(headers[p][:2], []).append(p)
    pairs = []
    for same in by_size.values():
        if len(same) < 2:
            continue
        with ThreadPoolExecutor(min(8, os.cpu_count() or 1)) as pool:  # OpenCV decodes without the GIL
            thumbs = list(pool.map(lambda p: _thumbnail(p, headers[p]), same))
        kept = [(p, t) for p, t in zip(same, thumbs) if t is not None and t.std() >= NEAR_COPY_FLAT]
        if len(kept) < 2:
            continue
        named = [p for p, _ in kept]
        T = torch.from_numpy(np.stack([t for _, t in kept]).reshape(len(kept), -1)).float()
        T = T - T.mean(0)  # smaller numbers: the float32 products stay within 0.02 of the rms squared
        sq, d = (T * T).sum(1), T.shape[1]
        for s in range(0, len(named), block):
            d2 = (sq[s:s + block, None] + sq[None] - 2 * T[s:s + block] @ T.T) / d  # mean squared difference
            i, j = torch.nonzero(d2 < NEAR_COPY_RMS ** 2, as_tuple=True)
            pairs += [(named[a], named[b]) for a, b in zip((i + s).tolist(), j.tolist()) if a < b]
    return pairs


def _thumbnail(path: Path, header: PhotoHeader) -> np.ndarray | None:
    """``path`` as a :data:`NEAR_COPY_SIDE`-px square greyscale thumbnail as shown (uint8), None when it does not
    decode. A JPEG is decoded at 1/2, 1/4 or 1/8 when its sides divide (else the last block row would shift it)."""
    h, w = header.h, header.w
    r = jpeg_reduction(h, w, 2 * NEAR_COPY_SIDE, 2 * NEAR_COPY_SIDE) if path.suffix.lower() in JPEG_SUFFIXES else 1
    flag = {1: cv2.IMREAD_GRAYSCALE, 2: cv2.IMREAD_REDUCED_GRAYSCALE_2, 4: cv2.IMREAD_REDUCED_GRAYSCALE_4,
            8: cv2.IMREAD_REDUCED_GRAYSCALE_8}[r]
    grey = imagecheck.read_image(path, flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if grey is None or grey.ndim != 2 or grey.size == 0:
        return None
    grey = oriented(grey, header.orientation)
    return cv2.resize(grey, (NEAR_COPY_SIDE, NEAR_COPY_SIDE), interpolation=cv2.INTER_AREA)


def _warn_near_copies(folder: Path, files: list[Path], headers: dict[Path, PhotoHeader]) -> None:
    """One warning naming each pair of :func:`near_copies` (both are kept: only byte-for-byte copies are left out)."""
    from anycity.city.plan import natural_key

    key = lambda p: natural_key(p.name)  # noqa: E731
    pairs = sorted((tuple(sorted(pair, key=key)) for pair in near_copies(files, headers)),
                   key=lambda pair: (key(pair[0]), key(pair[1])))
    if pairs:
        shown = ", ".join(f"{a.name} ~ {b.name}" for a, b in pairs[:5]) + (" ..." if len(pairs) > 5 else "")
        warnings.warn(f"predict_images: {len(pairs)} pair(s) of photos in {folder} look like one shot saved twice "
                      f"({shown}); both are used, as two views with no parallax between them (read as a flat "
                      "place): remove one of each pair if it is a copy", stacklevel=3)


class PhotoHeader(NamedTuple):
    """What a photo's header says: ``h, w`` as displayed (EXIF orientation applied), the ``orientation`` (1..8),
    the capture ``time`` (:func:`anycity.city.plan.exif_capture_time`) and whether it has ``alpha``."""

    h: int
    w: int
    orientation: int
    time: str | None
    alpha: bool


def photo_header(path: Path) -> PhotoHeader:
    """The :class:`PhotoHeader` of ``path``, from one Pillow open (a PNG's EXIF can follow its pixels, so Pillow
    decodes a PNG to look for it: once here, not once per tag); decompression bombs and truncated JPEGs are refused
    first, before anything is decoded (:func:`anycity.data.imagecheck.check_image_file`)."""
    from PIL import Image

    from anycity.city.plan import exif_capture_time

    if path.is_symlink() and not path.exists():
        raise ValueError(f"predict_images: {path} is a link to a file that does not exist; fix or remove the link")
    try:
        check_image_file(path)
    except ValueError as e:  # its messages name the file and the fix; this names the argument, as the rest here
        raise ValueError(f"predict_images: {e}") from None
    try:
        with pil_pixel_limit(), Image.open(path) as im:
            (w, h), exif = im.size, im.getexif()
            alpha = im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    except Exception as e:  # noqa: BLE001 - any decoder error means the same thing to the user
        raise ValueError(f"predict_images: cannot decode {path} ({type(e).__name__}); re-save it as JPEG or PNG, or "
                         "remove it") from None
    orientation = exif_orientation_of(exif)
    if orientation in (5, 6, 7, 8):  # rotated by 90 degrees when shown
        w, h = h, w
    try:
        time = exif_capture_time(exif)
    except Exception:  # noqa: BLE001 - a damaged EXIF block: no capture time, as for a photo without one
        time = None
    return PhotoHeader(h, w, orientation, time, alpha)


def photo_size(path: Path) -> tuple[int, int]:
    """``(h, w)`` as displayed (EXIF orientation applied), from the header (:func:`photo_header`)."""
    return photo_header(path)[:2]


def common_size(sizes: list[tuple[int, int]], size: tuple[int, int], mode: str = "keep", patch: int = 14
                ) -> tuple[tuple[int, int], list[int]]:
    """Output ``(H, W)`` for photos of ``sizes`` and the indices that do not share the most common aspect ratio.

    ``mode="keep"``: the most common aspect ratio (rounded to 2 %) at about H*W pixels, sides multiples of
    ``patch``; ``"crop"``: ``size`` itself (every photo centre-cropped to it, none are odd).
    """
    if mode == "crop":
        return tuple(size), []
    plans = [resize_plan(h, w, tuple(size), "keep", patch)[2:] for h, w in sizes]
    target, _ = Counter(plans).most_common(1)[0]
    aspect = lambda hw: round(np.log(hw[1] / hw[0]) / 0.02)  # noqa: E731
    odd = [i for i, (p, hw) in enumerate(zip(plans, sizes)) if p != target and aspect(hw) != aspect(target)]
    return target, odd


def load_photo(path: Path, hw: tuple[int, int], mode: str = "keep", patch: int = 14,
               size: tuple[int, int] | None = None, orientation: int | None = None) -> torch.Tensor:
    """One photo -> ``[3, H, W]`` float32 RGB in [0, 1] at exactly ``hw`` (its aspect kept when it matches).

    A JPEG much larger than ``hw`` is decoded at 1/2, 1/4 or 1/8 of its size by libjpeg's DCT scaling (a 20 MP
    drone photo for a 448x672 input: 43 instead of 253 ms with the resize), then area-resized as in full.
    ``size``, ``orientation``: the photo's :func:`photo_header` fields when the caller has read them already.
    """
    def fit(h: int, w: int) -> str:  # the folder's aspect ratio: kept; another one (or mode "crop"): cover, crop
        return "keep" if mode == "keep" and resize_plan(h, w, hw, "keep", patch)[2:] == tuple(hw) else "crop"

    r = 1
    if path.suffix.lower() in JPEG_SUFFIXES:
        h, w = size or photo_size(path)  # as shown
        r = jpeg_reduction(h, w, *resize_plan(h, w, hw, fit(h, w), patch)[:2])
    flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8}[r]
    # the orientation from where photo_size read it (Pillow), not OpenCV's: a PNG's ImageMagick "Raw profile type
    # exif" chunk is one that Pillow reads and OpenCV does not, which left such a photo sideways and cropped
    bgr = read_image(path, flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if bgr is None:
        raise ValueError(f"predict_images: cannot decode {path}; re-save it as JPEG or PNG, or remove it")
    bgr = oriented(bgr, exif_orientation(path) if orientation is None else orientation)
    h, w = bgr.shape[0] * r, bgr.shape[1] * r  # the full size (r divides both sides)
    K = np.array([[max(h, w), 0, w / 2], [0, max(h, w), h / 2], [0, 0, 1]], np.float64)  # unused placeholder
    rgb, *_ = resize_view(np.ascontiguousarray(bgr[..., ::-1]), K, hw, fit(h, w), patch, src_hw=(h, w))
    return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float() / 255


def oriented(img: np.ndarray, orientation: int) -> np.ndarray:
    """``img [H, W, C]`` as shown for an EXIF ``orientation`` (1..8): flipped and/or turned by 90-degree steps."""
    turned = {1: img, 2: img[:, ::-1], 3: img[::-1, ::-1], 4: img[::-1], 5: img.swapaxes(0, 1),
              6: np.rot90(img, -1), 7: img.swapaxes(0, 1)[::-1, ::-1], 8: np.rot90(img, 1)}
    return np.ascontiguousarray(turned.get(orientation, img))


GENERIC_FOLDERS = {"images", "imgs", "image", "photos", "input", "inputs", "rgb", "jpg", "jpgs"}
# file names may hold 255 bytes; the outputs' hidden siblings (".<scene>.anycity_city_work", ".<scene>.partial",
# ".<scene>.anycity-run.lock", ...) add up to 30 to the scene's name
MAX_SCENE_NAME_BYTES = 200


def folder_scene_name(folder: Path, generic: set[str] | frozenset[str] = frozenset(GENERIC_FOLDERS)) -> str:
    """``folder``'s own name, or its parent's when its own is one of ``generic`` (any case)."""
    return folder.parent.name if folder.name.lower() in generic and folder.parent.name else folder.name


def scene_name(folder: Path) -> str:
    """The scene's name for outputs: the folder's own name, or its parent's when the folder has a generic name
    (``boruszyn_kap/images`` -> ``boruszyn_kap``, as in the COLMAP / nerfstudio layouts). A name over
    :data:`MAX_SCENE_NAME_BYTES` (UTF-8) is cut there and given 8 hex digits of its hash, with a warning."""
    folder = Path(os.path.abspath(folder))  # a symlinked folder keeps its own name, not its target's
    name = folder_scene_name(folder)
    raw = name.encode("utf-8", "surrogateescape")
    if len(raw) <= MAX_SCENE_NAME_BYTES:
        return name
    short, size = "", 0
    for ch in name:  # whole characters, up to the budget less "-" and the hash
        size += len(ch.encode("utf-8", "surrogateescape"))
        if size > MAX_SCENE_NAME_BYTES - 9:
            break
        short += ch
    short = f"{short}-{hashlib.sha1(raw).hexdigest()[:8]}"
    warnings.warn(f"predict_images: the scene's name ({name[:40]}..., {len(raw)} bytes) is too long for its output "
                  f"files; they are named {short}", stacklevel=2)
    return short


class PhotoFolder:
    """The photos of one folder, in capture order, loaded on demand at one common size.

    Args:
        folder: one scene's photos (2 or more).
        size: ``(H, W)``: the pixel budget (``mode="keep"``) or the exact size (``"crop"``).
        mode: "keep" (predict's default: each aspect ratio kept, cropped by under one patch) or "crop".
        patch: side multiple for "keep".
        order: "auto" (capture time when every photo has one, else file name), "time" or "name" (for "tokens",
            load by name, then :meth:`reorder`).
    Attributes:
        files, names (in order), hw ``(H, W)``, ordered_by ("time"/"name").
    """

    def __init__(self, folder: str | Path, size: tuple[int, int], mode: str = "keep", patch: int = 14,
                 order: str = "auto") -> None:
        from anycity.city.plan import order_photos

        self.folder = Path(folder)
        files = list_photos(self.folder)
        self._headers = {f: photo_header(f) for f in files}  # read once: load reuses them
        _warn_near_copies(self.folder, files, self._headers)
        idx, self.ordered_by = order_photos(files, order, [self._headers[f].time for f in files])
        self.files = [files[i] for i in idx]
        self.names = [f.name for f in self.files]
        self.mode, self.patch = mode, patch
        alpha = [f.name for f in self.files if self._headers[f].alpha]
        if alpha:
            shown = ", ".join(alpha[:5]) + (" ..." if len(alpha) > 5 else "")
            warnings.warn(f"predict_images: {len(alpha)} photo(s) in {self.folder} have transparency ({shown}); it "
                          "is not read: a transparent pixel goes in as the colour stored under it (often black). "
                          "Flatten them onto the background you want to use them as intended", stacklevel=2)
        self.hw, odd = common_size([self._headers[f][:2] for f in self.files], tuple(size), mode, patch)
        if odd:
            shown = ", ".join(self.names[i] for i in odd[:5]) + (" ..." if len(odd) > 5 else "")
            warnings.warn(f"predict_images: {len(odd)} of {len(self.files)} photos in {self.folder} ({shown}) have "
                          f"another aspect ratio than the most common one; they are scaled and centre-cropped to "
                          f"{self.hw[1]}x{self.hw[0]} (width x height) like the rest", stacklevel=2)

    def __len__(self) -> int:
        return len(self.files)

    def reorder(self, order: list[int], ordered_by: str) -> None:
        """Put the photos in ``order`` (indices into the current order)."""
        if sorted(order) != list(range(len(self))):
            raise ValueError(f"PhotoFolder.reorder: expected a permutation of {len(self)} indices")
        self.files = [self.files[i] for i in order]
        self.names = [f.name for f in self.files]
        self.ordered_by = ordered_by

    def load(self, indices: list[int] | None = None) -> torch.Tensor:
        """``[V, 3, H, W]`` float32 of the photos at ``indices`` (all by default)."""
        indices = range(len(self)) if indices is None else indices
        heads = [self._headers[self.files[i]] for i in indices]
        return torch.stack([load_photo(self.files[i], self.hw, self.mode, self.patch, (hd.h, hd.w), hd.orientation)
                            for i, hd in zip(indices, heads)])


def load_photo_folder(folder: str | Path, size: tuple[int, int], mode: str = "keep", patch: int = 14,
                      order: str = "auto") -> dict:
    """Every photo of ``folder`` (see :class:`PhotoFolder`) at once.

    Returns:
        ``{"images": [V, 3, H, W] float32 in [0, 1], "scene": :func:`scene_name`, "names": file names}``.
    """
    photos = PhotoFolder(folder, size, mode, patch, order)
    return {"images": photos.load(), "scene": scene_name(photos.folder), "names": photos.names}
