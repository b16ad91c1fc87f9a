"""Recovering from damaged numba cache files (kept free of torch so that checking it is cheap)."""

from __future__ import annotations

import logging

_log = logging.getLogger(__name__)


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
