"""How the data streams of ranks x DataLoader workers share the samples: evaluation with a corrupt sample, spawned
workers, and ``resampled: false`` epochs (one pass, split evenly by sample)."""

import io
import json
import pickle
import tarfile
from pathlib import Path

import pytest
from helpers.faults import rewrite_shard
from torch.utils.data import DataLoader

from anycity.data.pipeline import SampleBuilder, SkipCounter, make_pipeline
from anycity.data.writer import shard_urls
from anycity.lit.datamodule import AerialDataModule


class _Keys(SampleBuilder):
    """Builds each sample as usual (so a corrupt one fails) and gives its key instead."""

    def __call__(self, sample):
        super().__call__(sample)
        return [{"key": sample["__key__"]}]


def _streams(monkeypatch, world: int, workers: int):
    """``(rank, worker)`` of every stream, each set in the environment (webdataset's RANK/WORLD_SIZE and
    WORKER/NUM_WORKERS) while the caller iterates it."""
    for rank in range(world):
        for worker in range(workers):
            monkeypatch.setenv("RANK", str(rank))
            monkeypatch.setenv("WORLD_SIZE", str(world))
            monkeypatch.setenv("WORKER", str(worker))
            monkeypatch.setenv("NUM_WORKERS", str(workers))
            yield rank, worker


def _split_shard(src: str, folder: Path, sizes: list[int]) -> list[str]:
    """``src``'s samples written to shards of ``sizes`` samples each, in order."""
    with tarfile.open(src) as t:
        members = [(m, t.extractfile(m).read()) for m in t.getmembers()]
    keys = list(dict.fromkeys(m.name.split(".")[0] for m, _ in members))
    assert sum(sizes) == len(keys)
    urls, start = [], 0
    for i, n in enumerate(sizes):
        mine = set(keys[start:start + n])
        start += n
        urls.append(str(folder / f"part{i}.tar"))
        with tarfile.open(urls[-1], "w") as out:
            for m, data in members:
                if m.name.split(".")[0] in mine:
                    out.addfile(m, io.BytesIO(data))
    return urls


@pytest.mark.timeout(120)
def test_a_stream_whose_whole_evaluation_share_is_corrupt_ends_quietly(synth_root, tmp_path, monkeypatch):
    """With ``skip_corrupt`` and one NaN camera among 6 held-out samples over 6 streams (ranks x workers), the
    stream that held only that sample stopped the evaluation with "none of the 1 sample(s) ... builds" although the
    other streams scored the rest; now it ends with nothing, the sample is counted once, and the rest is scored."""
    url = shard_urls(synth_root, "train")[0]
    first = next(n for n in tarfile.open(url).getnames() if n.endswith("cameras.json"))

    def nan_camera(name, data):
        if name != first:
            return data
        meta = json.loads(data)
        meta["views"][1]["w2c"][0][3] = float("nan")
        return json.dumps(meta).encode()

    bad = str(rewrite_shard(Path(url), tmp_path / "bad.tar", nan_camera))
    counter = SkipCounter(tmp_path / "skips")
    scored = []
    for _ in _streams(monkeypatch, world=3, workers=2):
        pipe = make_pipeline([bad], _Keys(2, 2, 0, (16, 16), train=False), train=False, skip_corrupt=True,
                             counter=counter)
        scored.append([s["key"] for s in pipe])
    keys = list(dict.fromkeys(n.split(".")[0] for n in tarfile.open(url).getnames()))
    assert len(keys) == 6 and scored[0] == [] and scored[1:] == [[k] for k in keys[1:]]
    assert counter.count == 1 and first.split(".")[0] in counter.records()[0]["what"]


@pytest.mark.timeout(300)
def test_spawned_workers_unpickle_the_pipeline_and_read_this_rank(synth_root, tmp_path, monkeypatch):
    """Spawned DataLoader workers (macOS, Windows; Linux's forkserver from Python 3.14) pickle the pipeline, whose
    handler and build step were local closures ("Can't pickle local object"). A spawned worker also has no
    torch.distributed: it now reads the rank from RANK/WORLD_SIZE set by the loader's worker_init_fn, so rank 1 of 2
    scores its own share, not every sample as rank 0 of 1."""
    import torch.distributed as dist

    urls = shard_urls(synth_root, "train")
    for kw in ({"train": True, "epoch_samples": 6}, {"train": True, "resampled": False}, {"train": False}):
        pipe = make_pipeline(urls, SampleBuilder(2, 2, 0, (16, 16), train=kw["train"], batch_size=1),
                             skip_corrupt=True, counter=SkipCounter(tmp_path / "skips"), **kw)
        copy = pickle.loads(pickle.dumps(pipe))
        assert [s["scene"] for s in copy] == [s["scene"] for s in pipe], kw

    def signature(b):
        return b.scene[0], tuple(b.target.index[0].tolist())

    dm = AerialDataModule(root=str(synth_root), val_shards=urls, image_size=(16, 16), num_context=2, num_targets=2,
                          num_dense=0, batch_size=1, num_workers=1, with_normals=False)
    expected = []  # rank 1's share, as the streams read it in this process
    for rank, _ in _streams(monkeypatch, world=2, workers=1):
        if rank == 1:
            pipe = dm.val_dataloader().dataset
            expected += [(s["scene"], tuple(s["target"]["index"].tolist())) for s in pipe]
    everything = []
    for _ in _streams(monkeypatch, world=1, workers=1):
        everything = [(s["scene"], tuple(s["target"]["index"].tolist())) for s in dm.val_dataloader().dataset]
    assert expected and len(expected) < len(everything)
    for var in ("RANK", "WORLD_SIZE", "WORKER", "NUM_WORKERS"):
        monkeypatch.delenv(var)
    monkeypatch.setattr(dist, "is_initialized", lambda: True)  # rank 1 of 2, as Lightning's DDP launcher has it
    monkeypatch.setattr(dist, "get_world_size", lambda group=None: 2)
    monkeypatch.setattr(dist, "get_rank", lambda group=None: 1)
    loader = dm.val_dataloader()
    spawned = DataLoader(loader.dataset, batch_size=1, collate_fn=loader.collate_fn, num_workers=1,
                         worker_init_fn=loader.worker_init_fn, multiprocessing_context="spawn")
    assert sorted(signature(b) for b in spawned) == sorted(expected)


def _pass(monkeypatch, urls, world, workers, epoch=0, batch_size=1):
    """Per stream, the keys of training epoch ``epoch`` with ``resampled: false``."""
    out = []
    for _ in _streams(monkeypatch, world, workers):
        pipe = make_pipeline(urls, _Keys(2, 2, 0, (16, 16), batch_size=batch_size), train=True, resampled=False,
                             shuffle=4, seed=5, first_epoch=epoch)
        out.append([s["key"] for s in pipe])
    return out


@pytest.mark.timeout(300)
def test_an_epoch_without_resampling_is_one_pass_split_evenly_by_sample(synth_root, tmp_path, monkeypatch):
    """``resampled: false`` split shards by rank and worker and cut epochs with ``with_epoch``: streams got unequal
    shares (nothing at all with fewer shards than streams), an epoch repeated some samples and missed others. Now
    each epoch is one pass in a per-epoch shard order, split by sample: floor(N / streams) samples per stream, none
    twice, and a resumed epoch (``first_epoch``) reads what the uninterrupted run read there."""
    urls = _split_shard(shard_urls(synth_root, "train")[0], tmp_path, [3, 2, 1])
    every = [k for s in _pass(monkeypatch, urls, 1, 1) for k in s]
    assert len(every) == len(set(every)) == 6
    for world, workers in ((1, 2), (2, 1), (2, 2), (3, 1), (4, 1)):
        epochs = []
        for epoch in range(3):
            streams = _pass(monkeypatch, urls, world, workers, epoch)
            seen = [k for s in streams for k in s]
            assert {len(s) for s in streams} == {6 // (world * workers)}, (world, workers, streams)
            assert len(seen) == len(set(seen)) and set(seen) <= set(every)
            epochs.append(streams)
        assert epochs[0] != epochs[1] or epochs[1] != epochs[2]  # the shard order moves on with the epoch
        assert _pass(monkeypatch, urls, world, workers, 2) == epochs[2]
    with pytest.raises(ValueError, match=r"^resampled: false: the 6 training sample\(s\) over 4 stream\(s\) .* give "
                                         r"each 1, fewer than batch_size 2, .*data.resampled: true"):
        _pass(monkeypatch, urls, 2, 2, batch_size=2)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("workers", [0, 2])
def test_without_resampling_every_rank_gets_equal_batches_from_one_shard(synth_root, monkeypatch, workers):
    """One training shard over 2 ranks with ``resampled: false``: split by shard, rank 1 got no batch while rank 0
    trained (unequal batch counts hang DDP). Split by sample, each rank gets half the pass; a run resumed mid-epoch
    (``--ckpt_path``) continues it and the next epoch as the uninterrupted run does (0 workers: exactly)."""
    from types import SimpleNamespace

    def signature(b):
        return tuple(b.scene), str(b.context.index.tolist()), round(b.context.images.sum().item(), 3)

    kw = dict(root=str(synth_root), image_size=(16, 16), num_context=2, num_targets=2, num_dense=0, batch_size=1,
              num_workers=workers, with_normals=False, resampled=False, epoch_samples=1)
    batches = []
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        loader = AerialDataModule(**kw).train_dataloader()
        batches.append([[signature(b) for b in loader] for _ in range(2)])
    per_rank = max(1, workers) * (6 // (2 * max(1, workers)))  # each worker its floor of the 6 samples
    assert [len(e) for r in batches for e in r] == [per_rank] * 4
    assert not {b for e in batches[0] for b in e} & {b for e in batches[1] for b in e}
    if workers == 0:
        resumed = AerialDataModule(**kw)
        done = 4  # epoch 1, after its first batch
        resumed.trainer = SimpleNamespace(fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(
            batch_progress=SimpleNamespace(total=SimpleNamespace(processed=done)))))
        assert [signature(b) for b in resumed.train_dataloader()] == batches[1][1][done - 3:]


def _tiny_shard(folder: Path, keys: list[str], nan_camera: tuple[str, ...] = ()) -> list[str]:
    """One shard of 4-view 16 px scenes named ``keys``; a scene in ``nan_camera`` has a NaN in a camera."""
    import numpy as np

    from anycity.data.schema import SceneRecord, ViewRecord
    from anycity.data.writer import ShardSetWriter

    rng = np.random.default_rng(0)
    K = np.array([[16.0, 0, 8.0], [0, 16.0, 8.0], [0, 0, 1]])
    with ShardSetWriter(folder, maxcount=64, check_views=False) as w:
        for key in keys:
            views = []
            for i in range(4):
                w2c = np.eye(4)
                w2c[0, 3] = float("nan") if key in nan_camera else 0.1 * i
                views.append(ViewRecord(name=f"{i}.png", image=rng.integers(0, 255, (16, 16, 3), dtype=np.uint8),
                                        w2c=w2c, K=K, width=16, height=16, ext="png"))
            w.write(SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0), "train")
    return shard_urls(folder, "train")


def _scenes(urls, **kw) -> list[str]:
    builder = SampleBuilder(2, 1, 0, (16, 16), with_depth=False, with_normals=False, batch_size=1)
    return [s["scene"] for s in make_pipeline(urls, builder, train=True, resampled=False, **kw)]


def test_a_sample_that_fails_to_build_does_not_leave_its_rank_a_batch_short(tmp_path, monkeypatch):
    """``resampled: false`` splits the pass before the build: with ``skip_corrupt`` a sample with a NaN camera left
    its rank one sample short (rank 0 two, rank 1 three), so ranks disagreed on the batch count (a DDP hang) and on
    the datamodule's count. Now the failed sample's place is filled by a repeat of the stream's previous sample; the
    skip is still counted, once."""
    urls = _tiny_shard(tmp_path, [f"s{i}" for i in range(6)], nan_camera=("s2",))
    counter = SkipCounter(tmp_path / "skips")
    ranks = [_scenes(urls, shuffle=0, skip_corrupt=True, counter=counter) for _ in _streams(monkeypatch, 2, 1)]
    assert [len(r) for r in ranks] == [3, 3] and "s2" not in ranks[0] + ranks[1]
    assert set(ranks[0] + ranks[1]) == {"s0", "s1", "s3", "s4", "s5"} and counter.count == 1


def test_a_pass_is_shuffled_anew_each_epoch(tmp_path):
    """Each epoch of ``resampled: false`` reads the pass in an order of its own (the shuffle is seeded per epoch)."""
    keys = [f"s{i}" for i in range(8)]
    urls = _tiny_shard(tmp_path, keys)
    epochs = [_scenes(urls, shuffle=4, seed=5, first_epoch=e) for e in range(3)]
    assert all(sorted(e) == keys for e in epochs) and not epochs[0] == epochs[1] == epochs[2]


def test_epoch_samples_does_not_cut_a_pass(tmp_path):
    """``epoch_samples`` cuts only resampled epochs: a pass of ``resampled: false`` gives every sample."""
    keys = [f"s{i}" for i in range(6)]
    assert _scenes(_tiny_shard(tmp_path, keys), shuffle=0, epoch_samples=2) == keys
