"""Write scenes into webdataset shards per split, plus ``index.json`` (shards, scenes, samples, views, split)."""

from __future__ import annotations

import errno
import json
import os
import time
from pathlib import Path

import numpy as np
import webdataset as wds

from anycity.atomic import atomic_write_bytes
from anycity.data.schema import SCHEMA_VERSION, SceneRecord, encode_scene, split_windows

SPLITS = ("train", "val", "test")


def split_scenes(n: int, seed: int = 0, ratios: tuple[float, float, float] = (0.8, 0.1, 0.1)) -> list[str]:
    """Deterministic 8:1:1 train/val/test assignment of ``n`` scenes (at least one val and test when n >= 3)."""
    if n < 3:
        return ["train"] * n
    n_val = max(1, round(n * ratios[1]))
    n_test = max(1, round(n * ratios[2]))
    order = np.random.default_rng(seed).permutation(n)
    out = ["train"] * n
    for i in order[:n_val]:
        out[i] = "val"
    for i in order[n_val:n_val + n_test]:
        out[i] = "test"
    return out


class ShardSetWriter:
    """Writes ``{split}-NNNNNN.tar`` shards, rolling over by sample count and byte size.

    Args:
        out: output directory (created).
        maxcount: most samples per shard.
        maxsize: most bytes per shard (a shard may exceed it by one sample).
        depth_dtype: "float16" or "float32" for the stored depth.
        window: cut each scene of the ``window_splits`` into samples of this many consecutive views (None: one
            sample per scene). Training reads only what it uses: a 24-view window of a 48-view scene is half
            the bytes per sample, and view selection happens within a window anyway.
        stride: views between window starts (default ``window // 2``: half-overlapping windows).
        window_splits: the splits that are windowed; evaluation splits stay whole scenes by default (each
            held-out view is scored once either way: windows own disjoint ranges).
    """

    def __init__(self, out: str | Path, maxcount: int = 64, maxsize: float = 1e9, depth_dtype: str = "float16",
                 window: int | None = None, stride: int | None = None,
                 window_splits: tuple[str, ...] = ("train",), overwrite: bool = False) -> None:
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.maxcount, self.maxsize, self.depth_dtype = maxcount, maxsize, depth_dtype
        self.window, self.stride, self.window_splits = window, stride, tuple(window_splits)
        index = self.out / "index.json"
        if index.exists() and not overwrite:
            raise FileExistsError(f"{self.out} already holds a shard set (index.json); pass --overwrite to replace "
                                  "it or choose another --out")
        index.unlink(missing_ok=True)  # from here on the old index can never list a half-rewritten shard
        for stale in self.out.glob("*.tar.partial"):  # leftovers of a killed run: never listed, safe to drop
            stale.unlink()
        self._writers: dict[str, wds.ShardWriter] = {}
        self._scenes: dict[str, dict] = {}
        self._samples: list[dict] = []

    def write(self, rec: SceneRecord, split: str = "train") -> None:
        """Write one scene (or a part of one: ``rec.scene`` / ``rec.first_index`` say where it lies)."""
        if split not in SPLITS:
            raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
        if split not in self._writers:
            # an integer mtime keeps tar headers plain ustar (a float one adds a pax header to every member)
            # shards are written as ``*.tar.partial`` and renamed when complete (``_publish``): a killed run
            # leaves no ``.tar`` that looks complete, and index.json (written last, atomically) lists only those
            self._writers[split] = wds.ShardWriter(str(self.out / f"{split}-%06d.tar.partial"),
                                                   maxcount=self.maxcount, maxsize=self.maxsize, verbose=0,
                                                   mtime=int(time.time()), post=_publish)
        w = self._writers[split]
        parts = split_windows(rec, self.window, self.stride) if split in self.window_splits else [rec]
        for part in parts:
            sample = encode_scene(part, split, self.depth_dtype)
            try:
                w.write(sample)
            except OSError as e:
                _raise_if_disk_full(e, Path(w.fname or self.out),
                                    sum(len(v) for v in sample.values() if isinstance(v, bytes)))
                raise
            self._samples.append({"key": part.key, "scene": part.scene or part.key, "split": split,
                                  "first": part.first_index, "num_views": len(part.views),
                                  "shard": Path(w.fname).name.removesuffix(".partial")})
        sid = rec.scene or rec.key
        sc = self._scenes.setdefault(sid, {"key": sid, "split": split, "num_views": 0, "num_samples": 0,
                                           "source": rec.source})
        sc["num_views"] = max(sc["num_views"], rec.scene_views or rec.first_index + len(rec.views))
        sc["num_samples"] += len(parts)

    def close(self) -> dict:
        """Finish all shards and write ``index.json`` (idempotent); returns the index.

        ``scenes``: one entry per scene (``key``, ``split``, ``num_views``, ``num_samples``, ``source``);
        ``samples``: one per sample (``key``, ``scene``, ``split``, ``first``, ``num_views``, ``shard``).
        """
        if getattr(self, "_index", None) is not None:
            return self._index
        for w in self._writers.values():
            w.close()
        shards: dict[str, dict] = {}
        for s in self._samples:
            e = shards.setdefault(s["shard"], {"path": s["shard"], "split": s["split"], "num_samples": 0})
            e["num_samples"] += 1
        index = {"schema_version": SCHEMA_VERSION, "shards": sorted(shards.values(), key=lambda e: e["path"]),
                 "scenes": list(self._scenes.values()), "samples": self._samples,
                 "window": {"size": self.window, "stride": self.stride or (self.window and self.window // 2),
                            "splits": list(self.window_splits)},
                 "splits": {sp: sorted(e["path"] for e in shards.values() if e["split"] == sp) for sp in SPLITS}}
        data = json.dumps(index, indent=1).encode()
        try:
            atomic_write_bytes(self.out / "index.json", data)
        except OSError as e:
            _raise_if_disk_full(e, self.out / "index.json", len(data))
            raise
        self._index = index
        return index

    def __enter__(self) -> ShardSetWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
            return
        # failed part-way: no index.json, and no shard left that looks complete
        for w in self._writers.values():
            if w.tarstream is not None:
                w.post = None
                try:
                    w.tarstream.close()
                except OSError:
                    pass
                w.tarstream = None
        for stale in self.out.glob("*.tar.partial"):
            stale.unlink(missing_ok=True)


def _publish(fname: str) -> None:
    """``ShardWriter`` post hook: fsync a finished ``*.tar.partial`` and rename it to ``*.tar``."""
    with open(fname, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(fname, fname.removesuffix(".partial"))


def _raise_if_disk_full(e: OSError, path: Path, nbytes: int) -> None:
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        raise OSError(e.errno, f"disk full writing {path}: about {nbytes} more bytes needed; free space on "
                               f"{path.parent} and rerun (no index.json was written for this run)") from e


def read_index(root: str | Path) -> dict:
    """Load ``index.json`` of a shard directory, checking its schema version."""
    p = Path(root) / "index.json"
    if not p.exists():
        raise FileNotFoundError(f"{p}: no index.json; point to a directory written by `anycity data synth|convert`")
    try:
        index = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: not JSON ({e}); re-create the shard set with `anycity data synth|convert`") from None
    if not isinstance(index, dict):
        raise ValueError(f"{p}: not a shard index (a {type(index).__name__}); re-create the shard set with "
                         "`anycity data synth|convert`")
    if index.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(f"{p}: written with shard schema_version {index.get('schema_version')}, but this anycity "
                         f"reads schema_version {SCHEMA_VERSION}; re-create the shards with this version")
    return index


def shard_urls(root: str | Path, split: str) -> list[str]:
    """Shard paths of one split of a shard directory (from its index.json)."""
    index = read_index(root)
    return [str(Path(root) / p) for p in index["splits"].get(split, [])]
