"""The training CLI's model checks: which class runs, what each source (``-c`` file, command-line option) sets and
drops, where ``-c`` goes, Stage II keys in Stage I, and the one-line messages for misplaced model keys."""

from __future__ import annotations

import pytest

from anycity import cli

QS, QS2 = "configs/quickstart.yaml", "configs/quickstart_stage2.yaml"


@pytest.fixture(autouse=True)
def _plain(monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])  # LightningCLI warns when sys.argv also carries arguments
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)


def _one_line_error(argv, capsys) -> str:
    capsys.readouterr()
    assert cli.main(argv) == 2, argv
    lines = capsys.readouterr().err.strip().splitlines()  # (before it, Lightning's "Seed set to 0" may be logged)
    assert lines and lines[-1].startswith("anycity: error: ") and sum("anycity:" in ln for ln in lines) == 1, lines
    return lines[-1]


def test_the_base_class_as_model_is_refused_in_one_line_before_fit(tmp_path, capsys):
    """``--model AnyCityModule`` (the base, "not used directly") parsed, and fit then crashed with a 40-line
    MisconfigurationException ("No `training_step()` method defined")."""
    err = _one_line_error(["fit", "-c", QS, "--model", "AnyCityModule", "--data.root", str(tmp_path / "none"),
                           "--trainer.fast_dev_run", "1"], capsys)
    assert "model.class_path anycity.lit.AnyCityModule: the base class" in err
    assert "--model anycity.lit.ScaffoldModule (Stage I) or --model anycity.lit.RefinementModule (Stage II)" in err
    # the pose prior's own module is a LightningModule, but no stage: jsonargparse said "Expected a path"
    err = _one_line_error(["fit", "-c", QS, "--model", "anycity.lit.pose_prior.PosePriorModule", "--print_config"],
                          capsys)
    assert "PosePriorModule: the pose prior's pretraining module, which scripts/pose_prior.py runs" in err
    assert "anycity.lit.ScaffoldModule" in err and "anycity.lit.RefinementModule" in err
    from anycity.lit import RefinementModule, ScaffoldModule

    class MyStage1(ScaffoldModule):
        pass

    for ok in ("anycity.lit.ScaffoldModule", "RefinementModule", f"{__name__}.MyStage1"):
        globals()["MyStage1"] = MyStage1
        cli.check_model_class(ok)
    assert cli._model_class("RefinementModule") is RefinementModule


def test_a_config_before_the_subcommand_is_refused_unless_it_holds_subcommand_sections(tmp_path, capsys):
    """``anycity -c FILE fit`` read nothing of FILE (--print_config showed the defaults) or named its keys as
    unknown; jsonargparse reads only subcommand sections there."""
    err = _one_line_error(["-c", QS, "fit", "--print_config"], capsys)
    assert f"-c {QS} before the subcommand" in err and f"put -c after the subcommand: anycity fit -c {QS}" in err
    err = _one_line_error(["--config", QS], capsys)
    assert "with no subcommand" in err and "anycity fit -c" in err
    sections = tmp_path / "sections.yaml"
    sections.write_text("fit:\n  trainer:\n    max_steps: 7\n")
    cli.check_config_placement(["-c", str(sections), "fit", "-c", QS])
    cli.check_config_placement(["fit", "-c", QS])


def test_a_later_source_that_switches_the_model_class_names_the_keys_it_drops(monkeypatch):
    """jsonargparse keeps the init_args both classes take and silently drops the others."""
    said = cli.dropped_model_keys(["fit", "-c", QS2, "-c", QS])
    assert len(said) == 1, said
    assert said[0].startswith(f"--config {QS} switches model.class_path from RefinementModule to ScaffoldModule, "
                              "which does not take init_from, d2s_weight, pres_weight, reg_weight, d2s_depth_scale "
                              f"from {QS2}: they are not used;"), said
    said = cli.dropped_model_keys(["fit", "-c", QS, "--model.init_args.depth_weight", "0.5", "-c", QS2])
    assert len(said) == 1 and "does not take depth_weight from --model.init_args.depth_weight: it is not" in said[0]
    said = cli.dropped_model_keys(["fit", "-c", QS, "--model.lr", "1", "--model.warmup_steps=3",
                                   "--model.init_args.ray_weight", "2", "--model", "anycity.lit.RefinementModule"])
    assert len(said) == 1 and "does not take ray_weight from --model.init_args.ray_weight:" in said[0], said
    # the documented order, a Stage II config on its Stage I one: the Stage I settings are that config's own
    for chain in ([QS, QS2], ["configs/stage1.yaml", "configs/stage2.yaml"], [QS, "configs/debug/cpu.yaml", QS2],
                  [QS, "configs/ablations/scaffold_only.yaml"]):
        assert cli.dropped_model_keys(["fit", *[a for c in chain for a in ("-c", c)]]) == [], chain
    monkeypatch.setattr(cli, "build_cli", lambda *a, **k: None)
    with pytest.warns(UserWarning, match="switches model.class_path from RefinementModule to ScaffoldModule"):
        assert cli.main(["fit", "-c", QS2, "-c", QS]) == 0


def test_a_net_dict_on_the_command_line_that_drops_keys_is_named(tmp_path, monkeypatch):
    """``--model.init_args.net '{sh_degree: 2}'`` replaced the config's whole net with no word (a -c file's warns)."""
    said = cli.replaced_net_keys(["fit", "-c", QS, "--model.init_args.net", "{sh_degree: 2}"])
    assert said == ["--model.init_args.net {sh_degree: 2}: it replaces the model.init_args.net from "
                    f"{QS} whole, so camera_trunk_depth from {QS} is not used; repeat it in this value, or set "
                    "single keys with dotted overrides (--model.init_args.net.KEY VALUE), which merge"], said
    # dotted keys merge; a whole dict that keeps every key drops nothing (refinement.stage1_net_flags' form)
    assert cli.replaced_net_keys(["fit", "-c", QS, "--model.init_args.net.sh_degree", "2"]) == []
    assert cli.replaced_net_keys(["fit", "-c", QS, "--model.init_args.net={camera_trunk_depth: 2, sh_degree: 0}"]) == []
    # a dotted key, then a file whose net replaces the dict: named with its option
    overlay = tmp_path / "mine.yaml"
    overlay.write_text("model:\n  init_args:\n    net: {camera_trunk_depth: 2}\n")
    said = cli.replaced_net_keys(["fit", "-c", QS, "--model.init_args.net.sh_degree", "0", "-c", str(overlay)])
    assert len(said) == 1 and "so sh_degree from --model.init_args.net.sh_degree is not used" in said[0], said
    monkeypatch.setattr(cli, "build_cli", lambda *a, **k: None)
    with pytest.warns(UserWarning, match="camera_trunk_depth from configs/quickstart.yaml is not used"):
        assert cli.main(["fit", "-c", QS, "--model.init_args.net", "{sh_degree: 2}"]) == 0


@pytest.mark.parametrize("net", [{"video_prior": "wan2"}, {"refine_cameras": True}, {"wan_lora_rank": 8},
                                 {"inject_layers": [0, 1]}, {"pose_prior_mix": True}, {"wan_dir": "weights/Wan"}])
def test_stage1_refuses_stage2_net_keys(net):
    """They were accepted, stored in the checkpoint and never used (``video_prior: wan2``, which Stage II refuses)."""
    from anycity.lit import ScaffoldModule

    key = next(iter(net))
    with pytest.raises(ValueError, match=rf"^model\.net\.{key} .*: a Stage II option of the completion branch, which "
                                         r"Stage I \(ScaffoldModule\) does not build; drop it"):
        ScaffoldModule(preset="tiny", net=net)


def test_stage1_takes_stage2_keys_at_the_presets_values_and_the_list_is_complete():
    """configs/debug/cpu_ddp.yaml sets video_prior: small and inject_layers: null for either stage."""
    import dataclasses

    from anycity.lit import ScaffoldModule
    from anycity.lit.scaffold import STAGE2_NET_KEYS
    from anycity.models.presets import NetConfig

    m = ScaffoldModule(preset="tiny", net={"video_prior": "small", "inject_layers": None, "camera_trunk_depth": 2})
    assert m.net.completion is None and m.hparams.net["completion"] is False
    names = [f.name for f in dataclasses.fields(NetConfig)]
    assert set(STAGE2_NET_KEYS) == set(names[names.index("completion") + 1:])  # a new branch option is listed


def test_misplaced_model_keys_and_class_typos_are_named(tmp_path, capsys):
    """``init_arg`` read as an unknown top-level section, ``freeze: {pattern}`` lost its section and the suggestion,
    a class typo was offered the module ``anycity.lit.scaffold``, and a wrong type in a YAML ``net`` named only
    ``net``."""
    cases = [("model: {init_arg: {lr: 0.1}}", "unknown key model.init_arg (in model.init_arg.lr) in a --config file; "
              "did you mean model.init_args?"),
             (["--model.init_arg.lr", "0.1"], "unknown option --model.init_arg.lr; did you mean --model.init_args.lr?"),
             ("freeze: {pattern: [x]}", "unknown key freeze.pattern in a --config file; did you mean patterns?"),
             ("model: {init_args: {net: {camera_trunk_depth: 2, inject_layers: 3}}}",
              "model.init_args.net.inject_layers 3: not accepted; expected a list of integers or null"),
             (["--model", "anycity.lit.Scaffold"], "did you mean anycity.lit.ScaffoldModule?")]
    for extra, said in cases:
        if isinstance(extra, str):
            (tmp_path / "y.yaml").write_text(extra + "\n")
            extra = ["-c", str(tmp_path / "y.yaml")]
        err = _one_line_error(["fit", "-c", QS, *extra, "--print_config"], capsys)
        assert said in err, err


def test_test_without_a_model_names_the_run_config_or_the_classes(tmp_path, capsys):
    """``anycity test --ckpt_path X`` said "the following arguments are required: test.model", no fix."""
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"x")
    err = _one_line_error(["test", "--ckpt_path", str(ckpt)], capsys)
    assert "anycity test: no model given" in err and "-c <run folder>/config.yaml" in err
    assert "--model anycity.lit.ScaffoldModule (Stage I) or --model anycity.lit.RefinementModule (Stage II)" in err
    (tmp_path / "run" / "config.yaml").write_text("trainer: {}\n")
    assert f"-c {tmp_path / 'run' / 'config.yaml'}," in _one_line_error(["test", "--ckpt_path", str(ckpt)], capsys)


def test_a_checkpoint_path_under_home_is_found(tmp_path, monkeypatch):
    """``--ckpt_path=~/run.ckpt`` (no shell expands a ``~`` after ``=``) was "no such file" for a file that exists."""
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "run.ckpt").write_bytes(b"x")
    cli.check_input_files(["test", "--ckpt_path=~/run.ckpt"])
    with pytest.raises(FileNotFoundError, match="no such file"):
        cli.check_input_files(["test", "--ckpt_path=~/other.ckpt"])
