"""Write the views of an ``anycity data synth`` scene as a photo folder plus its ground-truth ``cameras.json``.

    anycity data synth --out data/city200 --scenes 1 --views 200 --size 48x48 --trajectory orbit --seed 1
    python scripts/synth_to_folder.py data/city200 runs/city200_photos   # -> photos/*.jpg + cameras_gt.json

Shards hold overlapping trajectory windows; each view is written once, named by its index along the trajectory.
The shards are those the set's ``index.json`` lists (never other ``*.tar`` files in the folder). ``--seed 1``: the
quickstart's cities are seed 0's scenes 0 to 79, so seed 0's scene 0 is one it trained on. A set of several scenes
needs ``--scene KEY`` (a key of its ``index.json``'s scenes); a non-empty ``OUT/photos`` is refused.
"""

from __future__ import annotations

import argparse
import json
import sys
import tarfile
from pathlib import Path


def _scene_keys(index: dict, scene: str | None, ap: argparse.ArgumentParser) -> set[str]:
    """The sample keys of the one scene to write (views of two scenes share their indices)."""
    scenes = [sc["key"] for sc in index.get("scenes", [])]
    if scene is None and len(scenes) > 1:
        ap.error(f"{len(scenes)} scenes in the set; pass --scene KEY, one of {', '.join(scenes)}")
    if scene is not None and scene not in scenes:
        ap.error(f"--scene {scene}: not in the set; pass one of {', '.join(scenes)}")
    scene = scene or (scenes[0] if scenes else None)
    return {sm["key"] for sm in index.get("samples", []) if scene is None or sm.get("scene") == scene}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", help="an anycity data synth folder (its index.json)")
    ap.add_argument("out", help="writes OUT/photos/*.jpg and OUT/cameras_gt.json")
    ap.add_argument("--scene", default=None, help="the scene's key (index.json's scenes), where the set has several")
    args = ap.parse_args(argv)
    from anycity.data.writer import read_index

    src, out = Path(args.src), Path(args.out)
    try:
        index = read_index(src)  # its shards only: not other *.tar files that may lie in the folder
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    keys = _scene_keys(index, args.scene, ap)
    photos = out / "photos"
    if photos.is_dir() and any(photos.iterdir()):  # an earlier run's photos would mix with these
        ap.error(f"{photos} is not empty; delete it or pass another OUT")
    photos.mkdir(parents=True, exist_ok=True)
    cams: dict[int, dict] = {}
    for shard in [src / e["path"] for e in index["shards"]]:
        with tarfile.open(shard) as tar:
            members = {m.name: m for m in tar.getmembers()}
            for name in sorted(n for n in members if n.endswith(".cameras.json")):
                meta = json.loads(tar.extractfile(members[name]).read())
                key = name.removesuffix(".cameras.json")
                if keys and key not in keys:
                    continue
                for v in meta["views"]:
                    g = int(v["index"])  # along the whole trajectory
                    if g in cams:
                        continue
                    data = tar.extractfile(members[f"{key}.{v['image']}"]).read()
                    (photos / f"view_{g:04d}.jpg").write_bytes(data)
                    cams[g] = {"name": f"view_{g:04d}.jpg", "w2c": v["w2c"], "K": v["K"], "width": v["width"],
                               "height": v["height"]}
    views = [cams[g] for g in sorted(cams)]
    (out / "cameras_gt.json").write_text(json.dumps({"views": views}))
    print(f"{len(views)} views -> {photos}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
