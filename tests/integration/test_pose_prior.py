"""scripts/pose_prior.py pretrains the pose prior; Stage II (the prior_cameras row of scripts/stage2_tables.py)
loads it frozen, trains around it, and its checkpoint tests with it, also where the prior's file is gone."""

import json

import pytest
import torch
from helpers.scripts import anycity_in_process, load_script

from anycity.cli import build_cli


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["script.py"])


def test_pretrain_then_stage2_row(tiny_shards, tmp_path, capsys, monkeypatch):
    pretrain = load_script("pose_prior")
    prior = tmp_path / "prior.pt"
    args = ["--data", str(tiny_shards), "--out", str(prior), "--steps", "4", "--val-every", "2", "--val-batches",
            "1", "--image-size", "32", "32", "--num-context", "2", "--accelerator", "cpu"]
    assert pretrain.main(args) == 0
    saved = torch.load(prior, weights_only=True)
    assert {"state_dict", "channels", "grid", "rre_val", "rre_test"} <= set(saved)
    assert saved["steps"] == 4 and 0 <= saved["rre_test"] < 180
    assert "test cities, mean relative rotation error" in capsys.readouterr().out
    assert pretrain.main(args) == 2 and f"--out {prior} exists" in capsys.readouterr().err  # never overwritten
    assert pretrain.main([*args[:1], str(tmp_path / "nowhere"), *args[2:]]) == 2
    assert "no index.json" in capsys.readouterr().err

    extra = ["--data.image_size", "[32, 32]", "--data.num_context", "2", "--data.num_targets", "1",
             "--data.num_dense", "2", "--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1",
             "--model.init_args.warmup_steps", "1", "--model.init_args.render_backend", "torch",
             "--model.init_args.camera_refine_steps", "2", "--model.init_args.eval_pose_align_steps", "0"]
    s1 = tmp_path / "s1"
    build_cli(["fit", "-c", "configs/quickstart.yaml", "--data.root", str(tiny_shards), *extra,
               "--trainer.max_steps", "2", "--trainer.default_root_dir", str(s1),
               "--trainer.logger.init_args.save_dir", str(s1)])
    tables = load_script("stage2_tables")
    # each row's `anycity fit|test` in this process; the script's own launches: test_stage2_tables.py
    monkeypatch.setattr(tables, "_anycity", anycity_in_process)
    out = tmp_path / "tables"
    argv = ["--stage1", str(s1 / "checkpoints" / "last.ckpt"), "--data", str(tiny_shards), "--out", str(out),
            "--steps", "2", "--rows", "prior_cameras", *extra]
    assert tables.main(argv) == 2  # the row needs its prior
    assert "pass --pose_prior" in capsys.readouterr().err
    assert tables.main([*argv, "--pose_prior", str(tmp_path / "none.pt")]) == 2
    assert "none.pt: no such file" in capsys.readouterr().err
    assert tables.main([*argv, "--pose_prior", str(prior)]) == 0
    argv[argv.index("prior_cameras")] = "prior_mix"
    assert tables.main([*argv, "--pose_prior", str(prior)]) == 0

    cfg = (out / "prior_cameras" / "fit" / "config.yaml").read_text()
    assert f"pose_prior: {prior}" in cfg and "refine_cameras: true" in cfg and "camera_video: true" in cfg
    ckpt = torch.load(out / "prior_cameras" / "fit" / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    for k, v in saved["state_dict"].items():  # the frozen prior travels in the checkpoint, unchanged
        torch.testing.assert_close(ckpt[f"net.pose_prior.{k}"], v)
    assert any(k.startswith("net.completion.camera_pose.") for k in ckpt)
    assert "pose_prior_mix: true" in (out / "prior_mix" / "fit" / "config.yaml").read_text()
    mix = torch.load(out / "prior_mix" / "fit" / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert "net.completion.camera_mix.weight" in mix and "net.completion.camera_mix.weight" not in ckpt
    res = json.loads((out / "tables.json").read_text())
    assert set(res["goal"]) == {"prior_mix"}  # the tables of this run: its rows only
    assert "| full + re-placed cameras + pose prior, poses mixed towards it (beyond the paper) | " in (
        out / "tables.md").read_text()

    # another machine: `anycity test` from the checkpoint alone, the prior's file gone, scores the same
    prior.rename(tmp_path / "moved.pt")
    elsewhere = tmp_path / "elsewhere"
    logger = {"class_path": "lightning.pytorch.loggers.CSVLogger",
              "init_args": {"save_dir": str(elsewhere), "name": "", "version": ""}}
    build_cli(["test", "-c", "configs/quickstart.yaml", "-c", "configs/quickstart_stage2.yaml", "--data.root",
               str(tiny_shards), *extra, *tables.ROWS["prior_mix"].overrides, "--model.init_args.net.pose_prior",
               str(prior), "--trainer.default_root_dir", str(elsewhere), "--trainer.logger", json.dumps(logger),
               "--ckpt_path", str(out / "prior_mix" / "fit" / "checkpoints" / "last.ckpt")])
    again = tables._test_metrics(elsewhere / "metrics.csv")
    row = tables._test_metrics(out / "prior_mix" / "test" / "metrics.csv")
    assert again["psnr_refined"] == pytest.approx(row["psnr_refined"], abs=1e-6)
    assert again["rre"] == pytest.approx(row["rre"], abs=1e-6)


def _tiny_args(data, out):
    return ["--data", str(data), "--out", str(out), "--steps", "2", "--batch", "1", "--image-size", "32", "32",
            "--num-context", "2", "--accelerator", "cpu"]


def test_problems_stop_it_before_training_and_a_failed_test_keeps_the_weights(tiny_shards, tmp_path, capsys,
                                                                             monkeypatch):
    """A missing test split and an --out under a file used to stop it after the last step, losing the run;
    --val-batches 0 ended in KeyError 'val/rre'."""
    import shutil

    import lightning.pytorch as pl

    pretrain = load_script("pose_prior")
    notest = tmp_path / "notest"
    shutil.copytree(tiny_shards, notest)
    index = json.loads((notest / "index.json").read_text())
    index["splits"]["test"] = []
    (notest / "index.json").write_text(json.dumps(index))
    fit = []
    monkeypatch.setattr(pl.Trainer, "fit", lambda *a, **k: fit.append(1) or pytest.fail("trained"))
    assert pretrain.main(_tiny_args(notest, tmp_path / "p.pt")) == 2
    err = capsys.readouterr().err
    assert "no test shards" in err and "--data.test_shards" not in err and len(err.splitlines()) == 1, err
    (tmp_path / "file").write_text("")
    assert pretrain.main(_tiny_args(tiny_shards, tmp_path / "file" / "p.pt")) == 2
    assert "is a file, not a folder" in capsys.readouterr().err and not fit
    monkeypatch.undo()
    monkeypatch.setattr("sys.argv", ["script.py"])

    def broken_test(*a, **k):
        raise RuntimeError("the test run failed")

    monkeypatch.setattr(pl.Trainer, "test", broken_test)
    out = tmp_path / "p.pt"
    with pytest.raises(RuntimeError, match="the test run failed"):
        pretrain.main([*_tiny_args(tiny_shards, out), "--val-batches", "0"])
    saved = torch.load(out, weights_only=True)  # the trained weights are kept
    assert saved["rre_val"] is None and saved["rre_test"] is None and saved["state_dict"]
