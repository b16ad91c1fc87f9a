"""Write scenes into webdataset shards per split, plus ``index.json`` (shards, scenes, views, split)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import webdataset as wds

from anycity.data.schema import SCHEMA_VERSION, SceneRecord, encode_scene

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
    """

    def __init__(self, out: str | Path, maxcount: int = 64, maxsize: float = 1e9, depth_dtype: str = "float16"):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.maxcount, self.maxsize, self.depth_dtype = maxcount, maxsize, depth_dtype
        self._writers: dict[str, wds.ShardWriter] = {}
        self._scenes: list[dict] = []

    def write(self, rec: SceneRecord, split: str = "train") -> None:
        if split not in SPLITS:
            raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
        if split not in self._writers:
            self._writers[split] = wds.ShardWriter(str(self.out / f"{split}-%06d.tar"), maxcount=self.maxcount,
                                                   maxsize=self.maxsize, verbose=0)
        w = self._writers[split]
        w.write(encode_scene(rec, split, self.depth_dtype))
        self._scenes.append({"key": rec.key, "split": split, "num_views": len(rec.views),
                             "shard": Path(w.fname).name, "source": rec.source})

    def close(self) -> dict:
        """Finish all shards and write ``index.json`` (idempotent); returns the index."""
        if getattr(self, "_index", None) is not None:
            return self._index
        for w in self._writers.values():
            w.close()
        shards: dict[str, dict] = {}
        for s in self._scenes:
            e = shards.setdefault(s["shard"], {"path": s["shard"], "split": s["split"], "num_samples": 0})
            e["num_samples"] += 1
        index = {"schema_version": SCHEMA_VERSION, "shards": sorted(shards.values(), key=lambda e: e["path"]),
                 "scenes": self._scenes,
                 "splits": {sp: sorted(e["path"] for e in shards.values() if e["split"] == sp) for sp in SPLITS}}
        (self.out / "index.json").write_text(json.dumps(index, indent=1))
        self._index = index
        return index

    def __enter__(self) -> ShardSetWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_index(root: str | Path) -> dict:
    """Load ``index.json`` of a shard directory, checking its schema version."""
    p = Path(root) / "index.json"
    if not p.exists():
        raise FileNotFoundError(f"{p}: no index.json; point to a directory written by `anycity data synth|convert`")
    index = json.loads(p.read_text())
    if index.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(f"{p}: written with shard schema_version {index.get('schema_version')}, but this anycity "
                         f"reads schema_version {SCHEMA_VERSION}; re-create the shards with this version")
    return index


def shard_urls(root: str | Path, split: str) -> list[str]:
    """Shard paths of one split of a shard directory (from its index.json)."""
    index = read_index(root)
    return [str(Path(root) / p) for p in index["splits"].get(split, [])]
