"""Shard schema: what one webdataset sample (one trajectory window of a scene) holds, and how to decode it.

A sample is a set of tar members ``<key>.<member>`` with ``<key>`` free of dots:

* ``NNN.jpg`` or ``NNN.png``: view ``NNN`` of the sample (8-bit sRGB).
* ``NNN.depth.npy``: optional z-depth (float16/float32, the scene's world units, 0 = invalid).
* ``NNN.normal.npy``: optional unit normals in the view's OpenCV camera frame, octahedral-encoded as ``[H, W, 2]``
  uint8 (:func:`encode_normals`; an error of 0.34 deg on average and up to about 1 deg (0.95 deg at most over a
  million random unit normals), a third of the bytes of float16 xyz; the code of +z, which no visible surface has,
  means "no normal"). Written only on request (``anycity data synth --normals``): no loss
  consumes ground-truth normals, and the reader derives them from depth (as
  :func:`anycity.geometry.depth_to_normals` does) when asked for normals the shard lacks; float16 depth of
  distant aerial views makes those derived normals noisy, so store them when they matter.
* ``NNN.mask.png``: optional validity mask (255 = valid depth/normal, 0 = sky or unknown); not written when it
  equals ``depth > 0``, which is what the reader assumes without it.
* ``cameras.json``: ``schema_version``, ``scene`` (scene id), ``key`` (sample key), ``source``, ``units``,
  ``metres_per_unit`` (or null), ``world_from_source`` (the 4x4 similarity the converter applied,
  ``p_stored = T @ p_source``, scale included), ``split``, ``extra``, ``window`` (``first``: scene position of
  the first view, ``scene_views``: views in the whole scene, ``own``: ``[lo, hi)`` scene positions whose
  llffhold targets this sample scores; overlapping windows own disjoint ranges) and ``views``: per view ``name``
  (source file name), ``image``, ``depth``, ``normal``, ``mask`` (member names or null), ``w2c`` (OpenCV 4x4),
  ``K`` (3x3, pixels of the stored image), ``width``, ``height``, ``index`` (position along the scene's
  trajectory, so llffhold and scene splits are the same whatever the windowing).

Version history: 1 = one sample per scene, float16 normals and masks always written; 2 = trajectory windows,
``window`` and ``key`` in ``cameras.json``, scene positions in ``index``, optional octahedral normals, masks only
when they differ from ``depth > 0``.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from anycity.data.imagecheck import pil_pixel_limit
from anycity.geometry import camera_problem

SCHEMA_VERSION = 2
CAMERAS_KEY = "cameras.json"
NORMAL_FRAME = "camera_opencv"


def view_keys(i: int, image_ext: str = "jpg") -> dict[str, str]:
    """Member names of view ``i``."""
    s = f"{i:03d}" if i < 1000 else f"{i:05d}"
    return {"image": f"{s}.{image_ext}", "depth": f"{s}.depth.npy", "normal": f"{s}.normal.npy",
            "mask": f"{s}.mask.png"}


def check_key(key: str) -> str:
    """Validate a sample key (webdataset splits member names at the first dot)."""
    if not key or "." in key or "/" in key:
        raise ValueError(f"sample key {key!r}: expected a non-empty name without '.' or '/'; replace them, "
                         "e.g. key.replace('.', '_')")
    return key


@dataclass
class ViewRecord:
    """One view before encoding. ``image`` is ``[H, W, 3]`` uint8 RGB or already-encoded bytes (with ``ext``)."""

    name: str
    image: np.ndarray | bytes
    w2c: np.ndarray
    K: np.ndarray
    width: int
    height: int
    depth: np.ndarray | None = None
    normal: np.ndarray | None = None
    mask: np.ndarray | None = None
    ext: str = "jpg"


@dataclass
class SceneRecord:
    """One sample: a scene or a window of a trajectory, in the converter's output world frame.

    ``scene`` (default ``key``), ``first_index`` (scene position of ``views[0]``), ``scene_views`` (views in the
    whole scene, default ``first_index + len(views)``) and ``own`` (``[lo, hi)`` scene positions this sample
    scores in evaluation, default all of its views) place a window in its scene.
    """

    key: str
    views: list[ViewRecord]
    source: str
    units: str
    metres_per_unit: float | None = None
    world_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    extra: dict[str, Any] = field(default_factory=dict)
    scene: str | None = None
    first_index: int = 0
    scene_views: int | None = None
    own: tuple[int, int] | None = None


def window_bounds(n: int, size: int | None, stride: int | None = None) -> list[tuple[int, int, int, int]]:
    """``(start, stop, own_lo, own_hi)`` of windows of ``size`` consecutive views every ``stride`` views over an
    n-view trajectory; the last window ends at ``n``; the own ranges partition ``[0, n)`` (each view belongs to
    the window whose centre is nearest). ``size`` None or >= n: one window."""
    if size is None or size >= n:
        return [(0, n, 0, n)]
    stride = size // 2 if stride is None else stride
    if size < 2 or not 1 <= stride <= size:
        raise ValueError(f"window: expected size >= 2 and 1 <= stride <= size, got size={size}, stride={stride}; "
                         "pass --window of at least 2 views and a --stride from 1 to --window (or no --stride)")
    starts = sorted(set(range(0, n - size, stride)) | {n - size})
    cuts = [0] + [(a + b + size) // 2 for a, b in zip(starts[:-1], starts[1:])] + [n]
    return [(s, s + size, cuts[i], cuts[i + 1]) for i, s in enumerate(starts)]


def split_windows(rec: SceneRecord, size: int | None, stride: int | None = None) -> list[SceneRecord]:
    """Cut a scene record into overlapping trajectory windows (keys ``<key>_wNNNN``, NNNN the first position)."""
    n = len(rec.views)
    bounds = window_bounds(n, size, stride)
    if len(bounds) == 1:
        return [rec]
    f = rec.first_index
    own = rec.own if rec.own is not None else (f, f + n)
    out = []
    for a, b, lo, hi in bounds:
        out.append(SceneRecord(
            key=check_key(f"{rec.key}_w{f + a:04d}"), views=rec.views[a:b], source=rec.source, units=rec.units,
            metres_per_unit=rec.metres_per_unit, world_from_source=rec.world_from_source, extra=rec.extra,
            scene=rec.scene or rec.key, first_index=f + a, scene_views=rec.scene_views or f + n,
            own=(max(own[0], f + lo), min(own[1], f + hi))))
    return out


def check_version(meta: dict, where: str) -> None:
    """Raise if a sample's ``cameras.json`` was written by another schema version."""
    got = meta.get("schema_version")
    if got != SCHEMA_VERSION:
        raise ValueError(f"{where}: written with shard schema_version {got}, but this anycity reads "
                         f"schema_version {SCHEMA_VERSION}; re-create the shards with `anycity data synth` or "
                         "`anycity data convert` from this version")


def encode_npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def decode_npy(b: bytes) -> np.ndarray:
    return np.load(io.BytesIO(b), allow_pickle=False)


def encode_normals(n: np.ndarray) -> np.ndarray:
    """``[H, W, 3]`` unit normals (zero = none) -> ``[H, W, 2]`` uint8 octahedral codes (127 is 0; (127, 127),
    the code of +z, means none)."""
    n = np.asarray(n, np.float32)
    l1 = np.abs(n).sum(-1, keepdims=True)
    p = np.divide(n[..., :2], l1, out=np.zeros_like(n[..., :2]), where=l1 > 0)
    folded = (1 - np.abs(p[..., ::-1])) * np.where(p >= 0, 1.0, -1.0)
    p = np.where((n[..., 2:] < 0), folded, p)
    return np.round(p * 127 + 127).astype(np.uint8)


def decode_normals(c: np.ndarray) -> np.ndarray:
    """Inverse of :func:`encode_normals`: ``[H, W, 2]`` uint8 -> ``[H, W, 3]`` float32 unit normals (zero = none).
    ``[H, W, 3]`` float arrays (plain xyz) pass through as float32."""
    if c.ndim == 3 and c.shape[-1] == 3:
        return c.astype(np.float32)
    p = np.clip(c.astype(np.float32) / 127 - 1, -1, 1)
    z = 1 - np.abs(p).sum(-1, keepdims=True)
    folded = (1 - np.abs(p[..., ::-1])) * np.where(p >= 0, 1.0, -1.0)
    n = np.concatenate([np.where(z < 0, folded, p), z], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[(c[..., 0] == 127) & (c[..., 1] == 127)] = 0
    return n


def encode_image(rgb: np.ndarray, ext: str, quality: int = 95) -> bytes:
    """``[H, W, 3]`` uint8 RGB (or ``[H, W]`` gray) -> jpg/png bytes."""
    img = rgb[..., ::-1] if rgb.ndim == 3 else rgb
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if ext in ("jpg", "jpeg") else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode("." + ext, np.ascontiguousarray(img), params)
    if not ok:
        raise ValueError(f"could not encode an image as {ext}")
    return buf.tobytes()


def decode_image(b: bytes, gray: bool = False, reduce: int = 1) -> np.ndarray:
    """jpg/png bytes -> ``[H, W, 3]`` uint8 RGB (or ``[H, W]`` with ``gray``); raises on corrupt data.

    ``reduce`` 2, 4 or 8 decodes a JPEG at that fraction of its size (libjpeg's DCT scaling: much faster than
    decoding in full and resizing; the result covers the same field of view, ``ceil(side / reduce)`` pixels).
    The stored pixels: a JPEG's EXIF orientation is not applied, as the shard's cameras describe them unrotated.
    """
    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    if reduce > 1:
        flag = {(2, False): cv2.IMREAD_REDUCED_COLOR_2, (4, False): cv2.IMREAD_REDUCED_COLOR_4,
                (8, False): cv2.IMREAD_REDUCED_COLOR_8, (2, True): cv2.IMREAD_REDUCED_GRAYSCALE_2,
                (4, True): cv2.IMREAD_REDUCED_GRAYSCALE_4, (8, True): cv2.IMREAD_REDUCED_GRAYSCALE_8}[reduce, gray]
    arr = cv2.imdecode(np.frombuffer(b, np.uint8), flag | cv2.IMREAD_IGNORE_ORIENTATION)
    if arr is None:
        raise ValueError("undecodable image bytes")
    return arr if gray else cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)


def _stored_hw(image: np.ndarray | bytes) -> tuple[int, int] | None:
    """``(h, w)`` of an image array, or of encoded bytes from their header (None when unreadable)."""
    if not isinstance(image, bytes):
        return tuple(np.shape(image)[:2])
    from PIL import Image, UnidentifiedImageError

    try:
        with pil_pixel_limit(1 << 62), Image.open(io.BytesIO(image)) as im:  # the header only: no size limit
            return im.size[::-1]
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError):
        return None


def view_problem(v: ViewRecord) -> str | None:
    """What makes one view unfit for a shard, or None: an unsound camera (:func:`anycity.geometry.camera_problem`),
    or an image, depth (``[H, W]``), normal (``[H, W, 3]``) or mask (``[H, W]``) that is not ``height`` x ``width``."""
    problem = camera_problem(v.w2c, v.K)
    if problem:
        return problem
    want = (int(v.height), int(v.width))
    if min(want) < 1:
        return f"width x height {v.width}x{v.height}; expected positive sides"
    for name, a in (("image", v.image), ("depth", v.depth), ("normal", v.normal), ("mask", v.mask)):
        if a is None:
            continue
        got = _stored_hw(a)
        if got is None:
            return f"image bytes are not a readable {v.ext} file"
        if got != want or (name in ("depth", "mask") and np.ndim(a) != 2):
            shape = "x".join(map(str, got if isinstance(a, bytes) else np.shape(a)))
            return f"{name} is {shape}, expected {want[0]}x{want[1]} (the view's height x width)"
    return None


def encode_scene(rec: SceneRecord, split: str, depth_dtype: str = "float16", check: bool = True) -> dict[str, Any]:
    """SceneRecord -> webdataset sample dict (bytes values), ``cameras.json`` included.

    Normals are written when the views carry them; a mask only when it differs from ``depth > 0``. ``check``: refuse
    in one line, naming the sample key and view, a view with a :func:`view_problem`.
    """
    sample: dict[str, Any] = {"__key__": check_key(rec.key)}
    views = []
    for i, v in enumerate(rec.views):
        problem = view_problem(v) if check else None
        if problem:
            raise ValueError(f"sample {rec.key!r} view {i} ({v.name}): {problem}; fix that view or leave it out")
        keys = view_keys(i, v.ext)
        sample[keys["image"]] = v.image if isinstance(v.image, bytes) else encode_image(v.image, v.ext)
        entry: dict[str, Any] = {"name": v.name, "image": keys["image"], "depth": None, "normal": None, "mask": None,
                                 "w2c": np.asarray(v.w2c, float).tolist(), "K": np.asarray(v.K, float).tolist(),
                                 "width": int(v.width), "height": int(v.height), "index": rec.first_index + i}
        depth = None if v.depth is None else np.asarray(v.depth, depth_dtype)
        if depth is not None:
            sample[keys["depth"]] = encode_npy(depth)
            entry["depth"] = keys["depth"]
        if v.normal is not None:
            sample[keys["normal"]] = encode_npy(encode_normals(v.normal))
            entry["normal"] = keys["normal"]
        if v.mask is not None:
            mask = np.asarray(v.mask, bool)
            if depth is None or not np.array_equal(mask, depth > 0):
                sample[keys["mask"]] = encode_image(mask.astype(np.uint8) * 255, "png")
                entry["mask"] = keys["mask"]
        views.append(entry)
    n = len(rec.views)
    own = rec.own if rec.own is not None else (rec.first_index, rec.first_index + n)
    meta = {"schema_version": SCHEMA_VERSION, "scene": rec.scene or rec.key, "key": rec.key, "source": rec.source,
            "units": rec.units, "metres_per_unit": rec.metres_per_unit, "depth": {"kind": "z", "units": rec.units},
            "normal_frame": NORMAL_FRAME, "world_from_source": np.asarray(rec.world_from_source, float).tolist(),
            "split": split, "extra": rec.extra,
            "window": {"first": rec.first_index, "scene_views": rec.scene_views or rec.first_index + n,
                       "own": [int(own[0]), int(own[1])]},
            "views": views}
    sample[CAMERAS_KEY] = json.dumps(meta).encode()
    return sample


def sample_where(sample: dict) -> str:
    return f"shard {sample.get('__url__', '?')} sample {sample.get('__key__', '?')}"


def read_meta(sample: dict) -> dict:
    """Parse and version-check ``cameras.json``; errors name the shard and key."""
    where = sample_where(sample)
    if CAMERAS_KEY not in sample:
        raise ValueError(f"{where}: missing key {CAMERAS_KEY!r} (has {sorted(k for k in sample if k[0] != '_')[:6]}); "
                         "the shard was not written by anycity or is truncated")
    try:
        meta = json.loads(member(sample, CAMERAS_KEY))
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{where}: key {CAMERAS_KEY!r} is not valid JSON ({e}); re-create the shard") from e
    check_version(meta, where)
    return meta


def member(sample: dict, key: str | None) -> bytes:
    """Raw bytes of a member (read now when it is a lazy :class:`~anycity.data.tario.Member`), with an error
    naming shard and key when it is missing."""
    if key is None or key not in sample:
        raise ValueError(f"{sample_where(sample)}: missing key {key!r}; the shard is incomplete, re-create it")
    v = sample[key]
    return v if isinstance(v, bytes) else v.read()
