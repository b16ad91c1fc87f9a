"""Trajectory windows: bounds, keys, scene positions, and llffhold evaluation that scores every held-out view of
a windowed scene exactly once."""

import numpy as np
import pytest
import webdataset as wds

from anycity.data.pipeline import SampleBuilder, make_pipeline
from anycity.data.schema import SceneRecord, ViewRecord, read_meta, split_windows, window_bounds
from anycity.data.writer import ShardSetWriter, read_index, shard_urls


@pytest.mark.parametrize("n,size,stride", [(48, 24, 12), (50, 16, 8), (30, 24, 6), (10, 24, None), (20, 8, 8)])
def test_window_bounds_cover_and_own_once(n, size, stride):
    b = window_bounds(n, size, stride)
    assert b[0][0] == 0 and b[-1][1] == n
    assert all(stop - start == min(size, n) for start, stop, _, _ in b)
    owned = [i for _, _, lo, hi in b for i in range(lo, hi)]
    assert owned == list(range(n))  # the own ranges partition the trajectory, in order
    assert all(start <= lo and hi <= stop for start, stop, lo, hi in b)  # a window owns only its own views
    with pytest.raises(ValueError, match="stride"):
        window_bounds(40, 8, 9)


def _scene(key, n, h=16, w=20):
    rng = np.random.default_rng(0)
    K = np.array([[20.0, 0, w / 2], [0, 20.0, h / 2], [0, 0, 1]])
    views = []
    for i in range(n):
        w2c = np.eye(4)
        w2c[:3, 3] = [0.3 * i, 0, 5]
        views.append(ViewRecord(name=f"v{i}.png", image=rng.integers(0, 255, (h, w, 3), dtype=np.uint8), w2c=w2c,
                                K=K, width=w, height=h, depth=np.full((h, w), 5.0, np.float32), ext="png"))
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


def test_split_windows_keys_and_positions():
    parts = split_windows(_scene("s", 20), 8, 4)
    assert [p.key for p in parts] == ["s_w0000", "s_w0004", "s_w0008", "s_w0012"]
    assert [p.first_index for p in parts] == [0, 4, 8, 12] and all(p.scene == "s" for p in parts)
    assert all(p.scene_views == 20 for p in parts)
    assert parts[1].views[0] is parts[0].views[4]


def test_windowed_shards_train_and_eval(tmp_path):
    with ShardSetWriter(tmp_path, window=8, stride=4, window_splits=("train", "test")) as w:
        w.write(_scene("a", 20), "train")
        w.write(_scene("b", 26), "test")
        w.write(_scene("c", 12), "val")  # not windowed
    index = read_index(tmp_path)
    assert [(s["key"], s["num_views"], s["num_samples"]) for s in index["scenes"]] == [
        ("a", 20, 4), ("b", 26, 6), ("c", 12, 1)]
    assert [s["first"] for s in index["samples"] if s["scene"] == "b"] == [0, 4, 8, 12, 16, 18]
    sample = next(iter(wds.WebDataset(str(tmp_path / "train-000000.tar"), shardshuffle=False)))
    meta = read_meta(sample)
    assert meta["scene"] == "a" and meta["key"] == "a_w0000" and meta["window"]["scene_views"] == 20
    assert [v["index"] for v in meta["views"]] == list(range(8))
    # training: view indices are scene positions inside the sample's window
    pipe = make_pipeline(shard_urls(tmp_path, "train"), SampleBuilder(2, 2, 3, (16, 16), seed=0), train=True,
                         epoch_samples=12)
    for item in pipe:
        idx = np.concatenate([item[g]["index"].numpy() for g in ("context", "target", "dense")])
        assert idx.max() - idx.min() < 8 and idx.max() < 20
    # evaluation: every held-out view (scene position % 8 == 0) is scored, by exactly one window
    scored = {}
    for item in make_pipeline(shard_urls(tmp_path, "test"), SampleBuilder(2, 2, 2, (16, 16), train=False),
                              train=False):
        tgt = set(item["target"]["index"].tolist())
        assert all(i % 8 == 0 for i in tgt)
        assert not set(item["context"]["index"].tolist()) & {0, 8, 16, 24}
        for i in tgt:
            scored.setdefault(i, set()).add(item["scene"] + str(item["context"]["index"].tolist()))
    assert sorted(scored) == [0, 8, 16, 24] and all(len(v) == 1 for v in scored.values())


def test_a_held_out_view_on_the_end_of_an_own_range_is_scored_once(tmp_path):
    """Windows of 12 every 4 over 24 views own [0, 8), [8, 12), [12, 16), [16, 24): held-out views 8 and 16 sit on
    an own range's end, which is exclusive; scoring them in two windows would count them twice in the metrics."""
    with ShardSetWriter(tmp_path, window=12, stride=4, window_splits=("test",)) as w:
        w.write(_scene("b", 24), "test")
    assert [s["first"] for s in read_index(tmp_path)["samples"]] == [0, 4, 8, 12]
    scored = {}  # held-out view -> how many evaluation items score it (a short chunk repeats its own views)
    for item in make_pipeline(shard_urls(tmp_path, "test"), SampleBuilder(2, 2, 2, (16, 16), train=False),
                              train=False):
        for i in set(item["target"]["index"].tolist()):
            assert i % 8 == 0
            scored[i] = scored.get(i, 0) + 1
    assert scored == {0: 1, 8: 1, 16: 1}
