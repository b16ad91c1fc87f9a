"""scripts/stage2_tables.py: each row is its own Stage II run with its overrides, the tables come from the test
figures, finished rows are reused and foreign ones refused."""

import json
import math
import os
import shutil
import sys
from pathlib import Path

import pytest
from helpers.scripts import anycity_in_process, load_script

from anycity.cli import build_cli


def _script():
    return load_script("stage2_tables")


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["stage2_tables.py"])


def _tiny(tmp_path):
    every = tmp_path / "ckpt_every_2.yaml"
    every.write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelCheckpoint\n"
                     "    init_args: {save_last: true, save_top_k: 0, every_n_train_steps: 2}\n")
    return ["--data.image_size", "[32, 32]", "--data.num_context", "2", "--data.num_targets", "1",
            "--data.num_dense", "2", "--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1",
            "--model.init_args.warmup_steps", "1", "--model.init_args.render_backend", "torch",
            "--model.init_args.camera_refine_steps", "2", "--model.init_args.eval_pose_align_steps", "0"], every


def test_rows_tables_reuse_and_refusal(tiny_shards, tmp_path, capsys):
    extra, every = _tiny(tmp_path)
    s1 = tmp_path / "s1"
    build_cli(["fit", "-c", "configs/quickstart.yaml", "-c", str(every), "--data.root", str(tiny_shards), *extra,
               "--trainer.max_steps", "2", "--trainer.default_root_dir", str(s1),
               "--trainer.logger.init_args.save_dir", str(s1)])
    ckpt = s1 / "checkpoints" / "last.ckpt"
    out = tmp_path / "tables"
    argv = ["--stage1", str(ckpt), "--data", str(tiny_shards), "--out", str(out), "--steps", "2",
            "--rows", "full,tokens,frozen_all",
            "--configs", "configs/quickstart.yaml", "configs/quickstart_stage2.yaml", str(every), *extra]
    mod = _script()
    mod._anycity = anycity_in_process  # the launches themselves: test_each_command_is_its_own_anycity_process
    assert mod.main(argv) == 0

    # the row's overrides reached its run
    cfg = (out / "tokens" / "fit" / "config.yaml").read_text()
    assert "video_prior: none" in cfg and "d2s_weight: 0" in cfg
    assert "video_prior: none" not in (out / "full" / "fit" / "config.yaml").read_text()

    res = json.loads((out / "tables.json").read_text())
    assert set(res["rows"]) == {"scaffold", "full", "tokens"}
    for name, fig in res["rows"].items():
        for key in ("psnr_obs", "psnr_weak", "psnr_obs_camrefine", "psnr_weak_camrefine"):
            assert math.isfinite(fig[key]), (name, key)
    assert set(res["goal"]) == {"full"}
    assert res["scaffold_spread_db"] == 0.0  # Stage II leaves the frozen scaffold's figures untouched
    full = json.loads((out / "full" / "metrics.json").read_text())
    assert res["rows"]["scaffold"] == full["scaffold"] and res["rows"]["full"] == full["refined"]
    for protocol, sfx in (("feed-forward", ""), ("camrefine", "_camrefine")):
        g = res["goal"]["full"][protocol]
        d_weak = full["refined"][f"psnr_weak{sfx}"] - full["scaffold"][f"psnr_weak{sfx}"]
        d_obs = full["refined"][f"psnr_obs{sfx}"] - full["scaffold"][f"psnr_obs{sfx}"]
        assert g["weak_gain_db"] == pytest.approx(d_weak) and g["obs_gain_db"] == pytest.approx(d_obs)
        assert g["reached"] == (d_weak >= 0.5 and d_obs >= -0.2)
    md = (out / "tables.md").read_text()
    assert "| + completion tokens (no prior, no D2S) | " in md and "| + D2S | not run: not in --rows |" in md
    assert "frozen-all (its own Stage I) | not run: pass --frozen_all_stage1" in md

    # a finished row is reused; one made with other settings is refused, naming its directory and the fix
    stamp = (out / "full" / "metrics.json").stat().st_mtime_ns
    capsys.readouterr()
    assert mod.main(argv) == 0
    assert "full: reusing" in capsys.readouterr().out
    assert (out / "full" / "metrics.json").stat().st_mtime_ns == stamp
    with pytest.raises(SystemExit, match=f"{out / 'full'} holds a run made with other settings.*delete"):
        mod.main([*argv[:argv.index("--steps") + 1], "3", *argv[argv.index("--steps") + 2:]])
    os.utime(ckpt, ns=(stamp, stamp + 1))  # Stage I trained again to the same path: the rows are stale
    with pytest.raises(SystemExit, match=f"{out / 'full'} holds a run made with other settings.*delete"):
        mod.main(argv)


def test_each_command_is_its_own_anycity_process(monkeypatch):
    """A row's fit and test each run as `python -m anycity.cli CMD ARGS` (so --trainer.devices 2 launches DDP), and a
    failed one stops the script naming the row and the command."""
    mod, launched, rc = _script(), [], [0]

    class Launch:
        def __init__(self, argv):
            launched.append(argv)

        def wait(self):
            return rc[0]

    monkeypatch.setattr(mod.subprocess, "Popen", Launch)
    mod._anycity("fit", ["-c", "configs/stage2.yaml", "--trainer.devices", "2"], "full")
    assert launched == [[sys.executable, "-m", "anycity.cli", "fit", "-c", "configs/stage2.yaml",
                         "--trainer.devices", "2"]]
    rc[0] = 3
    with pytest.raises(SystemExit, match="row tokens: `anycity test` failed \\(exit 3\\)"):
        mod._anycity("test", [], "tokens")


def test_bad_rows_and_missing_checkpoint(tmp_path, capsys):
    mod = _script()
    assert mod.main(["--rows", "full,wo_prior", "--out", str(tmp_path / "o")]) == 2
    assert "wo_prior" in capsys.readouterr().err
    assert mod.main(["--rows", "full", "--stage1", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "none.ckpt" in err and "--stage1" in err
    assert mod.main(["--rows", "frozen_aa", "--out", str(tmp_path / "o")]) == 2  # its flag missing: nothing to run
    assert "pass --frozen_aa_stage1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_goal_and_own_scaffold_lines():
    mod = _script()

    def fig(obs, weak):
        return {"psnr_obs": obs, "psnr_weak": weak, "psnr_obs_camrefine": obs + 1, "psnr_weak_camrefine": weak + 1}

    scaffold = fig(19.0, 18.0)
    results = {
        "full": {"refined": fig(18.85, 18.6), "scaffold": scaffold},     # weak +0.6, observed -0.15: reached
        "cameras": {"refined": fig(18.7, 18.6), "scaffold": scaffold},   # weak +0.6, observed -0.3: not reached
        "frozen_all": {"refined": fig(17.0, 16.0), "scaffold": fig(16.5, 15.5)},
    }
    md, res = mod.tables(results, scaffold, {"tokens": "not in --rows"})
    assert res["goal"]["full"]["camrefine"]["reached"] and res["goal"]["full"]["feed-forward"]["reached"]
    assert not res["goal"]["cameras"]["camrefine"]["reached"]
    assert res["goal"]["cameras"]["feed-forward"]["obs_gain_db"] == pytest.approx(-0.3)
    assert "- the frozen-all row's own scaffold: 16.500 / 15.500 feed-forward, 17.500 / 16.500 camrefine" in md
    assert "| full | 18.850 / 18.600 | 19.850 / 19.600 |" in md  # Table 3 names the full model "full"
    assert "| scaffold only | 19.000 / 18.000 | 20.000 / 19.000 |" in md
    assert "- goal, the full model, camrefine: weak +0.60 dB" in md and "NOT reached" in md


def _fake_anycity(cmd, args, row):
    """A stand-in launch: no training; the test run leaves a CSV log with one figure."""
    if cmd == "test":
        d = Path(args[args.index("--trainer.default_root_dir") + 1])
        d.mkdir(parents=True, exist_ok=True)
        (d / "metrics.csv").write_text("test/psnr_refined,test/psnr_obs_refined\n20.0,19.0\n")


def test_a_changed_pose_prior_or_config_file_makes_the_row_stale(tiny_shards, tmp_path):
    """The rows' settings name the --pose_prior and --configs files by path only; one rewritten in place (a prior
    trained again, an edited config) used to have the row reused."""
    mod = _script()
    mod._anycity = _fake_anycity
    (tmp_path / "stage1.ckpt").write_bytes(b"x")
    prior, cfg = tmp_path / "prior.pt", tmp_path / "extra.yaml"
    prior.write_bytes(b"6000-step prior")
    cfg.write_text("seed_everything: 1\n")
    out = tmp_path / "o"
    argv = ["--stage1", str(tmp_path / "stage1.ckpt"), "--rows", "prior_mix", "--pose_prior", str(prior),
            "--out", str(out), "--configs", "configs/quickstart.yaml", str(cfg), "--data", str(tiny_shards)]
    assert mod.main(argv) == 0
    assert mod.main(argv) == 0  # unchanged: reused
    stale = f"{out / 'prior_mix'} holds a run made with other settings.*delete"
    prior.write_bytes(b"12000-step prior, trained again")
    with pytest.raises(SystemExit, match=stale):
        mod.main(argv)
    shutil.rmtree(out)
    assert mod.main(argv) == 0
    cfg.write_text("seed_everything: 2\n")
    st = cfg.stat()
    os.utime(cfg, ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(SystemExit, match=stale):
        mod.main(argv)


def _stub_run(tmp_path, tiny_shards):
    """The script with stand-in launches, a Stage I file, a copy of the shard set, and the argv of the full row."""
    mod = _script()
    mod._anycity = _fake_anycity
    (tmp_path / "stage1.ckpt").write_bytes(b"x")
    data = tmp_path / "data"
    shutil.copytree(tiny_shards, data)
    return mod, data, ["--stage1", str(tmp_path / "stage1.ckpt"), "--rows", "full", "--out", str(tmp_path / "o"),
                       "--data", str(data)]


def test_a_rebuilt_shard_set_makes_the_row_stale_and_an_older_row_is_adopted_once(tiny_shards, tmp_path, capsys):
    """A row's settings named --data by path only: shards written again there (other scenes) had the row reused."""
    mod, data, argv = _stub_run(tmp_path, tiny_shards)
    assert mod.main(argv) == 0
    done = tmp_path / "o" / "full" / "metrics.json"
    capsys.readouterr()
    assert mod.main(argv) == 0 and "full: reusing" in capsys.readouterr().out
    rebuilt = json.loads((data / "index.json").read_text())
    rebuilt["scenes"] = rebuilt["scenes"][:2]
    (data / "index.json").write_text(json.dumps(rebuilt))  # what `anycity data synth --overwrite` does last
    stale = f"{tmp_path / 'o' / 'full'} holds a run made with other settings \\(differing: data_index;.*delete"
    with pytest.raises(SystemExit, match=stale):
        mod.main(argv)
    st = (data / "index.json").stat()
    assert json.loads(done.read_text())["settings"]["data_index"] != [st.st_size, st.st_mtime_ns]

    # a row an earlier version wrote (no data_index): reused once with a line saying so, then held to the data
    older = json.loads(done.read_text())
    del older["settings"]["data_index"]
    done.write_text(json.dumps(older))
    assert mod.main(argv) == 0
    said = capsys.readouterr().out
    assert "full: reusing" in said and "made before rows recorded --data's index.json" in said
    assert json.loads(done.read_text())["settings"]["data_index"] == [st.st_size, st.st_mtime_ns]  # stamped
    assert mod.main(argv) == 0 and "made before" not in capsys.readouterr().out
    os.utime(data / "index.json", ns=(1, 1))
    with pytest.raises(SystemExit, match=stale):
        mod.main(argv)
    assert mod.main([*argv[:-1], str(tmp_path / "nowhere")]) == 2
    assert "--data" in capsys.readouterr().err


def test_metrics_json_is_written_whole_and_a_damaged_one_is_an_unfinished_row(tiny_shards, tmp_path, monkeypatch):
    """metrics.json was written in place: a kill mid-write left half a file, and the rerun died in json.loads with a
    traceback."""
    from helpers.faults import fail_writes_midway

    mod, _, argv = _stub_run(tmp_path, tiny_shards)
    row = tmp_path / "o" / "full"
    row.mkdir(parents=True)
    (row / "metrics.json").write_text('{"settings": {"stage1": "')  # what an older version's kill could leave
    with pytest.raises(SystemExit, match=f"^error: {row} holds an unfinished run \\({row / 'metrics.json'} is "
                                         f"unreadable: JSONDecodeError\\): delete {row} or pass --out NEW_DIR$"):
        mod.main(argv)
    shutil.rmtree(row)
    with monkeypatch.context() as m:
        fail_writes_midway(m, "metrics.json")
        with pytest.raises(OSError, match="disk full writing .*metrics.json"):
            mod.main(argv)
    assert (row / "test" / "metrics.csv").is_file() and not (row / "metrics.json").exists()  # no half file


FAKE_ANYCITY = """#!{python}
import os, signal, sys, time
os.dup2(os.open(os.devnull, os.O_WRONLY), 2)  # the script's stderr pipe closes when the script ends
def stop(signum, frame):
    open(os.environ["FAKE_SIGNALS"], "a").write(f"{{signum}}\\n")
    sys.exit(143)
signal.signal(signal.SIGTERM, stop)
open(os.environ["FAKE_PID"], "w").write(str(os.getpid()))
time.sleep(60)
"""
DRIVER = """import sys
sys.path.insert(0, sys.argv[1])
from helpers.scripts import load_script
mod = load_script("stage2_tables")
mod.sys.executable = sys.argv[2]  # the rows' `python -m anycity.cli fit ...`: a stand-in that waits for a signal
sys.exit(mod.main(sys.argv[3:]))
"""


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_sigterm_to_the_script_alone_reaches_its_running_anycity(tiny_shards, tmp_path):
    """A SIGTERM to the script's PID alone (a single-PID kill, a preemption) ended the script and left its
    `anycity fit` training with no parent."""
    import signal
    import subprocess
    import time

    fake, pid, got = tmp_path / "anycity", tmp_path / "child.pid", tmp_path / "child.signals"
    fake.write_text(FAKE_ANYCITY.format(python=sys.executable))
    fake.chmod(0o755)
    (tmp_path / "stage1.ckpt").write_bytes(b"x")
    script = subprocess.Popen(
        [sys.executable, "-c", DRIVER, str(Path(__file__).parents[1]), str(fake), "--stage1",
         str(tmp_path / "stage1.ckpt"), "--rows", "full", "--out", str(tmp_path / "o"), "--data", str(tiny_shards)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "FAKE_PID": str(pid), "FAKE_SIGNALS": str(got)})
    child = None
    try:
        deadline = time.monotonic() + 60
        while not (pid.is_file() and pid.read_text()) and time.monotonic() < deadline:
            time.sleep(0.05)
        child = int(pid.read_text())
        script.send_signal(signal.SIGTERM)
        _, err = script.communicate(timeout=30)
        assert script.returncode == 143, err
        assert got.read_text().split() == [str(int(signal.SIGTERM))]  # passed on, and waited for
        assert err.strip().splitlines()[-1] == (
            f"stage2_tables: row full: stopped by SIGTERM during `anycity fit` (passed on to it); delete "
            f"{tmp_path / 'o' / 'full'} and rerun the same command (a row is not resumed)")
    finally:
        script.kill()
        script.wait()
        if child is not None:
            try:
                os.kill(child, signal.SIGKILL)  # left running by the old script
            except ProcessLookupError:
                pass
