"""``AerialDataModule``: webdataset shards -> :class:`~anycity.structures.ViewBatch` for Lightning.

YAML (LightningCLI)::

    data:
      class_path: anycity.lit.datamodule.AerialDataModule
      init_args: {root: data/synth, image_size: [64, 64], num_context: 2, num_dense: 4, num_targets: 2}
"""

from __future__ import annotations

import copy
import math
import os
import signal
from pathlib import Path
from typing import NoReturn

import lightning.pytorch as pl
import torch
from lightning.pytorch.utilities import rank_zero_warn
from torch.utils.data import DataLoader
from webdataset.utils import pytorch_worker_info

from anycity.data.photos import list_photos, scene_name
from anycity.data.pipeline import (
    SampleBuilder,
    SkipCounter,
    collate,
    context_count_probs,
    count_samples,
    make_pipeline,
    to_float32,
)
from anycity.data.tario import is_url
from anycity.data.writer import read_index, shard_urls
from anycity.structures import ViewBatch


def _expand(spec: str | list[str] | None, split: str) -> list[str]:
    """Shard directory (with index.json), brace pattern, file, or a list of those -> shard paths. Each entry of a
    list must give shards of the split (:func:`_no_shards`): one that gave none was dropped, and the run read the
    others alone."""
    if spec is None:
        return []
    if isinstance(spec, (list, tuple)):
        return [u for s in spec for u in _expand(s, split) or _no_shards(split, s, f"{split}_shards entry {s!r}")]
    if not is_url(spec) and Path(spec).is_dir():
        return shard_urls(spec, split)
    import webdataset as wds

    return list(wds.shardlists.expand_urls(spec))


def _no_shards(split: str, where, given: str) -> NoReturn:
    """Raise the one-line error for ``where`` (a shard folder, pattern or list; ``given`` names it) giving no shards
    of ``split``: a folder whose index.json lists none says how to write that split."""
    if isinstance(where, str) and (Path(where) / "index.json").is_file():
        has = {k: len(v) for k, v in read_index(where)["splits"].items() if v}
        skip = {"val": "; or skip validation with --trainer.limit_val_batches 0", "train": ""}.get(split, "")
        raise ValueError(f"{split} shards: {Path(where) / 'index.json'} lists none (it has "
                         f"{', '.join(f'{k}: {n}' for k, n in has.items()) or 'no shards'}; the 8:1:1 scene "
                         f"split puts a set of few scenes in train alone): write a {split} set with anycity "
                         f"data convert --split {split} --out OTHER_FOLDER and pass --data.{split}_shards "
                         f"OTHER_FOLDER{skip}")
    raise ValueError(f"{split} shards: none found ({given}); give a shard directory with index.json listing {split} "
                     "shards, or a shard pattern")


def _collate_photos(items: list[dict]) -> dict:
    """Photo folders (see :func:`anycity.data.photos.load_photo_folder`) -> ``{"images": [B, V, 3, H, W], "scene":
    [B], "names": [B][V]}``."""
    out = {"images": torch.stack([it["images"] for it in items]), "scene": [it["scene"] for it in items],
           "names": [it["names"] for it in items]}
    if items[0].get("chunk") is not None:
        out["chunk"] = items[0]["chunk"]
    return out


class _IgnoreSignalsInWorkers:
    """DataLoader ``worker_init_fn``: a worker ignores SIGUSR1, then runs ``then`` (an earlier ``worker_init_fn``) if
    given, else Lightning's worker seeding when ``seed_everything(workers=True)`` asked for it (Lightning adds that
    only to a loader without a ``worker_init_fn``).

    A forked worker inherits Lightning's handlers: on SLURM's SIGUSR1 (sent to every process of the step) each worker
    would save an HPC checkpoint from its stale copy of the trainer and run ``scontrol requeue``. SIGTERM keeps torch's
    own worker handler, installed before this runs (so Lightning's never runs in a worker): it exits quietly when the
    loader's process ends the worker (``terminate()``) and dies by the signal otherwise. Ignored, workers outlived
    ``terminate()`` and hung the exit; reset to the default action, each died by the signal and torch printed "worker
    killed by signal: Terminated" at exit. A module-level class, so spawned workers can unpickle it.

    ``streams``: the ``(rank, world size)`` the data streams of the loader's process read, set as ``RANK`` and
    ``WORLD_SIZE`` in a worker that has neither: a spawned worker does not inherit ``torch.distributed``, and its
    streams would otherwise all be rank 0 of 1 (every rank training on the same samples, scoring every one)."""

    def __init__(self, then=None, rank: int | None = None, streams: tuple[int, int] | None = None) -> None:
        self.then, self.rank, self.streams = then, rank, streams

    def __call__(self, worker_id: int) -> None:
        if hasattr(signal, "SIGUSR1"):  # not on Windows
            signal.signal(signal.SIGUSR1, signal.SIG_IGN)
        if self.streams is not None and not ("RANK" in os.environ and "WORLD_SIZE" in os.environ):
            os.environ["RANK"], os.environ["WORLD_SIZE"] = (str(x) for x in self.streams)
        if self.then is not None:
            self.then(worker_id)
        elif int(os.environ.get("PL_SEED_WORKERS", 0)):
            from lightning.fabric.utilities.seed import pl_worker_init_function

            pl_worker_init_function(worker_id, rank=self.rank)


def worker_init_fn(then=None, rank: int | None = None,
                   streams: tuple[int, int] | None = None) -> _IgnoreSignalsInWorkers:
    """The ``worker_init_fn`` of every loader of :class:`AerialDataModule` (see :class:`_IgnoreSignalsInWorkers`);
    ``then``: a loader's own one, run after it; ``rank``: the global rank, for Lightning's worker seeding;
    ``streams``: the data streams' ``(rank, world size)``, for spawned workers."""
    return then if isinstance(then, _IgnoreSignalsInWorkers) else _IgnoreSignalsInWorkers(then, rank, streams)


class _PhotoChunks(torch.utils.data.Dataset):
    """The chunks of a photo folder, loaded one at a time. One chunk: the plain photo-folder sample; several: each
    carries ``"chunk": {"index", "count", "views", "plan", "names", "hw", "ordered_by"}`` for the exporter to align
    and merge (``ordered_by``: what ordered the photos, "time", "name" or "tokens")."""

    def __init__(self, photos, chunks: list[list[int]]) -> None:
        self.photos, self.chunks = photos, chunks

    def __len__(self) -> int:
        return len(self.chunks)

    def __getitem__(self, k: int) -> dict:
        views = self.chunks[k]
        item = {"images": self.photos.load(views), "scene": scene_name(self.photos.folder),
                "names": [self.photos.names[v] for v in views]}
        if len(self.chunks) > 1:
            item["chunk"] = {"index": k, "count": len(self.chunks), "views": views, "plan": self.chunks,
                             "names": self.photos.names, "hw": tuple(self.photos.hw),
                             "ordered_by": self.photos.ordered_by}
        return item


class AerialDataModule(pl.LightningDataModule):
    """Aerial multi-view batches from anycity webdataset shards.

    Args:
        root: a shard directory written by ``anycity data synth|convert`` (its ``index.json`` gives the
            train/val/test shards). Per-split arguments below override it.
        train_shards: shard directory, brace pattern (``data/x/train-{000000..000009}.tar``) or list for training.
        val_shards: the same for validation (llffhold targets of held-out scenes).
        test_shards: the same for testing.
        num_context: context (input) views per sample, 1..64 (evaluation, and training unless
            ``train_num_context`` is set).
        train_num_context: ``[lo, hi]``: training draws each batch's context count from ``lo..hi``, as VGGT and
            AnySplat train (2..24 views), so that training sees the counts inference will get. None: every batch
            has ``num_context``. Measured at quickstart scale in docs/stage2.md ("More views, a worse scaffold").
        train_context_weighting: "uniform", or "square" (probability proportional to the count squared, as
            AnySplat draws its counts).
        num_targets: target views per sample (rendered and scored).
        num_dense: dense teacher views per training sample for Stage II distillation; 0 disables the dense set.
            Evaluation samples carry none unless ``eval_dense`` (evaluation reads none); their context views are
            spread over the ``2 x num_context`` non-held-out views nearest the targets whatever ``num_dense``, so
            Stage I and Stage II configs test from the same context views.
        eval_dense: validation/test samples decode their ``num_dense`` dense views too (for diagnostics that read
            them, e.g. ``benchmarks/stage2_headroom.py --fit-steps``); the context and target views are the same.
        image_size: output ``[H, W]`` in pixels.
        resize_mode: "crop" (scale to cover, centre-crop to exactly image_size) or "keep" (keep the aspect ratio,
            about H*W pixels, sides multiples of ``patch_size``, cropped by under one patch so pixels stay square;
            all scenes of a batch must share an aspect ratio).
        patch_size: side multiple for ``resize_mode: keep``.
        batch_size: training samples per batch.
        eval_batch_size: validation/test samples per batch (default: batch_size).
        num_workers: DataLoader worker processes (0 decodes in the main process).
        epoch_samples: training samples per epoch per rank (``with_epoch``) of the resampled stream; not used with
            ``resampled: false``.
        resampled: draw training shards with replacement (True), or make each epoch one pass over the training
            samples in a shuffled shard order, split evenly by sample over ranks x workers (False: each sample at
            most once per epoch, floor(samples / (ranks x workers)) per worker; the remainder waits for a later
            epoch's order).
        shuffle_buffer: sample shuffle buffer for training.
        window: training sliding-window length in views (None: 2 x the largest view group), within one sample
            (shards hold trajectory windows of 24 views by default, see ``anycity data synth --window``).
        llffhold: evaluation targets are the views with index % llffhold == 0 (>= 2). An evaluation sample needs
            at least ``num_context`` other views.
        with_depth: load depth and masks when the shards have them.
        with_normals: give batches camera-frame normals: the shards' own when stored (``anycity data synth
            --normals``), else derived from depth (no loss consumes them; False reads ~1.5x faster at 448 px).
        seed: seed of shard resampling, shuffling and view selection.
        skip_corrupt: skip corrupt samples (unreadable, or NaN/inf in a camera, depth or image) and count them
            (logged as ``data/skipped_samples``); false: raise naming the shard and sample.
        pin_memory: DataLoader pin_memory.
        compact_batches: batches leave the DataLoader compact (uint8 images, float16 depth and normals: a third
            of the bytes through worker shared memory and host-to-device copies) and become the usual float32
            batch on the device after the transfer (``on_after_batch_transfer``). The LightningModule sees the
            same batch either way; code that iterates the DataLoader itself calls
            :func:`anycity.data.pipeline.to_float32`. Recommended for training at 448 px.
        predict_images: a folder of one scene's own photos (2 or more ``.jpg``/``.png``/``.webp``, no poses) that
            ``anycity predict`` reconstructs; None: ``predict`` reconstructs the test scenes. More photos than
            ``predict_chunk_size`` are reconstructed in overlapping chunks, aligned and merged (:mod:`anycity.city`).
        predict_chunk_size: photos per forward pass of ``predict_images`` (2..64, and 3 or more when the folder
            needs more than one chunk; 16 measured better than one pass of 32 with the quickstart model, and the
            camera refinement costs grow as its square).
        predict_chunk_overlap: photos shared by consecutive chunks (their alignment uses them).
        predict_order: photo order for chunking: "auto" (EXIF capture time when every photo has one, else file name),
            "time", "name" or "tokens" (a neighbour graph of the network's own global tokens from one low-resolution
            pass: for photos that form no sequence).
        predict_loop: the last photos see the first ones again (a closed orbit): add a loop-closure chunk of both
            ends, so the alignment's pose graph has a cycle.
        predict_resize: "keep" (each photo's aspect ratio, about image_size's pixel count, sides multiples of
            patch_size, cropped by under one patch so pixels stay square; mixed aspect ratios go to the most
            common one, with a warning) or "crop".
    """

    def __init__(self, root: str | None = None, train_shards: str | list[str] | None = None,
                 val_shards: str | list[str] | None = None, test_shards: str | list[str] | None = None,
                 num_context: int = 4, num_targets: int = 4, num_dense: int = 12,
                 image_size: tuple[int, int] = (448, 448), resize_mode: str = "crop", patch_size: int = 14,
                 batch_size: int = 1, eval_batch_size: int | None = None, num_workers: int = 2,
                 epoch_samples: int = 1000, resampled: bool = True, shuffle_buffer: int = 16,
                 window: int | None = None, llffhold: int = 8, with_depth: bool = True, with_normals: bool = True,
                 seed: int = 0, skip_corrupt: bool = True, pin_memory: bool = False,
                 compact_batches: bool = False, predict_images: str | None = None, predict_chunk_size: int = 16,
                 predict_chunk_overlap: int = 4, predict_order: str = "auto", predict_resize: str = "keep",
                 predict_loop: bool = False, train_num_context: tuple[int, int] | None = None,
                 train_context_weighting: str = "uniform", eval_dense: bool = False) -> None:
        super().__init__()
        if not 1 <= num_context <= 64:
            raise ValueError(f"num_context: expected 1..64 views, got {num_context}")
        if llffhold < 2:  # 0 divides by zero in every sample, 1 holds out every view
            raise ValueError(f"llffhold: expected >= 2 (every llffhold-th view of a scene is held out for evaluation; "
                             f"8 is the usual), got {llffhold}")
        context_count_probs(train_num_context, train_context_weighting)  # a typo fails here, not in a worker
        if resize_mode not in ("crop", "keep"):
            raise ValueError(f"resize_mode: expected 'crop' or 'keep', got {resize_mode!r}")
        if predict_resize not in ("crop", "keep"):
            raise ValueError(f"predict_resize: expected 'keep' or 'crop', got {predict_resize!r}")
        if predict_order not in ("auto", "time", "name", "tokens"):
            raise ValueError(f"predict_order: expected 'auto', 'time', 'name' or 'tokens', got {predict_order!r}")
        if len(image_size) != 2 or min(image_size) < 8:
            raise ValueError(f"image_size: expected [H, W] with sides >= 8, got {image_size!r}")
        _check_epoch(epoch_samples if resampled else None, num_workers, batch_size)
        if (isinstance(root, str) and predict_images is None and not is_url(root) and "{" not in root
                and not Path(root).exists()):
            # here, not when the first batch is read: before the run writes its config and logs (a predict from
            # photos reads no shards, so a config's root may point nowhere then)
            raise FileNotFoundError(f"data.root {root}: no such folder; fix the path, or write shards there with "
                                    f"anycity data synth --out {root} (or anycity data convert)")
        if predict_images is not None:  # as data.root: before the run writes any output
            _check_photo_count(predict_images)
        self.save_hyperparameters()
        self.hp = self.hparams
        self.skip_counter = SkipCounter()
        self._reported = 0

    def _urls(self, split: str) -> list[str]:
        spec = {"train": self.hp.train_shards, "val": self.hp.val_shards, "test": self.hp.test_shards}[split]
        if spec is None and split != "train":
            _check_root_names_splits(self.hp.root, split)
        where = spec if spec is not None else self.hp.root
        return _expand(where, split) or _no_shards(split, where, f"root={self.hp.root!r}, {split}_shards={spec!r}")

    def check_split(self, subcommand: str, trainer: pl.Trainer | None = None) -> None:
        """Refuse a run whose split has no shards (a train-only ``index.json``), in the line its first batch would
        give, before the run moves the previous run's logs aside; a ``fit`` checks ``val`` too when ``trainer``
        will validate (else its first validation, maybe hours in, would stop it)."""
        splits = {"fit": ["train"], "validate": ["val"], "test": ["test"], "predict": ["test"]}.get(subcommand, [])
        if subcommand == "fit" and trainer is not None and _validates(trainer):
            splits.append("val")
        if subcommand == "predict" and self.hp.predict_images is not None:
            splits = []
        for split in splits:
            self._urls(split)

    def _builder(self, train: bool) -> SampleBuilder:
        return SampleBuilder(self.hp.num_context, self.hp.num_targets, self.hp.num_dense, tuple(self.hp.image_size),
                             self.hp.resize_mode, train, self.hp.window, self.hp.with_depth, self.hp.with_normals,
                             self.hp.llffhold, self.hp.patch_size, self.hp.seed, self.hp.compact_batches,
                             self.hp.train_num_context if train else None, self.hp.train_context_weighting,
                             self.hp.batch_size, eval_dense=self.hp.eval_dense)

    def _loader(self, split: str, first_epoch: int = 0) -> DataLoader:
        train = split == "train"
        workers = self.hp.num_workers
        # epoch_samples per rank, split over its workers (each rank draws its own resampled stream)
        per_worker = math.ceil(self.hp.epoch_samples / max(1, workers)) if train and self.hp.resampled else None
        pipe = make_pipeline(self._urls(split), self._builder(train), train=train, resampled=self.hp.resampled,
                             epoch_samples=per_worker, shuffle=self.hp.shuffle_buffer, seed=self.hp.seed,
                             skip_corrupt=self.hp.skip_corrupt, counter=self.skip_counter, first_epoch=first_epoch)
        bs = self.hp.batch_size if train else (self.hp.eval_batch_size or self.hp.batch_size)
        return DataLoader(pipe, batch_size=bs, collate_fn=collate, num_workers=workers,
                          persistent_workers=workers > 0, pin_memory=self.hp.pin_memory, drop_last=train,
                          worker_init_fn=worker_init_fn(rank=self._rank(), streams=_stream_rank_world()))

    def _rank(self) -> int | None:
        return getattr(self.trainer, "global_rank", None)

    def train_dataloader(self) -> DataLoader | _FixedBatches:
        self._check_windows()
        overfit = getattr(self.trainer, "overfit_batches", 0)  # N batches (an int); a fraction stays Lightning's
        if isinstance(overfit, int) and overfit > 0:
            return _FixedBatches(self._loader("train"), overfit)
        # resumed (``--ckpt_path``): start at the interrupted run's epoch and skip the samples it already trained on
        # in it, so the resumed run sees the stream an uninterrupted one would (exact with num_workers=0)
        done, epoch = _batches_trained(self.trainer), 0
        per_epoch = self._batches_per_epoch() if done else None
        if per_epoch is not None:
            epoch, done = divmod(done, max(1, per_epoch))
        loader = self._loader("train", epoch)
        if done:
            loader = DataLoader(_SkipFirst(loader.dataset, done, loader.batch_size), batch_size=loader.batch_size,
                                collate_fn=loader.collate_fn, num_workers=loader.num_workers,
                                persistent_workers=loader.persistent_workers, pin_memory=loader.pin_memory,
                                drop_last=loader.drop_last, worker_init_fn=worker_init_fn(loader.worker_init_fn))
        return loader

    def _batches_per_epoch(self) -> int | None:
        """Training batches per epoch of this rank (None: a resampled stream without ``epoch_samples`` has one
        endless epoch). Each worker drops its own last partial batch."""
        workers = max(1, self.hp.num_workers)
        if self.hp.resampled:
            if not self.hp.epoch_samples:
                return None
            per_worker = math.ceil(self.hp.epoch_samples / workers)
        else:  # one pass, split by sample over every rank's workers (data/pipeline._PassShare)
            per_worker = count_samples(self._urls("train")) // (_stream_rank_world()[1] * workers)
        return workers * (per_worker // self.hp.batch_size)

    def _check_windows(self) -> None:
        """Refuse, before training starts, context + target counts that a training window of the shards' index (or
        ``window``) cannot hold as distinct views (select_train refuses the sample otherwise)."""
        hi = max(self.hp.train_num_context or [self.hp.num_context])
        need = int(hi) + self.hp.num_targets
        spec = self.hp.train_shards if self.hp.train_shards is not None else self.hp.root
        short = _shortest_train_sample(spec)
        if self.hp.window is not None and (short is None or self.hp.window < short[0]):
            short = (self.hp.window, "data.window")
        if short is not None and need > short[0]:
            n, where = short
            raise ValueError(f"train_num_context/num_context: up to {hi} context + {self.hp.num_targets} target "
                             f"views do not fit the {n}-view training windows of {where}, so targets would repeat or "
                             f"be context views; use at most {n - self.hp.num_targets} context views, fewer "
                             "num_targets, or longer windows (data.window; anycity data synth --window, "
                             "convert --max_views)")

    def val_dataloader(self) -> DataLoader:
        _warn_limit_per_rank(self.trainer, "limit_val_batches")
        return self._loader("val")

    def test_dataloader(self) -> DataLoader:
        _warn_limit_per_rank(self.trainer, "limit_test_batches")
        return self._loader("test")

    def predict_dataloader(self) -> DataLoader:
        if self.hp.predict_images is None:
            return self.test_dataloader()
        world = getattr(self.trainer, "world_size", 1)
        if world > 1:  # each rank would get some of the chunks and merge a part of the scene
            raise ValueError(f"predict_images: one photo folder is reconstructed in one process (its chunks are "
                             f"aligned and merged together), not on {world}; pass --trainer.devices 1")
        from anycity.city.plan import plan_chunks
        from anycity.data.photos import MAX_VIEWS, PhotoFolder

        if not 2 <= self.hp.predict_chunk_size <= MAX_VIEWS:
            raise ValueError(f"predict_chunk_size: expected 2..{MAX_VIEWS} photos per forward pass, got "
                             f"{self.hp.predict_chunk_size}")
        tokens = self.hp.predict_order == "tokens"
        photos = PhotoFolder(self.hp.predict_images, tuple(self.hp.image_size), self.hp.predict_resize,
                             self.hp.patch_size, "name" if tokens else self.hp.predict_order)
        if tokens and len(photos) > self.hp.predict_chunk_size:
            self._order_by_tokens(photos)
        chunks = plan_chunks(len(photos), self.hp.predict_chunk_size, self.hp.predict_chunk_overlap,
                             self.hp.predict_loop)
        return DataLoader(_PhotoChunks(photos, chunks), batch_size=1, collate_fn=_collate_photos,
                          worker_init_fn=worker_init_fn())

    def _order_by_tokens(self, photos) -> None:
        """Order ``photos`` along the neighbour graph of the network's own global tokens (one pass per photo at
        half the resolution, no cross-view attention), for photos that do not form a sequence by name or time."""
        from anycity.city.plan import order_from_descriptors, token_descriptors
        from anycity.data.photos import PhotoFolder

        module = self.trainer.lightning_module if self.trainer is not None else None
        if module is None or not hasattr(module, "net"):
            raise ValueError("predict_order 'tokens' needs the network: run it from `anycity predict`")
        p = self.hp.patch_size
        small = tuple(max(2 * p, s // 2) for s in self.hp.image_size)
        low = PhotoFolder(photos.folder, small, self.hp.predict_resize, p, "name")
        order = order_from_descriptors(token_descriptors(module.net, low.load, len(low)))
        photos.reorder(order, "tokens")

    @property
    def num_skipped(self) -> int:
        """Corrupt samples skipped so far (all workers of this process)."""
        return self.skip_counter.count

    def on_after_batch_transfer(self, batch, dataloader_idx: int):
        if self.hp.compact_batches and isinstance(batch, ViewBatch):  # photo folders are float32 already
            batch = to_float32(batch)
        if self.hp.skip_corrupt and self.trainer is not None and self.trainer.global_step % 50 == 0:
            n = self.num_skipped
            if self.trainer.logger is not None:
                self.trainer.logger.log_metrics({"data/skipped_samples": float(n)}, step=self.trainer.global_step)
            if n > self._reported:
                rank_zero_warn(f"AerialDataModule: skipped {n} corrupt samples so far (skip_corrupt=True); "
                               f"see {self.skip_counter.directory}")
                self._reported = n
        return batch


def _stream_rank_world() -> tuple[int, int]:
    """``(rank, world size)`` as this process's data streams read them: RANK/WORLD_SIZE, else torch.distributed."""
    rank, world, _, _ = pytorch_worker_info()
    return rank, world


def _check_epoch(epoch_samples: int | None, num_workers: int, batch_size: int) -> None:
    """Refuse an epoch whose samples leave each worker less than one whole batch: with ``drop_last`` the epoch would
    have no batch, and Lightning would run empty epochs forever."""
    workers = max(1, num_workers)
    if epoch_samples and math.ceil(epoch_samples / workers) < batch_size:
        raise ValueError(f"epoch_samples: {epoch_samples} samples over num_workers {num_workers} leave each worker "
                         f"fewer than batch_size {batch_size}, so every training epoch would have no batch; set "
                         f"epoch_samples >= {workers * batch_size} (num_workers x batch_size) or lower num_workers or "
                         "batch_size")


def _validates(trainer: pl.Trainer) -> bool:
    """Whether a ``fit`` with ``trainer`` reads the val split: its sanity check, or a validation within
    ``max_steps`` (an int ``val_check_interval`` past ``max_steps`` with no sanity check never validates)."""
    if trainer.limit_val_batches == 0:
        return False
    interval = trainer.val_check_interval
    never = isinstance(interval, int) and 0 < trainer.max_steps < interval
    return trainer.num_sanity_val_steps != 0 or not never


def _check_photo_count(folder: str) -> None:
    """Refuse a ``predict_images`` folder that is no folder or holds too few photos, by the photo loader's own
    listing (no photo is decoded); its warnings about files it does not read come when the photos are loaded."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        list_photos(folder)


def _warn_limit_per_rank(trainer, option: str) -> None:
    """One line when a multi-process run limits evaluation to a count of batches: Lightning counts them per rank,
    so the figures cover another set (and world-size times more views) than a one-process run's."""
    limit, world = getattr(trainer, option, None), getattr(trainer, "world_size", 1)
    if world > 1 and isinstance(limit, int) and not isinstance(limit, bool) and limit > 0:
        rank_zero_warn(f"trainer.{option} {limit} counts batches per process: {world} processes score up to "
                       f"{limit * world} batches, another set than one process's {limit}, so these figures compare "
                       f"only with runs on {world} processes; set --trainer.{option} 1.0 (the whole set) for figures "
                       "that do not depend on the number of processes")


def _check_root_names_splits(root: str | None, split: str) -> None:
    """Refuse a ``root`` that is a shard file or pattern for an evaluation split: it names no split, so validation
    and testing would read the training shards."""
    if isinstance(root, str) and (is_url(root) or not Path(root).is_dir()):
        raise ValueError(f"{split} shards: data.root {root} is a shard file or pattern, not a folder with index.json, "
                         f"so it names no {split} set ({split} would read the training shards); pass "
                         f"--data.{split}_shards FOLDER_OR_PATTERN, or point data.root at a folder written by anycity "
                         "data synth|convert")


def _shortest_train_sample(spec: str | list[str] | None) -> tuple[int, str] | None:
    """``(views, folder)`` of the shortest training sample that the index.json of ``spec``'s shard folders lists;
    None when ``spec`` names no folder."""
    found = []
    for folder in spec if isinstance(spec, (list, tuple)) else [spec]:
        if isinstance(folder, str) and not is_url(folder) and Path(folder).is_dir():
            views = [int(s["num_views"]) for s in read_index(folder).get("samples", []) if s.get("split") == "train"]
            found += [(min(views), folder)] if views else []
    return min(found, default=None)


def _batches_trained(trainer) -> int:
    """Training batches a resumed fit already took from its loader, all epochs (0 for a fresh fit): Lightning's
    restored loop progress. Not ``global_step x accumulate_grad_batches``: Lightning also steps on an epoch's last
    batch, whatever the accumulation."""
    loop = getattr(getattr(trainer, "fit_loop", None), "epoch_loop", None)
    return 0 if loop is None else int(loop.batch_progress.total.processed)


class _SkipFirst(torch.utils.data.IterableDataset):
    """The first iteration of ``dataset`` drops the samples of the loader's first ``batches`` batches of
    ``batch_size``; later ones are whole. A DataLoader takes batches from its W workers in turn, so worker k drops
    ``ceil((batches - k) / W)`` whole batches (a count of samples split evenly could cut a batch, whose samples then
    straddled two with ``train_num_context``)."""

    def __init__(self, dataset, batches: int, batch_size: int) -> None:
        self.dataset, self.batches, self.batch_size = dataset, int(batches), int(batch_size)

    def __iter__(self):
        info = torch.utils.data.get_worker_info()
        k, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        n = max(0, -(-(self.batches - k) // workers)) * self.batch_size
        it, self.batches = iter(self.dataset), 0
        for _ in range(n):
            if next(it, _END) is _END:
                return
        yield from it


_END = object()


class _FixedBatches:
    """``trainer.overfit_batches``: the first ``n`` batches of ``loader``, read once and given (as copies) on every
    iteration, so every epoch trains on the same tensors. Lightning takes the first batches of a fresh iterator each
    epoch, and each pass over the shard stream differs (the shard shuffle and the view draws move on)."""

    def __init__(self, loader: DataLoader, n: int) -> None:
        it = iter(loader)
        self.batches = [b for _, b in zip(range(n), it)]
        del it, loader  # the loader's workers (persistent) end with it

    def __len__(self) -> int:
        return len(self.batches)

    def __iter__(self):
        for b in self.batches:
            yield copy.deepcopy(b)  # a step that changes its batch in place leaves the next epoch's alone
