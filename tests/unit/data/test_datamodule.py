import io
import itertools
import os
import shutil
import tarfile
import warnings
from pathlib import Path

import pytest
import torch
import webdataset as wds
from helpers.faults import rewrite_shard

from anycity.data.pipeline import SampleBuilder, make_pipeline
from anycity.data.writer import read_index, shard_urls
from anycity.lit.datamodule import AerialDataModule
from anycity.structures import ViewBatch


def resumed_after(batches: int):
    """A trainer as Lightning restores it from a checkpoint taken after ``batches`` training batches (all epochs)."""
    from types import SimpleNamespace

    total = SimpleNamespace(processed=batches)
    return SimpleNamespace(fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=SimpleNamespace(
        total=total))))


def _dm(root, **kw):
    args = dict(root=str(root), image_size=(32, 32), num_context=2, num_dense=3, num_targets=2, batch_size=2,
                num_workers=0, epoch_samples=4, seed=1)
    args.update(kw)
    return AerialDataModule(**args)


@pytest.mark.parametrize("workers", [0, 2])
def test_train_batches(synth_root, workers):
    dm = _dm(synth_root, num_workers=workers)
    batches = list(dm.train_dataloader())
    assert len(batches) == 2  # epoch_samples=4 / batch 2 (split over workers)
    b = batches[0]
    assert isinstance(b, ViewBatch)
    b.validate()
    assert b.context.images.shape == (2, 2, 3, 32, 32) and b.dense.images.shape[1] == 3
    assert b.context.images.dtype == torch.float32 and 0 <= b.context.images.min() and b.context.images.max() <= 1
    assert b.context.mask.dtype == torch.bool and b.target.normal.shape == (2, 2, 3, 32, 32)
    assert torch.allclose(b.context.w2c[:, 0], torch.eye(4).expand(2, 4, 4), atol=1e-5)
    assert b.world_from_source.shape == (2, 4, 4) and (b.scale > 1).all()  # metres per unit


def test_dense_disabled_and_eval_deterministic(synth_root):
    dm = _dm(synth_root, num_dense=0)
    b1 = list(dm.val_dataloader())
    b2 = list(dm.val_dataloader())
    assert b1[0].dense is None
    assert all(i % 8 == 0 for b in b1 for i in b.target.index.flatten().tolist())
    assert torch.equal(b1[0].target.images, b2[0].target.images)
    assert [b.scene for b in b1] == [b.scene for b in b2]


def test_eval_split_by_rank_is_disjoint_and_complete(synth_root, monkeypatch):
    urls = shard_urls(synth_root, "train")
    seen = []
    for rank in (0, 1):
        monkeypatch.setenv("RANK", str(rank))
        monkeypatch.setenv("WORLD_SIZE", "2")
        pipe = make_pipeline(urls, SampleBuilder(2, 2, 0, (16, 16), train=False), train=False)
        seen.append({(s["scene"], i) for s in pipe for i in s["target"]["index"].tolist()})
    # the shards hold 8-view windows of 16-view scenes: each held-out view (0, 8) is scored once, by one rank
    scenes = {s["key"] for s in read_index(synth_root)["scenes"] if s["split"] == "train"}
    assert seen[0] and seen[1] and not seen[0] & seen[1]
    assert seen[0] | seen[1] == {(sc, i) for sc in scenes for i in (0, 8)}
    # resampled training streams differ between ranks but are reproducible
    streams = {}
    for rank in (0, 1, 0):
        monkeypatch.setenv("RANK", str(rank))
        pipe = make_pipeline(urls, SampleBuilder(2, 2, 0, (16, 16), seed=0), train=True, epoch_samples=6)
        streams.setdefault(rank, []).append([(s["scene"], s["context"]["index"].tolist()) for s in pipe])
    assert streams[0][0] == streams[0][1]


def test_missing_and_corrupt_shards(synth_root, tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.tar"):
        make_pipeline([str(tmp_path / "nope.tar")], SampleBuilder(2, 2, 0, (16, 16)), train=True)
    bad = tmp_path / "bad"
    shutil.copytree(synth_root, bad)
    tar = bad / "train-000000.tar"
    data = bytearray(tar.read_bytes())
    i = data.find(b"cameras.json")
    data[i + 600:i + 1600] = b"\x00" * 1000  # clobber the first sample's cameras.json payload
    tar.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="train-000000.tar"):
        list(_dm(bad, num_dense=0, skip_corrupt=False).train_dataloader())
    dm = _dm(bad, num_dense=0, skip_corrupt=True, epoch_samples=3)
    out = list(dm.train_dataloader())
    assert dm.num_skipped >= 1 and len(out) >= 1
    assert "train-000000.tar" in dm.skip_counter.records()[0]["where"]


@pytest.mark.timeout(60)
def test_a_stream_whose_every_shard_fails_stops_with_one_line(synth_root, tmp_path):
    """With skip_corrupt, a resampled training stream drew unreadable, empty or sample-less shards forever (a
    --data.root at a file that is not a shard hung `anycity fit`); now it stops once every shard has failed so, and a
    split with one shard that gives samples still streams."""
    urls = shard_urls(synth_root, "train")
    junk, empty = tmp_path / "junk.tar", tmp_path / "empty.tar"
    junk.write_bytes(b"not a tar" * 100)
    with tarfile.open(empty, "w"):
        pass
    keyless = tmp_path / "keyless.tar"  # members, but none with a key.extension name: no sample
    with tarfile.open(keyless, "w") as dst:
        info = tarfile.TarInfo("README")
        info.size = 2
        dst.addfile(info, io.BytesIO(b"hi"))
    for shards, why in (([junk], "unreadable tar"), ([empty], "an empty tar"), ([junk, empty], "(junk|empty).tar"),
                        ([keyless], "no webdataset samples")):
        pipe = make_pipeline([str(u) for u in shards], SampleBuilder(2, 1, 0, (16, 16)), train=True,
                             epoch_samples=4, skip_corrupt=True)
        with pytest.raises(ValueError, match=f"none of the {len(shards)} shard\\(s\\) gives a sample .*{why}") as e:
            next(iter(pipe))
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="none of the 2 shard\\(s\\) gives a sample"):  # a finite evaluation stream
        list(make_pipeline([str(junk), str(empty)], SampleBuilder(2, 1, 0, (16, 16), train=False), train=False,
                           skip_corrupt=True))
    mixed = make_pipeline([str(junk), *urls], SampleBuilder(2, 1, 0, (16, 16)), train=True, epoch_samples=20,
                          skip_corrupt=True)
    assert len(list(mixed)) == 20
    # a truncated shard is not a failed one when samples came out of it before the cut
    cut = tmp_path / "cut.tar"
    cut.write_bytes(Path(urls[0]).read_bytes()[:-3000])
    for seed in range(3):
        pipe = make_pipeline([str(cut), str(junk)], SampleBuilder(2, 1, 0, (16, 16)), train=True, epoch_samples=6,
                             skip_corrupt=True, seed=seed)
        assert len(list(pipe)) == 6


@pytest.mark.timeout(60)
def test_a_stream_whose_every_sample_fails_to_build_stops_with_one_line(synth_root, tmp_path):
    """Readable shards whose every sample fails to build (here: a cameras.json of another schema) streamed nothing
    forever with skip_corrupt; now they stop once every sample has failed 3 times (once, at the end of a finite
    stream). A sample that fails only for some view picks, and a split with one good shard, still stream."""
    good = shard_urls(synth_root, "train")
    bad = [rewrite_shard(Path(u), tmp_path / f"bad{i}.tar",
                    lambda n, b: b'{"scene": "x"}' if n.endswith("cameras.json") else b) for i, u in enumerate(good)]
    n = sum(1 for u in bad for m in tarfile.open(u).getnames() if m.endswith("cameras.json"))
    pipe = make_pipeline([str(u) for u in bad], SampleBuilder(2, 1, 0, (16, 16)), train=True, epoch_samples=4,
                         skip_corrupt=True)
    with pytest.raises(ValueError, match=f"none of the {n} sample\\(s\\) in the {len(bad)} shard\\(s\\) builds, "
                                         "tried 3 time\\(s\\) each .*schema_version") as e:
        next(iter(pipe))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="builds, tried 1 time\\(s\\) each"):  # a pass of resampled: false
        list(make_pipeline([str(u) for u in bad], SampleBuilder(2, 1, 0, (16, 16), batch_size=1), train=True,
                           resampled=False, skip_corrupt=True))
    # a finite evaluation stream ends (lit/base says when no rank scored anything)
    assert list(make_pipeline([str(u) for u in bad], SampleBuilder(2, 1, 0, (16, 16), train=False), train=False,
                              skip_corrupt=True)) == []
    mixed = make_pipeline([*map(str, bad), good[0]], SampleBuilder(2, 1, 0, (16, 16)), train=True,
                          epoch_samples=12, skip_corrupt=True)
    assert len(list(mixed)) == 12
    # one view of every sample is garbage: a sample builds whenever its picks miss that view
    one_bad = [rewrite_shard(Path(u), tmp_path / f"one_bad{i}.tar",
                        lambda n, b: b"garbage" if n.endswith(".003.jpg") else b)
               for i, u in enumerate(good)]
    assert any(b"garbage" in Path(u).read_bytes() for u in one_bad)
    pipe = make_pipeline([str(u) for u in one_bad], SampleBuilder(2, 1, 0, (16, 16)), train=True, epoch_samples=12,
                         skip_corrupt=True)
    assert len(list(pipe)) == 12


def test_a_corrupt_index_json_is_one_line_naming_it(tmp_path):
    for text, what in (("garbage{", "not JSON"), ("[1, 2]", "not a shard index")):
        (tmp_path / "index.json").write_text(text)
        with pytest.raises(ValueError, match=f"index.json: {what}.*anycity data synth"):
            read_index(tmp_path)


def test_yaml_config_parses(synth_root, tmp_path):
    from jsonargparse import ArgumentParser

    p = ArgumentParser()
    p.add_class_arguments(AerialDataModule, "data")
    cfg = p.parse_args(["--data.root", str(synth_root), "--data.image_size", "[64, 64]", "--data.num_dense", "0"])
    dm = AerialDataModule(**cfg.data.as_dict())
    assert tuple(dm.hparams.image_size) == (64, 64) and dm.hparams.num_dense == 0
    assert "skip_corrupt" in p.get_defaults().data
    os.environ.pop("RANK", None)


@pytest.mark.parametrize("workers", [0, 2])
def test_train_num_context_varies_per_batch(synth_root, workers):
    """train_num_context draws one context count per batch (each worker forms its own batches); the normalised
    frame still starts at the first context view, and evaluation keeps num_context."""
    dm = _dm(synth_root, num_workers=workers, num_context=2, train_num_context=[1, 4], batch_size=3,
             epoch_samples=36, num_dense=2)
    batches = list(dm.train_dataloader())
    counts = [b.context.images.shape[1] for b in batches]
    assert len(batches) == 12 and set(counts) <= {1, 2, 3, 4} and len(set(counts)) >= 3
    for b in batches:
        b.validate()
        assert b.target.images.shape[1] == 2 and b.dense.images.shape[1] == 2
        assert torch.allclose(b.context.w2c[:, 0], torch.eye(4).expand(3, 4, 4), atol=1e-5)
    assert {b.context.images.shape[1] for b in dm.val_dataloader()} == {2}


def test_train_context_weighting_square():
    from anycity.data.pipeline import context_count_probs

    counts, p = context_count_probs((2, 4), "square")
    assert counts.tolist() == [2, 3, 4] and p.tolist() == pytest.approx([4 / 29, 9 / 29, 16 / 29])
    b = SampleBuilder(2, 1, 0, (16, 16), context_range=(2, 4), context_weighting="square", batch_size=1)
    drawn = [b.train_context_count() for _ in range(1)]
    for _ in range(2000):
        b._built += 1
        drawn.append(b.train_context_count())
    freq = [drawn.count(c) / len(drawn) for c in (2, 3, 4)]
    assert freq == pytest.approx(p.tolist(), abs=0.04)


def test_train_context_count_survives_a_skipped_sample(synth_root):
    """A sample that fails to build (skip_corrupt) does not shift the batch boundaries: the next sample keeps the
    count of the batch it fills."""
    b = SampleBuilder(2, 1, 0, (16, 16), context_range=(1, 6), batch_size=4, seed=3)
    sample = next(iter(wds.WebDataset(shard_urls(synth_root, "train")[0], shardshuffle=False)))
    broken = {k: v for k, v in sample.items() if not k.endswith((".jpg", ".png"))}  # fails after the draw
    counts = []
    for i in range(40):
        if i % 7 == 3:  # corrupt: the builder raises, the handler skips the sample
            with pytest.raises(ValueError, match="missing key"):
                b(broken)
            continue
        counts.append(len(b(sample)[0]["context"]["images"]))
    groups = [counts[i:i + 4] for i in range(0, len(counts) - 3, 4)]
    assert all(len(set(g)) == 1 for g in groups) and len({g[0] for g in groups}) > 1


def test_train_num_context_typos_and_mixed_batches(synth_root):
    with pytest.raises(ValueError, match=r"train_num_context: expected \[lo, hi\]"):
        _dm(synth_root, train_num_context=[5, 2])
    with pytest.raises(ValueError, match="train_context_weighting: expected 'uniform' or 'square'"):
        _dm(synth_root, train_num_context=[2, 5], train_context_weighting="squared")
    from anycity.data.pipeline import collate

    items = list(make_pipeline(shard_urls(synth_root, "train"), SampleBuilder(2, 1, 0, (16, 16)), train=True,
                               epoch_samples=1))
    other = list(make_pipeline(shard_urls(synth_root, "train"), SampleBuilder(3, 1, 0, (16, 16)), train=True,
                               epoch_samples=1))
    with pytest.raises(ValueError, match=r"collate: the samples of one batch have \[2, 3\] context views"):
        collate([items[0], other[0]])


def test_a_photo_folder_is_predicted_in_one_process(tmp_path):
    """Under DDP each rank would get some of the chunks and merge a part of the scene: refused in one line."""
    from types import SimpleNamespace

    import numpy as np
    from PIL import Image

    for i in range(3):
        Image.fromarray(np.full((16, 16, 3), 40 * i, np.uint8)).save(tmp_path / f"{i}.png")
    dm = AerialDataModule(predict_images=str(tmp_path), image_size=(16, 16), patch_size=8, num_workers=0)
    dm.trainer = SimpleNamespace(world_size=2)
    with pytest.raises(ValueError, match="one photo folder is reconstructed in one process .* not on 2; pass "
                                         "--trainer.devices 1"):
        dm.predict_dataloader()
    dm.trainer = SimpleNamespace(world_size=1)
    assert len(list(dm.predict_dataloader())) == 1


def test_a_batch_count_limit_under_several_processes_is_said(synth_root):
    """Lightning's ``limit_val_batches: 2`` counts per rank: 2 processes scored 4 batches, another set than one
    process's 2, and nothing said so (the best checkpoint is picked by those figures)."""
    from types import SimpleNamespace

    dm = AerialDataModule(root=str(synth_root), image_size=(16, 16), patch_size=8, num_workers=0)
    for world, limit, said in ((2, 2, True), (1, 2, False), (2, 1.0, False), (2, 0, False), (4, 50, True)):
        dm.trainer = SimpleNamespace(world_size=world, limit_val_batches=limit, limit_test_batches=limit)
        for loader, option in ((dm.val_dataloader, "limit_val_batches"), (dm.test_dataloader, "limit_test_batches")):
            with warnings.catch_warnings(record=True) as w:
                warnings.simplefilter("always")
                loader()
            lines = [str(x.message) for x in w if "counts batches per process" in str(x.message)]
            assert len(lines) == said, (world, limit, lines)
            if said:
                assert lines[0].startswith(f"trainer.{option} {limit} counts batches per process: {world} processes "
                                           f"score up to {limit * world} batches") and "\n" not in lines[0]


def test_a_resumed_run_sees_the_uninterrupted_stream_in_any_epoch(synth_root):
    """Resumed at any step (``--ckpt_path``), the training stream continues as the uninterrupted run's did: the same
    epoch's shard draws, shuffle and view choices, from the same position, and the epochs after it too."""

    def signature(b):
        ctx = b.context
        return b.scene[0], ctx.index[0].tolist(), b.target.index[0].tolist(), round(ctx.images.sum().item(), 3)

    dm = _dm(synth_root, batch_size=1, num_dense=0)
    loader = dm.train_dataloader()
    epochs = [[signature(b) for b in loader] for _ in range(3)]  # Lightning iterates the loader once per epoch
    assert all(len(e) == 4 for e in epochs) and epochs[0] != epochs[1] != epochs[2]
    for step in (2, 4, 6):
        resumed = _dm(synth_root, batch_size=1, num_dense=0)
        resumed.trainer = resumed_after(step)
        loader = resumed.train_dataloader()
        epoch, pos = divmod(step, 4)
        assert [signature(b) for b in loader] == epochs[epoch][pos:], step
        assert [signature(b) for b in loader] == epochs[epoch + 1], step


def test_a_split_the_index_does_not_list_says_how_to_make_one(synth_root, tmp_path):
    """A set of few scenes goes to train alone; the error used to ask for an index.json that was there."""
    import json
    import shutil

    root = tmp_path / "one_split"
    shutil.copytree(synth_root, root)
    index = json.loads((root / "index.json").read_text())
    index["splits"]["val"], index["splits"]["test"] = [], []
    (root / "index.json").write_text(json.dumps(index))
    dm = _dm(root)
    with pytest.raises(ValueError, match=r"val shards: .*index.json lists none \(it has train: \d+; .*--split val "
                                         r".*--data.val_shards OTHER_FOLDER; or skip validation with "
                                         r"--trainer.limit_val_batches 0$"):
        dm.val_dataloader()
    with pytest.raises(ValueError, match=r"test shards: .*--split test .*--data.test_shards OTHER_FOLDER$"):
        dm.test_dataloader()


def test_each_rank_draws_its_own_stream_when_torch_distributed_names_it(synth_root, monkeypatch):
    """Lightning's DDP launcher (and SLURM's) sets no RANK: read from the environment alone, every rank drew the
    same views in the same shuffled order, so N GPUs trained on one GPU's data N times."""
    import torch.distributed as dist

    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    monkeypatch.setattr(dist, "is_initialized", lambda: True)
    monkeypatch.setattr(dist, "get_world_size", lambda group=None: 2)
    streams = []
    for rank in (0, 1):
        monkeypatch.setattr(dist, "get_rank", lambda group=None, r=rank: r)
        dm = _dm(synth_root, batch_size=1, num_dense=0, epoch_samples=8)
        streams.append([(b.scene[0], b.context.index[0].tolist()) for b in dm.train_dataloader()])
    assert len(streams[0]) == len(streams[1]) == 8
    assert sum(a == b for a, b in zip(*streams)) <= 2, streams


def test_two_workers_reading_one_shard_shuffle_it_differently(synth_root, monkeypatch):
    urls = shard_urls(synth_root, "train")[:1]
    orders = []
    for worker in (0, 1):  # webdataset reads WORKER / NUM_WORKERS as a DataLoader worker's id
        monkeypatch.setenv("WORKER", str(worker))
        monkeypatch.setenv("NUM_WORKERS", "2")
        pipe = make_pipeline(urls, SampleBuilder(2, 1, 0, (16, 16), train=True), train=True, epoch_samples=8, seed=1)
        orders.append([s["scene"] for s in pipe])
    assert len(orders[0]) == 8 and orders[0] != orders[1]


def test_a_run_resumed_with_workers_and_varied_context_counts_skips_whole_batches(synth_root):
    """Resumed at step 3 with 2 workers and batches of 3: splitting 9 samples over the workers cut a batch, and
    ``train_num_context`` (one count per batch) then failed to collate."""
    def signatures(dm):
        return sorted((tuple(b.scene), b.context.num_views, round(b.context.images.sum().item(), 3))
                      for b in dm.train_dataloader())

    kw = dict(batch_size=3, num_dense=0, num_workers=2, epoch_samples=24, train_num_context=(2, 4))
    whole = _dm(synth_root, **kw)
    resumed = _dm(synth_root, **kw)
    resumed.trainer = resumed_after(3)
    loader = whole.train_dataloader()
    batches = [(tuple(b.scene), b.context.num_views, round(b.context.images.sum().item(), 3)) for b in loader]
    assert len(batches) == 8
    assert signatures(resumed) == sorted(batches[3:])  # the same batches; workers take turns in another order


def test_evaluation_samples_decode_no_dense_views_and_keep_their_context(synth_root):
    """Stage II's counts (4 context, 4 targets, 12 dense): validation/test batches decoded 12 dense views that
    evaluation never reads. They are gone, and the context views are spread over the 2 x 4 nearest non-held-out
    views, as num_dense 0 spreads them (they were spread over the 12 nearest: [1, 5, 9, 13], so Stage I and
    Stage II runs tested from different context views)."""
    from anycity.data.views import select_eval

    dm = _dm(synth_root, num_context=4, num_targets=4, num_dense=12, batch_size=1)
    for split in ("val", "test"):
        batches = list(getattr(dm, f"{split}_dataloader")())
        assert len(batches) == 1 and batches[0].dense is None  # one 16-view scene per split
        assert batches[0].context.index.tolist() == [[1, 3, 6, 9]]
        assert batches[0].target.index.tolist() == [[0, 8, 0, 8]]
    assert select_eval(16, 4, 4, 0)[0].context == select_eval(16, 4, 4, 12)[0].context == [1, 3, 6, 9]
    for n in (16, 24, 96):  # the builder's selections: select_eval's, less the dense views
        sels = SampleBuilder(4, 4, 12, train=False, eval_dense=False).selections(n)
        assert [(s.context, s.target, s.dense) for s in sels] == [(s.context, s.target, []) for s in
                                                                   select_eval(n, 4, 4, 12)]
    kept = next(iter(_dm(synth_root, num_context=4, num_targets=4, num_dense=12, eval_dense=True).test_dataloader()))
    assert kept.dense.num_views == 12 and kept.context.index.tolist() == [[1, 3, 6, 9]]


def test_a_batch_mixing_samples_with_and_without_depth_is_refused(synth_root):
    """A sample without depth (a COLMAP conversion) in a batch of synthetic ones: collate dropped every sample's depth
    and mask, so the batch lost its depth loss, depth metrics and region figures without a word."""
    from anycity.data.pipeline import collate

    items = list(make_pipeline(shard_urls(synth_root, "train"), SampleBuilder(2, 1, 0, (16, 16), train=False),
                               train=False))[:2]
    bare = {**items[1], "scene": "colmap_x"}
    bare.update({g: {k: v for k, v in items[1][g].items() if k not in ("depth", "mask", "normal")}
                 for g in ("context", "target")})
    with pytest.raises(ValueError, match=r"^collate: a batch mixes samples with and without ground-truth depth "
                                         r"\(without: colmap_x\).*separate run.*batch_size \(eval_batch_size\) 1$"):
        collate([items[0], bare])
    assert collate(items).context.depth.shape[0] == 2 and collate(items).target.mask.shape[0] == 2
    assert collate([bare, bare]).context.depth is None


@pytest.mark.parametrize("workers", [0, 2])
def test_overfit_batches_trains_on_the_same_batch_every_epoch(synth_root, workers):
    """configs/debug/overfit.yaml: Lightning takes the first batches of a fresh iterator each epoch, and each pass over
    the stream drew other shards and views, so "overfit one batch" trained on a new batch every step."""
    from types import SimpleNamespace

    for kw in ({"resampled": False, "shuffle_buffer": 0}, {}):  # overfit.yaml's data settings, and the defaults
        dm = _dm(synth_root, num_workers=workers, epoch_samples=8, **kw)
        dm.trainer = SimpleNamespace(overfit_batches=2)
        loader = dm.train_dataloader()
        epochs = [list(itertools.islice(loader, 3)) for _ in range(3)]  # an epoch is as long as the loader says
        for e in epochs[1:]:
            for a, b in zip(epochs[0], e):
                assert a.scene == b.scene and torch.equal(a.context.images, b.context.images)
                assert torch.equal(a.target.w2c, b.target.w2c) and torch.equal(a.dense.depth, b.dense.depth)
        assert len(loader) == 2 and [len(e) for e in epochs] == [2, 2, 2]
        epochs[1][0].context.images.zero_()  # a step that changes its batch leaves the next epoch's alone
        assert torch.equal(next(iter(loader)).context.images, epochs[0][0].context.images)


def test_val_and_test_read_their_own_shards(synth_root, tmp_path):
    val, test = str(tmp_path / "val-000000.tar"), str(tmp_path / "test-000000.tar")
    dm = _dm(synth_root, val_shards=val, test_shards=test)
    assert dm._urls("val") == [val] and dm._urls("test") == [test]


def test_eval_batch_size_sets_the_val_and_test_batches_only(synth_root):
    dm = _dm(synth_root, batch_size=1, eval_batch_size=2)
    assert dm._loader("train").batch_size == 1
    assert dm._loader("val").batch_size == 2 and dm._loader("test").batch_size == 2


def test_train_num_context_leaves_evaluation_at_num_context(synth_root):
    dm = _dm(synth_root, num_context=4, train_num_context=[2, 3], num_dense=0)
    counts = [b.context.images.shape[1] for b in dm.val_dataloader()]
    assert counts and set(counts) == {4}


def test_fixed_batches_yield_copies():
    from anycity.lit.datamodule import _FixedBatches

    fixed = _FixedBatches([{"images": torch.ones(2, 3)}], 1)
    first = next(iter(fixed))
    first["images"].zero_()  # a step that changes its batch in place
    assert torch.equal(next(iter(fixed))["images"], torch.ones(2, 3))


def test_batches_per_epoch_counts_every_workers_batches(synth_root):
    """Each of 2 workers draws ceil(20 / 2) = 10 samples: 5 batches of 2 each, 10 per epoch."""
    dm = _dm(synth_root, num_workers=2, batch_size=2, epoch_samples=20, resampled=True)
    assert dm._batches_per_epoch() == 10


def _tiny_shards(folder: Path, keys: list[str], maxcount: int = 64, nan_camera: bool = False,
                 split: str = "train") -> list[str]:
    """Shards of 4-view 16 px scenes named ``keys`` (``maxcount`` per shard), no depth; ``nan_camera``: every view's
    camera holds a NaN, so no sample builds."""
    import numpy as np

    from anycity.data.schema import SceneRecord, ViewRecord
    from anycity.data.writer import ShardSetWriter

    rng = np.random.default_rng(0)
    K = np.array([[16.0, 0, 8.0], [0, 16.0, 8.0], [0, 0, 1]])
    with ShardSetWriter(folder, maxcount=maxcount, check_views=False) as w:
        for key in keys:
            views = []
            for i in range(4):
                w2c = np.eye(4)
                w2c[0, 3] = float("nan") if nan_camera else 0.1 * i
                views.append(ViewRecord(name=f"{i}.png", image=rng.integers(0, 255, (16, 16, 3), dtype=np.uint8),
                                        w2c=w2c, K=K, width=16, height=16, ext="png"))
            w.write(SceneRecord(key=key, views=views, source="test", units="metres", metres_per_unit=1.0), split)
    return shard_urls(folder, split)


def test_a_resampled_stream_is_the_same_every_time_it_is_built(tmp_path):
    """Shard draws are deterministic in the seed (a resumed run draws what the first run drew)."""
    urls = _tiny_shards(tmp_path, ["s0", "s1", "s2"], maxcount=1)
    runs = [[s["scene"] for s in make_pipeline(urls, SampleBuilder(2, 1, 0, (16, 16), with_depth=False), train=True,
                                               epoch_samples=10, shuffle=0, seed=1)] for _ in range(2)]
    assert runs[0] == runs[1] and len(set(runs[0])) > 1


def test_an_evaluation_stream_is_never_shuffled(tmp_path):
    """``shuffle`` is for training: evaluation reads the samples in shard order, every time."""
    keys = [f"s{i}" for i in range(8)]
    urls = _tiny_shards(tmp_path, keys, split="test")
    pipe = make_pipeline(urls, SampleBuilder(2, 1, 0, (16, 16), train=False, with_depth=False), train=False,
                         shuffle=16)
    assert [s["scene"] for s in pipe] == [s["scene"] for s in pipe] == keys


@pytest.mark.timeout(60)
def test_a_good_sample_in_the_shuffle_buffer_keeps_the_stream_going(tmp_path):
    """One shard whose sample never builds and one whose sample does: while the good one waits in the shuffle buffer
    the bad one fails again and again, and the stream must not stop as "none of the samples builds" (the rule waits
    for every kept sample to fail 3 times; seeds 13, 15, 24 and 26 draw the bad shard that often first)."""
    urls = _tiny_shards(tmp_path / "b", ["bad"], nan_camera=True) + _tiny_shards(tmp_path / "g", ["good"])
    for seed in (*range(12, 17), *range(23, 28)):
        pipe = make_pipeline(urls, SampleBuilder(2, 1, 0, (16, 16), seed=seed), train=True, epoch_samples=4,
                             shuffle=64, seed=seed, skip_corrupt=True)
        assert [s["scene"] for s in pipe] == ["good"] * 4, seed
