"""Checkpoints: atomic writes (crash / full disk keep the previous file), weights_only reads (no code runs)."""

import errno
import os
import re
import traceback
from pathlib import Path

import pytest
import torch
from helpers.faults import fail_writes_midway

from anycity.lit.checkpoint_io import SafeCheckpointIO, atomic_write_bytes, safe_torch_load


class _Evil:
    """Unpickling this calls a function: the canonical malicious-checkpoint payload."""

    def __reduce__(self):
        return (os.system, ("touch PWNED_BY_CHECKPOINT",))


def test_crafted_checkpoint_is_refused_and_runs_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(2)}, "payload": _Evil()}, path)
    with pytest.raises(ValueError, match=r"refusing to load .*evil\.ckpt") as e:
        SafeCheckpointIO().load_checkpoint(path)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "PWNED_BY_CHECKPOINT").exists()


def test_truncated_checkpoint_is_a_one_line_error(tmp_path):
    path = tmp_path / "t.ckpt"
    torch.save({"w": torch.arange(1000.0)}, path)
    path.write_bytes(path.read_bytes()[:300])
    with pytest.raises(ValueError, match=r"cannot read checkpoint .*t\.ckpt"):
        safe_torch_load(path)


@pytest.fixture(scope="module")
def _full_ckpt(tmp_path_factory):
    path = tmp_path_factory.mktemp("full") / "full.ckpt"
    torch.save({"state_dict": {"w": torch.randn(256, 256, generator=torch.Generator().manual_seed(0))}, "epoch": 3},
               path)
    return path.read_bytes()


@pytest.mark.parametrize("mmap", [False, True])
@pytest.mark.parametrize("cut", [0, 1, 100, 5_000, 20_000, 40_000, 60_000, 200_000])
def test_a_checkpoint_cut_anywhere_is_a_one_line_error(_full_ckpt, tmp_path, cut, mmap):
    """A download stopped at 5..69 KB raised OSError (Errno 22) from the zip reader, a traceback."""
    path = tmp_path / "cut.ckpt"
    path.write_bytes(_full_ckpt[:cut])
    with pytest.raises(ValueError, match=r"cannot read checkpoint .*cut\.ckpt: .*truncated or not a torch file") as e:
        safe_torch_load(path, mmap=mmap)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("body", ["Not Found", "<html><body>502 Bad Gateway</body></html>", "Repository not found",
                                  '{"error": 1}', "Nothing here", "(ello world", "]ello world", "hello", "jello"])
def test_a_text_file_saved_as_a_checkpoint_is_a_one_line_error(tmp_path, body):
    """An HTTP error body saved by `curl -o` (no -f): some text starting with 'N', '(' or ']' raised IndexError,
    with 'h' or 'j' KeyError, from the legacy unpickler."""
    path = tmp_path / "dl.ckpt"
    path.write_text(body + "\n")
    with pytest.raises(ValueError, match=r"cannot read checkpoint .*dl\.ckpt: .*truncated or not a torch file") as e:
        safe_torch_load(path)
    assert "\n" not in str(e.value)


def test_missing_and_unreadable_paths_keep_their_own_errors(tmp_path, monkeypatch):
    """OSError is now read as "truncated", but not a missing file or one this user may not read."""
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        safe_torch_load(tmp_path / "nope.ckpt")
    path = tmp_path / "private.ckpt"
    torch.save({"w": torch.zeros(2)}, path)

    def denied(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(torch, "load", denied)  # root reads a 0o000 file, so the refusal is simulated
    with pytest.raises(PermissionError, match="Permission denied"):
        safe_torch_load(path)


def test_a_checkpoint_folder_is_named_a_folder_not_missing(tmp_path):
    """A folder (a sharded FSDP/DeepSpeed checkpoint) passed as the checkpoint used to be reported as "not found";
    it is named a folder, still as FileNotFoundError (what the callers and the CLI's one-line handler catch)."""
    folder = tmp_path / "last.ckpt"
    folder.mkdir()
    one_line = f"^--ckpt_path {re.escape(str(folder))} is a folder; pass the checkpoint file$"
    with pytest.raises(FileNotFoundError, match=one_line):
        safe_torch_load(folder, what="--ckpt_path")
    with pytest.raises(FileNotFoundError, match="is a folder"):
        SafeCheckpointIO().load_checkpoint(folder)


def test_save_then_load_roundtrip_plain_data(tmp_path):
    io = SafeCheckpointIO()
    ckpt = {"state_dict": {"w": torch.randn(3)}, "epoch": 1, "hyper_parameters": {"lr": 1e-3, "size": (32, 32)}}
    io.save_checkpoint(ckpt, tmp_path / "a" / "x.ckpt")
    back = io.load_checkpoint(tmp_path / "a" / "x.ckpt")
    torch.testing.assert_close(back["state_dict"]["w"], ckpt["state_dict"]["w"])
    assert back["hyper_parameters"]["size"] == (32, 32)
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["x.ckpt"]  # no temp file left behind


def test_disk_full_keeps_previous_and_names_path_and_bytes(tmp_path, monkeypatch):
    io = SafeCheckpointIO()
    path = tmp_path / "last.ckpt"
    io.save_checkpoint({"w": torch.ones(4)}, path)
    before = path.read_bytes()

    fail_writes_midway(monkeypatch, ".anycity-tmp-")
    with pytest.raises(OSError, match=r"disk full writing .*last\.ckpt: \d+ bytes needed") as e:
        io.save_checkpoint({"w": torch.zeros(1000)}, path)
    assert e.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["last.ckpt"]
    # the error's traceback keeps save_checkpoint's buffer: no view of it may still be exported, else freeing it
    # (the garbage collector, later, anywhere) raises BufferError ("Exception ignored in: <_io.BytesIO ...>")
    frame = next(f for f, _ in traceback.walk_tb(e.value.__traceback__) if f.f_code.co_name == "save_checkpoint")
    frame.f_locals["buf"].close()



def test_remove_checkpoint_removes_a_folder_checkpoint_and_never_follows_a_link(tmp_path):
    """A checkpoint that is a folder (FSDP's sharded state dict) raised IsADirectoryError where Lightning's own
    checkpoint IO removes it: ModelCheckpoint(save_top_k=1) replacing its best checkpoint would fail. A link
    (save_last="link") goes, and what it points to stays."""
    io = SafeCheckpointIO()
    sharded = tmp_path / "run" / "epoch=0-step=2.ckpt"
    (sharded / "shards").mkdir(parents=True)
    (sharded / "shards" / "__0_0.distcp").write_bytes(b"x")
    (sharded / "meta.pt").write_bytes(b"x")
    outside = tmp_path / "elsewhere"
    (outside / "keep").mkdir(parents=True)
    (sharded / "link_out").symlink_to(outside, target_is_directory=True)  # inside the folder: not followed
    io.remove_checkpoint(sharded)
    assert not sharded.exists() and (outside / "keep").is_dir()
    io.save_checkpoint({"w": torch.ones(1)}, tmp_path / "run" / "best.ckpt")
    for name, target in (("last.ckpt", tmp_path / "run" / "best.ckpt"), ("last_dir.ckpt", outside)):
        link = tmp_path / "run" / name
        link.symlink_to(target)
        io.remove_checkpoint(link)
        assert not link.is_symlink() and target.exists()
    io.remove_checkpoint(tmp_path / "run" / "best.ckpt")
    io.remove_checkpoint(tmp_path / "run" / "gone.ckpt")  # already gone: nothing to do
    assert list((tmp_path / "run").iterdir()) == [] and (outside / "keep").is_dir()

def test_atomic_write_replaces_whole_file(tmp_path):
    p = tmp_path / "f.bin"
    atomic_write_bytes(p, b"old" * 10)
    atomic_write_bytes(p, b"new")
    assert p.read_bytes() == b"new"


def test_every_torch_file_a_user_passes_is_read_as_data_in_one_line(tmp_path, monkeypatch, capsys):
    """--ckpt_path (Lightning reads its hyperparameters with a bare torch.load first), model.init_from,
    net.pose_prior and pretrained weights: a payload is refused and runs nothing, garbage is named, each in one
    line that names the option."""
    from anycity import cli
    from anycity.lit import RefinementModule
    from anycity.models.pose_prior import load_pose_prior
    from anycity.models.pretrained import read_state_dict

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    evil, junk = tmp_path / "evil.ckpt", tmp_path / "junk.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(2)}, "payload": _Evil()}, evil)
    junk.write_text("not a checkpoint\n")
    config = str(Path(__file__).parents[2] / "configs" / "quickstart.yaml")
    for path, reason in ((evil, "refusing to load --ckpt_path"), (junk, "cannot read --ckpt_path")):
        assert cli.main(["test", "-c", config, "--ckpt_path", str(path), "--data.root", str(tmp_path)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"anycity: error: {reason} {path}" in err
    m = RefinementModule()
    for load, what in ((m.load_stage1, "model.init_from"), (load_pose_prior, "net.pose_prior"),
                       (read_state_dict, "pretrained weights")):
        with pytest.raises(ValueError, match=f"refusing to load {what} .*evil.ckpt") as e:
            load(str(evil))
        assert "\n" not in str(e.value)
        with pytest.raises(ValueError, match=f"cannot read {what} .*junk.ckpt: .*not a torch file"):
            load(str(junk))
    assert not (tmp_path / "PWNED_BY_CHECKPOINT").exists()


def _lightning_ckpt(path: Path, **extra) -> dict:
    """A Stage I checkpoint as LightningCLI writes one (tiny network, hyperparameters with their class path)."""
    import lightning

    from anycity.lit import ScaffoldModule

    m = ScaffoldModule(net={"camera_trunk_depth": 2})
    ckpt = {"pytorch-lightning_version": lightning.__version__, "epoch": 0, "global_step": 1,
            "state_dict": m.state_dict(), "hyper_parameters": {**dict(m.hparams), **extra,
                                                               "_class_path": "anycity.lit.ScaffoldModule"}}
    torch.save(ckpt, path)
    return ckpt


def test_a_plain_weights_file_as_ckpt_path_is_refused_before_anything_moves(tiny_shards, tmp_path, monkeypatch,
                                                                            capsys):
    """A state_dict (VGGT's model.pt) as --ckpt_path gave Lightning's KeyError 'pytorch-lightning_version' traceback,
    after the run had moved the previous run's logs aside."""
    from anycity import cli

    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.csv").write_text("step\n1\n")  # an earlier run's log, which a run would move aside
    plain = tmp_path / "model.pt"
    torch.save(_lightning_ckpt(tmp_path / "full.ckpt")["state_dict"], plain)
    config = str(Path(__file__).parents[2] / "configs" / "quickstart.yaml")
    assert cli.main(["test", "-c", config, "--data.root", str(tiny_shards), "--ckpt_path", str(plain),
                     "--trainer.default_root_dir", str(run), "--trainer.logger.init_args.save_dir", str(run)]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"anycity: error: --ckpt_path {plain}: not a Lightning checkpoint (a plain weights file?); pass it as "
        "model.init_args.pretrained  (--debug for the traceback)")
    assert sorted(p.name for p in run.iterdir()) == ["metrics.csv"]


@pytest.mark.parametrize("key", ["old_weight", "net.old_net_key"])
def test_a_checkpoint_with_hyperparameters_this_version_lacks_names_them(key, tiny_shards, tmp_path, monkeypatch,
                                                                         capsys):
    """A checkpoint of another anycity version was blamed on "a --config file" or a bare __init__ TypeError."""
    from anycity import cli

    monkeypatch.delenv("ANYCITY_DEBUG", raising=False)
    good = tmp_path / "good.ckpt"
    ckpt = _lightning_ckpt(good)
    cli.check_checkpoint(str(good))  # this version's: accepted
    hp = ckpt["hyper_parameters"]
    if key == "old_weight":
        hp["old_weight"] = 0.5
    else:
        hp["net"] = {**hp["net"], "old_net_key": 3}
    torch.save(ckpt, tmp_path / "other.ckpt")
    run = tmp_path / "run"
    config = str(Path(__file__).parents[2] / "configs" / "quickstart.yaml")
    assert cli.main(["test", "-c", config, "--data.root", str(tiny_shards), "--ckpt_path", str(tmp_path / "other.ckpt"),
                     "--trainer.default_root_dir", str(run), "--trainer.logger.init_args.save_dir", str(run)]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"anycity: error: --ckpt_path {tmp_path / 'other.ckpt'}: its stored model.{key} is not an option of this "
        "anycity (written by another version); use the anycity version that wrote it  (--debug for the traceback)")
    assert not run.exists()


@pytest.mark.parametrize("hp", ["hello", {"_class_path": 5, "lr": 0.1}, [1, 2]])
def test_a_checkpoint_whose_hyperparameters_are_not_a_models_is_one_line_naming_it(hp, tmp_path):
    """``hyper_parameters: "hello"`` gave a ValueError that did not name the file; ``_class_path: 5`` a raw
    AttributeError traceback."""
    from anycity import cli

    path = tmp_path / "odd.ckpt"
    torch.save({"pytorch-lightning_version": "2.4.0", "state_dict": {}, "hyper_parameters": hp}, path)
    with pytest.raises(ValueError, match=rf"^--ckpt_path {path}: its stored hyper_parameters are not an anycity "
                                         r"model's .*pass a checkpoint that an anycity fit wrote$"):
        cli.check_checkpoint(str(path))
