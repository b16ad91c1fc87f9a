"""scripts/pose_prior.py pretrains the pose prior; Stage II (the prior_cameras row of scripts/stage2_tables.py)
loads it frozen, trains around it, and its checkpoint tests with it, also where the prior's file is gone."""

import json
import os

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


def _ours(err: str) -> list[str]:
    """The script's own lines of stderr (not Lightning's INFO log)."""
    return [ln for ln in err.splitlines() if ln.startswith(("pose_prior:", "error:"))]


def test_sigterm_exits_143_with_one_line(tiny_shards, tmp_path, capsys, monkeypatch):
    """Lightning's SIGTERMException is a SystemExit with no code: a stopped pretraining exited 0 with no word and no
    file, so `pose_prior.py && stage2_tables.py` carried on."""
    from anycity.lit.pose_prior import PosePriorModule

    pretrain, out = load_script("pose_prior"), tmp_path / "p.pt"
    train = PosePriorModule.training_step

    def sigterm_at_step_1(self, batch, batch_idx):
        if batch_idx == 1:
            self.trainer._signal_connector.received_sigterm = True  # what Lightning's SIGTERM handler sets
        return train(self, batch, batch_idx)

    with monkeypatch.context() as m:
        m.setattr(PosePriorModule, "training_step", sigterm_at_step_1)
        assert pretrain.main([*_tiny_args(tiny_shards, out), "--steps", "4", "--val-batches", "0"]) == 143
    err = _ours(capsys.readouterr().err)
    assert err == [f"pose_prior: stopped by SIGTERM at step 2; nothing saved ({out} not written): rerun the same "
                   "command"]
    assert not out.exists()

    def sigterm_in_the_test(self, batch, batch_idx):
        from lightning.pytorch.utilities.exceptions import SIGTERMException

        raise SIGTERMException  # what Lightning raises after a test batch once SIGTERM came (not after the last)

    monkeypatch.setattr(PosePriorModule, "test_step", sigterm_in_the_test)
    assert pretrain.main([*_tiny_args(tiny_shards, out), "--val-batches", "0"]) == 143
    assert _ours(capsys.readouterr().err) == [
        f"pose_prior: stopped by SIGTERM during the test; {out} holds the trained weights with rre_test null"]
    saved = torch.load(out, weights_only=True)
    assert saved["state_dict"] and saved["rre_test"] is None


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device whose writes fail ENOSPC)")
def test_a_full_disk_says_in_one_line_that_the_weights_were_not_saved(tiny_shards, tmp_path, capsys, monkeypatch):
    """torch.save straight to the file failed ENOSPC as a RuntimeError: two tracebacks, and nothing saying the trained
    weights were lost. A disk already too full is found before training."""
    import shutil

    import lightning.pytorch as pl

    import anycity.atomic

    pretrain, out = load_script("pose_prior"), tmp_path / "p.pt"
    full = tmp_path / "full"
    real = anycity.atomic.temp_name

    def on_the_full_disk(folder, suffix=""):  # the temp file beside --out is the full disk
        if os.path.samefile(folder, tmp_path):
            full.unlink(missing_ok=True)
            full.symlink_to("/dev/full")
            return full
        return real(folder, suffix)

    monkeypatch.setattr(anycity.atomic, "temp_name", on_the_full_disk)
    assert pretrain.main([*_tiny_args(tiny_shards, out), "--val-batches", "0"]) == 1
    err = _ours(capsys.readouterr().err)
    assert len(err) == 1 and err[0].startswith(f"error: disk full writing {out}: ") and "bytes needed" in err[0], err
    assert err[0].endswith("the 2 trained steps' weights were NOT saved (nothing else holds them)")
    assert not out.exists()
    monkeypatch.undo()
    monkeypatch.setattr("sys.argv", ["script.py"])

    monkeypatch.setattr(pl.Trainer, "fit", lambda *a, **k: pytest.fail("trained"))
    usage = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(p)._replace(free=1000))
    assert pretrain.main(_tiny_args(tiny_shards, out)) == 2
    err = _ours(capsys.readouterr().err)
    assert len(err) == 1 and f"--out {out}: " in err[0] and "bytes needed for the weights but 1000 free" in err[0]
