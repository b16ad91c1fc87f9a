"""``anycity data synth|convert``: build shards from the built-in synthetic cities or from a dataset.

Usage::

    anycity data synth --out data/synth --scenes 64 --views 48 --size 256x256 --trajectory mixed --preview
    anycity data convert --format colmap --src ../shared/data/real_aerial --out data/real --split test
"""

from __future__ import annotations

import json
import sys

from jsonargparse import ActionYesNo, ArgumentParser


def _synth_parser() -> ArgumentParser:
    p = ArgumentParser(description="Render procedural aerial cities into webdataset shards.", allow_abbrev=False)
    p.add_argument("--out", type=str, required=True, help="output shard directory")
    p.add_argument("--overwrite", action=ActionYesNo, default=False,
                   help="replace a shard set already in --out, its preview.png included (default: refuse)")
    p.add_argument("--scenes", type=int, default=8,
                   help="number of cities, split 8:1:1 into train/val/test (training cities are written as --window "
                        "samples, the others whole); which city lands in which split depends on --scenes, so a "
                        "held-out set for a model trained on another set needs another --seed")
    p.add_argument("--views", type=int, default=48, help="views per city along the trajectory")
    p.add_argument("--size", type=str, default="256x256", help="image size HxW in pixels")
    p.add_argument("--seed", type=int, default=0,
                   help="dataset seed: city i is made from (seed, i) whatever --scenes, so sets made with one seed "
                        "share cities (across their splits when --scenes differs); use another seed for a held-out set")
    p.add_argument("--trajectory", default="mixed", choices=["orbit", "nadir", "mixed"],
                   help="camera path: orbit at 30-60 deg pitch, nadir lawnmower, or a per-scene mix")
    p.add_argument("--preview", action=ActionYesNo, default=False, help="write preview.png (contact sheet)")
    p.add_argument("--workers", type=int | None, default=None, help="processes (default: min(2, cpus))")
    p.add_argument("--image_format", default="jpg", choices=["jpg", "png"], help="view encoding")
    p.add_argument("--depth_dtype", default="float16", choices=["float16", "float32"],
                   help="stored depth precision")
    p.add_argument("--normals", action=ActionYesNo, default=False,
                   help="also store ground-truth normals (octahedral uint8, 2 bytes a pixel, the bytes of float16 "
                        "depth; readers derive them from depth when absent)")
    p.add_argument("--window", type=int | None, default=24,
                   help="training samples are trajectory windows of this many views (0 or None: whole scenes)")
    p.add_argument("--stride", type=int | None, default=None, help="views between window starts (default window/2)")
    p.add_argument("--supersample", type=int, default=1,
                   help="colour = box filter of k x k sub-pixel rays (1: one ray per pixel + edge anti-aliasing)")
    p.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view in degrees")
    return p


def _convert_parser() -> ArgumentParser:
    from anycity.data.parsers import PARSERS

    p = ArgumentParser(description="Convert a posed multi-view dataset into webdataset shards.", allow_abbrev=False)
    p.add_argument("--format", required=True, choices=sorted(PARSERS), help="source format")
    p.add_argument("--src", type=str, required=True, help="source dataset folder (or pose file)")
    p.add_argument("--out", type=str, required=True, help="output shard directory")
    p.add_argument("--overwrite", action=ActionYesNo, default=False,
                   help="replace a shard set already in --out (default: refuse)")
    p.add_argument("--split", default="auto", choices=["auto", "train", "val", "test"],
                   help="auto: the dataset's split, else 8:1:1 by scene")
    p.add_argument("--max_views", type=int, default=64, help="views per sample (longer trajectories are cut)")
    p.add_argument("--max_side", type=int | None, default=None, help="downscale images to this long side")
    p.add_argument("--seed", type=int, default=0, help="seed of the 8:1:1 scene split")
    return p


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="anycity data", description="Build anycity webdataset shards.", allow_abbrev=False)
    sub = parser.add_subcommands(dest="command")
    sub.add_subcommand("synth", _synth_parser(), help="procedural aerial cities")
    sub.add_subcommand("convert", _convert_parser(), help="convert COLMAP, nerfstudio, MatrixCity, ... data")
    return parser


def _summary(index: dict) -> str:
    n = {sp: sum(1 for s in index["scenes"] if s["split"] == sp) for sp in ("train", "val", "test")}
    return (f"{len(index['scenes'])} scenes ({json.dumps(n)}) as {len(index['samples'])} samples in "
            f"{len(index['shards'])} shards")


def _check_out(out: str) -> None:
    """Refuse an ``--out`` that names a file (the shard set is a folder) in one line, not ``[Errno 17] File exists``."""
    from pathlib import Path

    if Path(out).exists() and not Path(out).is_dir():
        raise FileExistsError(f"--out {out} is a file; the shard set is written to a folder: pass a new or empty "
                              "folder (or a shard set's, with --overwrite)")


def data_main(argv: list[str]) -> int:
    """Entry point of ``anycity data ...``; returns the exit code."""
    cfg = build_parser().parse_args(argv)
    _check_out(cfg[cfg.command].out)
    if cfg.command == "synth":
        from anycity.data.synthetic import synth

        a = cfg.synth
        index = synth(a.out, scenes=a.scenes, views=a.views, size=a.size, seed=a.seed, trajectory=a.trajectory,
                      preview=a.preview, workers=a.workers, image_format=a.image_format, depth_dtype=a.depth_dtype,
                      normals=a.normals, window=a.window or None, stride=a.stride,
                      supersample=a.supersample, hfov=a.hfov, overwrite=a.overwrite)
        print(f"synth: {_summary(index)} -> {a.out} in {index['seconds']:.1f} s"
              + (f"; preview {a.out}/preview.png" if a.preview else ""))
    else:
        from anycity.data.parsers import convert

        a = cfg.convert
        index = convert(a.format, a.src, a.out, split=a.split, max_views=a.max_views, max_side=a.max_side,
                        seed=a.seed, overwrite=a.overwrite)
        print(f"convert {a.format}: {_summary(index)} -> {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(data_main(sys.argv[1:]))
