"""``anycity export --from PATH --format splat|colmap|nerfstudio|ply --out DIR``.

``PATH`` is a ``predict`` scene folder (``scene.ply`` + ``cameras.json``) or a bare ``scene.ply`` (then only the
Gaussian formats can be written). No Lightning import: this runs in a second.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import torch

from anycity.atomic import check_writable_folder
from anycity.export.views import view_png

FORMATS = ("splat", "colmap", "nerfstudio", "ply")


def refuse_unknown_flags(parser, argv: list[str] | None) -> list[str] | None:
    """``argv`` unchanged, or argparse's one-line error naming a mistyped flag and the nearest real one: argparse
    reports a required flag that was mistyped as missing ("the following arguments are required: --format"),
    never naming the typo."""
    import difflib

    known = [s for action in parser._actions for s in action.option_strings]
    for arg in argv or []:
        flag = arg.split("=", 1)[0]
        if flag.startswith("--") and flag != "--" and flag not in known:
            near = difflib.get_close_matches(flag, known, n=1, cutoff=0.75)
            parser.error(f"unrecognized argument {flag}" + (f"; did you mean {near[0]}?" if near else ""))
    return argv


def load_scene(path: str | Path):
    """``(gaussians, cameras)`` of a predict folder or a ``scene.ply``; ``cameras`` is the ``cameras.json`` dict
    or None."""
    from anycity.export.cameras import load_cameras
    from anycity.export.ply import load_ply

    path = Path(path)
    ply = path / "scene.ply" if path.is_dir() else path
    if path.is_dir() and not ply.is_file():
        inside = sorted(p.parent.name for p in path.glob("*/scene.ply"))  # the --export.out_dir of a predict
        hint = (f"it holds the scene folder(s) {', '.join(inside[:3])}{' ...' if len(inside) > 3 else ''}: pass one "
                f"of them, e.g. {path / inside[0]}" if inside else
                "pass a scene folder written by `anycity predict` (<--export.out_dir>/<scene>/) or a .ply file")
        raise FileNotFoundError(f"{path}: no scene.ply inside; {hint}")
    if not ply.is_file():
        raise FileNotFoundError(f"{path}: does not exist; pass a predict scene folder or a scene.ply")
    if ply.suffix.lower() != ".ply":  # e.g. the .splat or cameras.json an export wrote: not damaged, just not read
        raise ValueError(f"{path}: reads a predict scene folder or its scene.ply, not a {ply.suffix or 'suffix-less'} "
                         f"file; pass {ply.parent} (if it holds scene.ply) or the scene.ply itself")
    cam_file = ply.parent / "cameras.json"
    return load_ply(ply), (load_cameras(cam_file) if cam_file.is_file() else None)


def camera_tensors(cams: dict) -> tuple[torch.Tensor, torch.Tensor, int, int, list[str]]:
    """``cameras.json`` dict -> ``(w2c [V,4,4], K [V,3,3], width, height, names)`` (float64)."""
    views = cams["views"]
    w2c = torch.tensor([v["w2c"] for v in views], dtype=torch.float64)
    K = torch.tensor([v["K"] for v in views], dtype=torch.float64)
    names = [v.get("name", f"{i:03d}") for i, v in enumerate(views)]  # optional, as cameras_to_dict names them
    return w2c, K, int(views[0]["width"]), int(views[0]["height"]), names


def export(src: str | Path, fmt: str, out: str | Path, overwrite: bool = False) -> Path:
    """Write scene ``src`` in format ``fmt`` under ``out``; returns the main file or folder written. An ``out`` that
    exists and is not empty is refused unless ``overwrite`` (it may be an earlier export, or the scene itself).

    An ``out`` that does not exist yet is written as ``.<out>.partial`` and renamed when complete
    (:func:`anycity.atomic.staged_folder`), so an export that fails or is killed leaves no ``out`` behind and a rerun
    needs no ``--overwrite``. Into an existing folder (empty, or with ``overwrite``) the files are written in place,
    each one whole."""
    from anycity.atomic import staged_folder

    if fmt not in FORMATS:
        raise ValueError(f"--format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    out = Path(out)
    check_out_keeps_inputs(src, out)  # whatever --overwrite says: it is for an earlier export, never the scene
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"anycity export: {out} is a file, not a folder; pass --out NEW_DIR")
    filled = out.is_dir() and any(out.iterdir())
    if filled and not overwrite:  # before reading the scene: a refusal costs nothing
        raise FileExistsError(f"anycity export: {out} exists and is not empty; pass --overwrite to write into it, or "
                              "--out NEW_DIR")
    src = Path(src)
    g, cams = load_scene(src)
    if cams is None and fmt in ("colmap", "nerfstudio"):
        raise ValueError(f"{src}: no cameras.json beside the scene; --format {fmt} needs the predicted cameras, "
                         "pass the predict scene folder")
    if out.is_dir():
        return _write(g, cams, src, fmt, out)
    with staged_folder(out) as stage:
        target = _write(g, cams, src, fmt, stage)
    return out / target.relative_to(stage)


# what an export writes in its --out folder (_write): these files, and anything under these folders
_WRITTEN_FILES = ("scale.json", "scene.splat", "scene.ply", "points3D.ply", "transforms.json")
_WRITTEN_DIRS = ("images", "sparse")


def check_out_keeps_inputs(src: str | Path, out: str | Path) -> None:
    """Refuse, in one line, an ``--out`` that is the scene folder ``--from`` reads (or the folder of a bare
    ``.ply``), or in which the export would write over an input (its ``scene.ply``, ``cameras.json``, ``inputs/``
    images): ``--from SCENE --out SCENE --overwrite`` replaced the predicted ``scene.ply`` with the export's."""
    src = Path(src).resolve()
    if not src.exists():
        return  # load_scene says so
    src_dir = src if src.is_dir() else src.parent
    out = Path(out).resolve()
    hint = f"pass another --out (the default is {src_dir / 'export_<format>'})"
    if out == src_dir:
        raise ValueError(f"--out {out} is the scene folder --from reads; the export would write over its files "
                         f"(--overwrite or not); {hint}")
    inputs = [src / "scene.ply", src / "cameras.json", src / "inputs"] if src.is_dir() else [src]
    for f in inputs:
        if f == out or out in f.parents and (f.parent == out and f.name in _WRITTEN_FILES or
                                             f.relative_to(out).parts[0] in _WRITTEN_DIRS):
            raise ValueError(f"--out {out}: the export would write over (or into) its input {f}; {hint}")


def _write(g, cams: dict | None, src: Path, fmt: str, out: Path) -> Path:
    """The files of format ``fmt`` in the folder ``out``; returns the main file or folder written."""
    from anycity.atomic import atomic_write_bytes
    from anycity.export.formats import save_colmap, save_points_ply, save_scale, save_splat, save_transforms
    from anycity.export.ply import save_ply

    out.mkdir(parents=True, exist_ok=True)
    scale = cams.get("metres_per_unit") if cams else None
    save_scale(out / "scale.json", scale, fmt)
    if fmt == "splat":
        target = out / "scene.splat"
        save_splat(g, target)
        return target
    if fmt == "ply":  # every reader's layout: no extra columns, SH degree 3 (SIBR reads fixed 62-float records)
        target = out / "scene.ply"
        save_ply(g, target, pad_degree=3)
        return target
    w2c, K, w, h, names = camera_tensors(cams)
    src_dir = src if src.is_dir() else src.parent
    images = image_names(names)
    inputs = [view_png(src_dir, "inputs", v) for v in range(len(names))]  # the images the cameras belong to
    if all(f.is_file() for f in inputs):
        for f, name in zip(inputs, images, strict=True):
            atomic_write_bytes(out / "images" / name, f.read_bytes())
    else:
        warnings.warn(f"{src_dir}: no inputs/ images for all {len(names)} cameras (predict with --export.save_renders "
                      f"false?); the {fmt} export names images/{images[0]} etc. without writing them", stacklevel=3)
    if fmt == "colmap":
        return save_colmap(out / "sparse" / "0", w2c, K, w, h, images, g)
    save_ply(g, out / "scene.ply", pad_degree=3)  # graphdeco's loader and SIBR take degree 3 only, as --format ply
    save_points_ply(out / "points3D.ply", g)  # nerfstudio seeds from x y z + red green blue, not from SH columns
    return save_transforms(out / "transforms.json", w2c, K, w, h, [f"images/{n}" for n in images],
                           ply_file_path="points3D.ply")


_PHOTO_SUFFIXES = (".jpg", ".jpeg", ".jfif", ".jpe", ".png", ".webp")  # data.photos' (export may not import data)


def image_names(names: list[str]) -> list[str]:
    """Exported image file names for the cameras' view names: ``DJI_0018.jpg`` -> ``DJI_0018.png`` (the inputs are
    PNGs at the cameras' size), ``003`` -> ``003.png``; whitespace becomes ``_`` (COLMAP's images.txt and the
    readers of it split lines on spaces: ``DJI 0018.jpg`` -> ``DJI_0018.png``); prefixed with the view index where
    two would collide. Only a name's last path component is used (``load_cameras`` refuses the others; this keeps
    every file inside ``images/``): ``a/../b.jpg`` -> ``b.png``, ``..`` -> ``view.png``."""
    bases = [n.replace("\\", "/").replace("\0", "").rsplit("/", 1)[-1] for n in names]
    stems = [Path(n).stem if Path(n).suffix.lower() in _PHOTO_SUFFIXES else n for n in bases]
    stems = ["_".join(s.split()) for s in stems]
    stems = [s if s not in ("", ".", "..") else "view" for s in stems]
    if len(set(stems)) < len(stems):
        stems = [f"{v:03d}_{s}" for v, s in enumerate(stems)]
    return [f"{s}.png" for s in stems]


def export_main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="anycity export", description="Export a predicted scene for other tools.",
                                allow_abbrev=False)
    p.add_argument("--from", dest="src", required=True, help="predict scene folder or scene.ply")
    p.add_argument("--format", required=True, choices=FORMATS, help="splat: antimatter15 .splat; colmap: text "
                   "model (sparse/0); nerfstudio: transforms.json + points3D.ply (its seed) + scene.ply; ply: "
                   "graphdeco's exact 3DGS PLY record (no provenance columns, SH padded to degree 3) for every reader, "
                   "SIBR's included")
    p.add_argument("--out", default=None, help="output folder (default: <from>/export_<format>)")
    p.add_argument("--overwrite", action="store_true", help="write into an --out folder that is not empty")
    a = p.parse_args(refuse_unknown_flags(p, argv))
    src = Path(a.src)
    out = Path(a.out) if a.out else (src if src.is_dir() else src.parent) / f"export_{a.format}"
    check_writable_folder(out, "--out")
    target = export(src, a.format, out, a.overwrite)
    print(f"wrote {target}")
    return 0
