"""Dataset converters: each ``parse(src) -> list[ParsedScene]`` in OpenCV w2c + pixel K, then :func:`convert`."""

from __future__ import annotations

from pathlib import Path

from anycity.data.parsers import blendedmvs, colmap, llff, matrixcity, nerfstudio
from anycity.data.parsers.base import ParsedScene, ParsedView, write_scenes
from anycity.data.parsers.guard import guarded

PARSERS = {name: guarded(name, fn) for name, fn in {
    "colmap": colmap.parse, "nerfstudio": nerfstudio.parse, "matrixcity": matrixcity.parse,
    "blendedmvs": blendedmvs.parse, "llff": llff.parse_llff, "bungeenerf": llff.parse_bungeenerf}.items()}
MIN_SIDE = 8  # the smallest --max_side: smaller images carry nothing to train on


def convert(format: str, src: str | Path, out: str | Path, split: str = "auto", max_views: int = 64,
            max_side: int | None = None, seed: int = 0, overwrite: bool = False) -> dict:
    """Convert a dataset in ``format`` under ``src`` into anycity shards under ``out``; returns the index."""
    if format not in PARSERS:
        raise ValueError(f"format: expected one of {sorted(PARSERS)}, got {format!r}")
    if not Path(src).exists():
        raise FileNotFoundError(f"{src}: source folder not found; pass --src the dataset folder")
    if max_views < 2:  # a sample needs a context view and another to score it on
        raise ValueError(f"max_views: expected >= 2 views per sample, got {max_views}")
    if max_side is not None and max_side < MIN_SIDE:  # 0 read as "no resize", a negative one crashed in OpenCV
        raise ValueError(f"max_side: expected the longer stored side in pixels, >= {MIN_SIDE}, got {max_side}; "
                         "leave it out to keep the images' size")
    return write_scenes(PARSERS[format](src), out, split=split, max_views=max_views, max_side=max_side, seed=seed,
                        overwrite=overwrite)


__all__ = ["PARSERS", "ParsedScene", "ParsedView", "convert"]
