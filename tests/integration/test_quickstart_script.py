"""scripts/quickstart.py refuses shards made with other settings instead of silently training on them."""

import json

from helpers.scripts import load_script


def _quickstart():
    return load_script("quickstart")


def test_foreign_shards_stop_with_the_fix(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["quickstart.py"])
    data = tmp_path / "qs"
    data.mkdir()
    (data / "index.json").write_text("{}")  # shards of unknown origin
    assert _quickstart().main(["--data", str(data), "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert str(data) in err and "delete" in err and "--data NEW_DIR" in err
    # other synth settings are refused too; nothing was trained or written
    (data / "quickstart_data.json").write_text(json.dumps(["--scenes", "3"]))
    assert _quickstart().main(["--data", str(data), "--out", str(tmp_path / "runs")]) == 2
    assert not (tmp_path / "runs").exists()


def test_printed_tables_are_well_formed_markdown(capsys):
    """Every row of each table has the header's cells and width (the baseline rows used to miss a cell)."""
    from collections import defaultdict

    _quickstart().print_tables(defaultdict(lambda: 19.876))
    lines = capsys.readouterr().out.splitlines()
    tables, current = [], []
    for line in [*lines, ""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            tables, current = [*tables, current], []
    assert [len(t) for t in tables] == [6, 5]
    for t in tables:
        assert len({len(r) for r in t}) == 1 and len({r.count("|") for r in t}) == 1, "\n".join(t)


def test_an_option_it_does_not_know_stops_in_one_line_naming_its_own(tmp_path, capsys, monkeypatch):
    """A typo used to reach LightningCLI, which printed its whole usage; hyphenated spellings of the script's own
    flags are accepted, dotted overrides and their values (negative numbers too) still pass through."""
    import re

    import pytest

    monkeypatch.setattr("sys.argv", ["quickstart.py"])
    data = tmp_path / "qs"
    data.mkdir()
    (data / "index.json").write_text("{}")  # stops with code 2 after parsing, before any training
    base = ["--data", str(data), "--out", str(tmp_path / "runs")]
    for ok in (["--stage1-steps", "5", "--stage2-steps", "2"], ["--trainer.max_steps", "3", "--seed_everything=1"],
               ["--model.init_args.lr", "-1e-4", "--data.eval_batch_size=2"]):
        assert _quickstart().main([*base, *ok]) == 2, ok
    capsys.readouterr()
    for typo in ("--stage1-step", "--steps", "-x", "--.trainer"):
        with pytest.raises(SystemExit) as e:
            _quickstart().main([*base, typo, "3"])
        assert e.value.code == 2
        err = capsys.readouterr().err
        message = [line for line in err.splitlines() if "error:" in line]
        assert len(message) == 1 and f"unknown option {typo}:" in message[0], err
        usage = err.split("error:")[0]
        assert "LightningCLI" in message[0] and len(err.splitlines()) < 8, err
        for flag in set(re.findall(r"--\w+", usage)):  # every flag of the parser is named in the message
            assert flag in message[0], (flag, message[0])


def test_metrics_json_is_strict_json_when_a_protocol_gave_no_figure():
    """A figure its protocol did not give (e.g. ``eval_pose_align_steps 0``) is ``null``, not Python's ``NaN``
    token, which jq and ``JSON.parse`` refuse."""
    qs = _quickstart()
    metrics = qs.quickstart_metrics({"psnr_baseline": 18.0, "psnr_scaffold": 19.5, "psnr_refined": float("nan")}, 1.0)
    text = json.dumps(qs.json_safe(metrics), allow_nan=False)
    back = json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))
    assert back["scaffold_psnr"] == 19.5 and back["refined_psnr"] is None and back["scaffold_psnr_camrefine"] is None
    assert back["protocols"]["feedforward"].startswith("feed-forward")


class _Trained(Exception):
    """Raised by the stand-in for build_cli: the quickstart went on to train on the folder."""


def _stop_at_training(monkeypatch):
    import anycity.cli

    def build_cli(args, **kw):
        raise _Trained(args[args.index("--data.root") + 1])

    monkeypatch.setattr(anycity.cli, "build_cli", build_cli)


def test_the_stamp_is_tied_to_the_shards_it_was_made_with(tmp_path, capsys, monkeypatch):
    """`anycity data synth --overwrite` with other settings keeps quickstart_data.json; the quickstart used to train
    on the new shards. A stamp of the earlier format (the synth arguments only) is still accepted while index.json
    lists what they asked for, and upgraded."""
    import pytest

    from anycity.data.cli import data_main

    monkeypatch.setattr("sys.argv", ["quickstart.py"])
    _stop_at_training(monkeypatch)
    data = tmp_path / "qs"
    argv = ["--data", str(data), "--out", str(tmp_path / "runs"), "--scenes", "3", "--views", "8"]
    with pytest.raises(_Trained):  # generated, stamped, trained on
        _quickstart().main(argv)
    stamp = data / "quickstart_data.json"
    synth_args = ["--scenes", "3", "--views", "8", "--size", "48x48", "--trajectory", "orbit", "--supersample", "2"]
    stamp.write_text(json.dumps(synth_args) + "\n")  # what the earlier quickstart wrote: still good
    with pytest.raises(_Trained):
        _quickstart().main(argv)
    assert json.loads(stamp.read_text()) != synth_args  # upgraded
    assert data_main(["synth", "--out", str(data), "--overwrite", "--scenes", "4", "--views", "8", "--size", "32x32",
                      "--workers", "1"]) in (0, None)
    capsys.readouterr()
    assert _quickstart().main(argv) == 2
    err = capsys.readouterr().err
    assert "index.json changed" in err and "delete" in err and len(err.splitlines()) == 1, err
    stamp.write_text(json.dumps(synth_args) + "\n")  # an earlier-format stamp over foreign shards
    assert _quickstart().main(argv) == 2
    assert "index.json lists 4 scenes, not 3" in capsys.readouterr().err


def test_a_bad_override_stops_in_one_line(tmp_path, capsys, monkeypatch):
    """A value `anycity fit` refuses in one line (exit 2) used to reach the user as a 51-line traceback."""
    monkeypatch.setattr("sys.argv", ["quickstart.py"])
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    argv = ["--data", str(tmp_path / "qs"), "--out", str(tmp_path / "runs"), "--scenes", "3", "--views", "8",
            "--data.num_context", "12"]
    capsys.readouterr()
    assert _quickstart().main(argv) == 2
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "error" in ln.lower()]  # Lightning's INFO lines come before it
    assert len(lines) == 1 and "num_context" in lines[0] and "Traceback" not in err, err


def test_metrics_json_names_the_protocols_the_test_run_ran():
    """The labels were constants: with camera_refine_steps 0 the targetalign figure (which then starts from the
    network's cameras) still said "after camrefine", and eval_align sim3 was still "relative to the first context
    view"; they follow the test run's hyperparameters."""
    qs = _quickstart()
    m = {"psnr_baseline": 18.0, "psnr_scaffold": 19.5}
    quickstart = {"eval_align": "none", "camera_refine_steps": 50, "eval_pose_align_steps": 50}
    assert qs.quickstart_metrics(m, 1.0, quickstart)["protocols"] == {
        (k.lstrip("_") or "feedforward"): v for k, v in qs.PROTOCOLS.items()}
    other = qs.quickstart_metrics(m, 1.0, {"eval_align": "sim3", "camera_refine_steps": 0,
                                           "eval_pose_align_steps": 50})["protocols"]
    assert sorted(other) == ["feedforward", "targetalign"]
    assert "Sim(3) fit" in other["feedforward"] and "first context view" not in other["feedforward"]
    assert other["targetalign"].startswith("from the network's cameras") and "camrefine" not in other["targetalign"]
    none = qs.quickstart_metrics(m, 1.0, {**quickstart, "eval_pose_align_steps": 0})["protocols"]
    assert sorted(none) == ["camrefine", "feedforward"]
