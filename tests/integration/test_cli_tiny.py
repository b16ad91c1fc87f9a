"""The training CLI end to end, in-process: fit -> test --ckpt_path -> predict, resume, config errors."""

import json
import os

import numpy as np
import pytest
import torch
from PIL import Image

from anycity.cli import build_cli, main


def _tiny_args(root, run_dir, steps=2, extra=(), configs=()):
    ckpt_every = run_dir.parent / "ckpt_every_2.yaml"
    ckpt_every.write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
                          "    init_args: {save_last: true, save_top_k: 0, every_n_train_steps: 2}\n")
    return [
        "-c", "configs/quickstart.yaml", *configs, "-c", str(ckpt_every),
        "--data.root", str(root), "--data.image_size", "[32, 32]", "--data.num_context", "2",
        "--data.num_targets", "1", "--data.num_dense", "2",
        "--trainer.max_steps", str(steps), "--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1",
        "--trainer.default_root_dir", str(run_dir), "--trainer.logger.init_args.save_dir", str(run_dir),
        "--model.init_args.warmup_steps", "1",
        "--model.init_args.render_backend", "torch",
        *extra,
    ]


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])  # LightningCLI warns when sys.argv also carries arguments


def test_fit_test_predict_stage1_then_stage2(tiny_shards, tmp_path):
    s1 = tmp_path / "s1"
    cli = build_cli(["fit", *_tiny_args(tiny_shards, s1, extra=["--model.init_args.depth_warmup_steps", "1"])])
    assert cli.trainer.global_step == 2
    ckpt1 = s1 / "checkpoints" / "last.ckpt"
    assert ckpt1.is_file() and list((s1 / "previews").glob("val_*.png"))

    # Stage II from the Stage I checkpoint, with LoRA on a (tiny, random) Wan prior's attention
    s2 = tmp_path / "s2"
    stage2 = dict(configs=["-c", "configs/quickstart_stage2.yaml"],
                  extra=["--model.init_args.init_from", str(ckpt1),
                         "--model.init_args.net",  # LoRA on a tiny random Wan prior
                         '{"camera_trunk_depth": 2, "video_prior": "wan-tiny", "wan_lora_rank": 2}'])
    cli = build_cli(["fit", *_tiny_args(tiny_shards, s2, **stage2)])
    ckpt2 = s2 / "checkpoints" / "last.ckpt"
    state = torch.load(ckpt2, map_location="cpu", weights_only=False)["state_dict"]
    assert any("lora_A" in k for k in state)
    before = torch.load(ckpt1, map_location="cpu", weights_only=False)["state_dict"]
    scaffold_keys = [k for k in before if k.startswith(("net.aggregator.", "net.depth_head.", "net.gaussian_head."))]
    for k in scaffold_keys:  # Stage II keeps the scaffold frozen
        torch.testing.assert_close(state[k], before[k], msg=k)

    t = tmp_path / "test"
    cli = build_cli(["test", *_tiny_args(tiny_shards, t, **stage2), "--ckpt_path", str(ckpt2)])
    metrics = cli.trainer.callback_metrics
    for key in ("test/psnr_scaffold", "test/psnr_refined", "test/psnr_baseline", "test/ssim_refined"):
        assert torch.isfinite(metrics[key]), key
    assert "test/psnr_refined_joint" not in metrics
    # test-time settings on the command line win over the hyperparameters stored in the checkpoint
    cli = build_cli(["test", *_tiny_args(tiny_shards, t, **stage2), "--ckpt_path", str(ckpt2),
                     "--model.init_args.eval_joint", "true", "--model.init_args.camera_refine_steps", "2"])
    assert cli.model.hparams.eval_joint and cli.model.hparams.camera_refine_steps == 2
    for key in ("test/psnr_refined_joint", "test/psnr_refined_camrefine", "test/rre_refined_camrefine"):
        assert torch.isfinite(cli.trainer.callback_metrics[key]), key

    # the Stage II config with the Stage I checkpoint: Lightning builds the checkpoint's class, and says so
    with pytest.warns(UserWarning, match=r"holds a ScaffoldModule, so that is what runs, not the config's "
                                         r"RefinementModule"):
        cli = build_cli(["validate", *_tiny_args(tiny_shards, t, **stage2), "--ckpt_path", str(ckpt1)])
    assert type(cli.model).__name__ == "ScaffoldModule"

    p = tmp_path / "pred"
    build_cli(["predict", *_tiny_args(tiny_shards, p, **stage2), "--ckpt_path", str(ckpt2),
               "--export.out_dir", str(p / "out")])
    scenes = sorted((p / "out").iterdir())
    assert scenes and (scenes[0] / "scene.ply").stat().st_size > 1000
    cams = json.loads((scenes[0] / "cameras.json").read_text())
    assert len(cams["views"]) == 2 and len(list((scenes[0] / "renders").glob("*.png"))) == 2
    from anycity.export import load_ply_extras

    prov = load_ply_extras(scenes[0] / "scene.ply")  # provenance columns (issue 14)
    assert prov["obs_views"].max() <= 2 and (prov["obs_views"] >= 1).mean() > 0.5
    assert np.isfinite(prov["completion"]).all() and prov["completion"].min() >= 0

    # the user's own photos: a folder of one scene, no poses
    photos = tmp_path / "my_photos"
    photos.mkdir()
    for i in range(3):
        pixels = np.random.default_rng(i).integers(0, 255, (40, 56, 3), dtype=np.uint8)
        Image.fromarray(pixels).save(photos / f"{i}.jpg")
    build_cli(["predict", *_tiny_args(tiny_shards, p, **stage2), "--ckpt_path", str(ckpt2),
               "--data.predict_images", str(photos), "--data.compact_batches", "true",
               "--export.out_dir", str(p / "mine")])
    cams = json.loads((p / "mine" / "my_photos" / "cameras.json").read_text())
    assert len(cams["views"]) == 3 and (p / "mine" / "my_photos" / "scene.ply").stat().st_size > 1000


def test_a_checkpoint_tests_on_another_machine_with_local_paths_and_no_pretrained_file(tiny_shards, tmp_path):
    """--ckpt_path re-applied every stored hyperparameter: the pretrained file a run started from was read again
    (on another machine: not found, though the checkpoint holds the weights), and the config's machine-local paths
    and voxel merge were silently replaced by the training run's. Now those win, the pretrained file is not read,
    and an architecture key the checkpoint overrules is named in a warning."""
    from anycity.models import build_network

    weights = tmp_path / "vggt_like.pt"
    torch.save(build_network("tiny", completion=False, camera_trunk_depth=2).state_dict(), weights)
    run = tmp_path / "s1"
    build_cli(["fit", *_tiny_args(tiny_shards, run, extra=["--model.init_args.pretrained", str(weights)])])
    weights.unlink()  # "another machine"
    t = tmp_path / "test"
    with pytest.warns(UserWarning, match="model.net camera_trunk_depth is 2, not 3 .*voxel_size"):
        cli = build_cli(["test", *_tiny_args(tiny_shards, t), "--ckpt_path", str(run / "checkpoints" / "last.ckpt"),
                         "--model.init_args.net", '{"camera_trunk_depth": 3, "voxel_size": 0.05}',
                         "--model.init_args.camera_refine_steps", "0", "--model.init_args.eval_pose_align_steps", "0"])
    assert cli.model.hparams.pretrained is None
    assert cli.model.net.cfg.voxel_size == 0.05 and cli.model.net.cfg.camera_trunk_depth == 2
    assert torch.isfinite(cli.trainer.callback_metrics["test/psnr_scaffold"])


def test_resume_continues_step_optimizer_and_schedule(tiny_shards, tmp_path):
    run = tmp_path / "r"
    build_cli(["fit", *_tiny_args(tiny_shards, run, steps=2)])
    ckpt = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 2 and ckpt["lr_schedulers"][0]["last_epoch"] == 2
    last = str(run / "checkpoints" / "last.ckpt")
    cli = build_cli(["fit", *_tiny_args(tiny_shards, run, steps=4), "--ckpt_path", last])
    assert cli.trainer.global_step == 4
    opt = cli.trainer.optimizers[0]
    steps = {int(s["step"]) for s in opt.state.values() if "step" in s}
    assert steps == {4}  # Adam moments continued from the checkpoint, not restarted
    sched = cli.trainer.lr_scheduler_configs[0].scheduler
    assert sched.last_epoch == 4
    assert opt.param_groups[0]["lr"] == pytest.approx(sched.get_last_lr()[0])
    # a run started from pretrained weights resumes on a machine without that file: the checkpoint's weights
    # replace them, so it is not read (it stopped the resume with FileNotFoundError), and it stays on record
    ckpt["hyper_parameters"]["pretrained"] = str(tmp_path / "elsewhere" / "vggt_model.pt")
    torch.save(ckpt, tmp_path / "from_vggt.ckpt")
    cli = build_cli(["fit", *_tiny_args(tiny_shards, run, steps=3), "--ckpt_path", str(tmp_path / "from_vggt.ckpt")])
    assert cli.trainer.global_step == 3 and cli.model.hparams.pretrained.endswith("vggt_model.pt")



def test_last_ckpt_holds_the_final_step_when_max_steps_is_not_a_multiple_of_the_interval(tiny_shards, tmp_path):
    """Lightning writes last.ckpt at the end of training only when its ModelCheckpoint saved nothing during the run:
    ``max_steps 3`` with ``every_n_train_steps 2`` (here a user config listing its own ModelCheckpoint) left it at
    step 2, so Stage II, ``test`` and ``--ckpt_path last`` silently took older weights (the quickstart with
    ``--stage1_steps 1500``: step 1000), and the closing line named that stale file."""
    run = tmp_path / "run"
    cli = build_cli(["fit", *_tiny_args(tiny_shards, run, steps=3, extra=["--trainer.limit_val_batches", "0"])])
    last = run / "checkpoints" / "last.ckpt"
    assert cli.trainer.global_step == 3
    assert torch.load(last, map_location="cpu", weights_only=False)["global_step"] == 3
    assert [c.last_model_path for c in cli.trainer.checkpoint_callbacks if c.last_model_path] == [str(last)]
    assert sorted(p.name for p in last.parent.iterdir()) == ["last.ckpt"]
    from anycity.callbacks.last_checkpoint import missing_private_api

    # Lightning is not pinned above 2.6: a rename of what FinalLastCheckpoint calls (it would then only warn) fails here
    assert missing_private_api() == [], "Lightning renamed ModelCheckpoint internals that FinalLastCheckpoint calls"


def test_a_fit_ended_by_epochs_alone_is_refused_in_one_line(tiny_shards, tmp_path, capsys, monkeypatch):
    """``--trainer.max_steps -1 --trainer.max_epochs N``: the LR schedule's cosine collapsed to its floor right after
    warm-up (its length read as -1), silently; with max_epochs -1 a traceback (int(inf))."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    for epochs in ("1", "-1"):
        rc = main(["fit", *_tiny_args(tiny_shards, tmp_path / f"e{epochs}",
                                      extra=["--trainer.max_steps", "-1", "--trainer.max_epochs", epochs,
                                             "--data.epoch_samples", "2"])])
        assert rc == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == (
            "anycity: error: trainer.max_steps is -1: the LR schedule is sized by it (the shard stream has no length, "
            "so max_epochs cannot size it); set --trainer.max_steps N  (--debug for the traceback)")

def test_fit_with_varied_context_counts(tiny_shards, tmp_path, monkeypatch):
    """``data.train_num_context`` through the CLI: Stage I trains on batches of different context counts."""
    from anycity.lit import ScaffoldModule

    seen, step = [], ScaffoldModule.training_step

    def record(self, batch, batch_idx):
        seen.append(batch.context.images.shape[1])
        return step(self, batch, batch_idx)

    monkeypatch.setattr(ScaffoldModule, "training_step", record)
    cli = build_cli(["fit", *_tiny_args(tiny_shards, tmp_path / "vc", steps=6,
                                        extra=["--data.train_num_context", "[1, 3]", "--data.seed", "2"])])
    assert cli.trainer.global_step == 6 and set(seen) <= {1, 2, 3} and len(set(seen)) >= 2, seen


def test_config_typo_fails_at_parse_time_naming_the_key(tmp_path, capsys):
    with pytest.raises(SystemExit):
        build_cli(["-c", "configs/quickstart.yaml", "--model.init_args.depht_weight", "0.1"], run=False)
    assert "depht_weight" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        build_cli(["-c", "configs/quickstart.yaml", "--model.init_args.net", '{"sh_degre": 1}'], run=False)
    assert "sh_degre" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("trainer:\n  max_stepz: 3\n")
    with pytest.raises(SystemExit):
        build_cli(["-c", "configs/quickstart.yaml", "-c", str(bad)], run=False)
    assert "max_stepz" in capsys.readouterr().err


def test_data_subcommand_dispatch_is_lazy(tmp_path):
    import subprocess
    import sys

    code = ("import sys; from anycity.cli import main; rc = main(['data', '--help']) if False else 0; "
            "import anycity.cli; print('lightning' in sys.modules, 'anycity.models' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
    with pytest.raises(SystemExit):
        main(["data", "--help"])


@pytest.fixture(scope="module")
def fitted(tiny_shards, tmp_path_factory):
    """A 2-step Stage I run: ``run/checkpoints/last.ckpt``."""
    run = tmp_path_factory.mktemp("fitted") / "run"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("sys.argv", ["anycity"])
        build_cli(["fit", *_tiny_args(tiny_shards, run, extra=["--trainer.limit_val_batches", "0"])])
    assert (run / "checkpoints" / "last.ckpt").is_file()
    return run


FAST_EVAL = ["--model.init_args.camera_refine_steps", "0", "--model.init_args.eval_pose_align_steps", "0"]


def test_predict_keeps_no_predictions_in_memory(tiny_shards, fitted):
    """Lightning's return_predictions (default True) kept every exported sample's Gaussians and renders in RAM until
    the end (~350 MB a sample at paper size). Also: ``--ckpt_path last`` in a training folder is the training's
    last.ckpt (the predict run's own log folder, <run>/predict/, has no checkpoints)."""
    cli = build_cli(["predict", *_tiny_args(tiny_shards, fitted), *FAST_EVAL, "--ckpt_path", "last",
                     "--export.save_renders", "false"])
    assert cli.trainer.predict_loop.predictions == []
    assert list((fitted / "predict" / "predictions").iterdir())  # exported
    assert cli.trainer.ckpt_path == str(fitted / "checkpoints" / "last.ckpt")
    cli = build_cli(["predict", *_tiny_args(tiny_shards, fitted), *FAST_EVAL, "--ckpt_path", "last",
                     "--export.save_renders", "false", "--return_predictions", "true"])
    assert len(cli.trainer.predict_loop.predictions) == 1  # asked for: kept


def test_a_checkpoint_holding_allow_listed_types_is_read_by_ckpt_path(tiny_shards, fitted, tmp_path):
    """--ckpt_path's first read (Lightning's, for the hyperparameters) was a bare weights_only torch.load: a
    checkpoint holding a type every other read allows (a Path, a defaultdict: a script's data module or callback
    state) was refused there, with the unpickler's multi-line error."""
    import collections
    from pathlib import Path

    from anycity.safe_load import safe_torch_load

    ckpt = safe_torch_load(fitted / "checkpoints" / "last.ckpt")
    ckpt["datamodule_hyper_parameters"] = {"root": Path(tiny_shards)}
    ckpt["callbacks"]["anycity-notes"] = collections.defaultdict(list)
    torch.save(ckpt, tmp_path / "paths.ckpt")
    with pytest.raises(Exception, match="Unsupported global"):
        torch.load(tmp_path / "paths.ckpt", weights_only=True)  # what Lightning's own read does
    cli = build_cli(["validate", *_tiny_args(tiny_shards, tmp_path / "v"), *FAST_EVAL,
                     "--ckpt_path", str(tmp_path / "paths.ckpt")])
    psnr = [v for k, v in cli.trainer.callback_metrics.items() if k.startswith("val/psnr")]
    assert psnr and all(torch.isfinite(v) for v in psnr)


def test_ckpt_path_last_without_a_last_checkpoint_is_refused(tiny_shards, fitted, tmp_path, capsys, monkeypatch):
    """Lightning only warns, and the fit started from random weights: after a fresh fit moved the checkpoints to
    checkpoints.1/, ``--ckpt_path last`` silently started over."""
    import shutil

    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    run = tmp_path / "r"
    (run / "checkpoints.1").mkdir(parents=True)
    shutil.copy(fitted / "checkpoints" / "last.ckpt", run / "checkpoints.1" / "last.ckpt")
    assert main(["fit", *_tiny_args(tiny_shards, run), "--ckpt_path", "last"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == (f"anycity: error: --ckpt_path last: no last*.ckpt in {run / 'checkpoints'}; an earlier run's is "
                   f"{run / 'checkpoints.1' / 'last.ckpt'} (a fresh fit moves the checkpoints before it aside): pass "
                   f"--ckpt_path {run / 'checkpoints.1' / 'last.ckpt'} to resume from it  (--debug for the traceback)")
    assert not (run / "checkpoints").exists() and not (run / "metrics.csv").exists()  # nothing ran
    assert main(["test", *_tiny_args(tiny_shards, tmp_path / "empty"), "--ckpt_path", "last"]) == 2
    assert "--ckpt_path last: no last*.ckpt in " in capsys.readouterr().err


def test_ckpt_path_last_is_the_newest_last_checkpoint(tmp_path):
    """``--ckpt_path last`` names, as Lightning's own look-up, the newest ``last*.ckpt`` by modification time (a run
    that wrote ``last-v1.ckpt`` beside an earlier ``last.ckpt`` resumes from the newer), not the oldest or the
    first by name."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from anycity.cli import _cli_class, configured_trainer

    for name, mtime in (("last.ckpt", 1000), ("last-v1.ckpt", 1001), ("last-v2.ckpt", 900)):
        (tmp_path / name).write_bytes(b"x")
        os.utime(tmp_path / name, (mtime, mtime))
    trainer = configured_trainer({"default_root_dir": str(tmp_path), "logger": False,
                                  "callbacks": [ModelCheckpoint(dirpath=tmp_path, save_last=True)]})
    assert _cli_class()._find_last("fit", trainer) == str(tmp_path / "last-v1.ckpt")


@pytest.mark.parametrize("bar", ["off", "rich"])
def test_turning_the_progress_bar_off_or_choosing_another_one_is_allowed(tiny_shards, tmp_path, bar):
    """The ``progress`` bar was added whatever the config said: Lightning refused --trainer.enable_progress_bar
    false, and a second progress bar, with a MisconfigurationException traceback."""
    from lightning.pytorch.callbacks import RichProgressBar

    from anycity.callbacks import LossProgressBar

    cli = build_cli(_tiny_args(tiny_shards, tmp_path / "default"), run=False)
    assert isinstance(cli.trainer.progress_bar_callback, LossProgressBar)
    if bar == "off":
        extra = ["--trainer.enable_progress_bar", "false"]
    else:
        (tmp_path / "rich.yaml").write_text("trainer:\n  callbacks:\n"
                                            "  - class_path: lightning.pytorch.callbacks.RichProgressBar\n")
        extra = ["-c", str(tmp_path / "rich.yaml")]
    cli = build_cli([*_tiny_args(tiny_shards, tmp_path / bar), *extra], run=False)
    assert not any(isinstance(c, LossProgressBar) for c in cli.trainer.callbacks)
    want = RichProgressBar if bar == "rich" else type(None)
    assert isinstance(cli.trainer.progress_bar_callback, want)


def test_a_predict_that_receives_sigterm_stops_with_143_and_writes_nothing_unfinished(tiny_shards, fitted,
                                                                                       tmp_path, monkeypatch):
    """predict never checked Lightning's SIGTERM flag: a preempted city ran to its end, and every stopped training
    command exited 0 (Lightning's SIGTERMException is a SystemExit with no code)."""
    from anycity.callbacks import PredictionExport
    from anycity.cli import Stopped

    photos = tmp_path / "flight"
    photos.mkdir()
    for i in range(6):
        Image.fromarray(np.random.default_rng(i).integers(0, 255, (32, 32, 3), dtype=np.uint8)).save(
            photos / f"{i}.png")
    write = PredictionExport.write_on_batch_end

    def sigterm_during_the_first_chunk(self, trainer, *a, **k):
        trainer._signal_connector.received_sigterm = True  # what Lightning's SIGTERM handler sets
        return write(self, trainer, *a, **k)

    monkeypatch.setattr(PredictionExport, "write_on_batch_end", sigterm_during_the_first_chunk)
    with pytest.raises(Stopped) as stop:
        build_cli(["predict", *_tiny_args(tiny_shards, tmp_path / "p"), *FAST_EVAL,
                   "--ckpt_path", str(fitted / "checkpoints" / "last.ckpt"), "--data.predict_images", str(photos),
                   "--data.predict_chunk_size", "4", "--data.predict_chunk_overlap", "2",
                   "--export.out_dir", str(tmp_path / "out")])
    assert stop.value.code == 143
    assert stop.value.message == ("stopped by SIGTERM during predict after 0 exported scene(s); the city flight was "
                                  "not finished, so nothing was written for it; rerun the command to predict them all")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_a_pose_prior_the_checkpoint_was_trained_without_is_ignored_naming_it(tiny_shards, fitted, tmp_path):
    """net.pose_prior adds weights (completion.camera_pose.*, pose_prior.*): asked for on a checkpoint trained
    without one, it used to fail strict loading with a traceback of missing keys. Only a moved file is taken."""
    from anycity.cli import merge_ckpt_net
    from anycity.models.pose_prior import PairFlowPose

    net, ignored = merge_ckpt_net({"pose_prior": "here/p.pt"}, {"pose_prior": "there/p.pt"}, "tiny")
    assert net["pose_prior"] == "here/p.pt" and not ignored  # the same prior, moved
    s2 = tmp_path / "s2"
    stage2 = ["-c", "configs/quickstart_stage2.yaml", "--model.init_args.net.refine_cameras", "true"]
    build_cli(["fit", *_tiny_args(tiny_shards, s2, steps=1, configs=stage2[:2], extra=[
        *stage2[2:], "--model.init_args.init_from", str(fitted / "checkpoints" / "last.ckpt"),
        "--trainer.limit_val_batches", "0"])])
    prior = tmp_path / "prior.pt"
    torch.save({"state_dict": PairFlowPose().state_dict(), "channels": 48, "grid": 12, "image_size": [32, 32]}, prior)
    with pytest.warns(UserWarning, match="pose_prior is None, not"):
        build_cli(["test", *_tiny_args(tiny_shards, tmp_path / "t", configs=stage2[:2], extra=[
            *stage2[2:], *FAST_EVAL, "--model.init_args.net.pose_prior", str(prior),
            "--ckpt_path", str(s2 / "checkpoints" / "last.ckpt")])])


def test_a_stage1_checkpoint_read_with_a_wan_dir_runs_and_names_it_unused(tiny_shards, fitted, tmp_path):
    """Stage I now refuses Stage II net keys; a machine-local wan_dir (a test-time key a config or the command line
    gives, e.g. a Stage II config's) read with a Stage I checkpoint is dropped and named, not refused."""
    with pytest.warns(UserWarning, match=r"wan_dir 'weights/Wan' is not used \(a Stage I network has no completion"):
        cli = build_cli(["test", *_tiny_args(tiny_shards, tmp_path / "t", extra=[
            *FAST_EVAL, "--model.init_args.net.wan_dir", "weights/Wan",
            "--ckpt_path", str(fitted / "checkpoints" / "last.ckpt")])])
    assert "wan_dir" not in cli.model.hparams.net and type(cli.model).__name__ == "ScaffoldModule"


def test_a_resumed_fit_names_the_model_settings_it_keeps_from_its_checkpoint(tiny_shards, tmp_path):
    # Lightning rebuilds the module from the checkpoint's hyperparameters: a new lr (or Stage II's init_from, as a
    # resubmitted SLURM job passes) was silently not used
    from anycity.cli import resumed_settings_ignored

    assert resumed_settings_ignored({"lr": 1e-3, "net": {"x": 1}, "camera_refine_steps": 5, "size": [1, 2]},
                                    {"lr": 5e-4, "net": {"x": 2}, "camera_refine_steps": 0, "size": (1, 2)}) == [
        "lr is 0.0005, not 0.001"]
    run = tmp_path / "r"
    build_cli(["fit", *_tiny_args(tiny_shards, run, steps=2)])
    last = str(run / "checkpoints" / "last.ckpt")
    with pytest.warns(UserWarning, match=r"a resumed fit continues .* model.init_args lr is 0.001, not 0.0005"):
        cli = build_cli(["fit", *_tiny_args(tiny_shards, run, steps=3, extra=["--model.init_args.lr", "5e-4"]),
                         "--ckpt_path", last])
    assert cli.model.hparams.lr == 1e-3 and cli.trainer.global_step == 3


def test_a_null_wan_dir_in_the_config_keeps_the_checkpoints_path():
    # configs/stage2.yaml ships wan_dir: null, so `anycity predict -c configs/stage2.yaml --ckpt_path X` dropped the
    # path the checkpoint was trained with and stopped with "needs wan_dir"
    from anycity.cli import merge_ckpt_net

    stored = {"wan_dir": "weights/Wan", "wan_empty_prompt": "weights/e.pt", "voxel_size": 0.1}
    net, _ = merge_ckpt_net({"wan_dir": None, "wan_empty_prompt": None, "voxel_size": None}, stored, "tiny")
    assert net == {"wan_dir": "weights/Wan", "wan_empty_prompt": "weights/e.pt", "voxel_size": None}  # null: no merge
    net, _ = merge_ckpt_net({"wan_dir": "here/Wan"}, stored, "tiny")
    assert net["wan_dir"] == "here/Wan"  # a moved folder still wins


def test_the_paper_configs_on_a_machine_without_cuda_stop_in_one_line(tiny_shards, tmp_path, capsys, monkeypatch):
    # configs/stage1.yaml and stage2.yaml ask for accelerator: gpu; Lightning's refusal was a 40-line traceback
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)  # Lightning's "gpu" on a Mac
    rc = main(["fit", "-c", "configs/stage1.yaml", "--data.root", str(tiny_shards),
               "--trainer.default_root_dir", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err[-1].startswith("anycity: error: trainer.accelerator gpu: this machine has no CUDA GPU")
    assert "--trainer.accelerator cpu --trainer.precision 32-true" in err[-1]
    assert not (tmp_path / "r").exists()  # before the run wrote anything


@pytest.mark.parametrize("accelerator", ["gpu", "mps"])
def test_apple_mps_is_refused_in_one_line(accelerator, monkeypatch):
    """Lightning takes ``gpu`` for MPS on a Mac, and MPS has no float64 (the DPT heads' pixel grid, the renderer's
    camera checks): the one-line check let it through and the first step failed with a traceback."""
    from anycity.cli import check_accelerator

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    with pytest.raises(ValueError, match=rf"^trainer.accelerator {accelerator}: this machine has no CUDA GPU .*Apple "
                                         r"MPS is not supported: it has no float64.*--trainer.accelerator cpu"):
        check_accelerator({"accelerator": accelerator})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    check_accelerator({"accelerator": "gpu"})  # CUDA: accepted
    with pytest.raises(ValueError, match=r"^trainer.accelerator mps: anycity runs on CUDA GPUs and the CPU only .*"
                                         r"--trainer.accelerator gpu$"):
        check_accelerator({"accelerator": "mps"})


def test_a_multi_node_config_outside_a_multi_node_job_is_refused(tiny_shards, tmp_path, capsys, monkeypatch):
    """A 2-node run's config.yaml reused for a test on one machine waited for ranks that never started, silently,
    until the process group's 30 min timeout (a fit too); inside SLURM/torchrun, or with NODE_RANK/MASTER_ADDR set,
    it runs."""
    from anycity.cli import check_nodes

    for var in ("SLURM_NTASKS", "SLURM_JOB_NAME", "SLURM_NODELIST", "TORCHELASTIC_RUN_ID", "LSB_JOBID", "NODE_RANK",
                "MASTER_ADDR", "WORLD_SIZE", "LOCAL_RANK", "GROUP_RANK", "RANK"):
        monkeypatch.delenv(var, raising=False)
    rc = main(["fit", *_tiny_args(tiny_shards, tmp_path / "r"), "--trainer.num_nodes", "2"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err[-1].startswith("anycity: error: trainer.num_nodes 2: this machine is not in a multi-node "
                                          "job") and "--trainer.num_nodes 1" in err[-1], err
    assert not (tmp_path / "r").exists()  # before the run wrote anything
    check_nodes({"num_nodes": 1})
    monkeypatch.setenv("NODE_RANK", "1")  # a hand-started multi-node run
    check_nodes({"num_nodes": 2})
    monkeypatch.delenv("NODE_RANK")
    monkeypatch.setenv("TORCHELASTIC_RUN_ID", "x")  # torchrun
    for var, value in (("RANK", "0"), ("WORLD_SIZE", "2"), ("LOCAL_RANK", "0"), ("GROUP_RANK", "0")):
        monkeypatch.setenv(var, value)
    check_nodes({"num_nodes": 2})
