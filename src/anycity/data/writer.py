"""Write scenes into webdataset shards per split, plus ``index.json`` (shards, scenes, samples, views, split).

One run writes in a folder at a time: :class:`ShardSetWriter` holds the lock file ``.anycity-writing.lock`` there
(pid and host of the run) from its start to its end, and a second run on the same folder is refused in one line.
A lock left by a killed run on this host (its pid no longer runs) is taken over with a warning; one from another
host is refused, naming the file to delete once that run is gone.
"""

from __future__ import annotations

import errno
import json
import os
import re
import secrets
import socket
import tarfile
import time
import warnings
from pathlib import Path

import numpy as np
import webdataset as wds

from anycity.atomic import atomic_write_bytes, pid_runs
from anycity.data.schema import CAMERAS_KEY, SCHEMA_VERSION, SceneRecord, encode_scene, split_windows, window_bounds

SPLITS = ("train", "val", "test")
DEPTH_DTYPES = ("float16", "float32")
LOCK_NAME = ".anycity-writing.lock"
"""The lock file a writing run holds in its output folder (JSON: ``pid``, ``host``, ``started``, ``token``)."""
PREVIEW_NAME = "preview.png"
"""The contact sheet ``anycity data synth --preview`` writes beside the shards; ``overwrite`` removes an earlier one."""
_SHARD_RE = re.compile(r"(train|val|test)-\d{6}\.tar")  # the names this writer gives its shards
SHARD_MTIME = 0
"""Modification time of every tar member: fixed, so identical runs write identical shard bytes."""


def split_scenes(n: int, seed: int = 0, ratios: tuple[float, float, float] = (0.8, 0.1, 0.1)) -> list[str]:
    """Deterministic 8:1:1 train/val/test assignment of ``n`` scenes (at least one val and test when n >= 3).

    The assignment is a permutation of all ``n`` scenes, so a scene's split depends on ``n`` as well as ``seed``,
    while a synthetic city depends only on ``(seed, scene index)`` (``anycity data synth``): sets of different
    sizes made with one seed share cities across their splits. A held-out set for a model trained on a synthetic
    set must be made with another ``--seed``.
    """
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
        overwrite: replace a shard set already in ``out`` (default: refuse), or files named like its shards; its
            ``index.json`` and :data:`PREVIEW_NAME` are removed here, its shards that the new set does not list
            when the new set is complete.
        check_views: refuse a view whose camera or array sizes are unsound (:func:`~anycity.data.schema.encode_scene`);
            False writes them as given (tests of how readers handle a damaged set).

    The writer holds ``out``'s lock file (:data:`LOCK_NAME`) from here to :meth:`close` (or a failure in a
    ``with`` block). Shards named like this writer's (``{train,val,test}-NNNNNN.tar``) that the new index does not
    list, an earlier run's or a killed run's, are removed when the set is complete, with a warning naming them.
    Without ``overwrite``, files of such names that are not an anycity run's (another webdataset set: their first
    sample has no ``cameras.json``) are refused here, before anything is written.
    """

    def __init__(self, out: str | Path, maxcount: int = 64, maxsize: float = 1e9, depth_dtype: str = "float16",
                 window: int | None = None, stride: int | None = None, window_splits: tuple[str, ...] = ("train",),
                 overwrite: bool = False, check_views: bool = True) -> None:
        try:  # an integer type would store metres truncated, modulo its range
            name = np.dtype(depth_dtype).name
        except (TypeError, ValueError):
            name = None
        if name not in DEPTH_DTYPES:
            raise ValueError(f"depth_dtype: expected one of {DEPTH_DTYPES} (the stored depth's precision), got "
                             f"{depth_dtype!r}")
        depth_dtype = name
        if window is not None:  # refused here, not after the first scene was rendered or read
            window_bounds(window + 1, window, stride)
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.maxcount, self.maxsize, self.depth_dtype = maxcount, maxsize, depth_dtype
        self.window, self.stride, self.window_splits = window, stride, tuple(window_splits)
        self.check_views = check_views
        self._lock: Path | None
        self._lock, self._lock_text = _acquire_lock(self.out)
        try:
            index = self.out / "index.json"
            if index.exists() and not overwrite:
                raise FileExistsError(f"{self.out} already holds a shard set (index.json); pass --overwrite to "
                                      "replace it or choose another --out")
            foreign = [] if overwrite else _foreign_shards(self.out)
            if foreign:
                shown = ", ".join(foreign[:4]) + (f" and {len(foreign) - 4} more" if len(foreign) > 4 else "")
                raise FileExistsError(f"{self.out} holds {len(foreign)} file(s) named like this writer's shards that "
                                      f"no anycity run wrote ({shown}); pass --overwrite to replace them or choose "
                                      "another --out")
            self._old_shards = _listed_shards(index)
            index.unlink(missing_ok=True)  # from here on the old index can never list a half-rewritten shard
            if overwrite:  # the earlier set's preview would sit beside the new shards (a run may not write one)
                (self.out / PREVIEW_NAME).unlink(missing_ok=True)
            for stale in self.out.glob("*.tar.partial"):  # leftovers of a killed run: never listed, safe to drop
                stale.unlink()
        except BaseException:
            self._release()
            raise
        self._writers: dict[str, wds.ShardWriter] = {}
        self._scenes: dict[str, dict] = {}
        self._samples: list[dict] = []
        self._keys: set[str] = set()

    def write(self, rec: SceneRecord, split: str = "train") -> None:
        """Write one scene (or a part of one: ``rec.scene`` / ``rec.first_index`` say where it lies)."""
        if split not in SPLITS:
            raise ValueError(f"split: expected one of {SPLITS}, got {split!r}")
        if split not in self._writers:
            # a fixed integer mtime: identical runs give identical bytes, and tar headers stay plain ustar (a float
            # one adds a pax header to every member)
            # shards are written as ``*.tar.partial`` and renamed when complete (``_publish``): a killed run
            # leaves no ``.tar`` that looks complete, and index.json (written last, atomically) lists only those
            self._writers[split] = wds.ShardWriter(str(self.out / f"{split}-%06d.tar.partial"),
                                                   maxcount=self.maxcount, maxsize=self.maxsize, verbose=0,
                                                   mtime=SHARD_MTIME, post=_publish)
        w = self._writers[split]
        parts = split_windows(rec, self.window, self.stride) if split in self.window_splits else [rec]
        self._claim_keys([part.key for part in parts])
        for part in parts:
            sample = encode_scene(part, split, self.depth_dtype, check=self.check_views)
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

    def _claim_keys(self, keys: list[str]) -> None:
        """Refuse, before anything of them is written, sample keys this set already holds: a reader groups tar
        members by key, so a second sample under one key would be merged into or replace the first."""
        for k in keys:
            if k in self._keys:
                raise ValueError(f"sample key {k!r}: already written to {self.out} (two scenes with one key); give "
                                 "each scene or window a distinct key")
        self._keys.update(keys)

    def close(self) -> dict:
        """Finish all shards and write ``index.json`` (idempotent); returns the index.

        ``scenes``: one entry per scene (``key``, ``split``, ``num_views``, ``num_samples``, ``source``);
        ``samples``: one per sample (``key``, ``scene``, ``split``, ``first``, ``num_views``, ``shard``).
        """
        if getattr(self, "_index", None) is not None:
            return self._index
        try:
            return self._close()
        finally:
            self._release()

    def _close(self) -> dict:
        self._finish_shards()
        shards: dict[str, dict] = {}
        for s in self._samples:
            e = shards.setdefault(s["shard"], {"path": s["shard"], "split": s["split"], "num_samples": 0})
            e["num_samples"] += 1
        index = {"schema_version": SCHEMA_VERSION, "shards": sorted(shards.values(), key=lambda e: e["path"]),
                 "scenes": list(self._scenes.values()), "samples": self._samples,
                 "window": {"size": self.window, "stride": self.stride or (self.window and self.window // 2),
                            "splits": list(self.window_splits)},
                 "splits": {sp: sorted(e["path"] for e in shards.values() if e["split"] == sp) for sp in SPLITS}}
        self._remove_unlisted(set(shards))
        data = json.dumps(index, indent=1).encode()
        try:
            atomic_write_bytes(self.out / "index.json", data)
        except OSError as e:
            _raise_if_disk_full(e, self.out / "index.json", len(data))
            raise
        self._index = index
        return index

    def _finish_shards(self) -> None:
        """Finish and publish every open shard. Finishing writes the tar's end blocks and flushes what is buffered,
        so a full disk can strike here too: then the unpublished shards are dropped, as after a failed write, and
        the error names the shard and the bytes still to be written."""
        todo = list(self._writers.values())
        for i, w in enumerate(todo):
            need = sum(_unwritten_bytes(x) for x in todo[i:])
            try:
                w.close()
            except BaseException as e:
                self._drop_partials()
                if isinstance(e, OSError):
                    _raise_if_disk_full(e, Path(w.fname or self.out), need)
                raise

    def _drop_partials(self) -> None:
        """Close the open shards without publishing them and remove every ``*.tar.partial`` (a failed run)."""
        for w in self._writers.values():
            if getattr(w, "tarstream", None) is not None:  # a closed ShardWriter has no ``tarstream`` left
                w.post = None
                try:
                    w.tarstream.close()
                except OSError:
                    pass
                w.tarstream = None
        for stale in self.out.glob("*.tar.partial"):
            stale.unlink(missing_ok=True)

    def _remove_unlisted(self, keep: set[str]) -> None:
        """Remove the shards of an earlier (or killed) run that this set does not list: readers that glob
        ``*.tar`` would otherwise mix them in."""
        names = {p.name for p in self.out.iterdir() if _SHARD_RE.fullmatch(p.name) and p.is_file()}
        names |= {n for n in self._old_shards if (self.out / n).is_file()}
        gone = sorted(names - keep)
        for n in gone:
            (self.out / n).unlink(missing_ok=True)
        if gone:
            shown = ", ".join(gone[:4]) + (f" and {len(gone) - 4} more" if len(gone) > 4 else "")
            warnings.warn(f"{self.out}: removed {len(gone)} shard(s) of an earlier run that this set does not list "
                          f"({shown})", stacklevel=4)

    def _release(self) -> None:
        """Remove the lock file if it is still this writer's (idempotent)."""
        lock, self._lock = self._lock, None
        if lock is not None:
            _release_lock(lock, self._lock_text)

    def __enter__(self) -> ShardSetWriter:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
            return
        self._drop_partials()  # failed part-way: no index.json, and no shard left that looks complete
        self._release()


def _listed_shards(index: Path) -> set[str]:
    """The shard names an existing ``index.json`` lists (plain names in its folder only; none if unreadable)."""
    try:
        shards = json.loads(index.read_text()).get("shards", [])
        return {e["path"] for e in shards if isinstance(e, dict) and isinstance(e.get("path"), str)
                and _SHARD_RE.fullmatch(e["path"])}
    except (OSError, ValueError, AttributeError, TypeError):
        return set()


def _foreign_shards(out: Path) -> list[str]:
    """The files of ``out`` named like this writer's shards whose first sample has no ``cameras.json`` member (every
    sample this writer writes has one; webdataset writes a sample's members in name order, so it comes last)."""
    return sorted(p.name for p in out.iterdir() if _SHARD_RE.fullmatch(p.name) and p.is_file()
                  and not _anycity_shard(p))


def _anycity_shard(path: Path) -> bool:
    """Whether the first sample of the tar ``path`` holds ``<key>.cameras.json`` (headers only are read)."""
    try:
        with tarfile.open(path, "r:") as tar:
            first = None
            while (m := tar.next()) is not None:
                key = m.name.split(".", 1)[0]
                if first not in (None, key):  # the first sample ended without one
                    return False
                first = key
                if m.name == f"{key}.{CAMERAS_KEY}":
                    return True
    except (OSError, tarfile.TarError):
        pass
    return False


def _read_lock(path: Path) -> tuple[str, dict | None] | None:
    """``(text, holder)`` of a lock file (holder None when it is not a lock this module wrote); None if absent."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError):
        return "", None
    try:
        holder = json.loads(text)
    except ValueError:
        return text, None
    ok = isinstance(holder, dict) and isinstance(holder.get("pid"), int) and holder["pid"] > 0 \
        and isinstance(holder.get("host"), str)
    return text, holder if ok else None


def _acquire_lock(out: Path) -> tuple[Path, str]:
    """Create ``out/LOCK_NAME`` exclusively (O_CREAT | O_EXCL) with this run's pid and host, or refuse in one line;
    a lock of a process of this host that no longer runs is taken over with a warning. Returns the lock's path and
    text."""
    path = out / LOCK_NAME
    host = socket.gethostname()
    mine = json.dumps({"pid": os.getpid(), "host": host, "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                       "token": secrets.token_hex(8)})
    for _ in range(5):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            found = _read_lock(path)
            if found is None:  # released meanwhile
                continue
            text, holder = found
            if holder is None:
                raise FileExistsError(f"{out}: another run may be writing a shard set here (lock file {path}, not "
                                      f"readable as one); wait for it or choose another --out, or, if no run writes "
                                      f"there, delete {path}") from None
            if holder["host"] != host or pid_runs(holder["pid"]):
                since = f", since {holder['started']}" if isinstance(holder.get("started"), str) else ""
                raise FileExistsError(f"{out}: another run (pid {holder['pid']} on {holder['host']}{since}) is "
                                      f"writing a shard set here (lock file {path}); wait for it to finish or choose "
                                      f"another --out, or, if that run is gone, delete {path}") from None
            # a killed run's lock: move it aside under a name of our own, then check that it is the one we read
            aside = out / f"{LOCK_NAME}.stale-{os.getpid()}-{secrets.token_hex(4)}"
            try:
                os.rename(path, aside)
            except FileNotFoundError:
                continue
            moved = _read_lock(aside)
            if moved is None or moved[0] != text:  # another run took it over meanwhile: give its lock back
                try:
                    os.link(aside, path)
                except OSError:
                    pass
                aside.unlink(missing_ok=True)
                continue
            aside.unlink(missing_ok=True)
            warnings.warn(f"{path}: taking over the lock of pid {holder['pid']} on {host}, which no longer runs "
                          "(a killed run); its unfinished shards are removed", stacklevel=3)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(mine)
        return path, mine
    raise FileExistsError(f"{out}: other runs keep taking the lock file {path}; run one `anycity data` at a time "
                          "on this folder, or choose another --out")


def _release_lock(path: Path, text: str) -> None:
    """Remove a lock file if it still holds ``text`` (a lock another run took over is left to that run)."""
    found = _read_lock(path)
    if found is not None and found[0] == text:
        path.unlink(missing_ok=True)


def _publish(fname: str) -> None:
    """``ShardWriter`` post hook: fsync a finished ``*.tar.partial`` and rename it to ``*.tar``."""
    with open(fname, "rb+") as f:
        os.fsync(f.fileno())
    os.replace(fname, fname.removesuffix(".partial"))


def _unwritten_bytes(w: wds.ShardWriter) -> int:
    """Bytes the open shard of ``w`` has yet to put on disk: its tar once finished (two end blocks, padded to a whole
    record) less what the file holds; 0 when no shard is open."""
    tar = getattr(getattr(w, "tarstream", None), "tarstream", None)
    if tar is None:
        return 0
    total = -(-(tar.offset + 2 * tarfile.BLOCKSIZE) // tarfile.RECORDSIZE) * tarfile.RECORDSIZE
    try:
        held = os.stat(w.fname).st_size
    except (OSError, TypeError):
        held = 0
    return max(total - held, 0)


def _raise_if_disk_full(e: OSError, path: Path, nbytes: int) -> None:
    if e.errno in (errno.ENOSPC, errno.EDQUOT):
        raise OSError(e.errno, f"disk full writing {path}: about {nbytes} more bytes needed; free space on "
                               f"{path.parent} and rerun (no index.json was written for this run)") from e


def read_index(root: str | Path) -> dict:
    """Load ``index.json`` of a shard directory, checking its schema version."""
    p = Path(root) / "index.json"
    if not p.exists():
        raise FileNotFoundError(_no_index_hint(Path(root)))
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


def _no_index_hint(root: Path) -> str:
    """The one-line reason a folder has no ``index.json``: a run still writing it, one that was interrupted (its
    lock, ``*.tar.partial`` files or shards are there), or not a shard set at all."""
    p = root / "index.json"
    try:
        names = [q.name for q in root.iterdir()] if root.is_dir() else []
    except OSError:
        names = []
    found = _read_lock(root / LOCK_NAME) if LOCK_NAME in names else None
    holder = found[1] if found else None
    if holder and holder["host"] == socket.gethostname() and pid_runs(holder["pid"]):
        return (f"{p}: no index.json yet: `anycity data` (pid {holder['pid']}) is still writing this shard set; "
                "wait for it to finish")
    left = sorted(n for n in names if n == LOCK_NAME or n.endswith(".tar.partial"))
    shards = sorted(n for n in names if _SHARD_RE.fullmatch(n))
    if shards and _anycity_shard(root / shards[0]):  # not another webdataset set under the same names
        left += shards
    if left:
        return (f"{p}: no index.json: the `anycity data synth|convert` run that wrote {root} was interrupted or "
                f"failed (it left {', '.join(left[:3])}{' ...' if len(left) > 3 else ''}); rerun the same command "
                "to write the set again (no --overwrite needed)")
    return f"{p}: no index.json; point to a directory written by `anycity data synth|convert`"


def shard_urls(root: str | Path, split: str) -> list[str]:
    """Shard paths of one split of a shard directory (from its index.json)."""
    index = read_index(root)
    return [str(Path(root) / p) for p in index["splits"].get(split, [])]
