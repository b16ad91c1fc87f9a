import io
import json
import tarfile

import numpy as np
import pytest
import webdataset as wds

from anycity.data.pipeline import SampleBuilder
from anycity.data.schema import SCHEMA_VERSION, SceneRecord, ViewRecord, check_key, read_meta
from anycity.data.writer import ShardSetWriter, read_index, split_scenes


def _record(key="scene_a", n=3):
    rng = np.random.default_rng(0)
    views = [ViewRecord(name=f"img{i}.png", image=rng.integers(0, 255, (20, 30, 3), dtype=np.uint8),
                        w2c=np.eye(4) + np.pad(np.eye(3)[:, :1] * i, ((0, 1), (3, 0))), K=np.diag([30.0, 30.0, 1.0]),
                        width=30, height=20, depth=np.full((20, 30), 5.0, np.float32), ext="png")
             for i in range(n)]
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


def test_roundtrip_and_index(tmp_path):
    with ShardSetWriter(tmp_path, maxcount=2) as w:
        for i in range(3):
            w.write(_record(f"s{i}"), "train")
        w.write(_record("v0"), "val")
    index = read_index(tmp_path)
    assert index["splits"]["train"] == ["train-000000.tar", "train-000001.tar"]
    assert [s["num_views"] for s in index["scenes"]] == [3, 3, 3, 3]
    sample = next(iter(wds.WebDataset(str(tmp_path / "train-000000.tar"), shardshuffle=False)))
    meta = read_meta(sample)
    assert meta["schema_version"] == SCHEMA_VERSION and meta["views"][0]["name"] == "img0.png"
    img = np.frombuffer(sample["000.png"], np.uint8)
    assert img.size > 0 and "000.depth.npy" in sample


def test_version_mismatch_names_both(tmp_path):
    sample = {"__key__": "k", "__url__": "x.tar", "cameras.json": json.dumps({"schema_version": 99}).encode()}
    with pytest.raises(ValueError, match=rf"schema_version 99.*schema_version {SCHEMA_VERSION}"):
        read_meta(sample)
    (tmp_path / "index.json").write_text(json.dumps({"schema_version": 0}))
    with pytest.raises(ValueError, match="schema_version 0"):
        read_index(tmp_path)
    with pytest.raises(FileNotFoundError, match="index.json"):
        read_index(tmp_path / "nope")


def test_missing_key_names_shard_and_key(tmp_path):
    with ShardSetWriter(tmp_path) as w:
        w.write(_record(), "train")
    sample = next(iter(wds.WebDataset(str(tmp_path / "train-000000.tar"), shardshuffle=False)))
    del sample["001.png"]
    with pytest.raises(ValueError, match=r"train-000000.tar.*scene_a.*'001.png'"):
        SampleBuilder(1, 1, 1, (16, 16), train=False)(sample)


def test_keys_and_splits():
    with pytest.raises(ValueError, match="without '.'"):
        check_key("a.b")
    s = split_scenes(20, seed=1)
    assert s.count("train") == 16 and s.count("val") == 2 and s.count("test") == 2
    assert split_scenes(20, seed=1) == s and split_scenes(2) == ["train", "train"]


@pytest.mark.parametrize("n", [3, 4])
def test_a_few_scenes_still_give_one_val_and_one_test_scene(n):
    s = split_scenes(n)  # n * 0.1 rounds to 0: the one val and test scene are the floor
    assert s.count("val") == 1 and s.count("test") == 1 and s.count("train") == n - 2


def test_corrupt_tar_bytes(tmp_path):
    p = tmp_path / "train-000000.tar"
    with tarfile.open(p, "w") as t:
        data = b"{not json"
        info = tarfile.TarInfo("k.cameras.json")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))
    sample = next(iter(wds.WebDataset(str(p), shardshuffle=False)))
    with pytest.raises(ValueError, match=r"train-000000.tar.*'cameras.json'"):
        read_meta(sample)


def _broken(case):
    rec = _record("bad")
    v = rec.views[1]
    if case == "scaled rotation":
        v.w2c = v.w2c.copy()
        v.w2c[:3, :3] *= 2
    elif case == "mirrored rotation":
        v.w2c = np.diag([-1.0, 1, 1, 1]) @ v.w2c
    elif case == "negative fy":
        v.K = np.diag([30.0, -30.0, 1.0])
    elif case == "NaN translation":
        v.w2c = v.w2c.copy()
        v.w2c[0, 3] = np.nan
    elif case == "depth":
        v.depth = v.depth[:, :16]
    elif case == "normal":
        v.normal = np.zeros((30, 20, 3), np.float32)
    elif case == "mask":
        v.mask = np.ones((20, 30, 1), bool)
    elif case == "image bytes":
        import cv2

        v.image = cv2.imencode(".png", np.zeros((20, 31, 3), np.uint8))[1].tobytes()
    return rec


@pytest.mark.parametrize("case,said", [
    ("scaled rotation", "camera pose is not a rigid rotation"), ("mirrored rotation", "not a rigid rotation"),
    ("negative fy", r"focal lengths > 0 \(got fx=30, fy=-30\)"), ("NaN translation", "camera holds NaN/inf"),
    ("depth", r"depth is 20x16, expected 20x30 \(the view's height x width\)"), ("normal", "normal is 30x20x3"),
    ("mask", "mask is 20x30x1"), ("image bytes", "image is 20x31, expected 20x30")])
def test_a_view_with_an_unsound_camera_or_array_size_is_refused_naming_it(tmp_path, case, said):
    """The writer stored cameras every converter refuses (camera_problem) and arrays of another size than the
    view's; the sample builder then read them without a word (a mirrored world, a stretched depth map)."""
    with pytest.raises(ValueError, match=rf"^sample 'bad' view 1 \(img1\.png\): .*{said}.*; fix that view or leave it "
                                         r"out$"):
        with ShardSetWriter(tmp_path / "out") as w:
            w.write(_record("good"), "train")
            w.write(_broken(case), "train")
    assert not (tmp_path / "out" / "index.json").exists()
    with ShardSetWriter(tmp_path / "raw", check_views=False) as w:  # a damaged set on purpose: readers' tests
        w.write(_broken(case), "train")
