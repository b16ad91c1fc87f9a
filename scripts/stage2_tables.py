"""The paper's Table 2 (cumulative) and Table 3 (ablations) for Stage II, from one Stage I checkpoint.

    python scripts/stage2_tables.py                       # the quickstart's Stage I and data, 600 steps a row
    python scripts/stage2_tables.py --rows full,wo_pres   # some rows only
    python scripts/stage2_tables.py --configs configs/stage2.yaml --stage1 runs/stage1/checkpoints/last.ckpt \\
        --data /data/matrixcity --steps 20000 --model.init_args.net.wan_dir weights/Wan2.2   # at scale, on GPUs

Each row is its own Stage II run (``anycity fit`` from ``--stage1`` with the row's overrides, then ``anycity test``
on the test split, each in its own process, so ``--trainer.devices 8`` runs DDP), so every figure is scored on unseen
scenes; each run logs to CSV in its directory. Rows write ``OUT/ROW/{fit,test}`` and
``OUT/ROW/metrics.json``; a finished row is reused when it was made with the same settings (the Stage I and pose
prior files' and ``--data``'s ``index.json``'s size and time, the config files' contents included) and refused
otherwise. A SIGTERM or SIGINT sent to this script is passed on to the running ``anycity`` and waited for; the script
then exits 143 (130) naming the row, whose folder is to be deleted before a rerun (a row is not resumed).
The tables go to stdout, ``OUT/tables.md`` and ``OUT/tables.json``.

Figures are observed / weak PSNR (``anycity.metrics.regions``) in two protocols that read no target image:
feed-forward, and after the context-only camera refinement (``camrefine``, when ``camera_refine_steps > 0``).
The "scaffold only" row is the scaffold variant every test also scores (the scaffold is frozen in Stage II).
The frozen AA and frozen-all rows need their own Stage I (``quickstart.yaml`` or ``stage1.yaml`` with
``configs/ablations/frozen_aa.yaml`` / ``frozen_all.yaml``, with ``--freeze.allow_random_init true`` when trained
from scratch): pass them as ``--frozen_aa_stage1`` / ``--frozen_all_stage1``; without it a row says so in its
table instead of a figure. The ``prior_*`` rows (beyond the paper) also load ``net.pose_prior`` from
``--pose_prior FILE`` (``scripts/pose_prior.py``), and say so likewise.
Unknown ``--x.y`` options go to every ``fit`` and ``test`` call.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import signal
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
GOAL_WEAK_DB, GOAL_OBS_DB = 0.5, -0.2  # issue 12: weak >= scaffold + 0.5 dB with observed >= scaffold - 0.2 dB
PROTOCOLS = {"": "feed-forward", "_camrefine": "camrefine"}


class Row(NamedTuple):
    name: str
    label: str
    overrides: tuple[str, ...] = ()
    stage1: str = "stage1"  # which Stage I checkpoint: "stage1", or the row's own (OWN_STAGE1)
    pose_prior: bool = False  # also net.pose_prior, the file --pose_prior names (scripts/pose_prior.py)


CAMERAS = ("--model.init_args.net.refine_cameras", "true", "--model.init_args.net.camera_video", "true",
           "--model.init_args.camera_loss_type", "l1", "--model.init_args.camera_weight", "5",
           "--model.init_args.lr", "5e-3")
UNORDERED = (*CAMERAS[:2], *CAMERAS[4:])  # the same without camera_video: the views' order is not read
MIX = ("--model.init_args.net.pose_prior_mix", "true")
ROWS = {r.name: r for r in (
    Row("tokens", "+ completion tokens (no prior, no D2S)",
        ("--model.init_args.net.video_prior", "none", "--model.init_args.d2s_weight", "0")),
    Row("d2s", "+ D2S", ("--model.init_args.net.video_prior", "none")),
    Row("full", "+ video prior with LoRA (full)"),
    Row("wo_lora", "w/o prior LoRA (the prior frozen)", ("--freeze.patterns", '["net.video_prior.*"]')),
    Row("wo_pres", "w/o L_pres", ("--model.init_args.pres_weight", "0")),
    Row("frozen_aa", "frozen AA (its own Stage I)", stage1="frozen_aa"),
    Row("frozen_all", "frozen-all (its own Stage I)", stage1="frozen_all"),
    Row("cameras", "full + re-placed cameras (beyond the paper)", CAMERAS),
    Row("cameras_pose_grad", "full + re-placed cameras, the render losses reaching their poses (beyond the paper)",
        (*CAMERAS, "--model.init_args.render_pose_grad", "true")),
    Row("prior_cameras", "full + re-placed cameras + pose prior (beyond the paper)", CAMERAS, pose_prior=True),
    Row("prior_mix", "full + re-placed cameras + pose prior, poses mixed towards it (beyond the paper)",
        (*CAMERAS, *MIX), pose_prior=True),
    Row("prior_mix_unordered", "full + re-placed cameras + pose prior, poses mixed towards it, views in any order "
        "(no camera_video; beyond the paper)", (*UNORDERED, *MIX), pose_prior=True),
)}
TABLES = {  # title -> its rows; "full" is named for its place in each table
    "Table 2 order (cumulative)": ("scaffold", "tokens", "d2s", "full"),
    "Table 3 order (ablations)": ("full", "wo_lora", "wo_pres", "frozen_aa", "frozen_all"),
    "Beyond the paper": ("full", "cameras", "cameras_pose_grad", "prior_cameras", "prior_mix", "prior_mix_unordered"),
}
FULL_LABEL = {"Table 3 order (ablations)": "full", "Beyond the paper": "full (the paper's Stage II)"}
DEFAULT_ROWS = ("tokens", "d2s", "full", "wo_lora", "wo_pres", "frozen_aa", "frozen_all")
OWN_STAGE1 = {  # rows whose scaffold is trained differently: their Stage I checkpoint comes from a flag
    "frozen_aa": ("--frozen_aa_stage1", "configs/ablations/frozen_aa.yaml"),
    "frozen_all": ("--frozen_all_stage1", "configs/ablations/frozen_all.yaml"),
}


def _figures(m: dict[str, float], variant: str) -> dict[str, float]:
    """``anycity test`` metrics (without ``test/``) -> the observed / weak PSNR of one variant per protocol."""
    nan = float("nan")
    return {f"psnr_{r}{sfx}": m.get(f"psnr_{r}_{variant}{sfx}", nan) for sfx in PROTOCOLS for r in ("obs", "weak")}


def _anycity(cmd: str, args: list[str], row: str) -> None:
    """``anycity CMD ARGS`` in its own process, as a user would run it (so ``trainer.devices`` > 1 launches DDP)."""
    rc, stop = _call([sys.executable, "-m", "anycity.cli", cmd, *args])
    if stop is not None:
        raise Stopped(stop, cmd)
    if rc:
        raise SystemExit(f"error: row {row}: `anycity {cmd}` failed (exit {rc}); its output is above")


class Stopped(SystemExit):
    """A row's ``anycity`` run stopped by a SIGTERM or SIGINT sent to this script: exit code 128 + the signal."""

    def __init__(self, signum: int, cmd: str) -> None:
        super().__init__(128 + signum)
        self.signum, self.cmd = signum, cmd


def _call(argv: list[str]) -> tuple[int, int | None]:
    """Run ``argv`` and wait for it: (its exit status, the first SIGTERM/SIGINT this script got meanwhile or None).

    Such a signal is passed on to it, and it is waited for: a single-PID ``kill`` or a scheduler's preemption used to
    end this script alone and leave ``anycity fit`` training with no parent. (A terminal's Ctrl-C reaches both
    processes; the second SIGINT is harmless, Lightning ignores SIGINT once it shuts down.)"""
    got: list[int] = []
    proc: list[subprocess.Popen] = []

    def pass_on(signum: int, frame) -> None:
        got.append(signum)
        if proc:
            proc[0].send_signal(signum)

    before = {s: signal.signal(s, pass_on) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        proc.append(subprocess.Popen(argv))
        if got:  # came while it was being started
            proc[0].send_signal(got[0])
        rc = proc[0].wait()
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)
    return rc, (got[0] if got else None)


def _test_metrics(csv_path: Path) -> dict[str, float]:
    """The ``test/*`` figures (names without ``test/``) from the CSV log of one ``anycity test`` run."""
    with csv_path.open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("test/psnr_refined")]
    if not rows:
        raise SystemExit(f"error: {csv_path} has no test figures: the test run logged nothing")
    return {k[len("test/"):]: float(v) for k, v in rows[-1].items() if k.startswith("test/") and v != ""}


def _file_id(path: str | Path) -> list[int]:
    """[size, mtime_ns]: a file rewritten at the same path (Stage I or a pose prior trained again) makes rows stale."""
    st = Path(path).stat()
    return [st.st_size, st.st_mtime_ns]


def _write_json(path: Path, obj) -> None:
    """``obj`` as indented JSON, written crash-safely (a kill leaves the old file or the new one, never a part)."""
    from anycity.atomic import atomic_write_bytes

    atomic_write_bytes(path, (json.dumps(obj, indent=1) + "\n").encode())


def _finished(d: Path, settings: dict) -> dict | None:
    """The saved result of the row in ``d`` when it was made with ``settings``; None when ``d`` does not exist.
    Raises ``SystemExit`` (one line) for a row made with other settings or an unfinished one."""
    done = d / "metrics.json"
    if not done.is_file():
        if d.exists():
            raise SystemExit(f"error: {d} holds an unfinished run (no metrics.json): delete {d} or pass --out NEW_DIR")
        return None
    try:
        saved = json.loads(done.read_text())
        made = dict(saved["settings"])
    except (ValueError, TypeError, KeyError) as e:  # a kill or power cut while an older version wrote it
        raise SystemExit(f"error: {d} holds an unfinished run ({done} is unreadable: {type(e).__name__}): delete {d} "
                         f"or pass --out NEW_DIR") from None
    if "data_index" not in made and {**made, "data_index": settings["data_index"]} == settings:
        print(f"{d.name}: reusing {done}, made before rows recorded --data's index.json: taken as made with the "
              f"shards there now (delete {d} if they were rebuilt since)", flush=True)
        saved["settings"] = settings
        _write_json(done, saved)
        return saved
    if made != settings:
        old = {"data_index": settings["data_index"], **made}  # an older row's missing data_index is not news
        differ = sorted(k for k in {*old, *settings} if old.get(k) != settings.get(k))
        raise SystemExit(f"error: {d} holds a run made with other settings (differing: {', '.join(differ)}; its "
                         f"settings: {made}): delete {d} or pass --out NEW_DIR")
    print(f"{d.name}: reusing {done}", flush=True)
    return saved


def config_digests(configs: list[str]) -> list[str]:
    """The sha256 of each config file's contents: a row's args name the files only."""
    return [hashlib.sha256(Path(c).read_bytes()).hexdigest() for c in configs]


def run_row(row: Row, ckpt: Path, out: Path, common: list[str], steps: int, pose_prior: str | None = None,
            configs_sha256: list[str] | None = None, data_index: list[int] | None = None) -> dict:
    """Fit and test one row (or reuse its finished run). ``data_index``: :func:`_file_id` of ``--data``'s
    ``index.json`` (a shard set written again rewrites it). Returns ``{"settings", "refined", "scaffold"}``."""
    d = out / row.name
    overrides = [*row.overrides, *(["--model.init_args.net.pose_prior", pose_prior] if row.pose_prior else [])]
    settings = {"stage1": str(ckpt), "stage1_file": _file_id(ckpt), "steps": steps, "args": [*common, *overrides],
                "configs_sha256": configs_sha256 or [], "data_index": data_index}
    if row.pose_prior:
        settings["pose_prior_file"] = _file_id(pose_prior)
    saved = _finished(d, settings)
    if saved is not None:
        return saved

    def run_dir(sub: str) -> list[str]:  # each run logs to CSV in its own directory; the tables read test's log
        logger = {"class_path": "lightning.pytorch.loggers.CSVLogger",
                  "init_args": {"save_dir": str(d / sub), "name": "", "version": ""}}
        return ["--trainer.default_root_dir", str(d / sub), "--trainer.logger", json.dumps(logger)]

    print(f"\n=== {row.name}: {row.label}", flush=True)
    try:
        _anycity("fit", [*common, *run_dir("fit"), "--model.init_args.init_from", str(ckpt),
                         "--trainer.max_steps", str(steps), *overrides], row.name)
        _anycity("test", [*common, *run_dir("test"), "--ckpt_path", str(d / "fit" / "checkpoints" / "last.ckpt"),
                          *overrides], row.name)
    except Stopped as e:
        print(f"stage2_tables: row {row.name}: stopped by {signal.Signals(e.signum).name} during `anycity {e.cmd}` "
              f"(passed on to it); delete {d} and rerun the same command (a row is not resumed)", file=sys.stderr,
              flush=True)
        raise
    m = _test_metrics(d / "test" / "metrics.csv")
    result = {"settings": settings, "refined": _figures(m, "refined"), "scaffold": _figures(m, "scaffold")}
    _write_json(d / "metrics.json", result)
    return result


def goal(refined: dict[str, float], scaffold: dict[str, float], sfx: str) -> tuple[float, float, bool]:
    """(weak gain, observed gain, reached?) of one protocol, against the issue's goal."""
    d_weak = refined[f"psnr_weak{sfx}"] - scaffold[f"psnr_weak{sfx}"]
    d_obs = refined[f"psnr_obs{sfx}"] - scaffold[f"psnr_obs{sfx}"]
    return d_weak, d_obs, bool(d_weak >= GOAL_WEAK_DB and d_obs >= GOAL_OBS_DB)


def tables(results: dict[str, dict], scaffold: dict[str, float], missing: dict[str, str]) -> tuple[str, dict]:
    """Markdown tables and their JSON from the rows' results, the figures of the ``--stage1`` scaffold, and
    ``missing`` (row -> why it was not run)."""
    rows = {**results, "scaffold": {"refined": scaffold}}
    labels = {"scaffold": "scaffold only", **{n: r.label for n, r in ROWS.items()}}

    def cell(fig: dict, sfx: str) -> str:
        o, w = fig[f"psnr_obs{sfx}"], fig[f"psnr_weak{sfx}"]
        return "" if math.isnan(o) else f"{o:.3f} / {w:.3f}"

    lines, as_json = [], {"rows": {}, "goal": {}}
    for title, names in TABLES.items():
        lines += ["", f"### {title}, observed / weak PSNR (dB)", "",
                  "| configuration | feed-forward | camrefine |", "|---|---|---|"]
        for n in names:
            if n in rows:
                fig = rows[n]["refined"]
                label = FULL_LABEL.get(title, labels[n]) if n == "full" else labels[n]
                lines.append(f"| {label} | {cell(fig, '')} | {cell(fig, '_camrefine')} |")
                as_json["rows"][n] = fig
            elif n in missing:
                lines.append(f"| {labels[n]} | not run: {missing[n]} | |")
    lines.append("")
    for n in (n for n in OWN_STAGE1 if n in results):
        own = results[n]["scaffold"]
        lines.append(f"- the {labels[n].split(' (')[0]} row's own scaffold: {cell(own, '')} feed-forward, "
                     f"{cell(own, '_camrefine')} camrefine")
    for n in (n for n in ("full", *TABLES["Beyond the paper"][1:]) if n in results):  # against each row's own scaffold
        for sfx, name in PROTOCOLS.items():
            d_weak, d_obs, ok = goal(results[n]["refined"], results[n]["scaffold"], sfx)
            if math.isnan(d_weak):
                continue
            as_json["goal"].setdefault(n, {})[name] = {"weak_gain_db": d_weak, "obs_gain_db": d_obs, "reached": ok}
            who = "the full model" if n == "full" else labels[n]
            lines.append(f"- goal, {who}, {name}: weak {d_weak:+.2f} dB (needs >= +{GOAL_WEAK_DB}), observed "
                         f"{d_obs:+.2f} dB (needs >= {GOAL_OBS_DB}): {'reached' if ok else 'NOT reached'}")
    return "\n".join(lines) + "\n", as_json


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--stage1", default="runs/quickstart/stage1/checkpoints/last.ckpt", help="Stage I checkpoint")
    for n, (flag, cfg) in OWN_STAGE1.items():
        p.add_argument(flag, default=None, help=f"a Stage I trained with {cfg} (the {n} row)")
    p.add_argument("--pose_prior", default=None,
                   help="a pose prior from scripts/pose_prior.py (the prior_* rows)")
    p.add_argument("--configs", nargs="+", default=["configs/quickstart.yaml", "configs/quickstart_stage2.yaml"],
                   help="the Stage II config stack, in order")
    p.add_argument("--data", default="data/quickstart", help="shard directory (same as --data.root)")
    p.add_argument("--out", default="runs/stage2_tables", help="one subdirectory per row")
    p.add_argument("--steps", type=int, default=600,
                   help="Stage II steps per row (docs/stage2.md's tables use 600; stage2.yaml trains 20000)")
    p.add_argument("--rows", default=",".join(DEFAULT_ROWS),
                   help=f"comma-separated, from: {', '.join(ROWS)} (the scaffold row comes with any of them)")
    args, extra = p.parse_known_args(argv)
    names = [n.strip() for n in args.rows.split(",") if n.strip()]
    unknown = [n for n in names if n not in ROWS]
    if unknown or not names:
        print(f"error: --rows {args.rows!r}: unknown row(s) {unknown}; choose from {', '.join(ROWS)}", file=sys.stderr)
        return 2
    flags = {"stage1": ("--stage1", args.stage1)}
    flags.update({n: (flag, getattr(args, flag[2:])) for n, (flag, _) in OWN_STAGE1.items()})
    missing = {n: "not in --rows" for n in ROWS if n not in names}
    requested = list(names)
    for n, (flag, cfg) in OWN_STAGE1.items():
        if n in names and flags[n][1] is None:
            names.remove(n)
            missing[n] = f"pass {flag} (a Stage I of {cfg})"
    for n in [n for n in names if ROWS[n].pose_prior]:
        if args.pose_prior is None:
            names.remove(n)
            missing[n] = "pass --pose_prior (a pose prior from scripts/pose_prior.py)"
        elif not Path(args.pose_prior).is_file():
            print(f"error: --pose_prior {args.pose_prior}: no such file (row {n}); run scripts/pose_prior.py",
                  file=sys.stderr)
            return 2
    if not names:
        print(f"error: --rows {args.rows!r}: no row left to run: {'; '.join(missing[n] for n in requested)}",
              file=sys.stderr)
        return 2
    ckpts = {k: Path(v) for k, (_, v) in flags.items() if v is not None}
    for n in names:
        if not ckpts[ROWS[n].stage1].is_file():
            flag = flags[ROWS[n].stage1][0]
            print(f"error: {flag} {ckpts[ROWS[n].stage1]}: no such checkpoint (row {n}); run `make quickstart` or "
                  f"pass {flag} PATH", file=sys.stderr)
            return 2
    for i, c in enumerate(args.configs):
        if not Path(c).is_file():
            if not (ROOT / c).is_file():
                print(f"error: --configs {c}: no such file", file=sys.stderr)
                return 2
            args.configs[i] = str(ROOT / c)  # a repository config, run from another directory
    index = Path(args.data) / "index.json"
    if not index.is_file():
        print(f"error: --data {args.data}: no index.json; make the shards first (make quickstart, or anycity data "
              "synth|convert)", file=sys.stderr)
        return 2
    common = [a for c in args.configs for a in ("-c", c)] + ["--data.root", args.data, *extra]
    out = Path(args.out)
    digests = config_digests(args.configs)
    results = {n: run_row(ROWS[n], ckpts[ROWS[n].stage1], out, common, args.steps, args.pose_prior, digests,
                          _file_id(index)) for n in names}
    scaffolds = [r["scaffold"] for n, r in results.items() if ROWS[n].stage1 == "stage1"]
    text, as_json = tables(results, scaffolds[0] if scaffolds else _figures({}, "scaffold"), missing)
    if scaffolds:  # the scaffold is frozen in Stage II, so every row from --stage1 must score it the same
        spread = max((abs(a[k] - b[k]) for a in scaffolds for b in scaffolds for k in a if not math.isnan(a[k])),
                     default=0.0)
        text += f"- the scaffold's figures agree across the rows from {args.stage1} within {spread:.4f} dB\n"
        as_json["scaffold_spread_db"] = spread
    from anycity.atomic import atomic_write_bytes

    atomic_write_bytes(out / "tables.md", text.encode())
    _write_json(out / "tables.json", as_json)
    print(text)
    print(f"wrote {out / 'tables.md'} and {out / 'tables.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
