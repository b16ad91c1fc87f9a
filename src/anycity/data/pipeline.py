"""webdataset pipelines from shards to :class:`~anycity.structures.ViewBatch`.

Training streams are resampled (each rank and worker draws shards with replacement from a deterministic
per-(seed, rank, worker, epoch) stream, so DDP needs no shard splitting) and cut into epochs by ``with_epoch``;
``resampled=False`` instead shuffles the shard list and uses ``split_by_node`` + ``split_by_worker``.
Evaluation streams read every shard in order and keep every (world x workers)-th sample, so every rank gets a
balanced, deterministic share even with a single shard. Only the selected views of a sample are decoded.
"""

from __future__ import annotations

import json
import os
import random
import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import webdataset as wds

from anycity.data.schema import decode_image, decode_npy, member, read_meta, sample_where
from anycity.data.views import Selection, normalise, resize_view, select_eval, select_train
from anycity.structures import ViewBatch, Views

GROUPS = ("context", "target", "dense")


class SkipCounter:
    """Counts skipped corrupt samples across processes (one append-only log file per process in ``directory``)."""

    def __init__(self, directory: str | Path | None = None) -> None:
        self.directory = Path(directory) if directory else Path(os.environ.get("TMPDIR", "/tmp")) / (
            f"anycity-skips-{uuid.uuid4().hex[:12]}")

    def add(self, where: str, error: BaseException) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        with open(self.directory / f"skips-{os.getpid()}.log", "a") as f:
            f.write(json.dumps({"where": where, "error": str(error)[:500]}) + "\n")

    @property
    def count(self) -> int:
        if not self.directory.exists():
            return 0
        return sum(len(p.read_text().splitlines()) for p in self.directory.glob("skips-*.log"))

    def records(self) -> list[dict]:
        if not self.directory.exists():
            return []
        logs = sorted(self.directory.glob("skips-*.log"))
        return [json.loads(line) for p in logs for line in p.read_text().splitlines()]


class SampleBuilder:
    """Turns a raw webdataset sample (bytes) into per-group tensors for one or more view selections.

    Args:
        num_context, num_targets, num_dense: views per group (num_dense 0 disables the dense set).
        image_size: ``(H, W)`` output size; resize_mode: "crop" or "keep" (see :func:`resize_view`).
        train: random sliding-window selection (True) or deterministic llffhold selection (False).
        window: training window length (None: 2 x the largest group).
        with_depth, with_normals: load depth+mask / normals when the shard has them.
        hold: the llffhold stride for evaluation.
    """

    def __init__(self, num_context: int = 4, num_targets: int = 4, num_dense: int = 12,
                 image_size: tuple[int, int] = (448, 448), resize_mode: str = "crop", train: bool = True,
                 window: int | None = None, with_depth: bool = True, with_normals: bool = True, hold: int = 8,
                 patch: int = 14, seed: int = 0) -> None:
        if num_context < 1 or num_targets < 1 or num_dense < 0:
            raise ValueError(f"view counts: expected num_context >= 1, num_targets >= 1, num_dense >= 0, got "
                             f"{num_context}, {num_targets}, {num_dense}")
        self.nc, self.nt, self.nd = num_context, num_targets, num_dense
        self.size, self.mode, self.train, self.window = tuple(image_size), resize_mode, train, window
        self.with_depth, self.with_normals, self.hold, self.patch = with_depth, with_normals, hold, patch
        self.seed = seed
        self._rng: np.random.Generator | None = None

    def rng(self) -> np.random.Generator:
        if self._rng is None:
            info = torch.utils.data.get_worker_info()
            rank = int(os.environ.get("RANK", 0))
            self._rng = np.random.default_rng([self.seed, rank, info.id if info else 0])
        return self._rng

    def selections(self, n: int) -> list[Selection]:
        if self.train:
            return [select_train(n, self.nc, self.nt, self.nd, self.rng(), self.window)]
        return select_eval(n, self.nc, self.nt, self.nd, self.hold)

    def _load(self, sample: dict, view: dict) -> dict:
        img = decode_image(member(sample, view["image"]))
        K = np.asarray(view["K"], np.float64)
        if img.shape[:2] != (view["height"], view["width"]):
            raise ValueError(f"{sample_where(sample)}: key {view['image']!r} is {img.shape[1]}x{img.shape[0]}, "
                             f"cameras.json says {view['width']}x{view['height']}; re-create the shard")
        depth = normal = mask = None
        if self.with_depth and view.get("depth"):
            depth = decode_npy(member(sample, view["depth"])).astype(np.float32)
            mask = (decode_image(member(sample, view["mask"]), gray=True) > 127) if view.get("mask") else depth > 0
        if self.with_normals and view.get("normal"):
            normal = decode_npy(member(sample, view["normal"])).astype(np.float32)
        img, K, depth, normal, mask = resize_view(img, K, self.size, self.mode, self.patch, depth, normal, mask)
        return {"image": img, "K": K, "w2c": np.asarray(view["w2c"], np.float64), "depth": depth,
                "normal": normal, "mask": mask}

    def __call__(self, sample: dict) -> list[dict]:
        meta = read_meta(sample)
        views = meta["views"]
        cache: dict[int, dict] = {}
        out = []
        for sel in self.selections(len(views)):
            order = sel.context + sel.target + sel.dense
            for i in order:
                if i not in cache:
                    cache[i] = self._load(sample, views[i])
            out.append(self._assemble(meta, [cache[i] for i in order], order, sel))
        return out

    def _assemble(self, meta: dict, vs: list[dict], order: list[int], sel: Selection) -> dict:
        w2c = torch.as_tensor(np.stack([v["w2c"] for v in vs]))
        K = torch.as_tensor(np.stack([v["K"] for v in vs]))
        has_depth = all(v["depth"] is not None for v in vs)
        depth = mask = None
        if has_depth:
            depth = torch.as_tensor(np.stack([v["depth"] for v in vs]))[:, None]
            mask = torch.as_tensor(np.stack([v["mask"] for v in vs]))[:, None]
        w2c, s, T = normalise(w2c, K, self.nc, depth, mask)
        T = T @ torch.as_tensor(np.asarray(meta["world_from_source"], np.float64))
        images = torch.as_tensor(np.stack([v["image"] for v in vs])).permute(0, 3, 1, 2)  # uint8 [V, 3, H, W]
        normal = None
        if all(v["normal"] is not None for v in vs):
            normal = torch.as_tensor(np.stack([v["normal"] for v in vs])).permute(0, 3, 1, 2).float()
        out: dict = {"scene": meta["scene"], "scale": s * (meta.get("metres_per_unit") or 1.0),
                     "world_from_source": T.float()}
        bounds = np.cumsum([0, len(sel.context), len(sel.target), len(sel.dense)])
        for g, a, b in zip(GROUPS, bounds[:-1], bounds[1:]):
            if b == a:
                continue
            grp = {"images": images[a:b], "w2c": w2c[a:b].float(), "K": K[a:b].float(),
                   "index": torch.as_tensor(order[a:b], dtype=torch.long)}
            if depth is not None:
                grp["depth"] = (depth[a:b] / s).float()
                grp["mask"] = mask[a:b]
            if normal is not None:
                grp["normal"] = normal[a:b]
            out[g] = grp
        return out


def collate(samples: list[dict]) -> ViewBatch:
    """Stack per-sample dicts from :class:`SampleBuilder` into a :class:`ViewBatch` (images -> float [0, 1])."""

    def views(g: str) -> Views | None:
        if g not in samples[0]:
            return None
        grp = [s[g] for s in samples]
        opt = lambda k: torch.stack([x[k] for x in grp]) if all(k in x for x in grp) else None  # noqa: E731
        return Views(images=torch.stack([x["images"] for x in grp]).float().div_(255), w2c=opt("w2c"), K=opt("K"),
                     depth=opt("depth"), mask=opt("mask"), normal=opt("normal"), index=opt("index"))

    return ViewBatch(context=views("context"), target=views("target"), dense=views("dense"),
                     scene=[s["scene"] for s in samples],
                     scale=torch.tensor([s["scale"] for s in samples], dtype=torch.float32),
                     world_from_source=torch.stack([s["world_from_source"] for s in samples]))


def _eval_shard(src: Iterator[dict]) -> Iterator[dict]:
    """Keep every (world x workers)-th sample for this (rank, worker): balanced and deterministic."""
    rank, world, worker, workers = wds.utils.pytorch_worker_info()
    total, me = world * workers, rank * workers + worker
    for i, s in enumerate(src):
        if i % total == me:
            yield s


def make_pipeline(urls: list[str], builder: SampleBuilder, *, train: bool, resampled: bool = True,
                  epoch_samples: int | None = None, shuffle: int = 16, seed: int = 0,
                  skip_corrupt: bool = False, counter: SkipCounter | None = None) -> wds.DataPipeline:
    """Shards -> per-sample dicts (batch with :func:`collate` in the DataLoader).

    Raises ``FileNotFoundError`` for missing shard files, and (unless ``skip_corrupt``) ``ValueError`` naming the
    shard and key for corrupt samples; with ``skip_corrupt`` they are skipped and counted in ``counter``.
    """
    urls = [str(u) for u in urls]
    if not urls:
        raise ValueError("shards: the split has no shards; check the shard root / url pattern")
    for u in urls:
        if "://" not in u and not u.startswith("pipe:") and not Path(u).exists():
            raise FileNotFoundError(f"shard {u}: file not found; check the data root or re-run anycity data synth")

    def handler(exn: BaseException) -> bool:
        if skip_corrupt:
            if counter is not None:
                counter.add("shard", exn)
            return True
        if isinstance(exn, (ValueError, FileNotFoundError)) and "shard" in str(exn):
            raise exn
        raise ValueError(f"corrupt or unreadable shard: {exn}") from exn

    def build(sample: dict):
        try:
            return builder(sample)
        except Exception as e:
            msg = str(e) if "shard" in str(e) else f"{sample_where(sample)}: {e}"
            if skip_corrupt:
                if counter is not None:
                    counter.add(sample_where(sample), e)
                return None
            raise ValueError(msg) from e

    if train and resampled:
        stages = [wds.ResampledShards(urls, seed=seed, deterministic=True)]
    elif train:
        # same shuffled order on every rank (seeded by seed + epoch), then split by rank and worker
        stages = [wds.SimpleShardList(urls), wds.detshuffle(bufsize=len(urls), initial=len(urls), seed=seed),
                  wds.split_by_node, wds.split_by_worker]
    else:
        stages = [wds.SimpleShardList(urls)]
    stages.append(wds.tarfile_to_samples(handler=handler))
    if not train:
        stages.append(_eval_shard)
    elif shuffle > 1:
        stages.append(wds.shuffle(shuffle, initial=min(shuffle, 4), rng=random.Random(seed)))
    stages += [wds.map(build, handler=handler), _flatten]
    pipe = wds.DataPipeline(*stages)
    if train and epoch_samples:
        pipe = pipe.with_epoch(epoch_samples)
    return pipe


def _flatten(src):
    for items in src:
        yield from items
