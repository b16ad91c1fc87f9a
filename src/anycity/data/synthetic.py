"""Built-in synthetic aerial cities: procedural city + aerial trajectory + exact ray casting -> shards.

``anycity data synth --out DIR --scenes N --views V --size HxW --seed S --trajectory orbit|nadir|mixed``

Each scene is V views (RGB, z-depth in metres, optionally camera-frame normals; the sky mask is ``depth > 0``)
along one trajectory, written as overlapping trajectory windows of ``window`` views (training split; see
:class:`~anycity.data.writer.ShardSetWriter`). Trajectories reproduce the evidence imbalance of real captures:
*orbit* circles the city at 30-60 deg pitch (GoogleEarth / MatrixCity-like), *nadir* flies a serpentine
lawnmower grid looking straight down, *mixed* picks orbit, nadir or an oblique (45 deg forward) lawnmower per
scene. Everything is deterministic
from ``(seed, scene index)``.
"""

from __future__ import annotations

import ctypes
import math
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from anycity.atomic import atomic_write_bytes
from anycity.data.city import City, make_city
from anycity.data.raycast import SceneTensors, fov_intrinsics, look_at, render
from anycity.data.schema import SceneRecord, ViewRecord, decode_image, decode_npy, encode_image
from anycity.data.writer import PREVIEW_NAME, ShardSetWriter, split_scenes
from anycity.geometry import depth_to_normals, rescale_intrinsics

TRAJECTORIES = ("orbit", "nadir", "mixed")
HFOV_DEG = 60.0
_PR_SET_PDEATHSIG = 1  # linux/prctl.h


def parse_size(size: str | tuple[int, int] | list[int]) -> tuple[int, int]:
    """``"HxW"`` (or ``"S"``, or a pair) -> ``(H, W)``."""
    if isinstance(size, (tuple, list)):
        if len(size) != 2:
            raise ValueError(f"size: expected (H, W), got {size!r}")
        h, w = int(size[0]), int(size[1])
    else:
        parts = str(size).lower().split("x")
        try:
            h, w = (int(parts[0]), int(parts[-1])) if len(parts) <= 2 else (-1, -1)
        except ValueError:
            h = w = -1
    if h < 8 or w < 8:
        raise ValueError(f"size: expected HxW with both sides >= 8 pixels, e.g. 128x128, got {size!r}")
    return h, w


def trajectory(kind: str, n: int, city: City, rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """``[n, 4, 4]`` OpenCV world-to-camera poses in trajectory order, and the kind actually used."""
    if kind == "mixed":
        kind = str(rng.choice(["orbit", "nadir", "oblique"]))
    E, top = city.half_extent, city.max_height
    poses = []
    if kind == "orbit":
        pitch = math.radians(rng.uniform(30, 60))
        dist = max(E * rng.uniform(1.1, 1.6), (top + 25) / math.sin(pitch))
        target = np.r_[rng.uniform(-0.15, 0.15, 2) * E, 0.0]
        az0 = rng.uniform(0, 2 * math.pi)
        for k in range(n):
            az = az0 + 2 * math.pi * (k + rng.uniform(-0.25, 0.25)) / n
            p = pitch + math.radians(rng.uniform(-3, 3))
            d = dist * rng.uniform(0.95, 1.05)
            eye = target + d * np.array([math.cos(p) * math.cos(az), math.cos(p) * math.sin(az), math.sin(p)])
            poses.append(look_at(eye, target + np.r_[rng.normal(0, 0.03 * E, 2), 0.0]))
    elif kind in ("nadir", "oblique"):
        alt = max(E * rng.uniform(0.7, 1.0), top + 30)
        rows = max(1, round(math.sqrt(n)))
        cols = math.ceil(n / rows)
        span = 0.7 * E
        ys = np.linspace(-span, span, rows) if rows > 1 else np.zeros(1)
        xs = np.linspace(-span, span, cols) if cols > 1 else np.zeros(1)
        for k in range(n):
            r, c = divmod(k, cols)
            fwd = 1.0 if r % 2 == 0 else -1.0
            x = xs[c] if fwd > 0 else xs[cols - 1 - c]
            eye = np.array([x, ys[r], alt * rng.uniform(0.97, 1.03)]) + np.r_[rng.normal(0, 0.02 * E, 2), 0]
            heading = np.array([fwd, 0.0, 0.0])
            if kind == "nadir":  # the top of the image points along the flight line, however far the view tilts
                tilt = rng.normal(0, 0.015, 2)
                poses.append(look_at(eye, eye + np.r_[tilt, -1.0], up=heading, heading=heading))
            else:  # the camera trails the grid point by the altitude (45 deg) and the pitch jitter moves what it
                # looks at, not the camera: the camera steps forward along its flight line at every view
                ahead = eye[2] / math.tan(math.radians(45 + rng.uniform(-4, 4)))
                cam = np.r_[eye[:2] - alt * heading[:2], eye[2]]
                poses.append(look_at(cam, np.r_[cam[:2] + ahead * heading[:2], 0.0]))
    else:
        raise ValueError(f"trajectory: expected one of {TRAJECTORIES}, got {kind!r}")
    return np.stack(poses), kind


def render_view(scene: SceneTensors, w2c: Tensor, K: Tensor, h: int, w: int, aa: bool = True,
                supersample: int = 1) -> dict[str, Tensor]:
    """Ray-cast one view; ``supersample`` k > 1 box-filters colour over a k x k grid of sub-pixel rays (what a
    camera pixel integrates: texture detail finer than a pixel averages out instead of aliasing differently in
    every view). Depth, normals and the mask stay those of the pixel-centre ray."""
    r = render(scene, w2c, K, h, w, aa=aa and supersample == 1)
    if supersample > 1:
        k = int(supersample)
        fine = render(scene, w2c, rescale_intrinsics(K, k, k), k * h, k * w, aa=aa)["rgb"]
        r["rgb"] = fine.view(h, k, w, k, 3).mean(dim=(1, 3))
    return r


def render_scene(seed: int, index: int, views: int, size: tuple[int, int], traj: str = "mixed",
                 image_format: str = "jpg", aa: bool = True, supersample: int = 1,
                 hfov: float = HFOV_DEG) -> SceneRecord:
    """Generate and ray-cast scene ``index`` of the dataset with this ``seed`` (``supersample``: see
    :func:`render_view`; ``hfov``: horizontal field of view in degrees)."""
    rng = np.random.default_rng([seed, index])
    city = make_city(rng)
    w2c, kind = trajectory(traj, views, city, rng)
    h, w = size
    K = fov_intrinsics(w, h, hfov)
    scene = SceneTensors(city)
    Kt = torch.as_tensor(K, dtype=torch.float32)
    out = []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # many small ops: threads cost more than they give; scenes run in processes
    try:
        renders = [render_view(scene, torch.as_tensor(w2c[i], dtype=torch.float32), Kt, h, w, aa, supersample)
                   for i in range(views)]
    finally:
        torch.set_num_threads(threads)
    for i, r in enumerate(renders):
        rgb = (r["rgb"].numpy() * 255 + 0.5).astype(np.uint8)
        depth, mask = r["depth"].numpy(), r["mask"].numpy()
        far = depth > 6e4  # beyond float16 range (near the horizon): invalid
        depth, mask = np.where(far, 0, depth), mask & ~far
        out.append(ViewRecord(name=f"{i:03d}.{image_format}", image=rgb, w2c=w2c[i], K=K, width=w, height=h,
                              depth=depth, normal=r["normal"].numpy(), mask=mask,
                              ext=image_format))
    return SceneRecord(key=f"synth{seed}_{index:05d}", views=out, source="synthetic", units="metres",
                       metres_per_unit=1.0, extra={"trajectory": kind, "seed": seed, "index": index,
                                                   "sun": city.sun.tolist(), "hfov_deg": float(hfov),
                                                   "supersample": int(supersample)})


def _worker_init(parent: int) -> None:
    """Set up a render worker of the process ``parent`` (pid): one thread, and exit when ``parent`` dies."""
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    _exit_with_parent(parent)


def _exit_with_parent(parent: int) -> None:
    """End this process when ``parent`` (pid) dies: a ``kill -9``, OOM kill or plain ``kill`` of ``anycity data
    synth`` reaches only its own pid and would leave its workers rendering scenes nobody takes. Linux: the kernel's
    parent-death signal (SIGKILL); elsewhere a daemon thread that polls ``os.getppid()`` once a second (a no-op
    where an orphan keeps its parent's pid, as on Windows)."""
    if sys.platform.startswith("linux"):
        try:
            armed = ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
        if armed:  # the signal follows the thread that started the worker: synth's, which outlives the pool
            if os.getppid() != parent:  # the parent died before the signal was armed
                os._exit(1)
            return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="anycity-parent-watch", daemon=True).start()


def _job(args):
    """Render one scene and encode it where it was rendered (a fraction of the bytes travel back)."""
    *render_args, normals, depth_dtype = args
    rec = render_scene(*render_args)
    for v in rec.views:
        v.image = encode_image(v.image, v.ext)
        v.depth = np.asarray(v.depth, depth_dtype)
        v.mask = None  # the sky mask is depth > 0: the reader derives it
        if not normals:
            v.normal = None
    return rec


def synth(out: str | Path, scenes: int = 8, views: int = 48, size: str | tuple[int, int] = "256x256", seed: int = 0,
          trajectory: str = "mixed", preview: bool = False, workers: int | None = None, image_format: str = "jpg",
          depth_dtype: str = "float16", maxcount: int = 64, aa: bool = True, normals: bool = False,
          window: int | None = 24, stride: int | None = None, supersample: int = 1,
          hfov: float = HFOV_DEG, overwrite: bool = False) -> dict:
    """Render ``scenes`` synthetic cities into ``{train,val,test}-*.tar`` shards under ``out`` (8:1:1 split).

    City ``i`` depends only on ``(seed, i)``, but the split of each city on ``scenes`` too
    (:func:`~anycity.data.writer.split_scenes`): a held-out set for a model trained on a synthetic set needs another
    ``seed``, not another ``scenes``.

    Args:
        normals: also store ground-truth normals (octahedral uint8, 2 bytes a pixel: the bytes of float16 depth; no
            loss needs them and the reader derives them from depth on request).
        window, stride: training samples are windows of ``window`` consecutive views every ``stride`` (default
            ``window // 2``) views; None: one sample per scene. Validation and test scenes stay whole.
        supersample: colour from a k x k box filter of sub-pixel rays (k^2 + 1 times the rays; 1 = one ray per
            pixel plus adaptive 5-ray anti-aliasing at contrast edges).
        hfov: horizontal field of view in degrees (a narrower lens resolves the city in more pixels).
        overwrite: replace a shard set already in ``out`` (default: refuse), its ``preview.png`` included.
    Returns the written ``index.json`` content plus ``seconds``.
    """
    if trajectory not in TRAJECTORIES:
        raise ValueError(f"trajectory: expected one of {TRAJECTORIES}, got {trajectory!r}")
    if int(seed) < 0:  # numpy's seeds are non-negative: refused here, not when the first city is made
        raise ValueError(f"seed: expected an integer >= 0, got {seed}; pass --seed 0 or more")
    if scenes < 1 or views < 2:  # a sample needs a context view and another to score it on
        raise ValueError(f"scenes and views: expected scenes >= 1 and views >= 2, got scenes={scenes}, views={views}")
    if not 10 <= float(hfov) <= 120:
        raise ValueError(f"hfov: expected a horizontal field of view of 10..120 degrees, got {hfov!r}")
    if not 1 <= int(supersample) <= 4:
        raise ValueError(f"supersample: expected 1..4 (sub-pixel rays per side), got {supersample!r}")
    if image_format not in ("jpg", "png"):
        raise ValueError(f"image_format: expected 'jpg' or 'png', got {image_format!r}")
    hw = parse_size(size)
    workers = min(scenes, workers if workers is not None else min(2, os.cpu_count() or 1))
    t0 = time.perf_counter()
    jobs = [(seed, i, views, hw, trajectory, image_format, aa, int(supersample), float(hfov), normals, depth_dtype)
            for i in range(scenes)]
    splits = split_scenes(scenes, seed)
    first: list[SceneRecord] = []
    with ShardSetWriter(out, maxcount=maxcount, depth_dtype=depth_dtype, window=window, stride=stride,
                        overwrite=overwrite) as writer:
        pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_worker_init,
                                   initargs=(os.getpid(),)) if workers > 1 else None
        try:
            records = pool.map(_job, jobs) if pool else map(_job, jobs)
            for i, rec in enumerate(records):
                writer.write(rec, splits[i])
                if len(first) < 4:
                    first.append(rec)
        except BaseException:
            if pool:  # the queued scenes would only be rendered to be thrown away: wait for the running ones only
                pool.shutdown(cancel_futures=True)
            raise
        if pool:
            pool.shutdown()
    index = writer.close()
    index["seconds"] = time.perf_counter() - t0
    if preview:
        write_preview(first, Path(out) / PREVIEW_NAME)
    return index


def _colour_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    inv = np.where(mask, 1.0 / np.maximum(depth, 1e-6), 0)
    valid = inv[mask]
    lo, hi = (np.percentile(valid, 2), np.percentile(valid, 98)) if valid.size else (0, 1)
    x = np.clip((inv - lo) / max(hi - lo, 1e-9), 0, 1)
    col = cv2.applyColorMap((x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(mask[..., None], col, 0).astype(np.uint8)


def write_preview(records: list[SceneRecord], path: str | Path, per_scene: int = 6, tile: int = 128) -> Path:
    """Contact sheet: one row per scene with ``per_scene`` views, then the first view's depth and normals."""
    rows = []
    for rec in records:
        idx = np.linspace(0, len(rec.views) - 1, min(per_scene, len(rec.views))).round().astype(int)
        tiles = []
        for i in idx:
            v = rec.views[i]
            tiles.append(v.image if isinstance(v.image, np.ndarray) else decode_image(v.image))
        v0 = rec.views[idx[0]]
        if v0.depth is not None:
            m = v0.mask.astype(bool) if v0.mask is not None else v0.depth > 0
            tiles.append(_colour_depth(np.asarray(v0.depth, np.float32), m))
        normal = v0.normal
        if normal is None and v0.depth is not None:  # not stored: derive from depth, as the reader does
            d = torch.as_tensor(np.asarray(v0.depth, np.float32))[None]
            normal = depth_to_normals(d, torch.as_tensor(v0.K, dtype=torch.float32)).permute(1, 2, 0).numpy()
        if normal is not None:
            tiles.append(((np.asarray(normal, np.float32) * 0.5 + 0.5) * 255).clip(0, 255).astype(np.uint8))
        th = tile
        tw = round(tile * tiles[0].shape[1] / tiles[0].shape[0])
        rows.append(np.concatenate([cv2.resize(t, (tw, th), interpolation=cv2.INTER_AREA) for t in tiles], 1))
    width = max(r.shape[1] for r in rows)
    sheet = np.concatenate([np.pad(r, ((0, 2), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows])
    ok, png = cv2.imencode(".png", sheet[..., ::-1].copy(), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise ValueError(f"could not encode the preview {path} as PNG")
    # encoded here and written by Python: OpenCV 5's imwrite crashes the process on a path that is not UTF-8
    atomic_write_bytes(path, png.tobytes())
    return Path(path)


def load_depth(b: bytes) -> np.ndarray:
    """Stored depth bytes -> float32 ``[H, W]``."""
    return decode_npy(b).astype(np.float32)
