"""Shard sets: complete shards only, index.json atomic, disk-full and earlier sets handled without loss."""

import errno
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tarfile
import time

import numpy as np
import pytest

from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import LOCK_NAME, SHARD_MTIME, ShardSetWriter, read_index


def _record(key="scene_a", n=3):
    rng = np.random.default_rng(0)
    views = [ViewRecord(name=f"img{i}.png", image=rng.integers(0, 255, (20, 30, 3), dtype=np.uint8),
                        w2c=np.eye(4), K=np.diag([30.0, 30.0, 1.0]), width=30, height=20,
                        depth=np.full((20, 30), 5.0, np.float32), ext="png") for i in range(n)]
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


def _write(out, keys, overwrite=False):
    with ShardSetWriter(out, maxcount=1, overwrite=overwrite) as w:
        for k in keys:
            w.write(_record(k), "train")


def test_existing_set_is_refused_naming_the_flag_then_replaced_with_it(tmp_path):
    _write(tmp_path, ["a", "b"])
    before = (tmp_path / "index.json").read_bytes()
    with pytest.raises(FileExistsError, match=r"already holds a shard set.*--overwrite"):
        _write(tmp_path, ["c"])
    assert (tmp_path / "index.json").read_bytes() == before
    _write(tmp_path, ["c"], overwrite=True)
    assert [s["key"] for s in read_index(tmp_path)["samples"]] == ["c"]


def test_failure_midway_leaves_no_index_and_no_complete_looking_shard(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        with ShardSetWriter(tmp_path, maxcount=1) as w:
            w.write(_record("a"), "train")
            w.write(_record("b"), "train")  # shard 0 is now complete and published, shard 1 open
            raise RuntimeError("boom")
    assert not (tmp_path / "index.json").exists()
    assert not list(tmp_path.glob("*.partial"))
    assert sorted(p.name for p in tmp_path.glob("*.tar")) == ["train-000000.tar"]  # only the finished one
    _write(tmp_path, ["a", "b"])  # the rerun simply starts over (no index.json: nothing to refuse)
    assert len(read_index(tmp_path)["samples"]) == 2


def test_stale_partial_shards_of_a_killed_run_are_dropped(tmp_path):
    (tmp_path / "train-000000.tar.partial").write_bytes(b"half a tar")
    _write(tmp_path, ["a"])
    assert not list(tmp_path.glob("*.partial"))
    assert read_index(tmp_path)["shards"] == [{"path": "train-000000.tar", "split": "train", "num_samples": 1}]


def test_disk_full_names_path_and_bytes_and_keeps_previous_set(tmp_path, monkeypatch):
    _write(tmp_path, ["a"])
    shard = (tmp_path / "train-000000.tar").read_bytes()
    index = (tmp_path / "index.json").read_bytes()

    import webdataset as wds

    def full(self, obj):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(wds.ShardWriter, "write", full)
    with pytest.raises(OSError, match=r"disk full writing .*train-000000\.tar\.partial: about \d+ more bytes"):
        _write(tmp_path, ["b", "c"], overwrite=True)
    monkeypatch.undo()
    assert (tmp_path / "train-000000.tar").read_bytes() == shard  # the earlier shard is intact
    assert not (tmp_path / "index.json").exists() or (tmp_path / "index.json").read_bytes() == index


def test_a_second_run_on_the_same_folder_is_refused_while_the_first_writes(tmp_path):
    """Two runs on one --out: the second used to delete the first's open ``*.tar.partial``, and the first then
    published a half-written file. The first run's lock refuses the second in one line."""
    first = ShardSetWriter(tmp_path, maxcount=4)
    first.write(_record("a"), "train")
    with pytest.raises(FileExistsError, match=rf"another run \(pid {os.getpid()} on .*lock file .*{LOCK_NAME}.*"
                                              r"if that run is gone, delete"):
        ShardSetWriter(tmp_path, overwrite=True)
    lock = tmp_path / LOCK_NAME
    assert json.loads(lock.read_text())["pid"] == os.getpid()
    first.write(_record("b"), "train")
    first.close()
    assert not lock.exists()
    assert [s["key"] for s in read_index(tmp_path)["samples"]] == ["a", "b"]
    with tarfile.open(tmp_path / "train-000000.tar") as tar:  # the whole of the first run's shard
        assert sorted({m.name.split(".")[0] for m in tar.getmembers()}) == ["a", "b"]
    with pytest.raises(RuntimeError, match="boom"), ShardSetWriter(tmp_path / "x"):
        raise RuntimeError("boom")
    assert not (tmp_path / "x" / LOCK_NAME).exists()  # a failed run gives the lock back too


def test_a_killed_runs_lock_is_taken_over_and_another_hosts_is_refused(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # a pid of this host that no longer runs
    lock = tmp_path / LOCK_NAME
    lock.write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname()}))
    (tmp_path / "train-000000.tar.partial").write_bytes(b"half a tar")
    with pytest.warns(UserWarning, match=rf"taking over the lock of pid {dead.pid} .*no longer runs"):
        _write(tmp_path, ["a"])
    assert not lock.exists() and not list(tmp_path.glob("*.partial"))
    lock.write_text(json.dumps({"pid": 1, "host": "other-host"}))
    with pytest.raises(FileExistsError, match=r"pid 1 on other-host.*delete .*\.anycity-writing\.lock"):
        _write(tmp_path, ["b"], overwrite=True)
    lock.write_text("")  # not a lock this writer wrote
    with pytest.raises(FileExistsError, match=r"not readable as one.*delete"):
        _write(tmp_path, ["b"], overwrite=True)
    assert [s["key"] for s in read_index(tmp_path)["samples"]] == ["a"]  # the refused runs changed nothing


def test_overwrite_and_a_rerun_after_a_crash_leave_no_unlisted_shard(tmp_path):
    """Readers that glob ``*.tar`` (scripts/synth_to_folder.py did) mixed an earlier run's shards in."""
    _write(tmp_path, ["a", "b", "c"])
    assert len(list(tmp_path.glob("*.tar"))) == 3
    with pytest.warns(UserWarning, match=r"removed 2 shard\(s\) of an earlier run .*\(train-000001\.tar, "
                                         r"train-000002\.tar\)"):
        _write(tmp_path, ["d"], overwrite=True)
    assert sorted(p.name for p in tmp_path.glob("*.tar")) == ["train-000000.tar"]
    (tmp_path / "index.json").unlink()  # as a run killed after publishing shards leaves it
    shutil.copy(tmp_path / "train-000000.tar", tmp_path / "val-000003.tar")  # a killed run's (anycity) shard
    with pytest.warns(UserWarning, match=r"removed 1 shard"):
        _write(tmp_path, ["e"])
    assert sorted(p.name for p in tmp_path.glob("*.tar")) == ["train-000000.tar"]
    (tmp_path / "notes.tar").write_bytes(b"not ours")  # other names are left alone
    _write(tmp_path, ["f"], overwrite=True)
    assert (tmp_path / "notes.tar").exists()


def _foreign_tar(path, i):
    with tarfile.open(path, "w") as t:
        data = f"the user's own sample {i}".encode()
        info = tarfile.TarInfo(f"s{i}.txt")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))


def test_another_webdataset_set_in_out_is_refused_not_clobbered(tmp_path):
    """A folder holding another webdataset set under the common names ``train-NNNNNN.tar`` (no index.json): a run
    without --overwrite replaced its first shard and deleted the rest as "an earlier run's"."""
    for i in range(6):
        _foreign_tar(tmp_path / f"train-{i:06d}.tar", i)
    (tmp_path / "val-000000.tar").write_bytes(b"not even a tar")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(FileExistsError, match=rf"^{tmp_path} holds 7 file\(s\) named like this writer's shards that "
                                              r"no anycity run wrote \(train-000000\.tar, train-000001\.tar, "
                                              r"train-000002\.tar, train-000003\.tar and 3 more\); pass --overwrite "
                                              r"to replace them or choose another --out$"):
        _write(tmp_path, ["a"])
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # untouched, the lock given back
    for p in list(tmp_path.iterdir()):
        p.unlink()
    _write(tmp_path, ["a", "b"])  # a killed anycity run's shards (no index.json) are still recognised and replaced
    (tmp_path / "index.json").unlink()
    with pytest.warns(UserWarning, match=r"removed 1 shard"):
        _write(tmp_path, ["c"])
    _foreign_tar(tmp_path / "test-000000.tar", 0)
    with pytest.raises(FileExistsError, match=r"holds 1 file\(s\) .*\(test-000000\.tar\)"):
        (tmp_path / "index.json").unlink()
        _write(tmp_path, ["d"])
    with pytest.warns(UserWarning, match=r"removed 1 shard.*test-000000\.tar"):
        _write(tmp_path, ["d"], overwrite=True)  # --overwrite replaces them
    assert sorted(p.name for p in tmp_path.glob("*.tar")) == ["train-000000.tar"]


def test_bad_window_stride_and_depth_dtype_are_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"window: expected .*stride=30; pass --window"):
        ShardSetWriter(tmp_path / "a", window=24, stride=30)
    with pytest.raises(ValueError, match=r"depth_dtype: expected one of \('float16', 'float32'\).*got 'uint8'"):
        ShardSetWriter(tmp_path / "b", depth_dtype="uint8")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_identical_runs_write_identical_bytes(tmp_path):
    """Tar members carry a fixed mtime, not the time of the run."""
    _write(tmp_path / "a", ["a", "b"])
    time.sleep(1.1)
    _write(tmp_path / "b", ["a", "b"])
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "b").iterdir())
    for n in names:
        assert (tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes(), n
    with tarfile.open(tmp_path / "a" / "train-000000.tar") as tar:
        assert {m.mtime for m in tar.getmembers()} == {SHARD_MTIME}


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device whose writes fail ENOSPC)")
def test_disk_full_while_the_last_shards_are_finished_names_the_shard_and_leaves_no_partial(tmp_path):
    """The last shards are finished (end blocks written, buffers flushed, fsynced) after the last sample: a full disk
    there gave a bare "No space left on device" and left ``val-000000.tar.partial``."""
    w = ShardSetWriter(tmp_path, maxcount=4)
    w.write(_record("a", n=1), "train")
    # the val shard's file is the disk that is full: its buffered sample reaches it only when the shard is finished
    (tmp_path / "val-000000.tar.partial").symlink_to("/dev/full")
    w.write(_record("b", n=1), "val")
    w.write(_record("c", n=1), "test")
    with pytest.raises(OSError, match=r"^\[Errno 28\] disk full writing .*val-000000\.tar\.partial: about \d+ more "
                                      r"bytes needed; free space on .* and rerun") as err:
        w.close()
    assert int(str(err.value).split("about ")[1].split()[0]) >= 10240  # a finished shard is whole 10 KiB records
    assert not list(tmp_path.glob("*.partial")) and not (tmp_path / "index.json").exists()
    assert not (tmp_path / LOCK_NAME).exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train-000000.tar"]  # finished before the disk filled
    _write(tmp_path, ["d"])  # the rerun replaces it
    assert [s["key"] for s in read_index(tmp_path)["samples"]] == ["d"]


def test_overwrite_removes_the_earlier_sets_preview(tmp_path):
    """``data synth --overwrite`` without ``--preview`` left the earlier set's preview.png beside the new shards;
    it goes when the earlier set's index.json goes (so a killed --overwrite run leaves no stale one either)."""
    _write(tmp_path, ["a"])
    (tmp_path / "preview.png").write_bytes(b"the earlier set's contact sheet")
    with pytest.raises(FileExistsError):  # refused without --overwrite: nothing removed
        _write(tmp_path, ["b"])
    assert (tmp_path / "preview.png").exists()
    with ShardSetWriter(tmp_path, maxcount=1, overwrite=True) as w:
        assert not (tmp_path / "preview.png").exists()
        w.write(_record("b"), "train")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["index.json", "train-000000.tar"]


def test_a_killed_runs_folder_as_data_root_says_rerun_not_point_elsewhere(tmp_path):
    """A folder a killed ``data synth`` left (no index.json) was answered "point to a directory written by
    `anycity data synth|convert`", though it is one: the run that writes it was interrupted."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / LOCK_NAME).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname()}))
    (tmp_path / "train-000001.tar.partial").write_bytes(b"half a tar")
    rerun = r"rerun the same command to write the set again \(no --overwrite needed\)$"
    with pytest.raises(FileNotFoundError, match=rf"index\.json: no index\.json: .*was interrupted or failed \(it left "
                                                rf"\{LOCK_NAME}, train-000001\.tar\.partial\); {rerun}"):
        read_index(tmp_path)
    _write(tmp_path / "done", ["a", "b"])  # published shards but no index (killed before index.json)
    for p in (tmp_path / "done").glob("*.tar"):
        shutil.copy(p, tmp_path / p.name)
    for p in [tmp_path / LOCK_NAME, *tmp_path.glob("*.partial")]:
        p.unlink()
    with pytest.raises(FileNotFoundError, match=rf"interrupted or failed \(it left train-000000\.tar, "
                                                rf"train-000001\.tar\); {rerun}"):
        read_index(tmp_path)
    first = ShardSetWriter(tmp_path / "busy")  # a run that is still writing
    with pytest.raises(FileNotFoundError, match=rf"pid {os.getpid()}\) is still writing .*wait for it to finish$"):
        read_index(tmp_path / "busy")
    first.close()
    (tmp_path / "other").mkdir()
    _foreign_tar(tmp_path / "other" / "train-000000.tar", 0)  # not an anycity set: the old hint
    with pytest.raises(FileNotFoundError, match=r"no index\.json; point to a directory written by"):
        read_index(tmp_path / "other")


def test_another_hosts_lock_is_refused_even_when_its_pid_does_not_run_here(tmp_path):
    """A pid of another host says nothing about this one: its lock is not taken over however that pid fares here."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()  # no process of this pid runs here
    lock = tmp_path / LOCK_NAME
    text = json.dumps({"pid": dead.pid, "host": "other-host"})
    lock.write_text(text)
    with pytest.raises(FileExistsError, match=rf"another run \(pid {dead.pid} on other-host\)"):
        ShardSetWriter(tmp_path)
    assert lock.read_text() == text


def test_a_stale_partial_of_a_split_the_new_run_does_not_reach_is_removed(tmp_path):
    """``val-000007.tar.partial`` is not a name the new run writes over: only the clean-up at the start drops it."""
    (tmp_path / "val-000007.tar.partial").write_bytes(b"half a tar")
    _write(tmp_path, ["a"])
    assert not list(tmp_path.glob("*.partial"))
