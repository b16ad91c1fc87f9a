"""Reading local tar shards lazily: member headers are scanned, payloads are read only when a sample uses them.

A webdataset sample of a trajectory window holds every view's image and depth, but a training sample decodes
only the views it selects. For local shard files :func:`tar_samples` yields samples whose members are
:class:`Member` handles (``cameras.json`` is read eagerly); :func:`anycity.data.schema.member` reads the bytes
with one ``pread`` when a view is chosen. Remote URLs (``pipe:``, ``http://``, ...) go through webdataset's own
streaming reader and carry bytes. Grouping into samples is webdataset's ``group_by_keys``.
"""

from __future__ import annotations

import os
import tarfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from webdataset import tariterators

EAGER_SUFFIXES = (".json",)


class _File:
    """An open file descriptor shared by the members of one shard; closed when the last reference goes."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.fd = os.open(path, os.O_RDONLY)

    def __del__(self) -> None:
        fd = getattr(self, "fd", None)
        if fd is not None:
            os.close(fd)


class Member:
    """A tar member's payload (``size`` bytes at ``offset`` of a shard), read on demand with :meth:`read`."""

    __slots__ = ("_file", "offset", "size", "name")

    def __init__(self, file: _File, offset: int, size: int, name: str) -> None:
        self._file, self.offset, self.size, self.name = file, offset, size, name

    def read(self) -> bytes:
        data = os.pread(self._file.fd, self.size, self.offset)
        if len(data) != self.size:
            raise ValueError(f"shard {self._file.path}: member {self.name!r} is truncated ({len(data)} of "
                             f"{self.size} bytes); re-create the shard")
        return data

    def __len__(self) -> int:
        return self.size

    def __repr__(self) -> str:
        return f"Member({self.name!r}, {self.size} bytes)"


def is_local(url: str) -> bool:
    return "://" not in url and not url.startswith("pipe:") and Path(url).is_file()


def local_members(url: str) -> Iterator[dict]:
    """``{"fname", "data", "__url__"}`` per regular member of a local tar file, ``data`` a :class:`Member`
    (bytes for small eager members). Raises ``tarfile.ReadError`` / ``ValueError`` on corrupt archives."""
    file = _File(url)
    with open(url, "rb") as f, tarfile.open(fileobj=f, mode="r:") as tf:
        while (m := tf.next()) is not None:
            if not m.isfile():
                continue
            data: Member | bytes = Member(file, m.offset_data, m.size, m.name)
            if m.name.endswith(EAGER_SUFFIXES):
                data = data.read()
            yield {"fname": m.name, "data": data, "__url__": url}


class NoSampleGuard:
    """Stops a stream whose every shard is unreadable, empty, or holds no webdataset sample: once each of the
    split's shards has been seen to fail so (which :func:`tar_samples` decides within the shard, so nothing buffered
    downstream can change it), :meth:`check` raises. Without it a resampled training stream with ``skip_corrupt``
    draws them forever."""

    def __init__(self, urls: Iterable[str]) -> None:
        self.urls = set(urls)
        self.why: dict[str, str] = {}
        self.read: dict[str, int] = {}

    def failed(self, url: str, why: str) -> None:
        self.why.setdefault(url, why)

    def sample_read(self, url: str) -> None:
        self.read[url] = self.read.get(url, 0) + 1

    def check(self) -> None:
        if not self.urls or not self.why.keys() >= self.urls:
            return
        url = next(iter(self.why))
        raise ValueError(f"shards: none of the {len(self.urls)} shard(s) gives a sample (e.g. {url}: "
                         f"{self.why[url]}); point --data.root at shards written by `anycity data synth` or "
                         "`anycity data convert`")


def tar_samples(src: Iterable[dict], handler: Callable[[BaseException], bool],
                guard: NoSampleGuard | None = None) -> Iterator[dict]:
    """webdataset stage: shard dicts (``{"url": ...}``) -> samples, lazily for local files. ``guard`` hears of
    each local shard visit that gave no sample (unreadable, empty, no keyed members) and is checked before each
    shard."""

    def files() -> Iterator[dict]:
        for d in src:
            url = d["url"]
            if guard is not None:
                guard.check()
            if not is_local(url):
                yield from tariterators.tar_file_expander(tariterators.url_opener([d], handler=handler),
                                                          handler=handler)
                continue
            n, why = 0, None
            before = guard.read.get(url, 0) if guard is not None else 0
            try:
                for m in local_members(url):
                    n += 1
                    yield m
            except (tarfile.TarError, OSError, ValueError) as e:
                why = f"unreadable tar ({e})"
                if not handler(ValueError(f"shard {url}: {why}")):
                    return
            yield {}  # end of shard: a sample never spans two shards (a resampled shard may come twice in a row)
            # resumed after the shard's last sample went downstream, so every sample read from it is counted
            if guard is not None and guard.read.get(url, 0) == before:
                guard.failed(url, why or ("an empty tar" if n == 0 else
                                          "no webdataset samples (members sharing a key) in it"))
        if guard is not None:  # the end of a finite (evaluation) stream
            guard.check()

    samples = tariterators.group_by_keys(files(), handler=handler)
    if guard is None:
        return samples
    return _counted(samples, guard)


def _counted(samples: Iterator[dict], guard: NoSampleGuard) -> Iterator[dict]:
    for s in samples:
        guard.sample_read(s["__url__"])
        yield s
