"""Planning chunked prediction: the photo order and overlapping chunks of it.

Photos are ordered by capture time when every photo carries one (EXIF ``DateTimeOriginal``/``DateTime``), else by
file name (natural order: ``img2`` before ``img10``); a flight's photos form a sequence either way. For photos that
do not, :func:`order_from_descriptors` orders them along a neighbour graph of per-photo descriptors (e.g. the
network's own pooled global tokens at low resolution).
"""

from __future__ import annotations

import re
from pathlib import Path

import torch
from torch import Tensor

MIN_SHARED = 2  # photos two consecutive chunks must share to be aligned (align.pairwise_edges)


def natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def capture_time(path: str | Path) -> str | None:
    """EXIF capture time ``"YYYY:MM:DD HH:MM:SS"`` (+ sub-seconds when present) or None."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return exif_capture_time(im.getexif())
    except Exception:  # noqa: BLE001 - unreadable files are reported by the loader, with their name
        return None


def exif_capture_time(exif) -> str | None:
    """The capture time ``"YYYY:MM:DD HH:MM:SS"`` (+ ``.sub-seconds`` when present) of a Pillow ``Exif``, or None
    when it has none or a placeholder (``0000:00:00 00:00:00``, or blanks, as some cameras write with no clock)."""
    sub = exif.get_ifd(0x8769)
    t = sub.get(36867) or exif.get(306)  # DateTimeOriginal, DateTime
    frac = sub.get(37521) or ""  # SubSecTimeOriginal
    if not t or not str(t).strip("0: \x00"):
        return None
    return f"{t}.{frac}" if frac else str(t)


def order_photos(paths: list[Path], by: str = "auto", times: list[str | None] | None = None
                 ) -> tuple[list[int], str]:
    """Indices of ``paths`` in capture order and how it was decided (``"time"`` or ``"name"``).

    ``by="auto"`` uses capture time when every photo has a distinct one, else the natural file-name order.
    ``times``: the photos' :func:`capture_time` when the caller has read them already.
    """
    if by not in ("auto", "time", "name"):
        raise ValueError(f"predict_order: expected 'auto', 'time' or 'name', got {by!r}")
    by_name = sorted(range(len(paths)), key=lambda i: natural_key(paths[i].name))
    if by == "name":
        return by_name, "name"
    times = [capture_time(p) for p in paths] if times is None else times
    if all(times) and len(set(times)) == len(times):
        return sorted(by_name, key=lambda i: times[i]), "time"
    if by == "time":
        raise ValueError(f"predict_order 'time': {_time_problem(paths, times, by_name)}; use predict_order 'name' "
                         "or 'auto'")
    return by_name, "name"


def _time_problem(paths: list[Path], times: list[str | None], by_name: list[int]) -> str:
    """Why capture times cannot order ``paths``: the first photo (in name order) without one, else the first two
    that share one."""
    missing = next((paths[i].name for i in by_name if not times[i]), None)
    if missing:
        return f"{missing} has no EXIF capture time"
    first: dict[str, int] = {}
    for i in by_name:
        if times[i] in first:
            return f"{paths[first[times[i]]].name} and {paths[i].name} share the capture time {times[i]}"
        first[times[i]] = i
    raise AssertionError("unreachable: every photo has a distinct capture time")


def order_from_descriptors(desc: Tensor) -> list[int]:
    """Order photos along their neighbour graph: ``desc [N, D]`` (cosine similarity) -> a permutation.

    Greedy nearest-neighbour chain from the photo least similar to the rest (an end of the sequence), so that
    consecutive photos in the order are neighbours and chunks of it overlap in content.
    """
    d = torch.nn.functional.normalize(desc.double(), dim=-1)
    sim = d @ d.T
    n = sim.shape[0]
    sim.fill_diagonal_(-2)
    start = int(sim.clamp_min(-1).sum(-1).argmin())
    order, used = [start], torch.zeros(n, dtype=torch.bool)
    used[start] = True
    for _ in range(n - 1):
        row = sim[order[-1]].masked_fill(used, -3)
        nxt = int(row.argmax())
        order.append(nxt)
        used[nxt] = True
    return order


@torch.no_grad()
def token_descriptors(net, load, num: int, batch: int = 16) -> Tensor:
    """One descriptor per photo from the network's own global tokens: ``[num, D]``.

    Args:
        net: an :class:`anycity.models.anycity.AnyCityNet` (its ``aggregator``; duck-typed, no import).
        load: ``load(indices) -> [v, 3, H, W]`` photos, at a low resolution (a cheap pass).
        batch: photos per pass. Each photo goes through as its own one-view sample, so no photo sees another
            and the descriptors do not depend on the batching.
    Returns:
        the mean of the last layer's patch tokens of each photo.
    """
    agg = net.aggregator
    out = []
    for i in range(0, num, batch):
        images = load(list(range(i, min(num, i + batch))))[:, None]  # [v, 1, 3, H, W]
        param = next(net.parameters())
        tokens = agg(images.to(param.device, param.dtype), keep={agg.depth - 1})[-1]  # [v, 1, T, 2C]
        out.append(tokens[:, 0, agg.patch_start_idx:].float().mean(1).cpu())
    return torch.cat(out)


def plan_chunks(num: int, size: int, overlap: int, loop: bool = False) -> list[list[int]]:
    """Cut positions ``0..num-1`` into chunks of ``size`` consecutive positions, each sharing ``overlap`` with the
    next; the last chunk is shifted back to stay full (it then shares more). One chunk when ``num <= size`` (any
    ``overlap >= 0``: it is not used); more need ``size >= MIN_SHARED + 1`` and ``MIN_SHARED <= overlap < size``.

    ``loop=True`` (the last photos see the first ones again, e.g. a closed orbit) appends, whenever there is more
    than one chunk, a loop-closure chunk of the last ``size // 2`` and the first ``size - size // 2`` positions: it
    shares photos with the first and the last chunk, so the pose graph gets a cycle and spreads the drift around it
    (:func:`anycity.city.posegraph.align_chunks` drops it with a warning where it disagrees with the chain)."""
    if size < 2:
        raise ValueError(f"predict_chunk_size: expected >= 2 photos per chunk, got {size}")
    if overlap < 0:
        raise ValueError(f"predict_chunk_overlap: expected >= 0 photos shared by consecutive chunks, got {overlap}")
    if num <= size:  # one pass: the overlap is not used
        return [list(range(num))]
    if size <= MIN_SHARED:  # each chunk shares MIN_SHARED photos with the next and must add one of its own
        raise ValueError(f"predict_chunk_size: {num} photos in chunks of {size} cannot be aligned (consecutive "
                         f"chunks share {MIN_SHARED} photos, so a chunk needs {MIN_SHARED + 1} or more); raise "
                         f"predict_chunk_size to {MIN_SHARED + 1} or more")
    if overlap >= size:
        raise ValueError(f"predict_chunk_overlap: expected {MIN_SHARED}..{size - 1} (below the chunk size "
                         f"{size}), got {overlap}")
    if overlap < MIN_SHARED:  # said before the network runs over every chunk, not after
        raise ValueError(f"predict_chunk_overlap: {num} photos in chunks of {size} need an overlap of at least "
                         f"{MIN_SHARED} (consecutive chunks are aligned on the photos they share), got {overlap}")
    step = size - overlap
    starts = list(range(0, num - size, step)) + [num - size]
    chunks = [list(range(s, s + size)) for s in starts]
    if loop:  # two chunks too: they share the middle photos, not the ends
        if size // 2 < MIN_SHARED:  # said before the network runs, as the overlap is
            raise ValueError(f"predict_loop: the loop-closure chunk shares {size // 2} photo(s) with the last chunk "
                             f"(half a chunk of {size}), need {MIN_SHARED}; raise predict_chunk_size to "
                             f"{2 * MIN_SHARED} or more, or drop predict_loop")
        chunks.append(list(range(num - size // 2, num)) + list(range(size - size // 2)))
    return chunks


def owners(chunks: list[list[int]]) -> dict[int, int]:
    """For every view, the chunk that observes it best: the one where it sits most centrally (most chunk
    neighbours on its less-covered side); ties go to the earlier chunk. Each view's pixel-aligned Gaussians and
    camera are taken from its owner only, so no region is doubled where chunks overlap."""
    best: dict[int, tuple[int, int]] = {}
    for c, views in enumerate(chunks):
        if len(chunks) > 2 and c == len(chunks) - 1 and views[0] > views[-1]:
            continue  # a loop-closure chunk (see plan_chunks) aligns, but owns no photo
        for pos, v in enumerate(views):
            score = min(pos, len(views) - 1 - pos)
            if v not in best or score > best[v][0]:
                best[v] = (score, c)
    return {v: c for v, (_, c) in best.items()}
