"""Shard sets: complete shards only, index.json atomic, disk-full and earlier sets handled without loss."""

import errno

import numpy as np
import pytest

from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import ShardSetWriter, read_index


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
