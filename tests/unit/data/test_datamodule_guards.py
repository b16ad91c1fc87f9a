"""Settings and streams that used to fail quietly: an epoch with no batch, an evaluation whose every sample fails
under several workers, a shard pattern as data.root read as val/test, windows too short for distinct targets, skip
counts of events instead of things, resuming with gradient accumulation, data work nothing reads, a shard folder of a
list that gives none of the split, and scenes of another aspect ratio under resize_mode keep."""

import tarfile
from pathlib import Path

import pytest
import torch
import yaml
from helpers.faults import rewrite_shard

from anycity.data.pipeline import SampleBuilder, SkipCounter, make_pipeline
from anycity.data.writer import shard_urls
from anycity.lit.datamodule import AerialDataModule

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


def _dm(root, **kw):
    args = dict(root=str(root), image_size=(32, 32), num_context=2, num_dense=0, num_targets=2, batch_size=1,
                num_workers=0, epoch_samples=4, seed=1)
    args.update(kw)
    return AerialDataModule(**args)


def _unbuildable(synth_root, tmp_path, split: str) -> list[str]:
    """The split's shards with every sample's cameras.json replaced: no sample builds."""
    return [str(rewrite_shard(Path(u), tmp_path / f"bad{i}.tar", lambda n, b: b'{"scene": "x"}'
                         if n.endswith("cameras.json") else b)) for i, u in enumerate(shard_urls(synth_root, split))]


@pytest.mark.parametrize("epoch_samples,workers,batch", [(16, 4, 8), (7, 0, 8), (5, 2, 4)])
def test_an_epoch_that_leaves_a_worker_no_whole_batch_is_refused(synth_root, epoch_samples, workers, batch):
    """Each worker's share smaller than a batch: drop_last left every epoch empty and Lightning looped forever."""
    with pytest.raises(ValueError, match=rf"^epoch_samples: {epoch_samples} samples over num_workers {workers} leave "
                                         rf"each worker fewer than batch_size {batch}.*epoch_samples >= "
                                         rf"{max(1, workers) * batch} \(num_workers x batch_size\)[^\n]*$"):
        _dm(synth_root, epoch_samples=epoch_samples, num_workers=workers, batch_size=batch)
    _dm(synth_root, epoch_samples=max(1, workers) * batch, num_workers=workers, batch_size=batch)


def test_epoch_samples_is_not_checked_where_it_is_not_used(synth_root):
    """With ``resampled: false`` an epoch is one pass and ``epoch_samples`` is unused: a leftover small value was
    refused as an epoch with no batch; the resampled stream, which reads it, still refuses it."""
    kw = dict(epoch_samples=1, num_workers=2, batch_size=2)
    dm = _dm(synth_root, resampled=False, **kw)
    assert not dm.hp.resampled and dm.hp.epoch_samples == 1
    with pytest.raises(ValueError, match=r"^epoch_samples: 1 samples over num_workers 2 leave each worker fewer "):
        _dm(synth_root, resampled=True, **kw)


@pytest.mark.timeout(120)
def test_an_eval_stream_whose_every_sample_fails_ends_quietly_with_two_workers(synth_root, tmp_path, monkeypatch):
    """An evaluation stream holds 1/(ranks x workers) of the samples: its whole share failing says nothing about the
    others, so it ends without a batch (it used to raise, which stopped an evaluation the other streams could score);
    an evaluation that scored nothing on any rank stops with one line (tests/reliability/test_bad_values.py)."""
    bad = _unbuildable(synth_root, tmp_path, "train")  # trajectory windows: several samples, so each worker has some
    for worker in (0, 1):  # webdataset reads WORKER / NUM_WORKERS as a DataLoader worker's id
        monkeypatch.setenv("WORKER", str(worker))
        monkeypatch.setenv("NUM_WORKERS", "2")
        pipe = make_pipeline(bad, SampleBuilder(2, 1, 0, (16, 16), train=False), train=False, skip_corrupt=True)
        assert list(pipe) == []  # ends quietly: other streams may score; lit/base says when none did
    monkeypatch.delenv("WORKER")
    monkeypatch.delenv("NUM_WORKERS")
    dm = _dm(synth_root, test_shards=bad, num_workers=2)
    assert list(dm.test_dataloader()) == []


def test_a_shard_pattern_as_root_is_not_read_as_val_or_test(synth_root):
    """A pattern or file names no split: val and test read the training shards without a word."""
    train = shard_urls(synth_root, "train")
    for root in (train[0], str(Path(train[0]).parent / "train-{000000..000000}.tar")):
        dm = _dm(root)
        assert len(list(dm.train_dataloader())) == 4
        for split in ("val", "test"):
            with pytest.raises(ValueError, match=rf"^{split} shards: data.root .* is a shard file or pattern, not a "
                                                 rf"folder with index.json.* pass --data.{split}_shards [^\n]*$"):
                getattr(dm, f"{split}_dataloader")()
    dm = _dm(train[0], val_shards=shard_urls(synth_root, "val"))
    assert len(list(dm.val_dataloader())) > 0


def test_context_and_target_counts_a_window_cannot_hold_are_refused_at_the_loader(synth_root):
    """The fixture's training windows hold 8 views: up to 7 context + 2 targets would repeat targets or score
    context views as novel ones; refused when the training loader is built, naming the largest count that fits."""
    with pytest.raises(ValueError, match=r"^train_num_context/num_context: up to 7 context \+ 2 target views do not "
                                         r"fit the 8-view training windows of .*use at most 6 context views[^\n]*$"):
        _dm(synth_root, train_num_context=[2, 7]).train_dataloader()
    with pytest.raises(ValueError, match=r"up to 4 context \+ 2 target views do not fit the 5-view training windows "
                                         r"of data.window"):
        _dm(synth_root, num_context=4, window=5).train_dataloader()
    assert len(list(_dm(synth_root, train_num_context=[2, 6]).train_dataloader())) == 4
    # shards without an index: the sample is refused, not skipped as a corrupt one
    pipe = make_pipeline(shard_urls(synth_root, "train"), SampleBuilder(7, 2, 0, (16, 16)), train=True,
                         epoch_samples=2, skip_corrupt=True)
    with pytest.raises(ValueError, match=r"shard .* sample .*: view selection: a 8-view training window cannot hold"):
        list(pipe)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("workers", [0, 2])
def test_a_bad_shard_counts_once_however_many_workers_and_validations_read_it(synth_root, tmp_path, workers):
    """Skips were events: one unreadable shard counted once per worker, and again at every validation."""
    junk = tmp_path / "val-junk.tar"
    junk.write_bytes(b"this is not a tar file" * 100)
    windows = shard_urls(synth_root, "train")[0]  # several samples: one fails, the others build
    bad_sample = rewrite_shard(Path(windows), tmp_path / "val-one-bad.tar", lambda n, b: b'{"scene": "x"}'
                          if n.endswith("cameras.json") and n.startswith(_first_key(windows)) else b)
    dm = _dm(synth_root, val_shards=[str(junk), str(bad_sample)], num_workers=workers)
    loader = dm.val_dataloader()
    for _ in range(2):  # two validations (persistent workers, as Lightning runs them)
        assert len(list(loader)) > 0
    assert dm.num_skipped == 2  # the junk shard and the sample
    assert len(dm.skip_counter.records()) == 2


def _first_key(url: str) -> str:
    with tarfile.open(url) as t:
        return next(n for n in t.getnames() if n.endswith("cameras.json")).split(".")[0]


def test_the_skip_counter_counts_things_not_events(tmp_path):
    c = SkipCounter(tmp_path)
    for _ in range(3):
        c.add("shard a sample k", ValueError("bad"), what="a\tk")
    c.add("shard", ValueError("shard b: unreadable"), what="shard: b")
    assert c.count == 2 and [r["where"] for r in c.records()] == ["shard a sample k", "shard"]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("resume_step", [4, 5])
def test_a_run_resumed_with_gradient_accumulation_continues_at_its_batch(synth_root, tmp_path, resume_step):
    """accumulate_grad_batches 3, 10 batches an epoch: Lightning steps on batches 3, 6, 9 and the epoch's last, so
    global_step x 3 overcounted the batches trained (step 4 = the end of epoch 0 resumed at batch 2 of epoch 1, step 5
    at batch 5 instead of 3). The resumed run must see what the uninterrupted one saw after that step."""
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import ModelCheckpoint

    class Recorder(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.seen = []

        def training_step(self, batch, i):
            self.seen.append((batch.scene[0], batch.context.index[0].tolist(), round(batch.context.images.sum().item(),
                                                                                      3)))
            return (self.w * batch.context.images.mean() + self.w ** 2).sum()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    def fit(max_steps, ckpt_path=None, callbacks=()):
        trainer = pl.Trainer(accelerator="cpu", devices=1, max_steps=max_steps, accumulate_grad_batches=3,
                             logger=False, enable_progress_bar=False, enable_model_summary=False,
                             limit_val_batches=0, num_sanity_val_steps=0, callbacks=list(callbacks),
                             enable_checkpointing=bool(callbacks), default_root_dir=tmp_path)
        module = Recorder()
        trainer.fit(module, datamodule=_dm(synth_root, epoch_samples=10), ckpt_path=ckpt_path)
        return module.seen

    whole = fit(10)
    assert len(whole) == 26  # epochs of 10 batches, 4 steps each; steps 9 and 10 at batches 23 and 26
    ckpt = ModelCheckpoint(dirpath=tmp_path / "ckpt", filename="{step}", every_n_train_steps=resume_step, save_top_k=-1)
    fit(resume_step, callbacks=[ckpt])
    resumed = fit(10, ckpt_path=str(tmp_path / "ckpt" / f"step={resume_step}.ckpt"))
    trained = {4: 10, 5: 13}[resume_step]
    assert resumed == whole[trained:]


def test_shipped_configs_do_no_data_work_that_nothing_reads():
    """No loss reads the data's normals (L_normal renders its own from the Gaussians and their depth), so the shipped
    configs do not derive them per sample (about 1.5x the build time at 448 px)."""
    for name in ("stage1", "stage2", "quickstart"):
        cfg = yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())
        assert cfg["data"]["with_normals"] is False, name


def test_the_sample_check_skips_what_cannot_be_non_finite(synth_root, monkeypatch):
    """Images decoded from uint8 (and normals from uint8 or from the checked depth) cannot hold NaN/inf: checking
    them was about a third of the sample build at 448 px. Depth, cameras and intrinsics are still checked."""
    import anycity.data.pipeline as pipeline

    calls = []
    real = pipeline.check_finite

    def spy(obj, where="sample", path="", skip=()):
        calls.append(skip) if not path else None
        return real(obj, where, path, skip)

    monkeypatch.setattr(pipeline, "check_finite", spy)
    sample = next(iter(make_pipeline(shard_urls(synth_root, "train"), _Raw(), train=False)))
    SampleBuilder(2, 1, 0, (16, 16), train=False)(sample)
    assert calls and set(calls[0]) == {"images", "normal"}
    with pytest.raises(ValueError, match=r"context\.depth"):
        real({"context": {"images": torch.full((1,), float("nan")), "depth": torch.tensor([float("inf")])}}, "s",
             skip=("images",))


@pytest.mark.parametrize("hold", [0, 1, -8])
def test_an_llffhold_below_two_is_refused_in_one_line(synth_root, hold):
    """llffhold 0 parsed and then failed every sample as 'corrupt ... integer modulo by zero'; 1 holds out every
    view, reported as corrupt samples too."""
    with pytest.raises(ValueError, match=rf"^llffhold: expected >= 2 \(every llffhold-th view .*\), got {hold}$"):
        _dm(synth_root, llffhold=hold)
    assert len(list(_dm(synth_root, llffhold=2).test_dataloader())) > 0


def test_an_evaluation_sample_with_fewer_views_than_the_context_stops_in_one_line(synth_root):
    """num_context 16 on a 16-view test scene (views 0 and 8 held out): the context silently repeated views and a
    perfect camera prediction scored AUC 0.98. Stopped, naming the sample and the largest count that fits, even with
    skip_corrupt (a setting, not a corrupt sample)."""
    dm = _dm(synth_root, num_context=16, skip_corrupt=True)
    with pytest.raises(ValueError, match=r"^shard .* sample .*: view selection: a 16-view evaluation sample keeps 14 "
                                         r"views after data.llffhold 8 .*data.num_context <= 14[^\n]*$"):
        list(dm.test_dataloader())
    assert dm.num_skipped == 0
    assert len(list(_dm(synth_root, num_context=14).test_dataloader())) == 1


class _Raw:
    """A builder that passes the raw sample on (to get one sample as the pipeline reads it)."""

    def __call__(self, sample):
        return [sample]


def test_a_missing_photo_folder_is_refused_when_the_datamodule_is_built(tmp_path):
    # before the run writes its config and logs (it replaced the previous run's config.yaml, then failed)
    with pytest.raises(FileNotFoundError, match=r"^predict_images: .*nowhere is not a folder; pass a folder"):
        AerialDataModule(predict_images=str(tmp_path / "nowhere"))
    (tmp_path / "a.jpg").write_bytes(b"not decoded here")
    with pytest.raises(ValueError, match=r"^predict_images: .* holds 1 photo \(only a.jpg\).*a scene needs at least 2 "
                                         r"overlapping photos[^\n]*$"):
        AerialDataModule(predict_images=str(tmp_path))  # refused by the loader's own listing, not at predict
    (tmp_path / "b.jpg").write_bytes(b"not decoded here either")
    AerialDataModule(predict_images=str(tmp_path))  # the photos themselves are decoded by predict


def test_an_evaluation_split_with_no_shards_is_refused_by_check_split(tmp_path):
    """``check_split`` (the CLI calls it before any log file moves) refuses a train-only shard set for the split
    validate/test read; explicit ``test_shards`` and a predict from photos read no such split."""
    from anycity.data.cli import data_main

    data_main(["synth", "--out", str(tmp_path / "one"), "--scenes", "1", "--views", "8", "--size", "32x32",
               "--workers", "1"])
    dm = _dm(tmp_path / "one")
    for sub, split in (("test", "test"), ("validate", "val"), ("predict", "test")):
        with pytest.raises(ValueError, match=rf"^{split} shards: .*index.json lists none \(it has train: 1[^\n]*$"):
            dm.check_split(sub)
    dm.check_split("fit")  # no trainer: the train split alone
    _dm(tmp_path / "one", test_shards=shard_urls(str(tmp_path / "one"), "train")).check_split("test")


def test_a_fit_that_will_validate_is_refused_for_a_missing_val_split_and_one_that_will_not_runs(tmp_path):
    """A fit on a train-only shard set failed at its sanity check (or, with none, at its first validation, hours
    in) after writing config.yaml; ``check_split('fit', trainer)`` refuses it first, unless no validation runs."""
    import json
    from types import SimpleNamespace

    from anycity.data.cli import data_main

    data_main(["synth", "--out", str(tmp_path / "one"), "--scenes", "1", "--views", "8", "--size", "32x32",
               "--workers", "1"])
    dm = _dm(tmp_path / "one")

    def trainer(limit=1.0, sanity=2, interval=1.0, max_steps=-1):
        return SimpleNamespace(limit_val_batches=limit, num_sanity_val_steps=sanity, val_check_interval=interval,
                               max_steps=max_steps)

    for validating in (trainer(), trainer(sanity=0), trainer(sanity=0, interval=100, max_steps=100),
                       trainer(interval=1000, max_steps=10), trainer(sanity=0, interval=10)):
        with pytest.raises(ValueError, match=r"^val shards: .*lists none .*or skip validation with "
                                             r"--trainer.limit_val_batches 0$"):
            dm.check_split("fit", validating)
    for quiet in (trainer(limit=0), trainer(limit=0.0), trainer(sanity=0, interval=1000, max_steps=10)):
        dm.check_split("fit", quiet)
    index = json.loads((tmp_path / "one" / "index.json").read_text())
    index["splits"] = {"val": index["splits"]["train"]}  # the same shards, listed as val alone
    (tmp_path / "one" / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match=r"^train shards: .*lists none \(it has val: 1"):
        dm.check_split("fit", trainer(limit=0))


def test_the_shortest_train_sample_is_the_one_with_fewest_views(tmp_path):
    import json

    from anycity.data.writer import SCHEMA_VERSION
    from anycity.lit.datamodule import _shortest_train_sample

    index = {"schema_version": SCHEMA_VERSION, "splits": {},
             "samples": [{"split": "train", "num_views": 24}, {"split": "train", "num_views": 6},
                         {"split": "val", "num_views": 3}]}
    (tmp_path / "index.json").write_text(json.dumps(index))
    assert _shortest_train_sample(str(tmp_path)) == (6, str(tmp_path))


def _split_moved(synth_root, dst: Path, split: str) -> Path:
    """A copy of the fixture's shard folder whose index.json lists its shards as ``split`` alone (a folder written by
    ``anycity data convert --split test``)."""
    import json
    import shutil

    shutil.copytree(synth_root, dst)
    index = json.loads((dst / "index.json").read_text())
    index["splits"] = {split: [u for v in index["splits"].values() for u in v]}
    (dst / "index.json").write_text(json.dumps(index))
    return dst


def test_a_folder_of_a_shard_list_that_gives_none_of_the_split_is_refused(synth_root, tmp_path):
    """``--data.train_shards "[synth, boruszyn_test]"``, the second converted with --split test: it was dropped
    without a word and training read the first alone. Refused in the line one such folder alone gives."""
    other = _split_moved(synth_root, tmp_path / "other_test", "test")
    dm = _dm(synth_root, train_shards=[str(synth_root), str(other)], val_shards=[str(other), str(synth_root)])
    with pytest.raises(ValueError, match=r"^train shards: .*other_test/index.json lists none \(it has test: \d+;"
                                         r".*--data.train_shards OTHER_FOLDER$"):
        dm.check_split("fit")
    with pytest.raises(ValueError, match=r"^val shards: .*other_test/index.json lists none .*--data.val_shards "
                                         r"OTHER_FOLDER; or skip validation with --trainer.limit_val_batches 0$"):
        dm.val_dataloader()
    both = _dm(synth_root, test_shards=[str(other), str(synth_root)])
    assert both._urls("test") == shard_urls(other, "test") + shard_urls(synth_root, "test")


def _narrowed(synth_root, dst: Path, views) -> str:
    """The fixture's test shard with the chosen views (``views(i)``) centre-cropped to half their width, as a COLMAP
    scene of two cameras (another aspect ratio) gives them; returns the shard's path."""
    import json

    import cv2
    import numpy as np

    def edit(name: str, data: bytes) -> bytes:
        if name.endswith("cameras.json"):
            meta = json.loads(data)
            for i, v in enumerate(meta["views"]):
                if views(i):
                    x0 = v["width"] // 4
                    v["width"] -= 2 * x0
                    v["K"][0][2] -= x0
            return json.dumps(meta).encode()
        stem = name.rsplit(".", 2)
        if name.endswith(".jpg") and views(int(stem[-2])):
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
            x0 = img.shape[1] // 4
            return cv2.imencode(".jpg", np.ascontiguousarray(img[:, x0:img.shape[1] - x0]))[1].tobytes()
        return data

    return str(rewrite_shard(Path(shard_urls(synth_root, "test")[0]), dst, edit))


def test_a_scene_whose_views_keep_different_sizes_stops_the_run_instead_of_leaving_it(synth_root, tmp_path):
    """resize_mode keep and a scene of two aspect ratios: the scene was skipped as a corrupt sample (skip_corrupt,
    the default) and silently left training. A setting to change, so it stops the run in one line naming the scene."""
    url = _narrowed(synth_root, tmp_path / "mixed.tar", lambda i: i % 2 == 1)
    builder = SampleBuilder(2, 1, 0, (32, 32), "keep", train=False, with_depth=False, patch=8)
    counter = SkipCounter()
    with pytest.raises(ValueError, match=r"^shard .* sample .*: scene \S+: views resize to different sizes .*use "
                                         r"resize_mode 'crop' or one aspect ratio per scene$") as e:
        list(make_pipeline([url], builder, train=False, skip_corrupt=True, counter=counter))
    assert type(e.value).__name__ == "SettingsError" and counter.count == 0
    crop = SampleBuilder(2, 1, 0, (32, 32), "crop", train=False, with_depth=False)
    assert len(list(make_pipeline([url], crop, train=False, skip_corrupt=True))) > 0


def test_a_keep_batch_of_two_aspect_ratios_is_refused_in_one_line(synth_root, tmp_path):
    """resize_mode keep, eval_batch_size 2, a 4:3 and a 16:9 scene: torch.stack's "stack expects each tensor to be
    equal size" traceback. Refused naming the scenes, their sizes and the fixes."""
    from anycity.data.pipeline import collate

    narrow = _narrowed(synth_root, tmp_path / "narrow.tar", lambda i: True)
    builder = SampleBuilder(2, 1, 0, (32, 32), "keep", train=False, with_depth=False, patch=8)
    a = next(iter(make_pipeline(shard_urls(synth_root, "test"), builder, train=False)))
    b = {**next(iter(make_pipeline([narrow], builder, train=False))), "scene": "narrow_scene"}
    with pytest.raises(ValueError, match=rf"^collate: a batch mixes image sizes \(HxW 32x32: {a['scene']}; 40x24: "
                                         r"narrow_scene\): .*--data.batch_size 1 \(--data.eval_batch_size 1 .*\), use "
                                         r"--data.resize_mode crop, or shards of one aspect ratio per run$"):
        collate([a, b, a])
    assert collate([b, b]).context.images.shape[-2:] == (40, 24)
