"""Data throughput: synthetic generation speed, samples/s and MB/s reading shards into ViewBatch, and the photo
loader of ``anycity predict --data.predict_images`` on 20 MP JPEGs (reduced-scale decoding against a full decode).

    .venv/bin/python benchmarks/data.py [--root data/bench-448] [--samples 60] [--skip-synth]

Target (issue 3): >= 20 samples/s of 4 context + 12 dense views (+ targets) at 448x448 with 2 workers, and
synthetic generation of 8 scenes x 48 views at 256x256 in <= 60 s on 2 cores. Benchmark shards (8 scenes x 48
views at 448x448, 24-view training windows, no stored normals) are generated once and reused; they are
regenerated when the shard schema changed, but only in a folder the benchmark made (the default ``--root``, or one
holding its marker ``bench_data.json``): another unreadable ``--root`` stops with one line and is left alone. The
20 MP photos are written to a temporary folder. The machine's load average is printed: on a shared machine take the
best of a few runs at low load.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import shutil
import tarfile
import tempfile
import time
from pathlib import Path

from _bench import positive_int

from anycity.data.synthetic import synth
from anycity.data.writer import read_index
from anycity.lit.datamodule import AerialDataModule

DEFAULT_ROOT = "data/bench-448"
MARKER = "bench_data.json"  # written into each shard folder this benchmark generates


def load() -> str:
    return "load average " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def bench_synth(out: Path, scenes: int, views: int, size: str) -> float:
    shutil.rmtree(out, ignore_errors=True)
    index = synth(out, scenes=scenes, views=views, size=size, seed=0, trajectory="mixed")
    return index["seconds"]


def prepare_root(root: Path, default: bool) -> None:
    """Generate the benchmark shards in ``root`` unless it holds a readable shard set. A folder is only wiped and
    rebuilt when the benchmark made it (``default``, or its marker file) or when it is missing or empty."""
    try:
        read_index(root)
        return
    except (FileNotFoundError, ValueError) as e:
        why = str(e).split(";")[0]
    ours = default or (root / MARKER).is_file() or not root.exists() or (root.is_dir() and not any(root.iterdir()))
    if not ours:
        raise SystemExit(f"--root {root}: not a readable shard set ({why}) and not a folder this benchmark made "
                         f"(no {MARKER}), so it is left alone; pass a new or empty folder, or leave --root out "
                         f"({DEFAULT_ROOT})")
    s = bench_synth(root, 8, 48, "448x448")
    (root / MARKER).write_text(json.dumps({"made_by": "benchmarks/data.py", "size": "448x448"}) + "\n")
    print(f"synth 8 scenes x 48 views at 448x448 (benchmark shards): {s:.1f} s")


def stored_size(root: Path) -> str:
    """``WxH`` of the first view stored in the first train shard of ``root`` ("unknown size" if none is found)."""
    import cv2
    import numpy as np

    train = [s for s in read_index(root)["shards"] if s["split"] == "train"]
    if train:
        with tarfile.open(root / train[0]["path"]) as tar:
            for m in tar:
                if m.isfile() and m.name.endswith((".jpg", ".jpeg", ".png")) and ".mask." not in m.name:
                    img = cv2.imdecode(np.frombuffer(tar.extractfile(m).read(), np.uint8), cv2.IMREAD_UNCHANGED)
                    if img is not None:
                        return f"{img.shape[1]}x{img.shape[0]}"
    return "unknown size"


def bench_read(root: Path, workers: int, samples: int, targets: int, normals: bool = False,
               compact: bool = False) -> tuple[float, float]:
    dm = AerialDataModule(root=str(root), num_context=4, num_dense=12, num_targets=targets, image_size=(448, 448),
                          batch_size=1, num_workers=workers, epoch_samples=samples, seed=0, with_normals=normals,
                          compact_batches=compact)
    index = read_index(root)
    train = [s for s in index["shards"] if s["split"] == "train"]
    per_sample = sum((root / s["path"]).stat().st_size for s in train) / sum(s["num_samples"] for s in train)
    it = iter(dm.train_dataloader())
    next(it)  # worker start-up and first decode excluded
    t0 = time.perf_counter()
    n = 1
    for _ in it:
        n += 1
    rate = (n - 1) / (time.perf_counter() - t0)
    del it  # shut the workers down here, not in a later run's forked workers
    gc.collect()
    return rate, rate * per_sample / 1e6


def bench_photos(folder: Path, count: int = 8, hw: tuple[int, int] = (448, 672)) -> tuple[float, float, float]:
    """ms per 5472x3648 JPEG loaded for a ``hw`` input: the photo loader, then a full decode + the same resize; and
    the PSNR (dB) between the two inputs."""
    import cv2
    import numpy as np

    from anycity.data.photos import load_photo
    from anycity.data.views import resize_view

    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:3648, 0:5472].astype(np.float32)
    rng = np.random.default_rng(0)
    for i in range(count):  # a smooth field plus fine texture, JPEG quality 92 (about a drone photo's bytes)
        img = np.stack([np.sin(xx / (97 + i)) * 60 + 128, np.cos(yy / 83) * 60 + 128, (xx + yy) / 36 % 256], -1)
        img += rng.normal(0, 8, img.shape).astype(np.float32)
        cv2.imwrite(str(folder / f"{i:03d}.jpg"), img.clip(0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 92])
    files = sorted(folder.glob("*.jpg"))
    t = time.perf_counter()
    fast = [load_photo(f, hw) for f in files]
    t_fast = (time.perf_counter() - t) / count * 1e3
    t = time.perf_counter()
    full = []
    for f in files:
        rgb, *_ = resize_view(np.ascontiguousarray(cv2.imread(str(f))[..., ::-1]), np.eye(3), hw, "keep", 14)
        full.append(rgb)
    t_full = (time.perf_counter() - t) / count * 1e3
    mse = np.mean([((a.permute(1, 2, 0).numpy() - b / 255) ** 2).mean() for a, b in zip(fast, full)])
    return t_fast, t_full, float(10 * np.log10(1 / mse))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", default=DEFAULT_ROOT, help="benchmark shard folder (generated here if missing)")
    ap.add_argument("--samples", type=positive_int, default=60)
    ap.add_argument("--targets", type=positive_int, default=4)
    ap.add_argument("--skip-synth", action="store_true")
    a = ap.parse_args(argv)
    if not a.skip_synth:
        print(load())
        s = bench_synth(Path("data/bench-synth-256"), 8, 48, "256x256")
        print(f"synth 8 scenes x 48 views at 256x256: {s:.1f} s (target <= 60 s); {load()}")
    root = Path(a.root)
    prepare_root(root, root.resolve() == Path(DEFAULT_ROOT).resolve())
    size = stored_size(root)
    runs = [(0, False, False, ""), (2, False, False, ""),
            (2, False, True, ", compact_batches (uint8/float16, float32 on the device)"),
            (2, True, False, ", normals derived from depth")]
    for workers, normals, compact, what in runs:
        rate, mbs = bench_read(root, workers, a.samples, a.targets, normals, compact)
        print(f"read 4+12+{a.targets} views stored at {size}, as 448x448 inputs, {workers} workers{what}: "
              f"{rate:.1f} samples/s, {mbs:.0f} MB/s of shard data (target >= 20 samples/s with 2 workers); {load()}")
    with tempfile.TemporaryDirectory() as photos:
        fast, full, psnr = bench_photos(Path(photos))
    print(f"photo folder, 5472x3648 JPEG -> 448x672 input: {fast:.0f} ms per photo (libjpeg 1/8-scale decode) against "
          f"{full:.0f} ms decoding in full ({full / fast:.1f}x); the inputs agree to {psnr:.1f} dB PSNR; {load()}")


if __name__ == "__main__":
    main()
