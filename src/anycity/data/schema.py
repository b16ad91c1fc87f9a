"""Shard schema: what one webdataset sample (one scene or trajectory window) holds, and how to decode it.

A sample is a set of tar members ``<key>.<member>`` with ``<key>`` free of dots:

* ``NNN.jpg`` or ``NNN.png``: view ``NNN`` (8-bit sRGB).
* ``NNN.depth.npy``: optional z-depth (float16/float32, the scene's world units, 0 = invalid).
* ``NNN.normal.npy``: optional unit normals ``[H, W, 3]`` (float16) in the view's OpenCV camera frame.
* ``NNN.mask.png``: optional validity mask (255 = valid depth/normal, 0 = sky or unknown).
* ``cameras.json``: ``schema_version``, ``scene``, ``source``, ``units``, ``metres_per_unit`` (or null),
  ``world_from_source`` (the 4x4 similarity the converter applied, ``p_stored = T @ p_source``, scale
  included), ``split``, ``extra`` and ``views``: per view ``name`` (source file name), ``image``, ``depth``,
  ``normal``, ``mask`` (member names or null), ``w2c`` (OpenCV 4x4), ``K`` (3x3, pixels of the stored image),
  ``width``, ``height``, ``index`` (position along the trajectory).
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

SCHEMA_VERSION = 1
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
    """One sample: a scene or a window of a trajectory, in the converter's output world frame."""

    key: str
    views: list[ViewRecord]
    source: str
    units: str
    metres_per_unit: float | None = None
    world_from_source: np.ndarray = field(default_factory=lambda: np.eye(4))
    extra: dict[str, Any] = field(default_factory=dict)


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


def encode_image(rgb: np.ndarray, ext: str, quality: int = 95) -> bytes:
    """``[H, W, 3]`` uint8 RGB (or ``[H, W]`` gray) -> jpg/png bytes."""
    img = rgb[..., ::-1] if rgb.ndim == 3 else rgb
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if ext in ("jpg", "jpeg") else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode("." + ext, np.ascontiguousarray(img), params)
    if not ok:
        raise ValueError(f"could not encode an image as {ext}")
    return buf.tobytes()


def decode_image(b: bytes, gray: bool = False) -> np.ndarray:
    """jpg/png bytes -> ``[H, W, 3]`` uint8 RGB (or ``[H, W]`` with ``gray``); raises on corrupt data."""
    arr = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR)
    if arr is None:
        raise ValueError("undecodable image bytes")
    return arr if gray else arr[..., ::-1]


def encode_scene(rec: SceneRecord, split: str, depth_dtype: str = "float16") -> dict[str, Any]:
    """SceneRecord -> webdataset sample dict (bytes values), ``cameras.json`` included."""
    sample: dict[str, Any] = {"__key__": check_key(rec.key)}
    views = []
    for i, v in enumerate(rec.views):
        keys = view_keys(i, v.ext)
        sample[keys["image"]] = v.image if isinstance(v.image, bytes) else encode_image(v.image, v.ext)
        entry: dict[str, Any] = {"name": v.name, "image": keys["image"], "depth": None, "normal": None, "mask": None,
                                 "w2c": np.asarray(v.w2c, float).tolist(), "K": np.asarray(v.K, float).tolist(),
                                 "width": int(v.width), "height": int(v.height), "index": i}
        if v.depth is not None:
            sample[keys["depth"]] = encode_npy(np.asarray(v.depth, depth_dtype))
            entry["depth"] = keys["depth"]
        if v.normal is not None:
            sample[keys["normal"]] = encode_npy(np.asarray(v.normal, np.float16))
            entry["normal"] = keys["normal"]
        if v.mask is not None:
            sample[keys["mask"]] = encode_image(np.asarray(v.mask, np.uint8) * 255, "png")
            entry["mask"] = keys["mask"]
        views.append(entry)
    meta = {"schema_version": SCHEMA_VERSION, "scene": rec.key, "source": rec.source, "units": rec.units,
            "metres_per_unit": rec.metres_per_unit, "depth": {"kind": "z", "units": rec.units},
            "normal_frame": NORMAL_FRAME, "world_from_source": np.asarray(rec.world_from_source, float).tolist(),
            "split": split, "extra": rec.extra, "views": views}
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
        meta = json.loads(sample[CAMERAS_KEY])
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{where}: key {CAMERAS_KEY!r} is not valid JSON ({e}); re-create the shard") from e
    check_version(meta, where)
    return meta


def member(sample: dict, key: str | None) -> bytes:
    """Raw bytes of a member, with an error naming shard and key when it is missing."""
    if key is None or key not in sample:
        raise ValueError(f"{sample_where(sample)}: missing key {key!r}; the shard is incomplete, re-create it")
    return sample[key]
