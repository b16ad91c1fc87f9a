"""Compare the cameras of an ``anycity predict`` output folder with reference cameras after one global Sim(3).

    python scripts/city_cameras.py PRED_FOLDER --colmap SCENE        # e.g. real_aerial/boruszyn_kap
    python scripts/city_cameras.py PRED_FOLDER --cameras REF.json    # a cameras.json (e.g. ground truth)

Prints rotation error (degrees, after the Sim(3) fit of camera centres) and position error relative to the scene
extent (largest distance of a reference centre from their centroid), matched by photo name.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from anycity.city.oracle import camera_errors


def load_cameras_json(path: Path) -> dict[str, torch.Tensor]:
    views = json.loads(Path(path).read_text())["views"]
    return {v["name"]: torch.tensor(v["w2c"], dtype=torch.float64) for v in views}


def load_colmap(scene: Path) -> dict[str, torch.Tensor]:
    from anycity.data.parsers.colmap import read_model, w2c_of

    model = read_model(scene)
    return {im["name"]: torch.as_tensor(w2c_of(im), dtype=torch.float64) for im in model.images.values()}


def compare(pred: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> dict:
    names = sorted(set(pred) & set(ref))
    if len(names) < 3:
        raise ValueError(f"city_cameras: only {len(names)} photo names in common; compare the same photos")
    err = camera_errors(torch.stack([pred[n] for n in names]), torch.stack([ref[n] for n in names]))
    return {"photos": len(names), **{k: round(v, 5) for k, v in err.items()}}


def _reference(a: argparse.Namespace, ap: argparse.ArgumentParser) -> dict[str, torch.Tensor]:
    if a.colmap:
        try:
            return load_colmap(a.colmap)
        except (FileNotFoundError, NotADirectoryError) as e:
            why = str(e).split("; point --src")[0]  # the parser's advice names anycity data convert's flag
            ap.error(f"--colmap {a.colmap}: cannot read its cameras ({why}); pass a COLMAP scene folder")
    if not a.cameras.is_file():
        ap.error(f"--cameras {a.cameras}: no such file; pass the reference cameras.json")
    return load_cameras_json(a.cameras)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0], allow_abbrev=False)
    ap.add_argument("pred", type=Path, help="predict output folder (holding cameras.json)")
    ap.add_argument("--colmap", type=Path, help="COLMAP scene folder of the reference cameras")
    ap.add_argument("--cameras", type=Path, help="reference cameras.json")
    a = ap.parse_args(argv)
    if not (a.pred / "cameras.json").is_file():
        ap.error(f"{a.pred}: no cameras.json; pass the scene folder anycity predict wrote (<out_dir>/<scene>)")
    if not (a.colmap or a.cameras):
        ap.error("pass the reference cameras: --colmap SCENE or --cameras cameras.json")
    try:
        print(json.dumps(compare(load_cameras_json(a.pred / "cameras.json"), _reference(a, ap))))
    except ValueError as e:  # too few photo names in common
        ap.error(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
