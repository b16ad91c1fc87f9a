"""Quickstart: synthetic city shards -> Stage I -> Stage II (tiny preset, CPU) -> evaluation on unseen scenes.

    python scripts/quickstart.py            # what `make quickstart` runs; about 13 minutes on 2 CPU cores

Writes ``runs/quickstart/metrics.json`` ({baseline,scaffold,refined}_psnr, {scaffold,refined}_ssim, abs_rel,
delta1, minutes, nearest_view_psnr, {scaffold,refined}_psnr_{unaligned,feedforward}, and the context cameras' mean
relative rotation / translation-direction errors rot_err_deg, trans_err_deg and pose_auc30, of the network and, with
the suffix _refined_cameras, after test-time camera refinement), ``runs/quickstart/preview.png``
(context | target | scaffold | refined | depth for held-out views of test scenes) and prints a table. The baseline
paints every target pixel with the mean colour of the context views; the nearest-view reference shows the context
image closest along the trajectory (what a model that learnt no 3D would show). All numbers come from the test
split: scenes never seen in training.
The protocol has two test-time steps, both photometric with the Gaussians frozen. First the predicted context
cameras are refined from the context images alone (``model.camera_refine_steps``: every view's Gaussians must agree
when rendered into every context camera). Then each held-out camera, placed at its ground-truth pose relative to
the first context view, is aligned against its image (AnySplat's ``test.align_pose``, the usual protocol of pose-free
methods). The ``*_unaligned`` figures are the renders before the second step, ``*_feedforward`` those with neither
(the network's cameras as they come).

The cities are orbit captures (GoogleEarth / MatrixCity-like) rendered with 2 x 2 supersampling: the serpentine
nadir grids of ``--trajectory mixed`` flip the heading by 180 degrees between flight lines, which the tiny CPU
model cannot resolve (median relative-rotation error 32 deg against 9 deg on orbits).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGE1 = ROOT / "configs" / "quickstart.yaml"
STAGE2 = ROOT / "configs" / "quickstart_stage2.yaml"


def _run_args(out: Path, name: str) -> list[str]:
    d = str(out / name)
    return ["--trainer.default_root_dir", d, "--trainer.logger.init_args.save_dir", d]


def _banner(text: str, t0: float) -> None:
    print(f"\n=== {text}  [{(time.monotonic() - t0) / 60:.1f} min]", flush=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="data/quickstart", help="shard directory (generated when absent)")
    p.add_argument("--out", default="runs/quickstart", help="run directory")
    p.add_argument("--scenes", type=int, default=80, help="synthetic cities to generate when the data is absent")
    p.add_argument("--views", type=int, default=96, help="views per city (more = denser, overlapping views)")
    p.add_argument("--trajectory", default="orbit", choices=["orbit", "nadir", "mixed"], help="camera path")
    p.add_argument("--stage1_steps", type=int, default=None, help="override configs/quickstart.yaml max_steps")
    p.add_argument("--stage2_steps", type=int, default=None, help="override configs/quickstart_stage2.yaml")
    args, extra = p.parse_known_args(argv)  # unknown --x.y options go to every training CLI call
    sys.argv = sys.argv[:1]  # the training CLI below is driven by explicit argument lists
    t0 = time.monotonic()
    data, out = Path(args.data), Path(args.out)

    from anycity.cli import build_cli
    from anycity.data.cli import data_main

    synth_args = ["--scenes", str(args.scenes), "--views", str(args.views), "--size", "48x48",
                  "--trajectory", args.trajectory, "--supersample", "2"]
    stamp = data / "quickstart_data.json"  # the synth arguments these shards were made with
    if (data / "index.json").is_file():
        made_with = json.loads(stamp.read_text()) if stamp.is_file() else None
        if made_with != synth_args:
            print(f"error: {data} holds shards made with other settings ({made_with or 'unknown'}; the quickstart "
                  f"needs {' '.join(synth_args)}): delete {data} to regenerate it, or pass --data NEW_DIR",
                  file=sys.stderr)
            return 2
    else:
        _banner(f"generating {args.scenes} synthetic cities x {args.views} {args.trajectory} views at 48x48 -> {data}",
                t0)
        rc = data_main(["synth", "--out", str(data), *synth_args, "--preview"])
        if rc:
            return rc
        stamp.write_text(json.dumps(synth_args) + "\n")
    common = ["--data.root", str(data), *extra]

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
    cli = build_cli(["test", *stage2, *_run_args(out, "test"), "--ckpt_path", str(ckpt2)])
    m = {k: float(v) for k, v in cli.trainer.callback_metrics.items() if k.startswith("test/")}
    minutes = (time.monotonic() - t0) / 60
    metrics = {
        "baseline_psnr": m["test/psnr_baseline"], "scaffold_psnr": m["test/psnr_scaffold"],
        "refined_psnr": m["test/psnr_refined"], "scaffold_ssim": m["test/ssim_scaffold"],
        "refined_ssim": m["test/ssim_refined"], "abs_rel": m.get("test/abs_rel_refined", float("nan")),
        "delta1": m.get("test/delta1_refined", float("nan")), "minutes": round(minutes, 2),
        "nearest_view_psnr": m.get("test/psnr_nearest", float("nan")),
        "scaffold_psnr_unaligned": m.get("test/psnr_scaffold_unaligned", m["test/psnr_scaffold"]),
        "refined_psnr_unaligned": m.get("test/psnr_refined_unaligned", m["test/psnr_refined"]),
        "rot_err_deg": m.get("test/rre", float("nan")), "trans_err_deg": m.get("test/rte", float("nan")),
        "pose_auc30": m.get("test/pose_auc30", float("nan")),
        "scaffold_psnr_feedforward": m.get("test/psnr_scaffold_feedforward", float("nan")),
        "refined_psnr_feedforward": m.get("test/psnr_refined_feedforward", float("nan")),
        "rot_err_deg_refined_cameras": m.get("test/rre_refined", float("nan")),
        "trans_err_deg_refined_cameras": m.get("test/rte_refined", float("nan")),
        "pose_auc30_refined_cameras": m.get("test/pose_auc30_refined", float("nan")),
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    previews = sorted((out / "test" / "previews").glob("test_*.png"))
    if previews:
        shutil.copy(previews[-1], out / "preview.png")

    print("\n| model                      | PSNR (dB) | SSIM  |")
    print("|----------------------------|-----------|-------|")
    print(f"| mean-colour baseline       | {metrics['baseline_psnr']:9.2f} |   -   |")
    print(f"| nearest context view       | {metrics['nearest_view_psnr']:9.2f} |   -   |")
    print(f"| Stage I scaffold           | {metrics['scaffold_psnr']:9.2f} | {metrics['scaffold_ssim']:.3f} |")
    print(f"| Stage II refined           | {metrics['refined_psnr']:9.2f} | {metrics['refined_ssim']:.3f} |")
    print(f"| (refined, no target align) | {metrics['refined_psnr_unaligned']:9.2f} |   -   |")
    print(f"| (refined, feed-forward)    | {metrics['refined_psnr_feedforward']:9.2f} |   -   |")
    print(f"\ndepth (refined, held-out views): AbsRel {metrics['abs_rel']:.3f}  delta1 {metrics['delta1']:.3f}")
    print(f"context cameras (all view pairs), network -> after test-time refinement: rotation error "
          f"{metrics['rot_err_deg']:.1f} -> {metrics['rot_err_deg_refined_cameras']:.1f} deg, translation direction "
          f"error {metrics['trans_err_deg']:.1f} -> {metrics['trans_err_deg_refined_cameras']:.1f} deg, AUC@30 "
          f"{metrics['pose_auc30']:.3f} -> {metrics['pose_auc30_refined_cameras']:.3f}")
    gain = metrics["refined_psnr"] - metrics["baseline_psnr"]
    print(f"refined - baseline: {gain:+.2f} dB   total {minutes:.1f} min")
    print(f"wrote {out / 'metrics.json'} and {out / 'preview.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
