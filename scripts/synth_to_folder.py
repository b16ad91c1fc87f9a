"""Write the views of an ``anycity data synth`` scene as a photo folder plus its ground-truth ``cameras.json``.

    anycity data synth --out data/city200 --scenes 1 --views 200 --size 48x48 --trajectory orbit --seed 1
    python scripts/synth_to_folder.py data/city200 runs/city200_photos   # -> photos/*.jpg + cameras_gt.json

Shards hold overlapping trajectory windows; each view is written once, named by its index along the trajectory.
The shards are those the set's ``index.json`` lists (never other ``*.tar`` files in the folder). ``--seed 1``: the
quickstart's cities are seed 0's scenes 0 to 79, so seed 0's scene 0 is one it trained on.
"""

from __future__ import annotations

import json
import sys
import tarfile
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2:
        print(__doc__)
        return 2
    from anycity.data.writer import read_index

    src, out = Path(argv[0]), Path(argv[1])
    try:
        index = read_index(src)  # its shards only: not other *.tar files that may lie in the folder
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    photos = out / "photos"
    photos.mkdir(parents=True, exist_ok=True)
    cams: dict[int, dict] = {}
    for shard in [src / e["path"] for e in index["shards"]]:
        with tarfile.open(shard) as tar:
            members = {m.name: m for m in tar.getmembers()}
            for name in sorted(n for n in members if n.endswith(".cameras.json")):
                meta = json.loads(tar.extractfile(members[name]).read())
                key = name.removesuffix(".cameras.json")
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
