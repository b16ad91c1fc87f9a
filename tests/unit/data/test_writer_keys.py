"""ShardSetWriter refuses a sample key it already wrote: a reader groups tar members by key, so the second sample
would be merged into the first or replace it (two scenes whose names sanitised alike lost one)."""

import numpy as np
import pytest

from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import ShardSetWriter


def _record(key, n=2):
    views = [ViewRecord(name=f"v{i}.png", image=np.zeros((4, 6, 3), np.uint8), w2c=np.eye(4),
                        K=np.diag([6.0, 6.0, 1.0]), width=6, height=4, ext="png") for i in range(n)]
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


@pytest.mark.parametrize("second_split", ["train", "test"])
def test_a_key_already_written_is_refused_in_one_line(tmp_path, second_split):
    with pytest.raises(ValueError, match=rf"^sample key 'colmap_': already written to {tmp_path} \(two scenes with "
                                         r"one key\); give each scene or window a distinct key$"):
        with ShardSetWriter(tmp_path) as w:
            w.write(_record("colmap_"), "train")
            w.write(_record("colmap_"), second_split)
    assert not (tmp_path / "index.json").exists() and not list(tmp_path.glob("*.tar"))


def test_windows_of_distinct_scenes_that_share_a_key_are_refused(tmp_path):
    with pytest.raises(ValueError, match=r"sample key 'a_w0000': already written"):
        with ShardSetWriter(tmp_path, window=2) as w:
            w.write(_record("a", n=4), "train")  # windows a_w0000, a_w0002
            w.write(_record("a", n=4), "train")


def test_distinct_keys_are_all_written(tmp_path):
    with ShardSetWriter(tmp_path) as w:
        for k in ("a", "b", "c"):
            w.write(_record(k), "train")
    assert [s["key"] for s in w.close()["samples"]] == ["a", "b", "c"]


def test_only_the_window_splits_are_cut_into_windows(tmp_path):
    with ShardSetWriter(tmp_path, window=2) as w:
        w.write(_record("a", n=4), "test")  # an evaluation split stays one whole-scene sample
    assert [(s["key"], s["num_views"]) for s in w.close()["samples"]] == [("a", 4)]
