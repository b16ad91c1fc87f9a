"""webdataset pipelines from shards to :class:`~anycity.structures.ViewBatch`.

Training streams are resampled (each rank and worker draws shards with replacement from a deterministic
per-(seed, rank, worker, epoch) stream, so DDP needs no shard splitting) and cut into epochs by ``with_epoch``;
with ``resampled=False`` an epoch is one pass: every stream reads the shards in the same per-epoch shuffled order
and keeps its own sample of each run of (world x workers) samples, so the streams split the pass evenly, by sample.
Evaluation streams read every shard in order and keep every (world x workers)-th sample, so every rank gets a
balanced, deterministic share even with a single shard.

Every stage is a module-level function or class, so that spawned DataLoader workers (macOS and Windows, and
Linux's forkserver default from Python 3.14) can unpickle the pipeline.

Reading is lazy (:mod:`anycity.data.tario`): a local shard's members stay on disk until a sample's views are
chosen, then only those are read and decoded (JPEGs larger than needed at 1/2-1/8 scale). Each output buffer is
written once, in shared memory when in a DataLoader worker: on small VMs fresh memory, not decoding, is the
largest cost per sample, which is also why ``compact`` batches (uint8 images, float16 depth) exist.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import random
import uuid
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import torch
import webdataset as wds

from anycity.data.schema import decode_image, decode_normals, decode_npy, member, read_meta, sample_where
from anycity.data.tario import NoSampleGuard, is_url, tar_samples
from anycity.data.views import (
    Selection,
    SettingsError,
    jpeg_reduction,
    normalise,
    resize_plan,
    resize_view,
    select_eval,
    select_train,
)
from anycity.structures import ViewBatch, Views

GROUPS = ("context", "target", "dense")


class SkipCounter:
    """Counts what was skipped as corrupt across processes (one append-only log file per process in
    ``directory``): each distinct sample ``(shard, key)`` or failed shard once, however many workers met it and
    however many times it was read (every validation reads its shards again)."""

    def __init__(self, directory: str | Path | None = None) -> None:
        self.directory = Path(directory) if directory else Path(os.environ.get("TMPDIR", "/tmp")) / (
            f"anycity-skips-{uuid.uuid4().hex[:12]}")

    def add(self, where: str, error: BaseException, what: str | None = None) -> None:
        """Note a skip; ``what`` identifies the skipped thing (default ``where``): the same ``what`` counts once."""
        self.directory.mkdir(parents=True, exist_ok=True)
        with open(self.directory / f"skips-{os.getpid()}.log", "a") as f:
            f.write(json.dumps({"where": where, "error": str(error)[:500], "what": what or where}) + "\n")

    @property
    def count(self) -> int:
        return len(self.records())

    def records(self) -> list[dict]:
        """The first record of each distinct skipped thing."""
        if not self.directory.exists():
            return []
        logs = sorted(self.directory.glob("skips-*.log"))
        first: dict[str, dict] = {}
        for r in (json.loads(line) for p in logs for line in p.read_text().splitlines()):
            first.setdefault(r.get("what", r["where"]), r)
        return list(first.values())


@contextlib.contextmanager
def single_thread():
    """Run torch single-threaded for a while (data work in the main process, ``num_workers=0``): its ops are
    small, and intra-op threads on a busy machine wait for each other (10x slower at load 5 on 2 cores)."""
    n = torch.get_num_threads()
    if n > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if n > 1:
            torch.set_num_threads(n)


def context_count_probs(context_range: tuple[int, int] | list[int] | None,
                        weighting: str = "uniform") -> tuple[np.ndarray, np.ndarray] | None:
    """``(counts, probabilities)`` of a training context-count range, or None without one."""
    if weighting not in ("uniform", "square"):
        raise ValueError(f"train_context_weighting: expected 'uniform' or 'square', got {weighting!r}")
    if context_range is None:
        return None
    if len(context_range) != 2 or not 1 <= int(context_range[0]) <= int(context_range[1]) <= 64:
        raise ValueError(f"train_num_context: expected [lo, hi] with 1 <= lo <= hi <= 64 views, got "
                         f"{list(context_range)!r}")
    counts = np.arange(int(context_range[0]), int(context_range[1]) + 1)
    w = counts.astype(np.float64) ** (2 if weighting == "square" else 0)
    return counts, w / w.sum()


class SampleBuilder:
    """Turns a raw webdataset sample (bytes) into per-group tensors for one or more view selections.

    Decoding is lazy: the sample's members stay on disk (local shards) or raw bytes until the views are selected,
    then only the chosen views are read and decoded (JPEGs larger than the output at 1/2, 1/4 or 1/8 scale
    straight from the DCT).

    Args:
        num_context, num_targets, num_dense: views per group (num_dense 0 disables the dense set).
        image_size: ``(H, W)`` output size; resize_mode: "crop" or "keep" (see :func:`resize_view`).
        train: random sliding-window selection (True) or deterministic llffhold selection (False).
        window: training window length (None: 2 x the largest group).
        with_depth: load depth + mask when the shard has depth.
        with_normals: load normals; when the shard stores none, derive them from the (resized) depth (see
            :func:`_normals_from_depth`; zero where a pixel or a 4-neighbour is invalid).
        hold: the llffhold stride for evaluation.
        context_range: training only: ``(lo, hi)`` draws the context count per batch from ``lo..hi`` instead of
            ``num_context`` (VGGT and AnySplat train on varied counts); evaluation keeps ``num_context``.
        context_weighting: how ``context_range`` draws: "uniform", or "square" (probability proportional to the
            count squared, AnySplat's ``DynamicBatchSampler``).
        batch_size: samples per batch, so that all samples of a batch (in this worker) draw the same count.
        eval_dense: evaluation samples carry (and decode) their dense views. The context views are the same either
            way, and whatever ``num_dense`` (see :func:`~anycity.data.views.select_eval`).
        compact: compact tensors for the trip to the device: images uint8 ``[0, 255]``, depth and normals
            float16 (a third of the bytes; :func:`to_float32` restores the usual batch on the device).
    """

    def __init__(self, num_context: int = 4, num_targets: int = 4, num_dense: int = 12,
                 image_size: tuple[int, int] = (448, 448), resize_mode: str = "crop", train: bool = True,
                 window: int | None = None, with_depth: bool = True, with_normals: bool = True, hold: int = 8,
                 patch: int = 14, seed: int = 0, compact: bool = False,
                 context_range: tuple[int, int] | None = None, context_weighting: str = "uniform",
                 batch_size: int = 1, eval_dense: bool = True) -> None:
        if num_context < 1 or num_targets < 1 or num_dense < 0:
            raise ValueError(f"view counts: expected num_context >= 1, num_targets >= 1, num_dense >= 0, got "
                             f"{num_context}, {num_targets}, {num_dense}")
        self.nc, self.nt, self.nd = num_context, num_targets, num_dense
        self.context_counts = context_count_probs(context_range, context_weighting)
        self.batch_size, self._built, self._batch_nc = max(1, int(batch_size)), 0, num_context
        self.size, self.mode, self.train, self.window = tuple(image_size), resize_mode, train, window
        self.with_depth, self.with_normals, self.hold, self.patch = with_depth, with_normals, hold, patch
        self.seed, self.compact, self.eval_dense = seed, compact, eval_dense
        self._rng: np.random.Generator | None = None
        self._epoch = 0
        self._in_worker: bool | None = None

    def rng(self) -> np.random.Generator:
        if self._rng is None:
            # the rank from RANK or torch.distributed: Lightning's DDP launcher sets no RANK, and every rank drew
            # the same views when it was read from the environment alone
            rank, _, worker, _ = wds.utils.pytorch_worker_info()
            epoch = [self._epoch] if self._epoch else []  # epoch 0 keeps the builder's first seed
            self._rng = np.random.default_rng([self.seed, rank, worker, *epoch])
        return self._rng

    def begin_epoch(self, epoch: int) -> None:
        """Draw epoch ``epoch``'s samples from a seed of their own, so a run resumed in that epoch draws the same."""
        self._epoch, self._rng, self._built = epoch, None, 0

    def train_context_count(self) -> int:
        """The context count of the next training sample: ``num_context``, or with ``context_range`` a draw made
        once per ``batch_size`` samples (a worker's consecutive samples form its batches)."""
        if self.context_counts is None:
            return self.nc
        if self._built % self.batch_size == 0:  # a sample that fails to build does not count (it is skipped)
            counts, probs = self.context_counts
            self._batch_nc = int(self.rng().choice(counts, p=probs))
        return self._batch_nc

    def selections(self, n: int, meta: dict | None = None) -> list[Selection]:
        if self.train:
            return [select_train(n, self.train_context_count(), self.nt, self.nd, self.rng(), self.window)]
        views = meta["views"] if meta else None
        index = [v.get("index", i) for i, v in enumerate(views)] if views else None
        own = (meta.get("window") or {}).get("own") if meta else None
        sels = select_eval(n, self.nc, self.nt, self.nd, self.hold, index=index, own=own)
        return sels if self.eval_dense else [Selection(s.context, s.target, []) for s in sels]

    def _load(self, sample: dict, view: dict) -> dict:
        h, w = view["height"], view["width"]
        key = view["image"]
        nh, nw, _, _ = resize_plan(h, w, self.size, self.mode, self.patch)
        r = jpeg_reduction(h, w, nh, nw) if key.endswith((".jpg", ".jpeg")) else 1
        img = decode_image(member(sample, key), reduce=r)
        if img.shape[:2] != (-(-h // r), -(-w // r)):
            raise ValueError(f"{sample_where(sample)}: key {key!r} is {img.shape[1] * r}x{img.shape[0] * r}, "
                             f"cameras.json says {w}x{h}; re-create the shard")
        depth = normal = mask = None
        if self.with_depth and view.get("depth"):
            depth = decode_npy(member(sample, view["depth"]))  # float16 stays float16 until the batch copy
            if depth.shape != (nh, nw) and depth.dtype != np.float32:
                depth = depth.astype(np.float32)  # OpenCV resizes float32, not float16
            if view.get("mask"):  # else depth > 0, computed on the float32 batch (numpy float16 math is slow)
                mask = decode_image(member(sample, view["mask"]), gray=True) > 127
        if self.with_normals and view.get("normal"):
            normal = decode_normals(decode_npy(member(sample, view["normal"])))
        img, K, depth, normal, mask = resize_view(img, view["K"], self.size, self.mode, self.patch, depth, normal,
                                                  mask, src_hw=(h, w))
        return {"image": img, "K": K, "w2c": np.asarray(view["w2c"], np.float64), "depth": depth,
                "normal": normal, "mask": mask}

    def __call__(self, sample: dict) -> list[dict]:
        if self._in_worker is None:
            self._in_worker = torch.utils.data.get_worker_info() is not None
            if self._in_worker:
                cv2.setNumThreads(0)  # workers are the parallelism; OpenCV's threads would oversubscribe
        # a NaN camera/depth never reaches the loss; images (from uint8) and normals (from uint8, or from the depth
        # and K checked here) cannot be non-finite, and checking them was a third of the build at 448 px. Checked on
        # one thread too: torch's intra-op threads made it half the build's time with num_workers 0
        with contextlib.nullcontext() if self._in_worker else single_thread():
            out = self._build(sample)
            check_finite(out, sample_where(sample), skip=("images", "normal"))
        self._built += 1  # only a sample that reaches a batch counts (see train_context_count)
        return out

    def _build(self, sample: dict) -> list[dict]:
        meta = read_meta(sample)
        views = meta["views"]
        cache: dict[int, dict] = {}
        out = []
        for sel in self.selections(len(views), meta):
            order = sel.context + sel.target + sel.dense
            for i in order:
                if i not in cache:
                    cache[i] = self._load(sample, views[i])
            index = [int(views[i].get("index", i)) for i in order]
            out.append(self._assemble(meta, [cache[i] for i in order], index, sel))
        return out

    def _assemble(self, meta: dict, vs: list[dict], order: list[int], sel: Selection) -> dict:
        """Per-view arrays -> per-group tensors, written once into (shared, in a worker) batch-ready buffers:
        images ``[V, 3, H, W]`` float [0, 1], depth float32 in normalised units, mask bool, normals (``compact``:
        uint8 images, float16 depth and normals)."""
        V, nc = len(vs), len(sel.context)
        H, W = vs[0]["image"].shape[:2]
        if any(v["image"].shape[:2] != (H, W) for v in vs):
            raise SettingsError(f"scene {meta['scene']}: views resize to different sizes "
                                f"{sorted({v['image'].shape[:2] for v in vs})}; use resize_mode 'crop' or one "
                                "aspect ratio per scene")
        w2c = torch.as_tensor(np.stack([v["w2c"] for v in vs]))
        K = torch.as_tensor(np.stack([v["K"] for v in vs]))
        has_depth = all(v["depth"] is not None for v in vs)
        ctx_depth = ctx_mask = None
        if has_depth:  # the scale comes from the context views only
            ctx_depth = torch.as_tensor(np.stack([v["depth"] for v in vs[:nc]]))[:, None]
            if any(v["mask"] is not None for v in vs[:nc]):  # else normalise() takes depth > 0
                ctx_mask = torch.as_tensor(np.stack([v["depth"] > 0 if v["mask"] is None else v["mask"]
                                                     for v in vs[:nc]]))[:, None]
        w2c, s, T = normalise(w2c, K, nc, ctx_depth, ctx_mask)
        T = T @ torch.as_tensor(np.asarray(meta["world_from_source"], np.float64))
        # fresh (shared) memory is the dominant cost per sample on small VMs: write each buffer once
        real = torch.float16 if self.compact else torch.float32
        images = _alloc((V, 3, H, W), torch.uint8 if self.compact else torch.float32)
        for i, v in enumerate(vs):
            img = torch.from_numpy(v["image"]).permute(2, 0, 1)
            if self.compact:
                images[i].copy_(img)
            else:
                torch.div(img, 255.0, out=images[i])
        depth = mask = normal = None
        if has_depth:
            depth, mask = _alloc((V, 1, H, W), real), _alloc((V, 1, H, W), torch.bool)
            for i, v in enumerate(vs):
                torch.div(torch.from_numpy(v["depth"]), s, out=depth[i, 0])
                if v["mask"] is None:
                    torch.gt(depth[i, 0], 0, out=mask[i, 0])
                else:
                    mask[i, 0].copy_(torch.from_numpy(v["mask"]))
        if all(v["normal"] is not None for v in vs):
            normal = _alloc((V, 3, H, W), real)
            for i, v in enumerate(vs):
                normal[i].copy_(torch.from_numpy(v["normal"]).permute(2, 0, 1))
        elif self.with_normals and depth is not None:
            normal = _normals_from_depth([v["depth"] for v in vs], mask, K.float(), real)
        out: dict = {"scene": meta["scene"], "scale": s * (meta.get("metres_per_unit") or 1.0),
                     "world_from_source": T.float()}
        bounds = np.cumsum([0, len(sel.context), len(sel.target), len(sel.dense)])
        for g, a, b in zip(GROUPS, bounds[:-1], bounds[1:]):
            if b == a:
                continue
            grp = {"images": images[a:b], "w2c": w2c[a:b].float(), "K": K[a:b].float(),
                   "index": torch.as_tensor(order[a:b], dtype=torch.long)}
            if depth is not None:
                grp["depth"], grp["mask"] = depth[a:b], mask[a:b]
            if normal is not None:
                grp["normal"] = normal[a:b]
            out[g] = grp
        return out


def _normals_from_depth(depth: list | torch.Tensor, mask: torch.Tensor, K: torch.Tensor,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """V z-depth maps (``[V, 1, H, W]`` or a list of ``[H, W]`` arrays, any units) + validity ``[V, 1, H, W]`` ->
    camera-frame unit normals ``[V, 3, H, W]`` facing the camera, zero (never NaN) on the border and where the pixel
    or a 4-neighbour is invalid.

    The normal of the back-projected surface ``P = z (K^-1 [u, v, 1])`` in closed form from central depth
    differences ``g_u, g_v``: ``n ~ (fx g_u, fy g_v, -((u - cx) g_u + (v - cy) g_v + z))``; it agrees with
    :func:`anycity.geometry.depth_to_normals` (finite differences of the points) to first order, on 2-D planes,
    several times faster (this runs per sample in the data workers).
    """
    H, W = mask.shape[-2:]
    n = _alloc((len(depth), 3, H, W), dtype)
    uu = torch.arange(W, dtype=torch.float32) + 0.5
    vv = torch.arange(H, dtype=torch.float32)[:, None] + 0.5
    gu, gv = torch.zeros(H, W), torch.zeros(H, W)
    for i, d in enumerate(depth):
        z = torch.as_tensor(d).float().reshape(H, W)
        fx, fy, cx, cy = (float(x) for x in (K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]))
        torch.sub(z[:, 2:], z[:, :-2], out=gu[:, 1:-1]).mul_(0.5)
        torch.sub(z[2:], z[:-2], out=gv[1:-1]).mul_(0.5)
        nz = torch.addcmul(z, uu - cx, gu).addcmul_(vv - cy, gv).neg_()
        nx, ny = gu * fx, gv * fy
        inv = (nx * nx).addcmul_(ny, ny).addcmul_(nz, nz).clamp_(min=1e-30).rsqrt_()  # rsqrt(0) = inf: 0 * inf = NaN
        for c, comp in enumerate((nx, ny, nz)):
            n[i, c].copy_(comp.mul_(inv))
    ok = mask.clone()
    ok[..., 1:, :] &= mask[..., :-1, :]
    ok[..., :-1, :] &= mask[..., 1:, :]
    ok[..., :, 1:] &= mask[..., :, :-1]
    ok[..., :, :-1] &= mask[..., :, 1:]
    ok[..., 0, :] = ok[..., -1, :] = False
    ok[..., :, 0] = ok[..., :, -1] = False
    return n.masked_fill_(~ok, 0.0)  # not mul_: a NaN times 0 stays NaN


def _alloc(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """An empty tensor, in shared memory inside a DataLoader worker (it then crosses to the main process
    without a copy)."""
    if torch.utils.data.get_worker_info() is None:
        return torch.empty(shape, dtype=dtype)
    numel = int(np.prod(shape))
    storage = torch.UntypedStorage._new_shared(numel * torch.empty((), dtype=dtype).element_size())
    return torch.empty(0, dtype=dtype).set_(storage, 0, shape)


def _stack(xs: list[torch.Tensor]) -> torch.Tensor:
    """``torch.stack`` into shared memory (in a worker); a single item becomes a view, no copy."""
    if len(xs) == 1:
        return xs[0][None]
    out = _alloc((len(xs), *xs[0].shape), xs[0].dtype)
    return torch.stack(xs, out=out)


def to_float32(batch: ViewBatch) -> ViewBatch:
    """A ``compact`` batch (uint8 images, float16 depth/normals) -> the usual float32 batch (images in [0, 1]),
    in place, on the batch's device; other batches pass unchanged."""
    for v in (batch.context, batch.target, batch.dense):
        if v is None:
            continue
        if v.images.dtype == torch.uint8:
            v.images = v.images.float().div_(255.0)
        if v.depth is not None and v.depth.dtype != torch.float32:
            v.depth = v.depth.float()
        if v.normal is not None and v.normal.dtype != torch.float32:
            v.normal = v.normal.float()
    return batch


def collate(samples: list[dict]) -> ViewBatch:
    """Stack per-sample dicts from :class:`SampleBuilder` into a :class:`ViewBatch`."""
    with single_thread():
        return _collate(samples)


def _check_image_sizes(samples: list[dict], grp: list[dict]) -> None:
    """Refuse a batch whose samples' images differ in size (``resize_mode: keep`` keeps each scene's aspect ratio),
    in one line naming the scenes, rather than torch.stack's traceback."""
    sizes: dict[str, list[str]] = {}
    for s, x in zip(samples, grp):
        scenes = sizes.setdefault("x".join(str(d) for d in x["images"].shape[-2:]), [])
        if s["scene"] not in scenes:
            scenes.append(s["scene"])
    if len(sizes) > 1:
        mixed = "; ".join(f"{hw}: {', '.join(sc)}" for hw, sc in sizes.items())
        raise ValueError(f"collate: a batch mixes image sizes (HxW {mixed}): resize_mode 'keep' keeps each scene's "
                         "aspect ratio; set --data.batch_size 1 (--data.eval_batch_size 1 for val/test), use "
                         "--data.resize_mode crop, or shards of one aspect ratio per run")


def _collate(samples: list[dict]) -> ViewBatch:

    def views(g: str) -> Views | None:
        if g not in samples[0]:
            return None
        grp = [s[g] for s in samples]
        _check_image_sizes(samples, grp)
        if len({len(x["images"]) for x in grp}) > 1:
            raise ValueError(f"collate: the samples of one batch have {sorted(len(x['images']) for x in grp)} "
                             f"{g} views; a batch needs one count (batch_size 1, or draw counts per batch)")
        if 0 < sum("depth" in x for x in grp) < len(grp):  # stacking would drop every sample's depth and mask
            none = sorted({s["scene"] for s, x in zip(samples, grp) if "depth" not in x})
            raise ValueError(f"collate: a batch mixes samples with and without ground-truth depth (without: "
                             f"{', '.join(none)}), so it would lose every sample's depth; train or test shards "
                             "without depth in a separate run, give all shards depth (or data.with_depth: false), or "
                             "set data.batch_size (eval_batch_size) 1")
        opt = lambda k: _stack([x[k] for x in grp]) if all(k in x for x in grp) else None  # noqa: E731
        return Views(images=_stack([x["images"] for x in grp]), w2c=opt("w2c"), K=opt("K"),
                     depth=opt("depth"), mask=opt("mask"), normal=opt("normal"), index=opt("index"))

    batch = ViewBatch(context=views("context"), target=views("target"), dense=views("dense"),
                      scene=[s["scene"] for s in samples],
                      scale=torch.tensor([s["scale"] for s in samples], dtype=torch.float32),
                      world_from_source=torch.stack([s["world_from_source"] for s in samples]))
    return batch.validate(compact=True)  # shapes and dtypes only: no pass over the pixels


def _stream_slot() -> tuple[int, int]:
    """``(this stream's slot, number of slots)``: one slot per (rank, DataLoader worker)."""
    rank, world, worker, workers = wds.utils.pytorch_worker_info()
    return rank * workers + worker, world * workers


def _eval_shard(src: Iterator[dict]) -> Iterator[dict]:
    """Keep every (world x workers)-th sample for this (rank, worker): balanced and deterministic."""
    me, total = _stream_slot()
    for i, s in enumerate(src):
        if i % total == me:
            yield s


def check_finite(obj, where: str = "sample", path: str = "", skip: tuple[str, ...] = ()) -> None:
    """Raise ``ValueError`` naming ``where`` and the field if any floating tensor/array in ``obj`` (nested
    dicts/lists of a built sample: images, depths, ``w2c``, ``K``...) holds NaN or inf; dict entries named in
    ``skip`` are not checked. A view group's ``normal`` is checked only where its ``mask`` is valid: no loss reads
    normals where there is no depth (sky)."""
    if isinstance(obj, dict):
        mask = obj.get("mask")
        for k, v in obj.items():
            if k in skip:
                continue
            if k == "normal" and isinstance(v, torch.Tensor) and isinstance(mask, torch.Tensor):
                v = v.masked_fill(~mask.bool().expand_as(v), 0.0)
            check_finite(v, where, f"{path}.{k}" if path else str(k), skip)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            check_finite(v, where, f"{path}[{i}]", skip)
    elif isinstance(obj, torch.Tensor) and obj.is_floating_point():
        if not bool(torch.isfinite(obj).all()):
            raise ValueError(f"{where}: non-finite values (NaN/inf) in {path or 'tensor'}; fix or drop this sample "
                             "(skip_corrupt: true skips and counts it)")
    elif isinstance(obj, np.ndarray) and np.issubdtype(obj.dtype, np.floating):
        if not np.isfinite(obj).all():
            raise ValueError(f"{where}: non-finite values (NaN/inf) in {path or 'array'}; fix or drop this sample "
                             "(skip_corrupt: true skips and counts it)")


class _EpochStart:
    """A training stream's first stage. Each iteration of the pipeline is one epoch; this counts them from
    ``first_epoch`` and seeds each epoch's random draws (shards, shuffle, views) from ``(seed, epoch)`` and the
    stream's rank and worker, so a run resumed in epoch ``e`` (``first_epoch=e``) draws what the uninterrupted run
    drew there, and no two ranks or workers shuffle alike. Rank 0's first worker keeps the seeds the stream had
    before it counted epochs and streams.

    ``shards``: a ``wds.ResampledShards`` (resampled), or the list of shard urls, given whole in an order shuffled
    from ``(seed, epoch)`` alone, the same on every stream (``resampled=False``; :class:`_PassShare` splits it)."""

    def __init__(self, shards: wds.ResampledShards | list[str], first_epoch: int, shuffle_rng: random.Random,
                 seed: int, builder: SampleBuilder) -> None:
        self.shards, self.epoch, self.shuffle_rng, self.seed, self.builder = shards, first_epoch - 1, shuffle_rng, \
            seed, builder

    def __call__(self):
        self.epoch += 1
        rank, _, worker, _ = wds.utils.pytorch_worker_info()
        base = self.seed if self.epoch == 0 else f"{self.seed}:{self.epoch}"
        self.shuffle_rng.seed(f"{base}:{rank}:{worker}" if rank or worker else base)
        self.builder.begin_epoch(self.epoch)
        if isinstance(self.shards, wds.ResampledShards):
            self.shards.epoch = self.epoch - 1  # it counts its own epochs from -1, one per iteration
            return iter(self.shards)
        order = list(self.shards)
        random.Random(f"{self.seed}:{self.epoch}:shards").shuffle(order)
        return iter([{"url": u} for u in order])


class _PassShare:
    """webdataset stage of a ``resampled=False`` training stream: this stream's share of one pass. Every stream
    reads the same samples in the same order and keeps sample ``slot`` of each run of (world x workers) consecutive
    samples; an incomplete last run is dropped. So every stream gets floor(N / streams) samples, no sample goes to
    two streams, and ranks get equal batch counts, whatever the number of shards (a sample that then fails to build
    is replaced by :func:`_pass_refill`). Refuses a pass that leaves a stream fewer than ``batch_size`` samples
    (every epoch would have no batch)."""

    def __init__(self, batch_size: int) -> None:
        self.batch_size = batch_size

    def __call__(self, src: Iterator[dict]) -> Iterator[dict]:
        me, total = _stream_slot()
        kept, runs, read = None, 0, 0
        for read, s in enumerate(src, 1):
            if (read - 1) % total == me:
                kept = s
            if read % total == 0:
                runs += 1
                yield kept
        if runs < self.batch_size:
            raise ValueError(f"resampled: false: the {read} training sample(s) over {total} stream(s) (ranks x "
                             f"max(1, num_workers)) give each {runs}, fewer than batch_size {self.batch_size}, so "
                             "every epoch would have no batch; set data.resampled: true, or lower num_workers or "
                             "batch_size")


def _pass_refill(src: Iterator[list[dict]]) -> Iterator[list[dict]]:
    """webdataset stage of a ``resampled=False`` training stream, after the build: a sample that failed to build
    (``[]``; already counted as skipped) is replaced by a repeat of the stream's previous built sample (the first
    built one, for failures before it). :class:`_PassShare` splits the pass before the build, so without this a
    stream with a failure got fewer batches than the others (DDP ranks then disagree on the batch count and hang in
    an all-reduce) and than the datamodule's count of batches per epoch. Yields nothing if nothing builds (the
    stream's ``NoSampleGuard`` then says so)."""
    last, owed = None, 0
    for items in src:
        if not items:
            if last is None:
                owed += 1
            else:
                yield last
            continue
        last = items
        for _ in range(owed + 1):
            yield items
        owed = 0


def count_samples(urls: list[str]) -> int:
    """The samples one pass of a ``resampled=False`` training stream reads from ``urls`` (a shard that cannot be
    read gives none, a truncated one those before the cut, one with a corrupt header those before it)."""
    return sum(1 for _ in tar_samples([{"url": str(u)} for u in urls], handler=lambda e: True))


class _Handler:
    """The pipeline's webdataset exception handler: a ``SettingsError`` (the settings, not the sample) raises; with
    ``skip_corrupt`` anything else is skipped and counted in ``counter``, else raised as a ``ValueError`` naming the
    shard."""

    def __init__(self, skip_corrupt: bool, counter: SkipCounter | None, train: bool) -> None:
        self.skip_corrupt, self.counter, self.train = skip_corrupt, counter, train

    def __call__(self, exn: BaseException) -> bool:
        if isinstance(exn, SettingsError):  # the settings, not the sample: every sample would be skipped
            raise exn
        if self.skip_corrupt:
            # every evaluation stream reads every shard: only the first one counts a shard's failure
            if self.counter is not None and (self.train or _stream_slot()[0] == 0):
                self.counter.add("shard", exn, what=f"shard: {str(exn)[:500]}")
            return True
        if isinstance(exn, (ValueError, FileNotFoundError)) and "shard" in str(exn):
            raise exn
        raise ValueError(f"corrupt or unreadable shard: {exn}") from exn


class _Build:
    """The pipeline's map stage: a raw sample -> ``builder``'s selections; with ``skip_corrupt`` a sample that fails
    to build gives ``[]`` (skipped: no items; :func:`_pass_refill` fills its place in a pass), counted in
    ``counter`` and told to ``guard``; a :class:`SettingsError` raises, naming the sample."""

    def __init__(self, builder: SampleBuilder, skip_corrupt: bool, counter: SkipCounter | None,
                 guard: NoSampleGuard) -> None:
        self.builder, self.skip_corrupt, self.counter, self.guard = builder, skip_corrupt, counter, guard

    def __call__(self, sample: dict) -> list[dict] | None:
        try:
            out = self.builder(sample)
        except SettingsError as e:
            raise type(e)(f"{sample_where(sample)}: {e}") from None
        except Exception as e:
            msg = str(e) if "shard" in str(e) else f"{sample_where(sample)}: {e}"
            if self.skip_corrupt:
                url, key = sample.get("__url__", "?"), sample.get("__key__", "?")
                if self.counter is not None:
                    self.counter.add(sample_where(sample), e, what=f"{url}\t{key}")
                self.guard.sample_failed(url, key, msg)
                return []
            raise ValueError(msg) from e
        self.guard.sample_built()
        return out


def make_pipeline(urls: list[str], builder: SampleBuilder, *, train: bool, resampled: bool = True,
                  epoch_samples: int | None = None, shuffle: int = 16, seed: int = 0,
                  skip_corrupt: bool = False, counter: SkipCounter | None = None,
                  first_epoch: int = 0) -> wds.DataPipeline:
    """Shards -> per-sample dicts (batch with :func:`collate` in the DataLoader). A training stream starts at epoch
    ``first_epoch`` (a resumed run's; see :class:`_EpochStart`). ``epoch_samples`` cuts a resampled training
    stream's epochs; with ``resampled=False`` an epoch is one pass, split by sample (:class:`_PassShare`).

    Raises ``FileNotFoundError`` for missing shard files, and (unless ``skip_corrupt``) ``ValueError`` naming the
    shard and key for corrupt samples; with ``skip_corrupt`` they are skipped and counted in ``counter``.
    """
    urls = [str(u) for u in urls]
    if not urls:
        raise ValueError("shards: the split has no shards; check the shard root / url pattern")
    for u in urls:
        if not is_url(u) and not Path(u).exists():
            raise FileNotFoundError(f"shard {u}: file not found; check the data root or re-run anycity data synth")

    handler = _Handler(skip_corrupt, counter, train)
    # a finite evaluation stream holds a share of the samples and cannot loop: no every-sample-failed rule there
    guard = NoSampleGuard(urls, builds=train)
    shuffle_rng = random.Random(seed)
    if train:
        shards = wds.ResampledShards(urls, seed=seed, deterministic=True) if resampled else urls
        stages = [_EpochStart(shards, first_epoch, shuffle_rng, seed, builder)]
    else:
        stages = [wds.SimpleShardList(urls)]
    stages.append(functools.partial(tar_samples, handler=handler, guard=guard))
    if not train:
        stages.append(_eval_shard)
    elif not resampled:
        stages.append(_PassShare(builder.batch_size))
    stages.append(guard.kept)  # after the stream's share: the guard waits only for this stream's own samples
    if train and shuffle > 1:
        stages.append(wds.shuffle(shuffle, initial=min(shuffle, 4), rng=shuffle_rng))
    stages.append(wds.map(_Build(builder, skip_corrupt, counter, guard), handler=handler))
    if train and not resampled:
        stages.append(_pass_refill)
    stages.append(_flatten)
    if train and not resampled:
        stages.append(guard.ended)
    pipe = wds.DataPipeline(*stages)
    if train and resampled and epoch_samples:
        pipe = pipe.with_epoch(epoch_samples)
    return pipe


def _flatten(src):
    for items in src:
        yield from items
