"""Reading local tar shards lazily: member headers are scanned, payloads are read only when a sample uses them.

A webdataset sample of a trajectory window holds every view's image and depth, but a training sample decodes
only the views it selects. For local shard files :func:`tar_samples` yields samples whose members are
:class:`Member` handles (``cameras.json`` is read eagerly); :func:`anycity.data.schema.member` reads the bytes
with one ``pread`` (a seek and a read on Windows, which has no ``pread``) when a view is chosen. Remote URLs
(``pipe:``, ``http://``, ``file:``...) are opened with webdataset's ``gopen`` and read as a tar stream
(:func:`remote_members`), with the local reader's checks; their members carry bytes. Grouping into samples
is webdataset's ``group_by_keys``.
"""

from __future__ import annotations

import os
import re
import tarfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from webdataset import tariterators

EAGER_SUFFIXES = (".json",)
_pread = getattr(os, "pread", None)  # absent on Windows: seek + read under the file's lock there


class _File:
    """An open file descriptor shared by the members of one shard; closed when the last reference goes."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0))  # Windows: no newline translation
        self.lock = threading.Lock()

    def read(self, size: int, offset: int) -> bytes:
        if _pread is not None:
            return _pread(self.fd, size, offset)
        parts = []
        with self.lock:  # one file position shared by the threads that read this shard
            os.lseek(self.fd, offset, os.SEEK_SET)
            while size > 0 and (part := os.read(self.fd, size)):
                parts.append(part)
                size -= len(part)
        return b"".join(parts)

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
        data = self._file.read(self.size, self.offset)
        if len(data) != self.size:
            raise ValueError(f"shard {self._file.path}: member {self.name!r} is truncated ({len(data)} of "
                             f"{self.size} bytes); re-create the shard")
        return data

    def __len__(self) -> int:
        return self.size

    def __repr__(self) -> str:
        return f"Member({self.name!r}, {self.size} bytes)"


_SCHEME = re.compile(r"[A-Za-z][A-Za-z0-9+.-]+:")  # two letters or more: ``C:\\shards`` is a Windows path


def is_url(spec: str) -> bool:
    """Whether a shard spec is a URL webdataset opens (``http://``, ``pipe:cmd``, ``file:path``, ``s3://``...), not
    a local path."""
    return _SCHEME.match(spec) is not None


def is_local(url: str) -> bool:
    return not is_url(url) and Path(url).is_file()


_CURL_EXITS = {6: "host not found", 7: "could not connect", 18: "the transfer ended early (partial file)",
               22: "the server answered with an HTTP error (e.g. 404: no such file)", 28: "timed out",
               35: "TLS handshake failed", 56: "the connection broke while receiving"}


def remote_error(url: str, exn: BaseException) -> str:
    """One line for webdataset's exception while streaming remote shard ``url``: its args are ``(message, ...,
    stream, url)`` with a curl or pipe command's exit status in the message, which printed as a tuple of objects."""
    msg = str(exn.args[0]) if exn.args else str(exn)
    status = re.search(r"exit (\d+) \(read\)", " ".join(map(str, exn.args)))
    if status:
        code = int(status.group(1))
        curl = "curl" in " ".join(map(str, exn.args))
        why = (f"curl exit {code}: {_CURL_EXITS[code]}" if curl and code in _CURL_EXITS
               else f"{'curl' if curl else 'the pipe command'} exited with status {code}")
    elif msg == "empty file":
        why = "nothing was read (a missing file, a failed command or an empty response)"
    else:
        return f"shard {url}: {msg}; re-create the shard"
    return f"shard {url}: {why}; check the URL and that the shard is there"


def local_members(url: str) -> Iterator[dict]:
    """``{"fname", "data", "__url__", "url"}`` per regular member of a local tar file, ``data`` a :class:`Member`
    (bytes for small eager members). Raises ``tarfile.ReadError`` / ``ValueError`` on corrupt archives, and
    ``ValueError`` for a member that ends past the end of the file (truncated, or a header claiming an absurd size,
    which reading would allocate), and for an invalid header before the end of the file (a flipped bit there: tarfile
    stops there quietly, which dropped the rest of the shard unnoticed), and for a file that ends without the
    end-of-archive block (cut just after a member: tarfile ends there quietly too)."""
    file = _File(url)
    end = os.fstat(file.fd).st_size
    with open(url, "rb") as f, tarfile.open(fileobj=f, mode="r:") as tf:
        if tf.firstmember is None:  # an empty tar: Python 3.10's next() would seek to -1 (EINVAL)
            return
        while (m := tf.next()) is not None:
            if not m.isfile():
                continue
            if m.offset_data + m.size > end:
                raise ValueError(f"shard {url}: member {m.name!r} claims {m.size} bytes at offset {m.offset_data}, "
                                 f"past the end of the {end}-byte file (truncated or corrupt); re-create the shard")
            data: Member | bytes = Member(file, m.offset_data, m.size, m.name)
            if m.name.endswith(EAGER_SUFFIXES):
                data = data.read()
            yield {"fname": m.name, "data": data, "__url__": url, "url": url}  # url: webdataset's errors name it
        # tarfile stops at the end-of-archive block (zeros) and, silently, at an invalid header or at the end of
        # the file: a shard cut just after a member (every writer ends a tar with zero blocks) lost its other members
        if tf.offset >= end:
            raise ValueError(f"shard {url}: ends after {end} bytes without the end-of-archive block (truncated: its "
                             "remaining members are missing); re-create the shard")
        if file.read(tarfile.BLOCKSIZE, tf.offset).strip(b"\0"):
            raise ValueError(f"shard {url}: invalid tar header at byte {tf.offset} (corrupt); re-create the shard")


class NoSampleGuard:
    """Stops a stream that can never give a sample, which a resampled training stream with ``skip_corrupt``
    would otherwise draw forever. :meth:`check` raises once

    - each of the split's shards has been seen to be unreadable, empty, or to hold no webdataset sample (which
      :func:`tar_samples` decides within the shard, so nothing buffered downstream can change it), or
    - no sample has ever built, every shard has been read to its end, and every sample this stream keeps has
      failed to build at least ``attempts`` times. A sample still in the shuffle buffer has not failed yet, so the
      rule cannot race it; ``attempts`` > 1 because a training sample picks random views, and a sample with one bad
      view fails only when that view is picked.

    A stream counts every sample it reads (:meth:`sample_read`: does a shard give samples at all?) but waits only
    for those it keeps (:meth:`kept`, after an evaluation stream's share of the samples): another worker's or
    rank's samples never fail here, and waiting for them let a stream whose every sample failed end quietly.

    ``builds=False`` (a finite evaluation stream, which cannot draw forever) drops the second rule: a stream holds
    only its 1/(ranks x workers) share of the samples, and one corrupt sample can be a stream's whole share while
    the other streams score the rest; evaluation says instead when no rank scored anything
    (``lit/base.AnyCityModule._log_metrics``).
    """

    def __init__(self, urls: Iterable[str], attempts: int = 3, builds: bool = True) -> None:
        self.urls, self.attempts, self.builds = set(urls), attempts, builds
        self.why: dict[str, str] = {}
        self.read: dict[str, int] = {}
        self.visited: set[str] = set()
        self.built = 0
        self.build_fails: dict[tuple[str, str], int] = {}  # (url, key) -> failures; emptied by the first build
        self.build_why = ""

    def failed(self, url: str, why: str) -> None:
        self.why.setdefault(url, why)

    def sample_read(self, url: str, key: str) -> None:
        self.read[url] = self.read.get(url, 0) + 1

    def kept(self, samples: Iterable[dict]) -> Iterator[dict]:
        """webdataset stage: the samples this stream builds, each noted as one that must build or fail."""
        for s in samples:
            if not self.built:
                self.build_fails.setdefault((s.get("__url__", "?"), s.get("__key__", "?")), 0)
            yield s

    def ended(self, samples: Iterable) -> Iterator:
        """webdataset stage, the last of a finite training stream (a pass of ``resampled=False``): at its end each
        sample the stream kept has built or failed (none waits in a shuffle buffer), so one failure each is enough."""
        yield from samples
        self.check(attempts=1)

    def sample_built(self) -> None:
        self.built += 1
        self.build_fails.clear()

    def sample_failed(self, url: str, key: str, why: str) -> None:
        if not self.built:
            self.build_fails[(url, key)] = self.build_fails.get((url, key), 0) + 1
            self.build_why = self.build_why or why

    def check(self, attempts: int | None = None) -> None:
        """Raise if the stream can give no sample; ``attempts`` overrides the build failures asked of each sample
        (1 at the end of a finite stream, whose samples were each drawn once)."""
        if not self.urls:
            return
        if self.why.keys() >= self.urls:
            url = next(iter(self.why))
            raise ValueError(f"shards: none of the {len(self.urls)} shard(s) gives a sample (e.g. {url}: "
                             f"{self.why[url]}); point --data.root at shards written by `anycity data synth` or "
                             "`anycity data convert`")
        need = self.attempts if attempts is None else attempts
        if (not self.builds or self.built or not self.build_fails or not (self.visited | self.why.keys()) >= self.urls
                or min(self.build_fails.values()) < need):
            return
        raise ValueError(f"shards: none of the {len(self.build_fails)} sample(s) in the {len(self.urls)} shard(s) "
                         f"builds, tried {need} time(s) each (skip_corrupt skipped them all); the first failure: "
                         f"{self.build_why}")


class _Recorded:
    """A remote stream that counts the bytes read through it and keeps the last ``keep`` of them: what tarfile read
    ahead of its last header, to check after the last member that the stream held a whole tar."""

    def __init__(self, stream, keep: int = 1 << 16) -> None:
        self.stream, self.keep, self.pos, self.tail = stream, keep, 0, b""

    def read(self, size: int = -1) -> bytes:
        data = self.stream.read(size)
        self.pos += len(data)
        self.tail = (self.tail + data)[-self.keep:]
        return data

    def block_at(self, offset: int) -> bytes:
        """Up to one tar block of the stream at ``offset`` (at most ``keep`` bytes behind what was read), reading on
        if needed; then drains the stream (so a command or download that failed says so)."""
        held = self.tail[offset - (self.pos - len(self.tail)):]
        while len(held) < tarfile.BLOCKSIZE and (more := self.read(1 << 16)):
            held += more
        while self.read(1 << 16):
            pass
        return held[:tarfile.BLOCKSIZE]


def remote_members(url: str) -> Iterator[dict]:
    """``{"fname", "data", "__url__", "url"}`` per regular member of a remote tar (``http://``, ``pipe:``,
    ``file:``..., opened with webdataset's ``gopen``), ``data`` its bytes. Raises a one-line ``ValueError`` naming
    the URL (:func:`remote_error`) where the stream fails, and, as :func:`local_members` does, where an uncompressed
    tar ends without the end-of-archive block or at an invalid header (tarfile stops quietly at both)."""
    from webdataset.gopen import gopen

    stream = None
    try:
        stream = gopen(url, "rb")
        rec = _Recorded(stream)
        with tarfile.open(fileobj=rec, mode="r|*") as tf:
            headers = 0
            for m in tf:
                headers += 1
                if m.isfile():
                    yield {"fname": m.name, "data": tf.extractfile(m).read(), "__url__": url, "url": url}
            if headers and getattr(tf.fileobj, "comptype", "tar") == "tar":
                block = rec.block_at(tf.offset)
                if not block:
                    raise ValueError(f"ends after {tf.offset} bytes without the end-of-archive block (truncated: its "
                                     "remaining members are missing)")
                if block.strip(b"\0"):
                    raise ValueError(f"invalid tar header at byte {tf.offset} (corrupt)")
        stream.close()  # a pipe's command or curl: its exit status
    except Exception as e:
        raise ValueError(remote_error(url, _closing_error(stream) or e)) from e


def _closing_error(stream) -> BaseException | None:
    """The error closing ``stream`` raises (a failed download or command says why there: curl's exit status, where
    tarfile saw only an empty or short stream), or None."""
    try:
        if stream is not None:
            stream.close()
    except Exception as e:
        return e
    return None


def tar_samples(src: Iterable[dict], handler: Callable[[BaseException], bool],
                guard: NoSampleGuard | None = None) -> Iterator[dict]:
    """webdataset stage: shard dicts (``{"url": ...}``) -> samples, lazily for local files. ``guard`` hears of
    each local shard visit that gave no sample (unreadable, empty, no keyed members) or was read to its end, and
    of each sample read; it is checked before each shard and at the end of a finite stream."""

    def files() -> Iterator[dict]:
        for d in src:
            url = d["url"]
            if guard is not None:
                guard.check()
            n, why = 0, None
            before = guard.read.get(url, 0) if guard is not None else 0
            try:
                for m in local_members(url) if is_local(url) else remote_members(url):
                    n += 1
                    yield m
            except (tarfile.TarError, OSError, ValueError) as e:
                why = f"unreadable tar ({str(e).removeprefix(f'shard {url}: ')})"  # named once, below
                if not handler(ValueError(f"shard {url}: {why}")):
                    return
            yield {}  # end of shard: a sample never spans two shards (a resampled shard may come twice in a row)
            # resumed after the shard's last sample went downstream, so every sample read from it is counted
            if guard is not None and guard.read.get(url, 0) == before:
                guard.failed(url, why or ("an empty tar" if n == 0 else
                                          "no webdataset samples (members sharing a key) in it"))
            elif guard is not None:  # read as far as it goes (a truncated shard too)
                guard.visited.add(url)
        if guard is not None:  # the end of a finite stream (evaluation, or a pass of resampled: false)
            guard.check(attempts=1)

    samples = tariterators.group_by_keys(files(), handler=_ShardNamed(handler))
    if guard is None:
        return samples
    return _counted(samples, guard)


class _ShardNamed:
    """``group_by_keys``' exception handler: its errors (a member name twice in a shard) come with webdataset's
    ``(message, stream, url)`` args, which printed as a tuple naming no shard; they reach ``handler`` as one line
    ``ValueError`` naming the shard."""

    def __init__(self, handler: Callable[[BaseException], bool]) -> None:
        self.handler = handler

    def __call__(self, exn: BaseException) -> bool:
        if len(exn.args) >= 3 and isinstance(exn.args[-1], str):  # webdataset appended (stream, url)
            *why, _, url = exn.args
            exn = ValueError(f"shard {url}: {' '.join(map(str, why))}; re-create the shard")
        return self.handler(exn)


def _counted(samples: Iterator[dict], guard: NoSampleGuard) -> Iterator[dict]:
    for s in samples:
        guard.sample_read(s["__url__"], s.get("__key__", ""))
        yield s
