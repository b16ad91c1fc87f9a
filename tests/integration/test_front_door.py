"""``anycity`` front door: one help listing, no Lightning for the light commands, one-line user errors."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from anycity import cli


def _run(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_help_lists_every_subcommand_without_lightning():
    r = _run("import sys; from anycity.cli import main; main(['--help']); "
             "print('LIGHTNING_LOADED' if 'lightning' in sys.modules else 'NO_LIGHTNING'); "
             "print('TORCH_LOADED' if 'torch' in sys.modules else 'NO_TORCH')")
    assert r.returncode == 0, r.stderr
    for cmd in ("data synth", "data convert", "fit", "validate", "test", "predict", "export", "view",
                "render-video"):
        assert f"  {cmd} " in r.stdout, cmd
    assert "NO_LIGHTNING" in r.stdout
    assert "NO_TORCH" in r.stdout  # `anycity --help` took 1.5 s, nearly all of it `import torch`; now 0.04 s


def test_the_package_names_its_structures_lazily():
    r = _run("import sys, anycity; loaded = 'torch' in sys.modules; from anycity import Gaussians, ViewBatch; "
             "print(loaded, Gaussians.__module__, anycity.Views.__name__, anycity.__version__)")
    assert r.returncode == 0 and r.stdout.split() == ["False", "anycity.structures", "Views", "0.1.0"], r.stderr


class _Missing(torch.utils.data.Dataset):
    def __len__(self):
        return 2

    def __getitem__(self, i):
        raise FileNotFoundError("shard /nope/train-000.tar: not found; check --data.root")


def test_worker_error_reaches_the_user_as_one_line(monkeypatch, capsys):
    def dispatch(args, argv_given):
        next(iter(torch.utils.data.DataLoader(_Missing(), num_workers=1)))

    monkeypatch.setattr(cli, "_dispatch", dispatch)
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    assert cli.main(["fit"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["anycity: error: shard /nope/train-000.tar: not found; check --data.root  (--debug for the "
                   "traceback)"]
    with pytest.raises(FileNotFoundError, match="worker"):
        cli.main(["fit", "--debug"])


def test_an_existing_output_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    argv = ["data", "synth", "--out", str(tmp_path / "d"), "--scenes", "1", "--views", "8", "--size", "16x16"]
    assert cli.main(argv) == 0
    capsys.readouterr()
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "already holds a shard set (index.json); pass --overwrite" in err


def test_unknown_command_is_one_line(capsys):
    assert cli.main(["frobnicate"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_config_typo_names_the_nearest_key(capsys):
    argv = ["fit", "--config", "configs/quickstart.yaml", "--model.init_args.warmup_step", "3"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "unknown option --model.init_args.warmup_step; did you mean warmup_steps?" in err
    assert cli.main(["fit", "--config", "configs/quickstart.yaml", "--model.init_args.lerning_rate", "1e-3"]) == 2
    assert "did you mean lr (learning rate)?" in capsys.readouterr().err


@pytest.mark.parametrize("typo, said", [
    (["--data.num_contxt", "5"], "unknown option --data.num_contxt; did you mean num_context?"),
    (["--model.init_args.net.camera_trunk_dept", "3"],  # a network key: the network's keys are the candidates
     "unknown option --model.init_args.net.camera_trunk_dept; did you mean camera_trunk_depth?"),
    ({"data": {"num_contxt": 5}}, "unknown key data.num_contxt in a --config file; did you mean num_context?"),
    ({"trainer": {"max_stpes": 5}}, "unknown key trainer.max_stpes in a --config file; did you mean max_steps?"),
    ({"model": {"init_args": {"warmup_step": 5}}}, "unknown key warmup_step in a --config file; did you mean "
     "warmup_steps?"),
    ({"model": {"init_args": {"net": {"camera_trunk_dept": 3}}}}, "unknown key net.camera_trunk_dept in a --config "
     "file; did you mean camera_trunk_depth?"),
])
def test_typos_in_every_section_name_the_nearest_key(typo, said, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    if isinstance(typo, dict):
        import yaml

        (tmp_path / "typo.yaml").write_text(yaml.safe_dump(typo))
        typo = ["--config", str(tmp_path / "typo.yaml")]
    assert cli.main(["fit", "--config", "configs/quickstart.yaml", *typo]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and said in err, err


@pytest.mark.parametrize("message, argv, said", [  # older jsonargparse phrasings (4.39; 4.29)
    ("Validation failed: Subcommand 'fit' does not accept nested key 'trainer.max_stpes'", [],
     "unknown key trainer.max_stpes in a --config file; did you mean max_steps?"),
    ("Unrecognized arguments: --data.num_contxt 5", ["fit", "--data.num_contxt", "5"],
     "unknown option --data.num_contxt; did you mean num_context?"),
])
def test_older_jsonargparse_messages_name_the_nearest_key(message, argv, said):
    assert cli.config_error(message, argv) == said


def test_lightnings_pytree_deprecation_is_not_printed():
    """Lightning 2.6 + torch >= 2.10 printed a FutureWarning about Lightning's own code on every fit and test."""
    import warnings

    from lightning.pytorch.utilities._pytree import _tree_flatten

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _tree_flatten({"a": 1})
        if not any("LeafSpec" in str(w.message) for w in seen):
            pytest.skip("this Lightning/torch pair does not warn")
        seen.clear()
        cli.quiet_third_party_noise()
        _tree_flatten({"a": 1})
    assert not [str(w.message) for w in seen if "LeafSpec" in str(w.message)]


def test_lightnings_adverts_are_not_printed(tmp_path):
    """Lightning 2.6 logged two "💡 Tip: ... try installing litlogger / litmodels" lines at every Trainer; its own
    notices (the accelerator lines) still show."""
    import logging

    from lightning.pytorch import Trainer

    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    seen: list[str] = []
    handler = logging.Handler()
    handler.emit = lambda record: seen.append(record.getMessage())
    rank_zero.addHandler(handler)
    try:
        rank_zero.removeFilter(cli._not_an_advert)  # an earlier build_cli in this process installed it
        Trainer(accelerator="cpu", logger=False, default_root_dir=tmp_path, enable_model_summary=False)
        if not any(m.startswith("💡 Tip:") for m in seen):
            pytest.skip("this Lightning prints no tip")
        seen.clear()
        cli.quiet_third_party_noise()
        cli.quiet_third_party_noise()  # idempotent: one filter
        Trainer(accelerator="cpu", logger=False, default_root_dir=tmp_path, enable_model_summary=False)
    finally:
        rank_zero.removeHandler(handler)
    assert rank_zero.filters.count(cli._not_an_advert) == 1
    assert not [m for m in seen if "Tip" in m]
    assert any(m.startswith("GPU available") for m in seen)


@pytest.mark.parametrize("cmd", [["data", "synth"], ["data", "convert"], ["export"], ["view"], ["render-video"]])
def test_light_subcommand_help_is_readable(cmd, capsys):
    """No Python object reprs: jsonargparse printed ``type: <function <lambda> at 0x...>`` for a str option with
    choices."""
    with pytest.raises(SystemExit) as stop:
        cli.main([*cmd, "--help"])
    assert stop.value.code == 0
    text = capsys.readouterr().out
    assert "<function" not in text and " at 0x" not in text, text
    assert text.count("--") >= 3, text


@pytest.mark.parametrize("cmd, abbrev", [(["data", "synth"], "--ou"), (["data", "convert"], "--sr"),
                                         (["export"], "--fro"), (["view"], "--ho"), (["render-video"], "--fp")])
def test_light_subcommands_refuse_abbreviated_options(cmd, abbrev, tmp_path, monkeypatch, capsys):
    """An option is taken only by its full name: a prefix (argparse's default) would silently change meaning when
    a later option shares it."""
    monkeypatch.chdir(tmp_path)  # where an accepted abbreviation would write (data synth --ou 1: shards in ./1)
    with pytest.raises(SystemExit) as stop:
        cli.main([*cmd, "x", abbrev, "1"] if cmd[0] in ("view", "render-video") else [*cmd, abbrev, "1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert abbrev in err, err


def test_a_missing_config_or_checkpoint_is_one_line_before_lightning_is_imported(tmp_path):
    (tmp_path / "stage1.yaml").write_text("trainer: {max_steps: 1}\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "a.yaml").write_text("{}\n")
    (tmp_path / "sub" / "last.ckpt").write_bytes(b"")
    calls = [["fit", "-c", str(tmp_path / "stage1.yml")], ["test", f"--config={tmp_path / 'sub'}"],
             ["fit", "--config", "no/where.yaml"], ["test", "--ckpt_path", str(tmp_path / "sub" / "lst.ckpt")],
             ["predict", f"--ckpt_path={tmp_path / 'sub'}"]]
    code = (f"import sys; from anycity.cli import main; rcs = [main(a) for a in {calls!r}]; "
            "print(*rcs, 'lightning' in sys.modules)")
    r = _run(code)
    assert r.stdout.split() == ["2"] * 5 + ["False"], r.stderr  # refused in 0.1 s, not after 8 s of imports
    tail = "  (--debug for the traceback)"
    assert r.stderr.strip().splitlines() == [
        f"anycity: error: --config {tmp_path / 'stage1.yml'}: no such file; did you mean {tmp_path / 'stage1.yaml'}?"
        + tail,
        f"anycity: error: --config {tmp_path / 'sub'} is a folder; pass one of its YAML files (a.yaml)" + tail,
        "anycity: error: --config no/where.yaml: no such file; check the path (anycity's own configs are in the "
        "configs/ folder of its repository)" + tail,
        f"anycity: error: --ckpt_path {tmp_path / 'sub' / 'lst.ckpt'}: no such file; did you mean "
        f"{tmp_path / 'sub' / 'last.ckpt'}?" + tail,
        f"anycity: error: --ckpt_path {tmp_path / 'sub'} is a folder; pass one of its checkpoint files (last.ckpt)"
        + tail]
    # existing files, inline YAML (jsonargparse reads a --config value that is not a path as YAML) and Lightning's
    # checkpoint names pass
    cli.check_input_files(["fit", "-c", str(tmp_path / "stage1.yaml"), "--config", "{trainer: {max_steps: 2}}",
                           "--config=trainer:\n  max_steps: 3", "--ckpt_path", "last", "--ckpt_path=best",
                           "--ckpt_path", str(tmp_path / "sub" / "last.ckpt")])


def test_a_missing_data_root_is_one_line_and_the_run_writes_nothing(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    run = tmp_path / "run"
    argv = ["fit", "--config", "configs/quickstart.yaml", "--data.root", str(tmp_path / "nope"),
            "--trainer.default_root_dir", str(run), "--trainer.logger.init_args.save_dir", str(run)]
    assert cli.main(argv) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (  # after Lightning's "Seed set to 0"
        f"anycity: error: data.root {tmp_path / 'nope'}: no such folder; fix the path, or write shards there with "
        f"anycity data synth --out {tmp_path / 'nope'} (or anycity data convert)  (--debug for the traceback)")
    assert not run.exists()  # refused when the data module is built: no config.yaml for the next run to move aside
    from anycity.lit.datamodule import AerialDataModule

    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("a.jpg", "b.jpg"):  # listed, not decoded, when the data module is built
        (photos / name).write_bytes(b"")
    AerialDataModule(root=str(tmp_path / "nope"), predict_images=str(photos))  # predicting photos reads no shards


def test_a_misspelt_section_a_class_path_and_broken_yaml_are_named(tmp_path, capsys, monkeypatch):
    """``modle:`` used to be reported as its last key (``did you mean lr?``), a class_path typo lost jsonargparse's
    reason, and a --config file that is not YAML was not named."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    cases = [("modle:\n  init_args:\n    lr: 1\n",
              "unknown section modle (in modle.init_args.lr); did you mean model?"),
             ("model:\n  class_path: anycity.lit.ScafoldModule\n",
              "module 'anycity.lit' has no attribute 'ScafoldModule'; did you mean anycity.lit.ScaffoldModule?"),
             ("trainer: {max_steps: [1, 2\n", "typo.yaml: line 2, column 1: not valid YAML (expected ',' or ']'")]
    for text, said in cases:
        (tmp_path / "typo.yaml").write_text(text)
        assert cli.main(["fit", "--config", "configs/quickstart.yaml", "--config", str(tmp_path / "typo.yaml")]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and said in err, err
    assert cli.main(["fit", "--config", "configs/quickstart.yaml", "--tranier.max_steps", "3"]) == 2
    assert "unknown section tranier (in tranier.max_steps); did you mean trainer?" in capsys.readouterr().err


def test_sections_are_the_training_configs_top_level_keys(capsys, monkeypatch):
    import yaml

    monkeypatch.setattr("sys.argv", ["anycity"])
    with pytest.raises(SystemExit):
        cli.build_cli(["fit", "-c", "configs/quickstart.yaml", "--print_config"])
    assert set(yaml.safe_load(capsys.readouterr().out)) == set(cli.SECTIONS)


def test_version(capsys):
    import re
    from pathlib import Path

    from anycity import __version__

    assert cli.main(["--version"]) == 0 and capsys.readouterr().out == f"anycity {__version__}\n"
    pyproject = (Path(cli.__file__).parents[2] / "pyproject.toml").read_text()
    assert re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1) == __version__


def test_a_fit_stopped_by_sigterm_exits_143_naming_its_newest_checkpoint(tiny_shards, tmp_path):
    """Lightning stops a fit on SIGTERM with a SystemExit that has no code: ``anycity fit`` exited 0 (a preempted
    job looked finished) and said nothing."""
    import signal
    import time

    from reliability import harness as H

    run, log = tmp_path / "run", tmp_path / "fit.log"
    p = H.start(H.tiny_fit_args(tiny_shards, run, 200), log)
    try:
        t0 = time.monotonic()
        while p.poll() is None and log.read_bytes().count(b"] step ") < 2 and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        assert p.poll() is None, log.read_text()[-3000:]
        os.kill(p.pid, signal.SIGTERM)
        rc = p.wait(120)
    finally:
        if p.poll() is None:
            p.kill()
    text = log.read_text()
    assert rc == 143, text[-3000:]
    last = text.strip().splitlines()[-1]
    ckpt = run / "checkpoints" / "last.ckpt"
    step = H.safe_torch_load(ckpt)["global_step"]
    # the step it stopped at is the newest checkpoint's or one past it (a checkpoint every step)
    assert re.fullmatch(rf"anycity: stopped by SIGTERM at step (\d+); the newest checkpoint is {re.escape(str(ckpt))}; "
                        rf"resume with the same command and --ckpt_path {re.escape(str(ckpt))}", last), last
    assert int(re.search(r"step (\d+)", last).group(1)) in (step, step + 1), (last, step)


@pytest.mark.parametrize("extra, said", [
    (["--model.init_args.preset", "huge"],
     "--model.init_args.preset huge: not accepted; expected one of tiny, small, base, vggt-1b"),
    (["--model.init_args.eval_align", "sim4"], "--model.init_args.eval_align sim4: not accepted; expected one of "
     "sim3, none"),
    (["--model.init_args.lr", "fast"], "--model.init_args.lr fast: not accepted; expected a number"),
    (["--model.init_args.net.camera_trunk_depth", "three"],
     "--model.init_args.net.camera_trunk_depth three: not accepted; expected an integer"),
    (["--model.class_path", "anycity.lit.ScafoldModule"],
     "module 'anycity.lit' has no attribute 'ScafoldModule'; did you mean anycity.lit.ScaffoldModule?"),
    (["-c", "MODLE", "--print_config"], "unknown section modle (in modle.init_args.lr); did you mean model?"),
])
def test_a_bad_value_of_a_known_option_is_named_with_what_it_accepts(extra, said, tmp_path, capsys, monkeypatch):
    """A refused value (jsonargparse names the option only as NestedArg(key='preset', ...)) was reported as an unknown
    option ("did you mean preset?"), and under --print_config a misspelt section lost its hint."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    (tmp_path / "modle.yaml").write_text("modle:\n  init_args:\n    lr: 1\n")
    extra = [str(tmp_path / "modle.yaml") if a == "MODLE" else a for a in extra]
    assert cli.main(["fit", "--config", "configs/quickstart.yaml", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and said in err and "unknown option" not in err, err


def test_test_validate_predict_without_weights_are_refused(tiny_shards, tmp_path, capsys, monkeypatch):
    """Without --ckpt_path (or model.pretrained) they scored or exported a randomly initialised network with exit 0;
    a Stage II config's init_from is read by fit only (and holds no completion branch)."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    monkeypatch.chdir(tmp_path)
    repo = Path(cli.__file__).parents[2]
    run = tmp_path / "run"
    small = ["--data.root", str(tiny_shards), "--data.image_size", "[32, 32]", "--data.num_context", "2",
             "--data.num_targets", "1", "--data.num_dense", "2", "--trainer.limit_test_batches", "1",
             "--trainer.limit_val_batches", "1", "--trainer.limit_predict_batches", "1",
             "--model.init_args.render_backend", "torch", "--model.init_args.camera_refine_steps", "0",
             "--model.init_args.eval_pose_align_steps", "0", "--trainer.default_root_dir", str(run),
             "--trainer.logger.init_args.save_dir", str(run)]
    stage2 = ["-c", str(repo / "configs" / "quickstart_stage2.yaml")]
    for cmd, configs, init_from in (("test", [], ""), ("validate", [], ""),
                                    ("predict", stage2, " (model.init_from is read by fit only)")):
        assert cli.main([cmd, "-c", str(repo / "configs" / "quickstart.yaml"), *configs, *small]) == 2
        assert capsys.readouterr().err.strip().splitlines()[-1] == (
            f"anycity: error: anycity {cmd}: no --ckpt_path, so the network's weights would be random{init_from}; "
            f"pass the trained checkpoint, e.g. --ckpt_path {run / 'checkpoints' / 'last.ckpt'}  (--debug for the "
            "traceback)")
    assert not run.exists()  # refused before anything was written


@pytest.mark.parametrize("code", ["ENOSPC", "EDQUOT"])
def test_a_full_disk_is_one_line(code, monkeypatch, capsys):
    """anycity.atomic and the shard writer raise one-line OSErrors for a full disk or quota; main printed them as a
    44-line traceback."""
    import errno

    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    message = "disk full writing out/index.json: 583 bytes needed; free space on out (the previous file is unchanged)"

    def dispatch(args, argv_given):
        raise OSError(getattr(errno, code), message)

    monkeypatch.setattr(cli, "_dispatch", dispatch)
    assert cli.main(["data", "synth"]) == 1
    assert capsys.readouterr().err.splitlines() == [f"anycity: error: {message}  (--debug for the traceback)"]
    monkeypatch.setattr(cli, "_dispatch", lambda args, argv_given: (_ for _ in ()).throw(OSError(errno.EIO, "EIO")))
    with pytest.raises(OSError, match="EIO"):  # another OSError is a bug report: its traceback shows
        cli.main(["data", "synth"])


def test_data_out_naming_a_file_is_one_line(tmp_path, capsys, monkeypatch):
    """It was a bare "[Errno 17] File exists"."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    (tmp_path / "f").write_text("x")
    assert cli.main(["data", "synth", "--out", str(tmp_path / "f"), "--scenes", "1", "--views", "2"]) == 2
    assert capsys.readouterr().err == (f"anycity: error: --out {tmp_path / 'f'} is a file; the shard set is written to "
                                       "a folder: pass a new or empty folder (or a shard set's, with --overwrite)  "
                                       "(--debug for the traceback)\n")


def test_a_later_config_that_drops_net_keys_is_named(tmp_path, monkeypatch):
    """A later --config file's ``model.init_args.net`` replaces the earlier dict whole (jsonargparse): the paper's
    ``video_prior: wan`` of stage2.yaml vanished silently under an overlay that set only the LoRA rank."""
    overlay = tmp_path / "mine.yaml"
    overlay.write_text("model:\n  init_args:\n    net: {wan_lora_rank: 8}\n")
    said = cli.replaced_net_keys(["fit", "-c", "configs/stage2.yaml", "-c", str(overlay)])
    assert len(said) == 1 and "inject_layers, video_prior from configs/stage2.yaml are not used" in said[0], said
    monkeypatch.setattr(cli, "build_cli", lambda *a, **k: None)
    with pytest.warns(UserWarning, match="video_prior from configs/stage2.yaml are not used"):
        assert cli.main(["fit", "-c", "configs/stage2.yaml", "-c", str(overlay)]) == 0
    # the documented chains drop nothing that matters: `completion` is the stage module's, and the wan_* keys are
    # moot under another prior
    for chain in (["configs/stage1.yaml", "configs/debug/cpu_ddp.yaml"],
                  ["configs/stage2.yaml", "configs/debug/cpu_ddp.yaml"],
                  ["configs/stage2.yaml", "configs/ablations/wo_lora.yaml"],
                  ["configs/stage1.yaml", "configs/ablations/scaffold_only.yaml"],
                  ["configs/quickstart.yaml", "configs/quickstart_stage2.yaml", "configs/data/colmap.yaml"]):
        assert cli.replaced_net_keys(["fit", *[a for c in chain for a in ("-c", c)]]) == [], chain


def test_naming_trainer_plugins_keeps_safe_checkpoint_io(tiny_shards, tmp_path, monkeypatch):
    """Any ``--trainer.plugins`` replaced the CLI's default value, and with it SafeCheckpointIO (atomic, fsynced
    checkpoint writes); a CheckpointIO the user names is kept."""
    from lightning.pytorch.plugins import TorchCheckpointIO

    from anycity.lit.checkpoint_io import SafeCheckpointIO

    monkeypatch.setattr("sys.argv", ["anycity"])
    base = ["--config", "configs/quickstart.yaml", "--data.root", str(tiny_shards), "--trainer.logger", "false",
            "--trainer.default_root_dir", str(tmp_path / "run")]
    env = "lightning.pytorch.plugins.environments."
    for plugins, io in (([], SafeCheckpointIO), ([f"{env}SLURMEnvironment", "--trainer.plugins.auto_requeue", "false"],
                                                 SafeCheckpointIO),
                        ([f'[{{"class_path": "{env}LightningEnvironment"}}]'], SafeCheckpointIO),
                        (["lightning.pytorch.plugins.TorchCheckpointIO"], TorchCheckpointIO)):
        trainer = cli.build_cli([*base, *(["--trainer.plugins", *plugins] if plugins else [])], run=False).trainer
        assert type(trainer.strategy.checkpoint_io) is io, plugins


def test_pretrained_weights_are_enough_to_evaluate_or_predict():
    """``model.pretrained`` (a VGGT/AnySplat file) gives the network its weights: ``predict`` with it and no
    ``--ckpt_path`` runs (what the README's zero-shot export does); with neither it is refused."""
    cli.require_weights("predict", {"ckpt_path": None, "model.init_args.pretrained": "vggt/model.pt"})
    with pytest.raises(ValueError, match="no --ckpt_path"):
        cli.require_weights("predict", {"ckpt_path": None, "model.init_args.pretrained": None})


def test_a_run_folder_written_with_a_trailing_slash_is_the_loggers_folder():
    """``--trainer.default_root_dir runs/x/`` with the logger's ``save_dir runs/x`` name one folder: not refused.
    Another folder is."""
    logger = {"class_path": "lightning.pytorch.loggers.CSVLogger", "init_args": {"save_dir": "runs/x"}}
    cli.check_run_folder({"default_root_dir": "runs/x/", "logger": logger})
    cli.check_run_folder({"default_root_dir": "runs/./x", "logger": [logger]})
    with pytest.raises(ValueError, match="disagree"):
        cli.check_run_folder({"default_root_dir": "runs/y", "logger": logger})


def test_the_sigterm_line_names_the_newest_checkpoint_of_every_checkpoint_folder(tmp_path):
    """The "stopped by SIGTERM" line tells the user which file to resume from: the newest by modification time, over
    every checkpoint callback's folder (not the first file found)."""
    from types import SimpleNamespace

    a, b = tmp_path / "a", tmp_path / "b"
    for folder, name, mtime in ((a, "step2.ckpt", 900), (b, "last.ckpt", 1000), (b, "step4.ckpt", 1001)):
        folder.mkdir(exist_ok=True)
        (folder / name).write_bytes(b"x")
        os.utime(folder / name, (mtime, mtime))
    trainer = SimpleNamespace(global_rank=0, global_step=4, default_root_dir=str(tmp_path),
                              checkpoint_callbacks=[SimpleNamespace(dirpath=str(a)), SimpleNamespace(dirpath=str(b))])
    line = cli._cli_class()._stopped(SimpleNamespace(trainer=trainer), "fit")
    assert line == (f"stopped by SIGTERM at step 4; the newest checkpoint is {b / 'step4.ckpt'}; resume with the same "
                    f"command and --ckpt_path {b / 'step4.ckpt'}")
    # a SIGUSR1 requeue checkpoint in the run folder, newer than last.ckpt, was left out of the candidates
    (tmp_path / "hpc_ckpt_1.ckpt").write_bytes(b"x")
    os.utime(tmp_path / "hpc_ckpt_1.ckpt", (1002, 1002))
    line = cli._cli_class()._stopped(SimpleNamespace(trainer=trainer), "fit")
    assert line.startswith(f"stopped by SIGTERM at step 4; the newest checkpoint is {tmp_path / 'hpc_ckpt_1.ckpt'};")


def test_export_typos_a_model_class_typo_and_another_stages_key_are_named(tmp_path, capsys, monkeypatch):
    """--export.* typos got no suggestion and a literal "see anycity COMMAND --help"; a class typo as --model's value
    gave jsonargparse's "Expected a path"; an ablation overlay alone named preset for Stage II's pres_weight."""
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    cases = [(["predict", "-c", "configs/quickstart.yaml", "--export.outdir", "x"],
              "unknown option --export.outdir; did you mean out_dir?"),
             (["predict", "-c", "configs/quickstart.yaml", "--export.zzzz", "x"],
              "unknown option --export.zzzz; see anycity predict --help"),
             (["predict", "-c", "configs/quickstart.yaml", "--model", "anycity.lit.ScafoldModule"],
              "has no attribute 'ScafoldModule'; did you mean anycity.lit.ScaffoldModule?"),
             (["fit", "-c", "configs/ablations/wo_pres.yaml", "--print_config"],
              "pres_weight is an option of anycity.lit.RefinementModule (Stage II), not of the model class this run "
              "builds (AnyCityModule); put -c configs/stage2.yaml (or -c configs/quickstart.yaml -c "
              "configs/quickstart_stage2.yaml) before -c configs/ablations/wo_pres.yaml")]
    for argv, said in cases:
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and said in err, err
