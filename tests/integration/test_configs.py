"""Every shipped config parses with --print_config (overlays on top of the config they extend)."""

from pathlib import Path

import pytest

from anycity.cli import build_cli

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
COMPLETE = {"quickstart.yaml", "stage1.yaml", "stage2.yaml"}
BASE = {"quickstart_stage2.yaml": "quickstart.yaml", "ablations/wo_lora.yaml": "stage2.yaml",
        "ablations/wo_pres.yaml": "stage2.yaml", "debug/fast_dev_run.yaml": "quickstart.yaml",
        "debug/overfit.yaml": "quickstart.yaml"}  # every other overlay extends stage1.yaml


def _chain(rel: str) -> list[str]:
    if rel in COMPLETE:
        return [rel]
    return [*_chain(BASE.get(rel, "stage1.yaml")), rel]


ALL = sorted(str(p.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml"))


@pytest.mark.parametrize("rel", ALL)
def test_config_prints(rel, capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])
    args = []
    for c in _chain(rel):
        args += ["-c", str(CONFIGS / c)]
    with pytest.raises(SystemExit) as exc:
        build_cli([*args, "--print_config"], run=False)
    assert exc.value.code in (0, None)
    out = capsys.readouterr().out
    assert "model:" in out and "trainer:" in out and "freeze:" in out and "lora:" not in out


def _print_config(args: list[str], capsys) -> dict:
    """The merged config LightningCLI would run with (``--print_config``), as a dict."""
    import yaml

    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        build_cli([*args, "--print_config"], run=False)
    assert exc.value.code in (0, None)
    return yaml.safe_load(capsys.readouterr().out)


def _header_command(rel: str) -> list[str]:
    """The ``anycity fit ...`` command a config's header comment gives (continuation lines joined)."""
    import shlex

    lines = [ln.lstrip("# ").rstrip() for ln in (CONFIGS / rel).read_text().splitlines() if ln.startswith("#")]
    start = next(i for i, ln in enumerate(lines) if ln.startswith("anycity fit"))
    cmd = lines[start]
    while cmd.endswith("\\"):
        start += 1
        cmd = cmd[:-1] + " " + lines[start]
    return shlex.split(cmd)[2:]


@pytest.mark.parametrize("rel", ["ablations/frozen_aa.yaml", "ablations/frozen_all.yaml"])
def test_frozen_ablation_commands_freeze_loaded_weights(rel, capsys, monkeypatch):
    """Their header commands froze a random aggregator (pretrained: null); FreezeModules now refuses that."""
    monkeypatch.setattr("sys.argv", ["anycity"])
    monkeypatch.chdir(CONFIGS.parent)  # the commands name configs/... from the repository root
    cfg = _print_config(_header_command(rel), capsys)
    assert cfg["model"]["init_args"]["pretrained"] and cfg["freeze"]["patterns"]
    assert cfg["freeze"]["allow_random_init"] is False


def test_frozen_ablation_from_scratch_is_refused_unless_asked(tiny_shards, tmp_path, monkeypatch):
    """docs/stage2.md trains the frozen ablations at quickstart scale from random init, on purpose."""
    from anycity.callbacks import FreezeModules

    monkeypatch.setattr("sys.argv", ["anycity"])
    args = ["-c", str(CONFIGS / "quickstart.yaml"), "-c", str(CONFIGS / "ablations/frozen_aa.yaml"),
            "--data.root", str(tiny_shards), "--data.image_size", "[32, 32]", "--trainer.default_root_dir",
            str(tmp_path), "--trainer.logger.init_args.save_dir", str(tmp_path)]
    for extra, refused in (([], True), (["--freeze.allow_random_init", "true"], False)):
        cli = build_cli([*args, *extra], run=False)
        cb = next(c for c in cli.trainer.callbacks if isinstance(c, FreezeModules))
        if refused:
            with pytest.raises(ValueError, match="freeze.patterns: .*net.aggregator.*--freeze.allow_random_init true"):
                cb.setup(cli.trainer, cli.model, "fit")
        else:
            cb.setup(cli.trainer, cli.model, "fit")
            assert not any(p.requires_grad for p in cli.model.net.aggregator.parameters())


def test_the_overrides_load_stage1_names_rebuild_its_scaffold_after_stage2_yaml(tmp_path, capsys, monkeypatch):
    """load_stage1 said '-c the Stage I config -c the Stage II config', which cannot work: stage2.yaml's net dict
    replaces the Stage I one (and sets preset vggt-1b). The overrides it names now, given after stage2.yaml, do."""
    import shlex

    import torch

    from anycity.lit import RefinementModule, ScaffoldModule

    monkeypatch.setattr("sys.argv", ["anycity"])
    stage1 = ScaffoldModule(net={"sh_degree": 0, "camera_trunk_depth": 2, "head_layers": None})  # a tiny Stage I
    ckpt = tmp_path / "stage1.ckpt"
    torch.save({"state_dict": stage1.state_dict(), "hyper_parameters": dict(stage1.hparams)}, ckpt)
    stage2 = ["-c", str(CONFIGS / "stage2.yaml"), "--model.init_args.init_from", str(ckpt),  # CPU-sized prior:
              "--model.init_args.net.video_prior", "none", "--model.init_args.net.inject_layers", "[0, 1, 3]"]
    wrong = _print_config([*stage2, "--model.init_args.preset", "tiny"], capsys)["model"]["init_args"]
    with pytest.raises(ValueError, match="does not fit this network's scaffold") as err:
        RefinementModule(**wrong).load_stage1(str(ckpt))
    flags = shlex.split(str(err.value).split("after its config: ")[1])
    fixed = _print_config([*stage2, *flags], capsys)["model"]["init_args"]
    m = RefinementModule(**fixed)
    m.load_stage1(str(ckpt))
    torch.testing.assert_close(m.net.gaussian_head.state_dict(), stage1.net.gaussian_head.state_dict())
    assert m.net.cfg.completion and list(m.net.cfg.inject_layers) == [0, 1, 3]  # stage2.yaml's completion branch kept


# Each shipped config alone (with the config it extends) and as the README, docs and config headers combine them
COMBOS = sorted({tuple(_chain(rel)) for rel in ALL} | {
    ("quickstart.yaml", "ablations/frozen_aa.yaml"), ("quickstart.yaml", "ablations/frozen_all.yaml"),
    ("stage2.yaml", "debug/cpu_ddp.yaml"), ("stage2.yaml", "debug/cpu.yaml"),
    ("quickstart.yaml", "quickstart_stage2.yaml", "data/colmap.yaml")})
CHEAP = ["--trainer.accelerator", "cpu", "--trainer.devices", "1", "--trainer.strategy", "auto", "--trainer.precision",
         "32-true", "--model.init_args.preset", "tiny", "--model.init_args.pretrained", "null",
         "--model.init_args.pretrained_patterns", "[]", "--model.init_args.gradient_checkpointing", "false",
         "--data.image_size", "[32, 32]", "--data.patch_size", "8"]
STAGE2_NET = ["--model.init_args.net.video_prior", "none", "--model.init_args.net.inject_layers", "[0, 1, 3]"]


@pytest.mark.parametrize("chain", COMBOS, ids=["+".join(c) for c in COMBOS])
def test_every_config_checkpoints_into_its_default_root_dir(chain, tiny_shards, tmp_path, monkeypatch):
    """stage1.yaml / stage2.yaml kept Lightning's default logger, so each run wrote to a new
    runs/stageN/lightning_logs/version_K/checkpoints: `--ckpt_path last` never found the run before it, and the
    runs/stage1/checkpoints/last.ckpt that stage2.yaml's init_from and the README name never existed. An ablation on
    the quickstart wrote into runs/quickstart/stage1 (its default_root_dir lost to quickstart.yaml's logger)."""
    import os

    import yaml

    monkeypatch.setattr("sys.argv", ["anycity"])
    monkeypatch.chdir(tmp_path)  # the configs' relative runs/... folders, and their version_N numbering, start empty
    args = [a for c in chain for a in ("-c", str(CONFIGS / c))]
    stage2 = any(c in ("stage2.yaml", "quickstart_stage2.yaml", "ablations/wo_lora.yaml") for c in chain)
    net = STAGE2_NET if stage2 else []
    cli = build_cli([*args, *CHEAP, *net, "--data.root", str(tiny_shards)], run=False)
    root = next(yaml.safe_load((CONFIGS / c).read_text())["trainer"].get("default_root_dir") for c in reversed(chain)
                if "default_root_dir" in (yaml.safe_load((CONFIGS / c).read_text()).get("trainer") or {}))
    assert os.path.abspath(cli.trainer.default_root_dir) == os.path.abspath(root)
    for cb in cli.trainer.checkpoint_callbacks:  # where Lightning will write (ModelCheckpoint.setup resolves it so)
        assert cb._ModelCheckpoint__resolve_ckpt_dir(cli.trainer) == os.path.join(root, "checkpoints"), chain
    if not cli.trainer.fast_dev_run:
        assert os.path.abspath(cli.trainer.log_dir) == os.path.abspath(root)


@pytest.mark.parametrize("overlay", [["--trainer.default_root_dir", "runs/x"],
                                     ["-c", "ABLATION"]])  # an ablation that sets default_root_dir alone (as before)
def test_a_run_folder_the_logger_contradicts_is_refused_before_anything_is_written(overlay, tiny_shards, tmp_path,
                                                                                    capsys, monkeypatch):
    """The logger's save_dir decides where Lightning writes: an ablation overlay (or --trainer.default_root_dir alone)
    on the quickstart wrote into runs/quickstart/stage1 and moved its checkpoints aside."""
    from anycity.cli import main

    monkeypatch.setattr("sys.argv", ["anycity"])
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    (tmp_path / "ablation.yaml").write_text("trainer:\n  default_root_dir: runs/x\n")
    overlay = [str(tmp_path / "ablation.yaml") if a == "ABLATION" else a for a in overlay]
    argv = ["fit", "-c", str(CONFIGS / "quickstart.yaml"), *overlay, "--data.root", str(tiny_shards),
            "--data.image_size", "[32, 32]", "--data.num_context", "2", "--data.num_targets", "1", "--data.num_dense",
            "2", "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
            "--model.init_args.render_backend", "torch"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == ("anycity: error: trainer.default_root_dir runs/x and trainer.logger's save_dir "
                   "runs/quickstart/stage1 disagree: the checkpoints and logs would go to runs/quickstart/stage1; give "
                   "both the same folder, e.g. --trainer.default_root_dir runs/x --trainer.logger.init_args.save_dir "
                   "runs/x  (--debug for the traceback)")
    assert not (tmp_path / "runs").exists()
    # both given, as docs/stage2.md and the launch scripts do, or the logger off (scripts/gpu_check.py): accepted
    for extra in (["--trainer.logger.init_args.save_dir", "runs/x"], ["--trainer.logger", "false"]):
        build_cli(["-c", str(CONFIGS / "quickstart.yaml"), *overlay, *extra, "--data.root", str(tiny_shards)],
                  run=False)


def test_the_slurm_launch_options_keep_the_run_folder(tiny_shards, tmp_path, monkeypatch):
    """docker/slurm/launch.sh names the run folder with both options over a paper config that now has a logger."""
    import os
    import shlex

    monkeypatch.setattr("sys.argv", ["anycity"])
    monkeypatch.chdir(tmp_path)
    launch = (CONFIGS.parent / "docker" / "slurm" / "launch.sh").read_text()
    opts = shlex.split(launch[launch.index("--trainer.default_root_dir"):launch.index("${resume")].replace("\\\n", " ")
                       .replace('"${run_dir}"', "runs/job"))
    assert "--trainer.logger.init_args.save_dir" in opts
    for config in ("stage1.yaml", "stage2.yaml"):
        net = STAGE2_NET if config == "stage2.yaml" else []
        cli = build_cli(["-c", str(CONFIGS / config), *CHEAP, *net, "--data.root", str(tiny_shards), *opts], run=False)
        for cb in cli.trainer.checkpoint_callbacks:
            assert cb._ModelCheckpoint__resolve_ckpt_dir(cli.trainer) == os.path.join("runs/job", "checkpoints")


def test_debug_overlays_keep_out_of_the_recipes_run_folders():
    """configs/debug/cpu.yaml ("to check a config end to end") wrote into runs/stage1 and moved the paper run's
    checkpoints aside (checkpoints -> checkpoints.1). Each debug overlay that writes has its own folder, named by
    default_root_dir and the logger alike; fast_dev_run writes nothing, and cpu_ddp.yaml keeps the paper folders on
    purpose (docs/cluster.md chains stage1 -> stage2 through them), saying how to move it."""
    import yaml

    def trainer(rel):
        return yaml.safe_load((CONFIGS / rel).read_text()).get("trainer") or {}

    recipes = {trainer(rel).get("default_root_dir") for rel in ALL if not rel.startswith("debug/")} - {None}
    for rel in (r for r in ALL if r.startswith("debug/")):
        t = trainer(rel)
        if rel == "debug/fast_dev_run.yaml":
            assert t["fast_dev_run"] and "default_root_dir" not in t
        elif rel == "debug/cpu_ddp.yaml":
            assert "default_root_dir" not in t
            assert "--trainer.default_root_dir DIR --trainer.logger.init_args.save_dir DIR" in \
                (CONFIGS / rel).read_text()
        else:
            root = t.get("default_root_dir")
            assert root and root not in recipes, rel
            assert t["logger"]["init_args"]["save_dir"] == root, rel


@pytest.mark.parametrize("base", ["quickstart.yaml", "stage1.yaml"])
def test_scaffold_only_is_the_stage1_of_the_config_below_it(base, capsys, monkeypatch):
    """Its `model: {init_args: {net: {completion: false}}}` replaced the base's whole net: on the quickstart the
    ablation trained another network (camera_trunk_depth 2 -> 1). ScaffoldModule builds no completion branch anyway."""
    monkeypatch.setattr("sys.argv", ["anycity"])
    alone = _print_config(["-c", str(CONFIGS / base)], capsys)
    ablation = _print_config(["-c", str(CONFIGS / base), "-c", str(CONFIGS / "ablations/scaffold_only.yaml")], capsys)
    assert ablation["model"] == alone["model"]
    assert ablation["trainer"]["default_root_dir"] == "runs/ablations/scaffold_only"
