"""NaN/inf in one sample's camera or depth: caught where the sample is built, skipped and counted (default) or
refused with an error naming the sample (``skip_corrupt: false``); never passed on towards the loss."""

import numpy as np
import pytest
import torch

from anycity.data.pipeline import SampleBuilder, SkipCounter, check_finite, collate, make_pipeline
from anycity.data.schema import SceneRecord, ViewRecord
from anycity.data.writer import ShardSetWriter, shard_urls


def _scene(key, bad=None):
    rng = np.random.default_rng(0)
    views = []
    for i in range(4):
        w2c = np.eye(4)
        w2c[0, 3] = 0.1 * i
        depth = np.full((24, 24), 5.0, np.float32)
        K = np.diag([24.0, 24.0, 1.0])
        K[:2, 2] = 12.0
        if bad == "camera" and i == 1:
            w2c[1, 3] = np.nan
        if bad == "depth":
            depth[3:6, 3:6] = np.inf  # a 3x3 patch: every resize samples some of it
        if bad == "K" and i == 0:
            K[0, 0] = np.inf
        views.append(ViewRecord(name=f"{i}.png", image=rng.integers(0, 255, (24, 24, 3), dtype=np.uint8),
                                w2c=w2c, K=K, width=24, height=24, depth=depth, ext="png"))
    return SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0)


@pytest.fixture
def shards(tmp_path):
    with ShardSetWriter(tmp_path, maxcount=8, check_views=False) as w:
        for key, bad in (("good_a", None), ("nan_camera", "camera"), ("inf_depth", "depth"), ("inf_K", "K"),
                         ("good_b", None)):
            w.write(_scene(key, bad), "test")
    return shard_urls(tmp_path, "test")


def test_bad_samples_are_skipped_and_counted(shards, tmp_path):
    counter = SkipCounter(tmp_path / "skips")
    pipe = make_pipeline(shards, SampleBuilder(2, 1, 0, (16, 16), train=False), train=False, skip_corrupt=True,
                         counter=counter)
    out = list(pipe)
    assert sorted(s["scene"] for s in out) == ["good_a", "good_b"]
    assert counter.count == 3
    assert all("test-000000.tar" in r["where"] and "non-finite" in r["error"] for r in counter.records())
    batch = collate(out)  # what reaches the model and the loss
    for t in (batch.context.images, batch.context.w2c, batch.context.K, batch.target.images, batch.target.w2c):
        assert torch.isfinite(t.float()).all()


def test_bad_sample_raises_naming_it_without_skip(shards):
    pipe = make_pipeline(shards, SampleBuilder(2, 1, 0, (16, 16), train=False), train=False, skip_corrupt=False)
    with pytest.raises(ValueError, match=r"nan_camera.*(non-finite|NaN)"):
        list(pipe)


def test_check_finite_names_the_field():
    with pytest.raises(ValueError, match=r"s1: non-finite values .* in context\.depth"):
        check_finite({"context": {"depth": torch.tensor([1.0, float("nan")])}}, "s1")
    check_finite({"context": {"image": torch.zeros(2, dtype=torch.uint8), "K": torch.eye(3)}}, "s1")
    # normals derived from depth are NaN where there is no depth (sky): not corrupt there, corrupt where valid
    normal, mask = torch.zeros(1, 3, 2, 2), torch.ones(1, 1, 2, 2, dtype=torch.bool)
    normal[..., 0, 0], mask[..., 0, 0] = float("nan"), False
    check_finite({"context": {"normal": normal, "mask": mask}}, "s1")
    normal[..., 1, 1] = float("nan")
    with pytest.raises(ValueError, match=r"context\.normal"):
        check_finite({"context": {"normal": normal, "mask": mask}}, "s1")


def test_datamodule_skips_by_default(tmp_path):
    from anycity.lit.datamodule import AerialDataModule

    assert AerialDataModule(root=str(tmp_path)).hparams.skip_corrupt is True


def _two_ranks(monkeypatch, other_rank: list[str]):
    """torch.distributed as rank 0 of 2 sees it, the other rank's ``all_gather_object`` giving ``other_rank``."""
    import torch.distributed as dist

    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_world_size", lambda group=None: 2)

    def all_gather_object(out, obj, group=None):
        out[0], out[1] = obj, other_rank

    monkeypatch.setattr(dist, "all_gather_object", all_gather_object)


def test_an_evaluation_says_how_many_samples_every_rank_skipped(tmp_path, monkeypatch):
    """Skips were said every 50 training steps, from rank 0's count alone: a test run (its step fixed at the
    checkpoint's) could skip held-out targets and never say so. The ranks' counts were then summed, which counted a
    shard that every rank reads (training) once per rank, and under ddp_spawn (one skip folder shared by the ranks)
    every skip world-size times: now it is the number of distinct skipped things over all ranks."""
    from types import SimpleNamespace

    from anycity.lit import ScaffoldModule

    counter = SkipCounter(tmp_path / "skips")
    for i in range(3):
        counter.add(f"sample {i}", ValueError("non-finite values"))
    m = ScaffoldModule()
    m._trainer = SimpleNamespace(world_size=2, datamodule=SimpleNamespace(num_skipped=counter.count,
                                                                          skip_counter=counter))
    for other_rank, n in ((["sample 1", "sample 7"], 4), (["sample 0", "sample 1", "sample 2"], 3), ([], 3)):
        _two_ranks(monkeypatch, other_rank)
        with pytest.warns(UserWarning, match=rf"^test: {n} corrupt sample\(s\) skipped so far on all ranks "
                                             r"\(skip_corrupt: true\); these figures leave them out\. Rank 0's list: "
                                             r".*skips$"):
            assert m._report_skips("test") == n


def test_an_evaluation_that_scored_nothing_on_any_rank_says_so(tmp_path, monkeypatch):
    """A stream whose whole share of the held-out samples is corrupt ends quietly (another rank or worker scores
    the rest); when no rank scored anything, the evaluation stops with one line instead of logging no figures."""
    from types import SimpleNamespace

    from anycity.lit import ScaffoldModule

    counter = SkipCounter(tmp_path / "skips")
    counter.add("sample 0", ValueError("non-finite values"))
    m = ScaffoldModule()
    m._trainer = SimpleNamespace(world_size=1, datamodule=SimpleNamespace(num_skipped=1, skip_counter=counter),
                                 strategy=SimpleNamespace(reduce=lambda t, reduce_op: t))
    with pytest.warns(UserWarning, match="1 corrupt sample"), pytest.raises(
            ValueError, match=r"^val: no sample was scored on any rank \(1 corrupt sample\(s\) or shard\(s\) skipped, "
                              r"skip_corrupt: true\); fix or re-create the val shards$"):
        m._log_metrics(m.val_metrics, "val")
