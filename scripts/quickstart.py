"""Quickstart: synthetic city shards -> Stage I -> Stage II (tiny preset, CPU) -> evaluation on unseen scenes.

    python scripts/quickstart.py            # what `make quickstart` runs; 8 to 34 minutes on 2 CPU cores (README)

Writes ``runs/quickstart/metrics.json``, ``runs/quickstart/preview.png`` (context | target | scaffold | refined |
depth | regions for held-out views of test scenes) and prints two tables. All numbers come from the test split:
scenes never seen in training. Every figure is named for the images it reads (``PROTOCOLS`` below; the key
``protocols`` of metrics.json says the same):

* no suffix, the feed-forward figures (they come first): context images in, Gaussians out, each held-out view
  rendered at its ground-truth pose relative to the first context view; no target image is read.
* ``_camrefine``: after the test-time refinement of the predicted context cameras from the context images alone
  (``model.camera_refine_steps``); no target image is read.
* ``_targetalign``: then each target camera aligned against its own target image (AnySplat's ``test.align_pose``,
  NoPoSplat's protocol); this reads the target image.

Keys: ``{scaffold,refined}_{psnr,ssim}[_camrefine|_targetalign]``, the region diagnostic's
``psnr_{obs,weak}_{scaffold,refined}[_camrefine]`` (and ``ssim_``), ``psnr_{obs,weak}_baseline``, the regions' shares
``region_{obs,weak}``, ``baseline_psnr`` (every target pixel = the mean context colour), ``nearest_view_psnr`` (the
context image closest along the trajectory: what a model that learnt no 3D would show), ``abs_rel``/``delta1``
(feed-forward depth), the context cameras' mean relative rotation / translation-direction errors ``rot_err_deg``,
``trans_err_deg`` and ``pose_auc30`` of the network and, with the suffix ``_refined_cameras``, after camrefine;
``minutes``.

The cities are orbit captures (GoogleEarth / MatrixCity-like) rendered with 2 x 2 supersampling: the serpentine
nadir grids of ``--trajectory mixed`` flip the heading by 180 degrees between flight lines, which the tiny CPU
model cannot resolve (median relative-rotation error 32 deg against 9 deg on orbits).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGE1 = ROOT / "configs" / "quickstart.yaml"
STAGE2 = ROOT / "configs" / "quickstart_stage2.yaml"
USER_ERRORS = (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)


def _run_args(out: Path, name: str) -> list[str]:
    d = str(out / name)
    return ["--trainer.default_root_dir", d, "--trainer.logger.init_args.save_dir", d]


def _forwardable(arg: str) -> bool:
    """Whether an argument the script does not know may go to LightningCLI: a dotted override (``--trainer.x 1``,
    ``--model.init_args.y=2``), ``--seed_everything``, or the value of the option before it."""
    if not arg.startswith("-") or arg[1:2].isdigit() or arg[1:2] == ".":
        return True  # a value, negative numbers included
    name = arg.split("=", 1)[0]
    return name == "--seed_everything" or (name.startswith("--") and "." in name and not name.startswith("--."))


def _index_sha256(data: Path) -> str:
    return hashlib.sha256((data / "index.json").read_bytes()).hexdigest()


def write_stamp(data: Path, synth_args: list[str]) -> None:
    """``quickstart_data.json``: the synth arguments and the sha256 of the ``index.json`` they made (a folder
    regenerated with ``anycity data synth --overwrite`` keeps the stamp but not the index)."""
    from anycity.atomic import atomic_write_bytes

    stamp, text = data / "quickstart_data.json", json.dumps({"synth": synth_args, "index_sha256": _index_sha256(data)})
    if not stamp.is_file() or stamp.read_text().strip() != text:  # an earlier format's stamp is upgraded
        atomic_write_bytes(stamp, (text + "\n").encode())


def stamp_mismatch(data: Path, synth_args: list[str], scenes: int, views: int) -> str | None:
    """Why the shards in ``data`` are not the quickstart's (None when they are)."""
    stamp = data / "quickstart_data.json"
    made = json.loads(stamp.read_text()) if stamp.is_file() else None
    if isinstance(made, dict):
        if made.get("synth") != synth_args:
            return f"{' '.join(made.get('synth') or ['unknown'])}"
        return None if made.get("index_sha256") == _index_sha256(data) else "index.json changed since its stamp"
    if made != synth_args:
        return f"{' '.join(made) if made else 'unknown'}"
    # a stamp of the earlier format (the synth arguments only): the index must still say what they asked for
    index = json.loads((data / "index.json").read_text())
    found = index.get("scenes") or []
    if len(found) != scenes or any(sc.get("num_views") != views for sc in found):
        return f"index.json lists {len(found)} scenes, not {scenes} of {views} views"
    return None


def _banner(text: str, t0: float) -> None:
    print(f"\n=== {text}  [{(time.monotonic() - t0) / 60:.1f} min]", flush=True)


def _train_and_test(out: Path, common: list[str], args: argparse.Namespace, t0: float):
    """Stage I, Stage II, then ``anycity test`` of Stage II on the test split; returns the test's CLI."""
    from anycity.cli import build_cli

    _banner("Stage I: scaffold (tiny preset)", t0)
    steps1 = ["--trainer.max_steps", str(args.stage1_steps)] if args.stage1_steps else []
    build_cli(["fit", "-c", str(STAGE1), *common, *_run_args(out, "stage1"), *steps1])
    ckpt1 = out / "stage1" / "checkpoints" / "last.ckpt"

    _banner("Stage II: completion branch + video prior on the frozen scaffold", t0)
    steps2 = ["--trainer.max_steps", str(args.stage2_steps)] if args.stage2_steps else []
    stage2 = ["-c", str(STAGE1), "-c", str(STAGE2), *common]
    build_cli(["fit", *stage2, *_run_args(out, "stage2"), "--model.init_args.init_from", str(ckpt1), *steps2])
    ckpt2 = out / "stage2" / "checkpoints" / "last.ckpt"

    _banner("evaluation on held-out views of unseen (test) scenes", t0)
    # 4 test samples per step: a quarter faster. Each sample's figures ignore its batch-mates' content, but the
    # network's float rounding depends on the batch size (~1e-5), which the 50-step test-time camera fits amplify:
    # camrefine / targetalign images move by up to ~0.08 dB, their means by ~0.005 dB (feed-forward: ~1e-6 dB)
    return build_cli(["test", "--data.eval_batch_size", "4", *stage2, *_run_args(out, "test"), "--ckpt_path",
                     str(ckpt2)])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--data", default="data/quickstart", help="shard directory (generated when absent)")
    p.add_argument("--out", default="runs/quickstart", help="run directory")
    p.add_argument("--scenes", type=int, default=80, help="synthetic cities to generate when the data is absent")
    p.add_argument("--views", type=int, default=96, help="views per city (more = denser, overlapping views)")
    p.add_argument("--trajectory", default="orbit", choices=["orbit", "nadir", "mixed"], help="camera path")
    p.add_argument("--stage1_steps", "--stage1-steps", type=int, default=None,
                   help="override configs/quickstart.yaml max_steps")
    p.add_argument("--stage2_steps", "--stage2-steps", type=int, default=None,
                   help="override configs/quickstart_stage2.yaml")
    args, extra = p.parse_known_args(argv)  # unknown --x.y options go to every training CLI call
    bad = next((a for a in extra if not _forwardable(a)), None)
    if bad is not None:
        p.error(f"unknown option {bad}: this script takes --data, --out, --scenes, "
                f"--views, --trajectory, --stage1_steps and --stage2_steps; anything else must be a "
                "LightningCLI override such as --trainer.max_epochs 2 or --model.init_args.lr 1e-4")
    sys.argv = sys.argv[:1]  # the training CLI below is driven by explicit argument lists
    t0 = time.monotonic()
    data, out = Path(args.data), Path(args.out)

    from anycity.cli import Stopped
    from anycity.data.cli import data_main

    synth_args = ["--scenes", str(args.scenes), "--views", str(args.views), "--size", "48x48",
                  "--trajectory", args.trajectory, "--supersample", "2"]
    if (data / "index.json").is_file():
        why = stamp_mismatch(data, synth_args, args.scenes, args.views)
        if why:
            print(f"error: {data} holds shards made with other settings ({why}; the quickstart needs "
                  f"{' '.join(synth_args)}): delete {data} to regenerate it, or pass --data NEW_DIR", file=sys.stderr)
            return 2
    else:
        _banner(f"generating {args.scenes} synthetic cities x {args.views} {args.trajectory} views at 48x48 -> {data}",
                t0)
        rc = data_main(["synth", "--out", str(data), *synth_args, "--preview"])
        if rc:
            return rc
    write_stamp(data, synth_args)
    common = ["--data.root", str(data), *extra]
    try:
        cli = _train_and_test(out, common, args, t0)
    except USER_ERRORS as e:  # what `anycity fit|test` prints as one line (anycity.cli.main)
        if os.environ.get("ANYCITY_DEBUG", "") not in ("", "0"):
            raise
        from anycity.cli import _one_line

        print(f"quickstart: error: {_one_line(e)}  (ANYCITY_DEBUG=1 for the traceback)", file=sys.stderr)
        return 2
    except Stopped as e:  # SIGTERM: exit 143 and the line saying where it stopped
        if e.message:
            print(f"quickstart: {e.message}", file=sys.stderr)
        return e.code
    m = {k[len("test/"):]: float(v) for k, v in cli.trainer.callback_metrics.items() if k.startswith("test/")}
    metrics = quickstart_metrics(m, (time.monotonic() - t0) / 60, dict(cli.model.hparams))
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(json_safe(metrics), indent=2, allow_nan=False) + "\n")
    previews = sorted((out / "test" / "previews").glob("test_*.png"))
    if previews:
        shutil.copy(previews[-1], out / "preview.png")
    print_tables(metrics)
    print(f"wrote {out / 'metrics.json'} and {out / 'preview.png'}")
    return 0


PROTOCOLS = {
    "": "feed-forward: context images in, Gaussians out, targets rendered at their ground-truth poses relative to "
        "the first context view; no target image is read",
    "_camrefine": "after test-time refinement of the context cameras from the context images alone; no target "
                  "image is read",
    "_targetalign": "after camrefine, each target camera aligned against its own target image (AnySplat "
                    "align_pose / NoPoSplat protocol): reads the target image",
}


def protocol_texts(hp: dict | None = None) -> dict[str, str]:
    """:data:`PROTOCOLS` as the test run's hyperparameters ``hp`` made them (the quickstart's config when None):
    ``eval_align sim3`` places the targets by a Sim(3) fit to every context camera, and ``targetalign`` without
    camrefine starts from the network's cameras."""
    texts = dict(PROTOCOLS)
    hp = hp or {}
    if hp.get("eval_align", "none") == "sim3":
        texts[""] = texts[""].replace("relative to the first context view", "placed by a Sim(3) fit of the "
                                      "ground-truth context cameras to the predicted ones")
    if hp.get("camera_refine_steps", 1) == 0:
        texts.pop("_camrefine")
        texts["_targetalign"] = texts["_targetalign"].replace("after camrefine", "from the network's cameras")
    if hp.get("eval_pose_align_steps", 1) == 0:
        texts.pop("_targetalign")
    return texts


def quickstart_metrics(m: dict[str, float], minutes: float, hp: dict | None = None) -> dict:
    """``anycity test`` figures (names without ``test/``) -> the flat ``metrics.json`` of the quickstart.

    Every figure is named for its protocol (see ``PROTOCOLS``): no suffix = feed-forward, ``_camrefine``,
    ``_targetalign``; ``protocols`` describes those the test run ``hp`` (its hyperparameters) ran."""
    nan = float("nan")
    out: dict = {"minutes": round(minutes, 2), "baseline_psnr": m["psnr_baseline"],
                 "nearest_view_psnr": m.get("psnr_nearest", nan)}
    for sfx in PROTOCOLS:
        for v in ("scaffold", "refined"):
            out[f"{v}_psnr{sfx}"] = m.get(f"psnr_{v}{sfx}", nan)
            out[f"{v}_ssim{sfx}"] = m.get(f"ssim_{v}{sfx}", nan)
            if f"lpips_{v}{sfx}" in m:  # only where LPIPS's backbone weights are on the machine
                out[f"{v}_lpips{sfx}"] = m[f"lpips_{v}{sfx}"]
            if sfx != "_targetalign":
                for r in ("obs", "weak"):
                    out[f"psnr_{r}_{v}{sfx}"] = m.get(f"psnr_{r}_{v}{sfx}", nan)
                    out[f"ssim_{r}_{v}{sfx}"] = m.get(f"ssim_{r}_{v}{sfx}", nan)
    for r in ("obs", "weak"):
        out[f"psnr_{r}_baseline"] = m.get(f"psnr_{r}_baseline", nan)
        out[f"region_{r}"] = m.get(f"region_{r}", nan)
    out.update({
        "abs_rel": m.get("abs_rel_refined", nan), "delta1": m.get("delta1_refined", nan),
        "rot_err_deg": m.get("rre", nan), "trans_err_deg": m.get("rte", nan), "pose_auc30": m.get("pose_auc30", nan),
        "rot_err_deg_refined_cameras": m.get("rre_refined_camrefine", nan),
        "trans_err_deg_refined_cameras": m.get("rte_refined_camrefine", nan),
        "pose_auc30_refined_cameras": m.get("pose_auc30_refined_camrefine", nan),
        "protocols": {sfx.lstrip("_") or "feedforward": text for sfx, text in protocol_texts(hp).items()},
    })
    return out


def json_safe(x):
    """``x`` with every non-finite float (a figure its protocol or data did not give) as None: strict JSON
    (``null``), which jq and ``JSON.parse`` read; Python's ``NaN`` token they refuse."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    return None if isinstance(x, float) and not math.isfinite(x) else x


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A markdown table with every column padded to its widest cell (the model names left, the figures right)."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    fmt = lambda r: "| " + " | ".join(c.ljust(w) if i == 0 else c.rjust(w)  # noqa: E731
                                      for i, (c, w) in enumerate(zip(r, widths))) + " |"
    return "\n".join([fmt(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|", *map(fmt, rows)])


def print_tables(x: dict) -> None:
    """The PSNR table (feed-forward first, each test-time step named for the images it reads) and the region
    table of the paper's Table 2 (observation-supported / weak pixels)."""
    pair = lambda v, p: f"{x[f'{v}_psnr{p}']:.2f} / {x[f'{v}_ssim{p}']:.3f}"  # noqa: E731
    rows = [["mean-colour baseline", f"{x['baseline_psnr']:.2f}", "", ""],
            ["nearest context view", f"{x['nearest_view_psnr']:.2f}", "", ""]]
    rows += [[label, pair(v, ""), pair(v, "_camrefine"), pair(v, "_targetalign")]
             for v, label in (("scaffold", "Stage I scaffold"), ("refined", "Stage II refined"))]
    print("\n" + markdown_table(["model", "feed-forward PSNR / SSIM", "+ camrefine (context only)",
                                 "+ targetalign (reads target)"], rows))
    print(f"\nregions of the target pixels (ground-truth depth reprojected into the context views): observed "
          f"{100 * x['region_obs']:.1f}%, weak {100 * x['region_weak']:.1f}% (the rest is sky)")
    rows = [["baseline", f"{x['psnr_obs_baseline']:.2f}", f"{x['psnr_weak_baseline']:.2f}", "", ""]]
    rows += [[v, *(f"{x[f'psnr_{r}_{v}{p}']:.2f}" for p in ("", "_camrefine") for r in ("obs", "weak"))]
             for v in ("scaffold", "refined")]
    print(markdown_table(["model", "observed PSNR", "weak PSNR", "observed, camrefine", "weak, camrefine"], rows))
    print(f"\ndepth (refined, feed-forward, held-out views): AbsRel {x['abs_rel']:.3f}  delta1 {x['delta1']:.3f}")
    print(f"context cameras (all view pairs), network -> after camrefine: rotation error {x['rot_err_deg']:.1f} -> "
          f"{x['rot_err_deg_refined_cameras']:.1f} deg, translation direction error {x['trans_err_deg']:.1f} -> "
          f"{x['trans_err_deg_refined_cameras']:.1f} deg, AUC@30 {x['pose_auc30']:.3f} -> "
          f"{x['pose_auc30_refined_cameras']:.3f}")
    print(f"refined - baseline: {x['refined_psnr'] - x['baseline_psnr']:+.2f} dB feed-forward, "
          f"{x['refined_psnr_camrefine'] - x['baseline_psnr']:+.2f} dB after camrefine   total {x['minutes']:.1f} min")


if __name__ == "__main__":
    sys.exit(main())
