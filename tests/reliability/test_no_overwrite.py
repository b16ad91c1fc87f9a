"""Every command leaves earlier runs' logs, checkpoints and outputs intact (moved aside or refused)."""

import contextlib
import os
import re
import subprocess
import sys
import warnings

import numpy as np
import pytest
from PIL import Image

from anycity.cli import build_cli, main
from anycity.data.cli import data_main
from anycity.lit.keep import free_name

from .harness import REPO


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])


def _args(shards, run, extra=()):
    return ["-c", str(REPO / "configs/quickstart.yaml"), "--data.root", str(shards), "--data.image_size", "[32, 32]",
            "--data.num_context", "2", "--data.num_targets", "1", "--data.num_dense", "2",
            "--trainer.max_steps", "1", "--trainer.val_check_interval", "1", "--trainer.limit_val_batches", "1",
            "--trainer.limit_test_batches", "1", "--trainer.limit_predict_batches", "1",
            "--trainer.default_root_dir", str(run), "--trainer.logger.init_args.save_dir", str(run),
            "--model.init_args.warmup_steps", "1", "--model.init_args.render_backend", "torch",
            "--model.init_args.camera_refine_steps", "0", "--model.init_args.eval_pose_align_steps", "0", *extra]


def test_fit_validate_test_predict_keep_earlier_runs(tiny_shards, tmp_path):
    run = tmp_path / "run"
    ck = ["-c", str(tmp_path / "ck.yaml")]
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    build_cli(["fit", *_args(tiny_shards, run, ck)])
    first = (run / "checkpoints" / "last.ckpt").read_bytes()
    metrics1 = (run / "metrics.csv").read_text()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_cli(["fit", *_args(tiny_shards, run, ck + ["--seed_everything", "1"])])  # a fresh second fit, same dir
    # nothing is deleted, so Lightning's "previous log files ... will be deleted" must not be shown
    assert not [w for w in caught if "will be deleted" in str(w.message)]
    assert (run / "checkpoints.1" / "last.ckpt").read_bytes() == first  # the first run's checkpoint is kept
    assert (run / "metrics.1.csv").read_text() == metrics1 and (run / "config.1.yaml").is_file()
    ckpt = str(run / "checkpoints" / "last.ckpt")
    training = {f: (run / f).read_bytes() for f in ("metrics.csv", "config.yaml", "hparams.yaml")}
    for cmd in ("validate", "test", "test"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            build_cli([cmd, *_args(tiny_shards, run), "--ckpt_path", ckpt])
        # in a training run's folder, evaluation writes to its own subfolder: the training's files stay as they are
        assert {f: (run / f).read_bytes() for f in training} == training, cmd
        assert (run / cmd / "config.yaml").is_file() and (run / cmd / "metrics.csv").is_file(), cmd
        # evaluation writes no checkpoint, so Lightning's notes on restoring the callbacks' state are not shown
        assert not [str(w.message) for w in caught if "ckpt_path`, callbacks" in str(w.message)
                    or "dirpath has changed" in str(w.message)], cmd
    assert (run / "test" / "metrics.1.csv").is_file()  # the second test kept the first one's
    assert not list(run.glob("metrics.2.csv")) and not list(run.glob("config.2.yaml"))
    build_cli(["predict", *_args(tiny_shards, run), "--ckpt_path", ckpt])
    assert list((run / "predict" / "predictions").rglob("scene.ply")) and not (run / "predictions").exists()
    assert {f: (run / f).read_bytes() for f in training} == training
    out = tmp_path / "export"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_cli(["predict", *_args(tiny_shards, run), "--ckpt_path", ckpt, "--export.out_dir", str(out)])
    assert not [str(w.message) for w in caught if "batch indices" in str(w.message)]  # the export does not use them
    plys = sorted(p.relative_to(out) for p in out.rglob("scene.ply"))
    first_ply = (out / plys[0]).read_bytes()
    build_cli(["predict", *_args(tiny_shards, run), "--ckpt_path", ckpt, "--export.out_dir", str(out)])
    assert (tmp_path / "export.1" / plys[0]).read_bytes() == first_ply  # the first export is kept
    assert (out / plys[0]).is_file()

    # photo folders: each scene has its own folder, so a second scene joins the first; a rerun moves only its own
    rng = np.random.default_rng(0)
    for scene in ("farm", "beach"):
        (tmp_path / scene / "images").mkdir(parents=True)
        for i in range(3):
            Image.fromarray(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)).save(
                tmp_path / scene / "images" / f"{i}.png")
    photos = tmp_path / "photos_out"
    for scene in ("farm", "beach", "farm"):
        build_cli(["predict", *_args(tiny_shards, run), "--ckpt_path", ckpt, "--export.out_dir", str(photos),
                   "--data.predict_images", str(tmp_path / scene / "images")])
    assert sorted(p.name for p in photos.iterdir()) == ["beach", "farm", "farm.1"]
    assert all((photos / d / "scene.ply").is_file() for d in ("beach", "farm", "farm.1"))


def test_data_synth_refuses_to_overwrite_without_the_flag(tmp_path):
    args = ["synth", "--out", str(tmp_path / "d"), "--scenes", "2", "--views", "4", "--size", "16x16",
            "--workers", "1"]
    data_main(args)
    index = (tmp_path / "d" / "index.json").read_bytes()
    with pytest.raises(FileExistsError, match="--overwrite"):
        data_main(args)
    assert (tmp_path / "d" / "index.json").read_bytes() == index
    data_main(args + ["--overwrite"])


def test_free_name(tmp_path):
    (tmp_path / "m.csv").write_text("a")
    (tmp_path / "m.1.csv").write_text("b")
    assert free_name(tmp_path / "m.csv") == tmp_path / "m.2.csv"
    assert free_name(tmp_path / "checkpoints") == tmp_path / "checkpoints.1"


def test_free_name_skips_a_kept_folder(tmp_path):
    """A kept folder (checkpoints.1 from an earlier run) is taken, like a kept file: the next free name is .2."""
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints.1").mkdir()
    assert free_name(tmp_path / "checkpoints") == tmp_path / "checkpoints.2"


def test_a_run_that_fails_before_its_first_step_leaves_the_checkpoints_and_exports_where_they_were(tiny_shards,
                                                                                                     tmp_path, caplog):
    """They used to be moved aside before anything was checked: a wrong image size, a fast_dev_run or a photo that
    does not decode left no ``checkpoints/last.ckpt`` (``--ckpt_path last`` then trained from scratch) and no scene."""
    run = tmp_path / "run"
    ck = ["-c", str(tmp_path / "ck.yaml")]
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    with caplog.at_level("INFO"):
        build_cli(["fit", *_args(tiny_shards, run, ck)])
    last = run / "checkpoints" / "last.ckpt"
    first = last.read_bytes()
    assert f"anycity: last checkpoint {last} (--ckpt_path last resumes from it)" in caplog.text
    with pytest.raises(ValueError, match="multiples of the patch size"):
        build_cli(["fit", *_args(tiny_shards, run, [*ck, "--data.image_size", "[36, 36]"])])
    logs = {f: (run / f).read_bytes() for f in ("config.yaml", "metrics.csv", "hparams.yaml")}
    files = sorted(run.iterdir())
    build_cli(["fit", *_args(tiny_shards, run, [*ck, "--trainer.fast_dev_run", "true"])])
    assert last.read_bytes() == first and not (run / "checkpoints.1").exists()
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.ckpt"]  # fast_dev_run wrote none
    # nor any log file (its logger is a dummy): the training's config.yaml, metrics.csv and hparams.yaml stay
    assert {f: (run / f).read_bytes() for f in logs} == logs and sorted(run.iterdir()) == files

    # a fresh fit that takes a step does move them aside (and writes its own)
    build_cli(["fit", *_args(tiny_shards, run, [*ck, "--seed_everything", "1"])])
    assert (run / "checkpoints.1" / "last.ckpt").read_bytes() == first and last.read_bytes() != first
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last.ckpt"]  # not last-v1.ckpt

    photos, out = tmp_path / "farm" / "images", tmp_path / "out"
    photos.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for i in range(3):
        Image.fromarray(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8)).save(photos / f"{i}.jpg")
    predict = ["predict", *_args(tiny_shards, run), "--ckpt_path", str(last), "--export.out_dir", str(out),
               "--data.predict_images", str(photos)]
    build_cli(predict)
    ply = (out / "farm" / "scene.ply").read_bytes()
    (photos / "3.jpg").write_bytes((photos / "0.jpg").read_bytes()[:200])  # a truncated photo
    with pytest.raises(ValueError, match="3.jpg"):
        build_cli(predict)
    assert (out / "farm" / "scene.ply").read_bytes() == ply and sorted(p.name for p in out.iterdir()) == ["farm"]
    (photos / "3.jpg").unlink()
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(NotADirectoryError, match="--export.out_dir .*a_file is a file, not a folder"):
        build_cli([*predict[:-4], "--export.out_dir", str(tmp_path / "a_file" / "out"), *predict[-2:]])
    # the export folder the user's photos are in: refused before the network runs (it was moved aside, photos too)
    with pytest.raises(ValueError, match=r"--export.out_dir: the scene folder .*farm would hold the photos .*pass an "
                                         "--export.out_dir outside it"):
        build_cli([*predict[:-4], "--export.out_dir", str(tmp_path), *predict[-2:]])
    assert sorted(p.name for p in photos.iterdir()) == ["0.jpg", "1.jpg", "2.jpg"]
    # a scene folder of someone else's files: refused, not moved aside and not written into
    (tmp_path / "mine" / "farm").mkdir(parents=True)
    (tmp_path / "mine" / "farm" / "notes.txt").write_text("not a predict output")
    with pytest.raises(ValueError, match=r"--export.out_dir: .*mine/farm holds files `anycity predict` did not write"):
        build_cli([*predict[:-4], "--export.out_dir", str(tmp_path / "mine"), *predict[-2:]])
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["farm"]
    assert sorted(p.name for p in (tmp_path / "mine" / "farm").iterdir()) == ["notes.txt"]


def test_evaluation_without_a_logger_leaves_the_training_config_where_it_was(tiny_shards, tmp_path):
    """With ``--trainer.logger false`` a predict/test run in a training run's folder wrote its ``config.yaml`` there,
    and the training's own was moved to ``config.1.yaml``; it goes to ``<run>/<subcommand>/`` as with a logger."""
    run = tmp_path / "run"
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    build_cli(["fit", *_args(tiny_shards, run, ["-c", str(tmp_path / "ck.yaml")])])
    training = (run / "config.yaml").read_bytes()
    files = sorted(p.name for p in run.iterdir())
    ckpt = str(run / "checkpoints" / "last.ckpt")
    for cmd in ("predict", "test"):
        build_cli([cmd, *_args(tiny_shards, run), "--ckpt_path", ckpt, "--trainer.logger", "false"])
        assert (run / "config.yaml").read_bytes() == training and not (run / "config.1.yaml").exists(), cmd
        assert (run / cmd / "config.yaml").is_file(), cmd
    assert list((run / "predict" / "predictions").rglob("scene.ply"))
    assert sorted(p.name for p in run.iterdir()) == sorted([*files, "predict", "test"])
    # --ckpt_path hpc is the training folder's newest hpc_ckpt_N.ckpt, not one in <run>/test/, where this run writes
    (run / "hpc_ckpt_1.ckpt").write_bytes((run / "checkpoints" / "last.ckpt").read_bytes())
    cli = build_cli(["test", *_args(tiny_shards, run), "--ckpt_path", "hpc", "--trainer.logger", "false"])
    assert cli.config_init["test"]["ckpt_path"] == str(run / "hpc_ckpt_1.ckpt")
    assert (run / "test" / "config.yaml").is_file()


# A run lock taken as anycity takes it (an exclusive flock on the file, which names the holder), by another process.
_HOLD = ("import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644); "
         "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB); "
         "os.write(fd, f'{sys.argv[2]} (pid {os.getpid()} on here)'.encode()); print('held', flush=True); "
         "sys.stdin.read()")


@contextlib.contextmanager
def _held(lock, subcommand="fit"):
    """Another process holding ``lock`` as a running ``anycity <subcommand>`` does, until the block ends."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(lock), subcommand], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        yield p.pid
    finally:
        p.stdin.close()
        p.wait(timeout=30)


def _tree(folder):
    """Every file under ``folder`` with its bytes (the lock file aside)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not p.name.endswith(".anycity-run.lock")}


@pytest.mark.skipif(sys.platform == "win32", reason="no flock: runs are not guarded")
def test_a_second_fit_in_a_running_fits_folder_is_refused_and_moves_nothing(tiny_shards, tmp_path, capsys):
    """Two fits with one default_root_dir each moved the other's live checkpoints/ aside, wrote last.ckpt into one
    folder and interleaved metrics.csv; the second now stops in one line naming the folder, the run and the fix."""
    run = tmp_path / "run"
    build_cli(["fit", *_args(tiny_shards, run)])
    (run / "checkpoints").mkdir(exist_ok=True)
    (run / "checkpoints" / "last.ckpt").write_bytes(b"the running fit's")
    before = _tree(run)
    assert not (run / ".anycity-run.lock").exists()  # a finished run leaves no lock file
    with _held(run / ".anycity-run.lock") as pid:
        assert main(["fit", *_args(tiny_shards, run)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert f"{run}: another anycity fit (pid {pid} on here) is writing there; wait for it to end, or pass another " \
           "--trainer.default_root_dir" in err
    assert _tree(run) == before and not list(run.glob("*.1*"))
    build_cli(["fit", *_args(tiny_shards, run)])  # the lock is free again: a fresh fit moves the earlier run aside
    assert (run / "config.1.yaml").is_file() and not (run / ".anycity-run.lock").exists()


@pytest.mark.skipif(sys.platform == "win32", reason="no flock: runs are not guarded")
def test_evaluation_started_while_a_fresh_fit_runs_leaves_its_files_alone(tiny_shards, tmp_path, capsys):
    """A fresh fit has moved its earlier checkpoints to checkpoints.1/ and written none yet: a ``test`` there took
    the folder for its own, moved the fit's config.yaml and metrics.csv aside and broke its log."""
    run = tmp_path / "run"
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    build_cli(["fit", *_args(tiny_shards, run, ["-c", str(tmp_path / "ck.yaml")])])
    (run / "checkpoints").rename(run / "checkpoints.1")  # what the running fit's first step did
    ckpt = tmp_path / "earlier.ckpt"
    ckpt.write_bytes((run / "checkpoints.1" / "last.ckpt").read_bytes())
    training = _tree(run)
    with _held(run / ".anycity-run.lock"):
        build_cli(["test", *_args(tiny_shards, run), "--ckpt_path", str(run / "checkpoints.1" / "last.ckpt")])
        now = _tree(run)
        assert all(now.get(f) == b for f, b in training.items()) and (run / "test" / "metrics.csv").is_file()
        # no checkpoint in the folder at all (a first fit before its first one): the fit's lock tells
        (run / "checkpoints.1").rename(tmp_path / "aside")
        build_cli(["predict", *_args(tiny_shards, run), "--ckpt_path", str(ckpt)])
        assert list((run / "predict" / "predictions").rglob("scene.ply"))
    assert {f: (run / f).read_bytes() for f in ("config.yaml", "metrics.csv", "hparams.yaml")} == \
        {f: training[f] for f in ("config.yaml", "metrics.csv", "hparams.yaml")}
    assert not list(run.glob("*.1.*")) and not list(run.glob("*.2.*"))
    # two evaluations in one folder (its own, not a training's): the second is refused, nothing moved
    ev = tmp_path / "ev"
    build_cli(["test", *_args(tiny_shards, ev), "--ckpt_path", str(ckpt)])
    before = _tree(ev)
    with _held(ev / ".anycity-run.lock", "test") as pid:
        assert main(["test", *_args(tiny_shards, ev), "--ckpt_path", str(ckpt)]) == 2
    assert f"{ev}: another anycity test (pid {pid} on here) is writing there" in capsys.readouterr().err
    assert _tree(ev) == before


@pytest.mark.skipif(sys.platform == "win32", reason="no flock: runs are not guarded")
def test_a_shard_set_predict_does_not_move_aside_an_export_another_predict_writes(tiny_shards, tmp_path, capsys):
    """A shard-set predict moves its whole --export.out_dir aside: it did so under another predict writing there."""
    out = tmp_path / "out"
    (out / "scene_a").mkdir(parents=True)
    (out / "scene_a" / "scene.ply").write_bytes(b"being written")
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    build_cli(["fit", *_args(tiny_shards, tmp_path / "run", ["-c", str(tmp_path / "ck.yaml")])])
    with _held(tmp_path / ".out.anycity-run.lock", "predict") as pid:
        assert main(["predict", *_args(tiny_shards, tmp_path / "p"), "--ckpt_path", str(ckpt),
                     "--export.out_dir", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{out}: another anycity predict (pid {pid} on here) is writing there; " \
                                          "wait for it to end, or pass another --export.out_dir" in err, err
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("out")) == ["out"]
    assert _tree(out) == {"scene_a/scene.ply": b"being written"}


def test_moving_aside_never_replaces_a_name_another_run_took_meanwhile(tmp_path, monkeypatch):
    """``move_aside`` chose a free name, then renamed onto it: a file another process moved there in between was
    silently replaced."""
    from anycity.lit import keep

    (tmp_path / "config.yaml").write_text("mine")
    (tmp_path / "config.1.yaml").write_text("the other run's")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_text("mine")
    (tmp_path / "checkpoints.1").mkdir()
    (tmp_path / "checkpoints.1" / "last.ckpt").write_text("the other run's")
    stale = iter([tmp_path / "config.1.yaml", tmp_path / "checkpoints.1"])  # free when chosen, taken at the rename
    real = keep.free_name
    monkeypatch.setattr(keep, "free_name", lambda p: next(stale, None) or real(p))
    assert keep.move_aside(tmp_path / "config.yaml") == tmp_path / "config.2.yaml"
    assert keep.move_aside(tmp_path / "checkpoints") == tmp_path / "checkpoints.2"
    assert (tmp_path / "config.1.yaml").read_text() == "the other run's" == \
        (tmp_path / "checkpoints.1" / "last.ckpt").read_text()
    assert (tmp_path / "config.2.yaml").read_text() == "mine" == (tmp_path / "checkpoints.2" / "last.ckpt").read_text()
    assert not (tmp_path / "config.yaml").exists() and not (tmp_path / "checkpoints").exists()


def test_a_folder_holding_only_an_earlier_fits_moved_checkpoints_is_a_training_folder(tmp_path):
    """A fresh fit moves its earlier checkpoints to ``checkpoints.<N>/`` before it writes its first: an evaluation
    there took the folder for its own and moved the training's config.yaml and metrics.csv aside."""
    from anycity.lit.keep import is_training_folder

    moved, empty, other = (tmp_path / n for n in ("moved", "empty", "other"))
    (moved / "checkpoints.1").mkdir(parents=True)
    (moved / "checkpoints.1" / "last.ckpt").write_bytes(b"x")
    assert is_training_folder(moved)
    (empty / "checkpoints.1").mkdir(parents=True)  # no checkpoint in it
    (empty / "checkpoints").mkdir()
    assert not is_training_folder(empty)
    (other / "checkpoints.x").mkdir(parents=True)  # not a name move_aside gives
    (other / "checkpoints.x" / "a.ckpt").write_bytes(b"x")
    assert not is_training_folder(other)


@pytest.mark.skipif(sys.platform == "win32", reason="no flock: runs are not guarded")
def test_releasing_a_run_lock_leaves_a_lock_file_another_run_made_at_its_path(tmp_path):
    """``release`` unlinked whatever file was at the lock's path: one another run had made there (after this one's
    was removed) and locked went too, so a third run found the folder free while the second wrote to it."""
    from anycity.lit.keep import RUN_LOCK, RunLocks

    run = tmp_path / "run"
    locks = RunLocks("fit")
    locks.take(run, "--trainer.default_root_dir")
    lock = run / RUN_LOCK
    lock.unlink()  # removed while held, and made again by another run (a new file: this run's is still open)
    lock.write_text("test (pid 1 on there)\n")
    locks.release()
    assert lock.is_file() and lock.read_text() == "test (pid 1 on there)\n"


@pytest.mark.skipif(sys.platform == "win32", reason="no flock: runs are not guarded")
def test_a_run_lock_taken_on_a_file_removed_meanwhile_is_taken_again_on_the_file_at_the_path(tmp_path, monkeypatch):
    """The run before released (unlinked) the lock file between this run's open and its flock: the flock held a
    file no longer at the path, so the next run locked a new file there and two runs wrote one folder."""
    from anycity.lit import keep

    real, calls = keep.try_flock, []

    def released_meanwhile(fd):
        if not calls:
            (tmp_path / "run" / keep.RUN_LOCK).unlink()
        calls.append(fd)
        return real(fd)

    monkeypatch.setattr(keep, "try_flock", released_meanwhile)
    locks = keep.RunLocks("fit")
    locks.take(tmp_path / "run", "--trainer.default_root_dir")
    try:
        lock = tmp_path / "run" / keep.RUN_LOCK
        assert len(calls) == 2 and lock.exists()
        assert os.fstat(locks.held[0][0]).st_ino == os.stat(lock).st_ino
        assert lock.read_text().startswith(f"fit (pid {os.getpid()} on ")
    finally:
        locks.release()


def test_a_fresh_fits_checkpoints_go_aside_once_not_at_every_batch(tmp_path):
    """:class:`KeepPreviousRun` moves the earlier run's checkpoints at the first batch's end only: at a later batch
    the folder holds this run's own checkpoints, which must stay."""
    from types import SimpleNamespace

    from anycity.lit.keep import KeepPreviousRun

    ckpts = tmp_path / "checkpoints"
    ckpts.mkdir()
    (ckpts / "a.ckpt").write_bytes(b"earlier run")
    keep, trainer = KeepPreviousRun([ckpts], checkpoints=True), SimpleNamespace(global_rank=0, world_size=1)
    keep.on_train_batch_end(trainer)
    ckpts.mkdir()
    (ckpts / "b.ckpt").write_bytes(b"this run")  # what this run's ModelCheckpoint wrote meanwhile
    keep.on_train_batch_end(trainer)
    assert (tmp_path / "checkpoints.1" / "a.ckpt").read_bytes() == b"earlier run"
    assert not (tmp_path / "checkpoints.2").exists()
    assert (ckpts / "b.ckpt").read_bytes() == b"this run" and keep.moved == [tmp_path / "checkpoints.1"]


def test_a_fit_resumed_with_ckpt_path_keeps_its_checkpoints_folder(tmp_path):
    """``keep_previous_run`` attaches no :class:`KeepPreviousRun` to a fit given ``--ckpt_path``: the resumed run
    extends its own checkpoints/ (a fresh fit, ``ckpt_path`` None, gets one)."""
    from types import SimpleNamespace

    from lightning.pytorch.callbacks import ModelCheckpoint

    from anycity.lit.keep import KeepPreviousRun, keep_previous_run

    def trainer():
        return SimpleNamespace(fast_dev_run=False, callbacks=[], global_rank=0, log_dir=str(tmp_path),
                               default_root_dir=str(tmp_path), loggers=[],
                               checkpoint_callbacks=[ModelCheckpoint(dirpath=tmp_path / "checkpoints")])

    resumed, fresh = trainer(), trainer()
    keep_previous_run(resumed, "fit", ckpt_path=str(tmp_path / "checkpoints" / "last.ckpt"))
    keep_previous_run(fresh, "fit", ckpt_path=None)
    assert not any(isinstance(c, KeepPreviousRun) for c in resumed.callbacks)
    assert [type(c) for c in fresh.callbacks] == [KeepPreviousRun]


def test_an_empty_folder_is_not_moved_aside(tmp_path):
    """``move_aside`` leaves an empty folder where it is (nothing to keep) and says so by returning None."""
    from anycity.lit.keep import move_aside

    (tmp_path / "checkpoints").mkdir()
    assert move_aside(tmp_path / "checkpoints") is None
    assert (tmp_path / "checkpoints").is_dir() and not (tmp_path / "checkpoints.1").exists()


def test_a_run_refused_for_its_input_leaves_the_previous_runs_logs_where_they_were(tmp_path, capsys):
    """A predict from a folder of 1 photo, and a test or validate of a shard set with no shards of that split, were
    refused only after the previous run's config.yaml and metrics.csv were moved aside (config.1.yaml, and a folder
    with a config.yaml but no metrics.csv); they are refused, in one line, before anything moves."""
    import torch

    data_main(["synth", "--out", str(tmp_path / "train_only"), "--scenes", "1", "--views", "8", "--size", "32x32",
               "--workers", "1"])
    run, photos = tmp_path / "run", tmp_path / "one_photo"
    args = _args(tmp_path / "train_only", run)
    ckpt = tmp_path / "weights.ckpt"  # the config's network, untrained, and no stored settings
    torch.save({"pytorch-lightning_version": "2.4.0", "hyper_parameters": {},
                "state_dict": build_cli(args, run=False).model.state_dict()}, ckpt)
    run.mkdir()
    photos.mkdir()
    Image.fromarray(np.zeros((32, 32, 3), dtype=np.uint8)).save(photos / "0.jpg")
    logs = {"config.yaml": b"an earlier run's config\n", "metrics.csv": b"step,test/psnr\n0,20.0\n"}
    for name, data in logs.items():
        (run / name).write_bytes(data)
    args += ["--ckpt_path", str(ckpt)]
    for cmd, extra, refused in (("predict", ["--data.predict_images", str(photos)], "holds 1 photo"),
                                ("test", [], "test shards: .*index.json lists none"),
                                ("validate", [], "val shards: .*index.json lists none")):
        assert main([cmd, *args, *extra]) == 2, cmd
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and re.match(rf"anycity: error: [^\n]*{refused}", err), (cmd, err)
        assert sorted(p.name for p in run.iterdir()) == sorted(logs), cmd  # no config.1.yaml, nothing written
        assert {n: (run / n).read_bytes() for n in logs} == logs, cmd
    # a fresh fit that would validate, on a set with no val shards: refused before its config.yaml is written (it
    # failed at the sanity check, leaving config.yaml and hparams.yaml for the next run to move aside)
    assert main(["fit", *_args(tmp_path / "train_only", tmp_path / "fit_run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.match(r"anycity: error: val shards: [^\n]*index.json lists none", err)
    assert not (tmp_path / "fit_run").exists() or not any((tmp_path / "fit_run").iterdir())


def test_a_run_resumed_in_another_folder_writes_over_its_last_ckpt_and_not_last_v1(tiny_shards, tmp_path):
    """Lightning restores where it wrote ``last`` only for the checkpoint folder path it stored: a copied or moved
    run (or a SLURM RUN_DIR relative in one job, absolute in the next) wrote last-v1.ckpt beside the stale
    last.ckpt, which launch.sh, Stage II's init_from and --ckpt_path last then read (step 4, not 8)."""
    import shutil

    import torch

    ck = ["-c", str(tmp_path / "ck.yaml")]
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    a, b = tmp_path / "a", tmp_path / "b"
    build_cli(["fit", *_args(tiny_shards, a, ck + ["--trainer.max_steps", "2"])])
    shutil.copytree(a, b)
    build_cli(["fit", *_args(tiny_shards, b, ck + ["--trainer.max_steps", "3"]),
               "--ckpt_path", str(b / "checkpoints" / "last.ckpt")])
    assert sorted(p.name for p in (b / "checkpoints").iterdir()) == ["last.ckpt"]
    assert torch.load(b / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == 3


def test_a_stage2_fit_resuming_a_stage1_checkpoint_is_refused(tiny_shards, tmp_path, capsys):
    """A Stage II job sent to a Stage I run folder resumed Stage I under Stage II's trainer settings, with only a
    warning (Stage I done: it ended at once with exit 0, and the jobs waiting on it started)."""
    ck = ["-c", str(tmp_path / "ck.yaml")]
    (tmp_path / "ck.yaml").write_text("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks."
                                      "ModelCheckpoint\n    init_args: {save_last: true, save_top_k: 0, "
                                      "every_n_train_steps: 1}\n")
    run = tmp_path / "s1"
    build_cli(["fit", *_args(tiny_shards, run, ck)])
    last = run / "checkpoints" / "last.ckpt"
    args = _args(tiny_shards, run, ck)  # Stage II's config right after Stage I's: the run folder stays this test's
    stage2 = [*args[:2], "-c", str(REPO / "configs/quickstart_stage2.yaml"), *args[2:]]
    assert main(["fit", *stage2, "--ckpt_path", str(last)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.match(
        rf"anycity: error: --ckpt_path {re.escape(str(last))} holds a ScaffoldModule, but the config fits a "
        r"RefinementModule: a fit resumes its own stage; to start Stage II from it, pass it as "
        r"--model.init_args.init_from in another run folder", err), err
