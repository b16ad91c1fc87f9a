"""Two CPU processes (gloo DDP) through the paper configs: Stage I fit -> Stage II fit -> test -> predict.

Each step is a subprocess (``python -m anycity.cli``; Lightning re-launches it as rank 1), so pytest itself is
never re-executed by the DDP launcher. A probe callback (tests/helpers/ddp_probe.py) records what every rank
scored and its final parameters, and poisons one rank: an inf gradient in Stage I, a NaN loss in Stage II.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.ddp_probe import assert_params_equal, subprocess_env

ROOT = Path(__file__).resolve().parents[2]
CFG = ROOT / "configs"
TIMEOUT = 180  # per command; a collective mismatch aborts (gloo) or hangs, and then this fails the test


def _run(args: list[str], cwd: Path) -> str:
    proc = subprocess.run([sys.executable, "-m", "anycity.cli", *args], cwd=cwd, env=subprocess_env(),
                          capture_output=True, text=True, timeout=TIMEOUT)
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, log[-4000:]
    return log


def _overlay(tmp: Path, name: str, probe: Path, **poison) -> Path:
    """Logger at a fixed place, last.ckpt every 2 steps, plus the probe (a later list replaces the overlay's)."""
    kw = ", ".join(f"{k}: {json.dumps(v)}" for k, v in poison.items())
    path = tmp / f"{name}.yaml"
    path.write_text(
        "trainer:\n"
        f"  default_root_dir: {tmp / name}\n"
        "  logger:\n    class_path: lightning.pytorch.loggers.CSVLogger\n"
        f"    init_args: {{save_dir: {tmp / name}, name: '', version: ''}}\n"
        "  callbacks:\n"
        "    - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
        f"      init_args: {{dirpath: {tmp / name / 'checkpoints'}, save_last: true, save_top_k: 0, "
        "every_n_train_steps: 2}\n"
        "    - class_path: helpers.ddp_probe.DDPProbe\n"
        f"      init_args: {{out_dir: {probe}{', ' + kw if kw else ''}}}\n")
    return path


def _scored(probe: Path, split: str) -> list[list[tuple[str, int]]]:
    ranks = []
    for r in (0, 1):
        f = probe / f"{split}_rank{r}.jsonl"
        lines = f.read_text().splitlines() if f.exists() else []
        ranks.append([(d["scene"], d["view"]) for d in map(json.loads, lines)])
    return ranks


def _held_out(ddp_shards: Path, split: str) -> list[tuple[str, int]]:
    """The target views of a split, read in one process (the reference for what the ranks must cover)."""
    from anycity.lit.datamodule import AerialDataModule

    dm = AerialDataModule(root=str(ddp_shards), image_size=(32, 32), patch_size=8, num_context=2, num_targets=1,
                          num_dense=2, num_workers=0)
    loader = {"val": dm.val_dataloader, "test": dm.test_dataloader}[split]()
    return [(s, int(i)) for b in loader for s, idx in zip(b.scene, b.target.index) for i in idx.tolist()]


def _skips(run: Path) -> float:
    import csv

    rows = list(csv.DictReader(open(run / "metrics.csv")))
    return max(float(r["train/nonfinite_skipped"]) for r in rows if r.get("train/nonfinite_skipped"))


def test_two_process_chain_stage1_stage2_test_predict(ddp_shards, tmp_path):
    base = ["-c", str(CFG / "debug" / "cpu_ddp.yaml"), "--data.root", str(ddp_shards)]

    # Stage I: rank 1 gets an inf gradient at step 1 -> both ranks skip that step, parameters stay identical
    p1 = tmp_path / "probe1"
    log = _run(["fit", "-c", str(CFG / "stage1.yaml"), *base,
                "-c", str(_overlay(tmp_path, "s1", p1, poison_rank=1, poison_step=1, poison="grad"))], tmp_path)
    assert "skipped optimiser step 1" in log and _skips(tmp_path / "s1") == 1.0
    assert_params_equal(p1)
    val = _scored(p1, "val")  # 2 validations x limit_val_batches 2 per rank, 3 val scenes
    expected = _held_out(ddp_shards, "val")
    assert sorted(val[0] + val[1]) == sorted(expected * 2)  # every val view exactly once per validation
    ckpt1 = tmp_path / "s1" / "checkpoints" / "last.ckpt"
    assert ckpt1.is_file()

    # Stage II from it (small built-in prior); rank 0's loss is NaN at step 2
    p2 = tmp_path / "probe2"
    log = _run(["fit", "-c", str(CFG / "stage2.yaml"), *base, "--model.init_args.init_from", str(ckpt1),
                "-c", str(_overlay(tmp_path, "s2", p2, poison_rank=0, poison_step=2, poison="loss"))], tmp_path)
    assert "skipped optimiser step 2" in log and _skips(tmp_path / "s2") == 1.0
    assert_params_equal(p2)
    ckpt2 = tmp_path / "s2" / "checkpoints" / "last.ckpt"

    # test: init_from points nowhere (stage2.yaml's default runs/stage1/... does not exist under tmp_path), 2 loader
    # workers per rank: 3 test scenes < 2 ranks x 2 workers, each held-out view scored exactly once, no hang
    p3 = tmp_path / "probe3"
    log = _run(["test", "-c", str(CFG / "stage2.yaml"), *base, "--data.num_workers", "2",
                "-c", str(_overlay(tmp_path, "t", p3)), "--ckpt_path", str(ckpt2)], tmp_path)
    scored = _scored(p3, "test")
    expected = _held_out(ddp_shards, "test")
    assert len(expected) == 3 and sorted(scored[0] + scored[1]) == sorted(expected)
    assert scored[0] and scored[1]  # both ranks took part
    assert "test/psnr_refined" in log

    # predict: each test sample exported once, by the rank that reconstructed it (rank 1's folders say so, so that
    # two ranks' samples of one scene cannot share a folder). The default folder, <log_dir>/predictions: log_dir is
    # a broadcast from rank 0, and read per sample (rank 0 exports 2, rank 1 one) it crashed gloo ("Connection
    # closed by peer") or hung NCCL
    _run(["predict", "-c", str(CFG / "stage2.yaml"), *base, "-c", str(_overlay(tmp_path, "p", tmp_path / "probe4")),
          "--ckpt_path", str(ckpt2)], tmp_path)
    out = tmp_path / "p" / "predictions"
    names = [d.name for d in out.iterdir()]
    assert len(names) == len(expected) and any(n.endswith("-rank1") for n in names)
    assert sorted(n.removesuffix("-rank1") for n in names) == sorted(s for s, _ in expected)
    assert all((d / "scene.ply").stat().st_size > 1000 for d in out.iterdir())


@pytest.mark.slow
def test_a_non_finite_forward_on_one_rank_is_skipped_by_every_rank(ddp_shards, tmp_path):
    """An overflow makes the whole forward NaN on rank 1 (rendering it would raise there alone)."""
    probe = tmp_path / "probe"
    log = _run(["fit", "-c", str(CFG / "stage1.yaml"), "-c", str(CFG / "debug" / "cpu_ddp.yaml"), "--data.root",
                str(ddp_shards), "-c", str(_overlay(tmp_path, "s1", probe, poison_rank=1, poison_step=1,
                                                poison="forward"))], tmp_path)
    assert "skipped optimiser step 1" in log and _skips(tmp_path / "s1") == 1.0
    assert_params_equal(probe)
