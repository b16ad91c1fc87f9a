"""numba's kernel cache made safe: stale after an edited constant, or damaged (kept free of torch and numba, so
that checking it is cheap and it can be tested on its own)."""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterable

import numpy as np

_log = logging.getLogger(__name__)


def _constant(value) -> bool:
    """A number, a numeric numpy array or scalar, or a tuple of these (what numba freezes as a constant; nothing
    whose repr or bytes could differ between processes, such as an address)."""
    if isinstance(value, (np.ndarray, np.generic)):
        return value.dtype.kind in "biufc"
    if isinstance(value, tuple):
        return all(_constant(v) for v in value)
    return isinstance(value, (bool, int, float, complex))


def constants_digest(namespace: dict) -> str:
    """sha256 of the compile-time constants in a module's ``namespace`` (``vars(module)``): every non-dunder global
    that ``_constant`` accepts, imported ones included. numba freezes the globals a kernel reads into its machine
    code, so these are what a cached kernel was compiled with."""
    h = hashlib.sha256()
    for name, value in sorted(namespace.items()):
        if name.startswith("__") or not _constant(value):
            continue
        if isinstance(value, (np.ndarray, np.generic)):
            h.update(f"{name}:{value.dtype.str}{np.shape(value)}:".encode() + np.ascontiguousarray(value).tobytes())
        else:
            h.update(f"{name}={value!r};".encode())
    return h.hexdigest()


def stamp_constants(dispatchers: Iterable) -> None:
    """Make the cache of each numba dispatcher (``@njit(cache=True)``) stale when a constant of its module changes.

    numba keeps a cache index fresh while the kernel's own source file keeps its modification time and size, but it
    freezes the kernel's globals into the cached code, so an edited constant imported from another file (e.g.
    ``projection.ALPHA_MAX``) left the cached kernel on the old value. Here the index's stamp becomes (numba's source
    stamp, ``constants_digest`` of the kernel's module): a changed constant makes numba find the index stale and
    compile the kernel again, as after an edit of its own file. Call it before the dispatcher's first call
    (idempotent). Constants must reach a kernel as module globals (``from ... import NAME``), not as attributes of
    an imported module. Dispatchers without a cache, or whose numba internals moved, are left as they are.
    """
    digests: dict[int, str] = {}
    for disp in dispatchers:
        try:
            cache = disp._cache
            cache_file, source = cache._cache_file, cache._impl.locator.get_source_stamp()
            namespace = disp.py_func.__globals__
        except AttributeError:  # caching off (numba's NullCache), or numba's internals moved
            continue
        if id(namespace) not in digests:
            digests[id(namespace)] = constants_digest(namespace)
        cache_file._source_stamp = (source, digests[id(namespace)])


def repair_cache(dispatchers: list) -> list[str]:
    """Drop the cache entries of numba ``dispatchers`` that cannot be read back, so that numba compiles them again.

    numba writes each cache file to a temporary name and renames it, but a disk that fills up, a copy cut short or
    a crash before the data reached the disk can leave a truncated or empty ``.nbi``/``.nbc`` file behind; numba then
    fails every call with an ``UnpicklingError`` instead of recompiling. Returns the index files dropped (each also
    logged as one warning). Reads every cache file once: about 2.5 MB for the renderer's kernels.
    """
    dropped = []
    for disp in dispatchers:
        try:
            cache_file = disp._cache._cache_file
        except AttributeError:  # caching off, or numba's internals moved: nothing to check
            continue
        try:
            for name in cache_file._load_index().values():
                try:
                    cache_file._load_data(name)
                except FileNotFoundError:  # an index naming a missing data file: numba recompiles that entry
                    continue
        except Exception as e:  # noqa: BLE001 (whatever unpickling a damaged file raises)
            _log.warning("anycity: the compiled-kernel cache %s is unreadable (%s: %s); dropped it, the kernel is "
                         "compiled again", cache_file._index_path, type(e).__name__, e)
            cache_file.flush()
            dropped.append(cache_file._index_path)
    return dropped
