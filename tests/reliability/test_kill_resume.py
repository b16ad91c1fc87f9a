"""SIGKILL ``anycity fit`` (Stage I and II) and ``anycity data synth`` anywhere, rerun, lose nothing.

Fast (``make test``): 2 kill points, one mid-checkpoint-write in Stage I, one in Stage II right after its second
step (the rerun resumes from a checkpoint). Slow (``-m slow``): >= 10 kill points per stage and for data synth.
Each resumed run must reach the end and its final parameters must be bit-identical to an uninterrupted run's (CPU,
num_workers=0, deterministic).
"""

import json
import random
import time

import pytest

from anycity.data.writer import read_index

from . import harness as H

STEP_LINE = b"] step "  # the progress line a training step prints: "[ScaffoldModule] step 1/3 ..."


def _resume_until_done(args, run, log, kills, rng, max_launches=60):
    """Run ``args`` again and again with ``--ckpt_path last``; the first ``len(kills)`` launches are killed per
    ``kills`` (``("save", k)``: mid-write of the k-th checkpoint save; ``("step", (k, s))``: SIGKILL s seconds after the
    launch's k-th training step line, so never during its imports)
    After each launch every checkpoint must be readable. Returns (kill points that hit a live process, launches)."""
    hit = 0
    for launch in range(max_launches):
        a = args + (["--ckpt_path", "last"] if (run / "checkpoints" / "last.ckpt").exists() else [])
        if launch < len(kills):
            kind, v = kills[launch]
            rc = H.run(a, log, ANYCITY_FAULT_KILL_IN_SAVE=str(v)) if kind == "save" else \
                H.kill_after(a, log, v[1], after=STEP_LINE, count=v[0])
        else:
            rc = H.run(a, log)
        H.check_checkpoints(run / "checkpoints")  # never an unreadable checkpoint
        if rc == 0:
            assert launch >= len(kills) or rc == 0
            return hit, launch + 1
        assert rc == -9, f"run failed (rc={rc}); see {log}:\n" + log.read_text()[-3000:]
        hit += 1
    raise AssertionError(f"no run completed in {max_launches} launches; see {log}")


def _stage(shards, tmp_path, steps, kills, stage2_from=None, name="s"):
    ref = tmp_path / f"{name}_ref"
    assert H.run(H.tiny_fit_args(shards, ref, steps, stage2_from), tmp_path / f"{name}_ref.log") == 0
    run = tmp_path / f"{name}_killed"
    hit, launches = _resume_until_done(H.tiny_fit_args(shards, run, steps, stage2_from), run,
                                       tmp_path / f"{name}_killed.log", kills, random.Random(0))
    diff = H.max_abs_diff(H.params(ref / "checkpoints" / "last.ckpt"), H.params(run / "checkpoints" / "last.ckpt"))
    final = H.safe_torch_load(run / "checkpoints" / "last.ckpt")
    assert final["global_step"] == steps
    assert diff == 0.0, f"resumed run differs from the uninterrupted one by {diff}"
    return ref, hit, launches


def test_kill_two_points_stage1_mid_write_and_stage2_after_a_step(tiny_shards, tmp_path):
    ref1, hit1, _ = _stage(tiny_shards, tmp_path, 3, [("save", 2)], name="s1")
    assert hit1 == 1
    leftovers = list((tmp_path / "s1_killed" / "checkpoints").glob(".anycity-tmp-*"))
    assert not leftovers or all(p.stat().st_size > 0 for p in leftovers)  # the torn write stayed in a temp file
    _, hit2, _ = _stage(tiny_shards, tmp_path, 3, [("step", (2, 0.0))],
                        stage2_from=ref1 / "checkpoints" / "last.ckpt", name="s2")
    assert hit2 == 1  # killed while training, after its second step's line
    assert (tmp_path / "s2_killed.log").read_text().count("] step 1/3 ") == 1  # the rerun resumed past step 1


def _sweep_kills(rng, n):
    # half mid-checkpoint-write (k-th save of that launch), half at a random moment up to 0.4 s after the launch's
    # first or second step (a step takes about 0.5 s; each launch gets 1 to 3 steps further, so the 40-step run
    # outlives all n kills)
    return [("save", rng.randint(1, 2)) if i % 2 == 0 else ("step", (rng.randint(1, 2), rng.uniform(0.0, 0.4)))
            for i in range(n)]


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["stage1", "stage2"])
def test_kill_sweep_ten_points_per_stage(tiny_shards, tmp_path, stage):
    rng = random.Random(16)
    s2_from = None
    if stage == "stage2":
        assert H.run(H.tiny_fit_args(tiny_shards, tmp_path / "base", 2), tmp_path / "base.log") == 0
        s2_from = tmp_path / "base" / "checkpoints" / "last.ckpt"
    _, hit, launches = _stage(tiny_shards, tmp_path, 40, _sweep_kills(rng, 12), stage2_from=s2_from, name=stage)
    (tmp_path.parent / f"kill_sweep_{stage}.json").write_text(json.dumps({"kills_hit": hit, "launches": launches}))
    print(f"\n{stage}: {hit} kill points hit a live run, {launches} launches, final params bit-identical")
    assert hit >= 10


def _synth_args(out, scenes):
    return ["data", "synth", "--out", str(out), "--scenes", str(scenes), "--views", "8", "--size", "32x32",
            "--workers", "1", "--window", "0"]


@pytest.mark.slow
def test_kill_sweep_data_synth(tmp_path):
    ref = tmp_path / "ref"
    t_ref = time.monotonic()
    assert H.run(_synth_args(ref, 40), tmp_path / "ref.log") == 0
    t_ref = time.monotonic() - t_ref  # kill points spread over the run's own length, on any machine load
    rng = random.Random(3)
    hit = 0
    for i in range(12):
        out = tmp_path / f"k{i}"
        t0 = time.monotonic()
        rc = H.kill_after(_synth_args(out, 40), tmp_path / "k.log", rng.uniform(0.3, 0.95) * t_ref)
        hit += rc == -9
        if (out / "index.json").exists():  # the index lists only complete, readable shards
            for s in read_index(out)["shards"]:
                assert (out / s["path"]).is_file()
        assert H.run(_synth_args(out, 40) + (["--overwrite"] if (out / "index.json").exists() else []),
                     tmp_path / "k.log") == 0, time.monotonic() - t0
        assert read_index(out)["samples"] == read_index(ref)["samples"]
        for s in read_index(ref)["shards"]:
            assert (out / s["path"]).stat().st_size == (ref / s["path"]).stat().st_size
        assert not list(out.glob("*.partial"))
    print(f"\ndata synth: {hit} kill points hit a live run, every rerun matched the uninterrupted shard set")
    assert hit >= 10


def test_ckpt_path_last_builds_the_network_the_checkpoint_was_trained_with(tiny_shards, tmp_path, monkeypatch):
    """A run trained with a command-line network option (camera_trunk_depth 3; the config says 2) resumes and tests
    with ``--ckpt_path last`` as with the file named: "last" was resolved only after the network had been built from
    the config, and loading the checkpoint failed (size mismatch). In-process, so that the code under test is this
    one's."""
    from anycity.cli import build_cli

    monkeypatch.setattr("sys.argv", ["anycity"])
    run = tmp_path / "run"
    fit = H.tiny_fit_args(tiny_shards, run, 1)[1:]
    build_cli(["fit", *fit, "--model.init_args.net.camera_trunk_depth", "3"])
    last = run / "checkpoints" / "last.ckpt"
    fast = ["--model.init_args.camera_refine_steps", "0", "--model.init_args.eval_pose_align_steps", "0"]
    cli = build_cli(["test", *fit, *fast, "--trainer.limit_test_batches", "1", "--ckpt_path", "last"])
    assert cli.trainer.ckpt_path == str(last) and cli.model.net.cfg.camera_trunk_depth == 3
    assert "test/psnr_scaffold" in cli.trainer.callback_metrics
    cli = build_cli(["fit", *H.tiny_fit_args(tiny_shards, run, 2)[1:], "--ckpt_path", "last"])  # the resume
    assert cli.trainer.global_step == 2 and cli.model.net.cfg.camera_trunk_depth == 3


class _Crash(Exception):
    pass


def test_a_resumed_fit_with_max_epochs_set_skips_the_samples_it_trained_on(tiny_shards, tmp_path, monkeypatch):
    """With ``trainer.max_epochs`` set as well as ``max_steps``, the LR schedule's length was read from Lightning's
    estimated_stepping_batches, which built the training loader before a resumed run's batch count was restored:
    the resumed run trained again on the stream's first samples (nothing said so) and ended elsewhere than an
    uninterrupted run. In-process (the code under test is this one's): the interrupted run raises in its third
    step, after step 2's checkpoint."""
    from anycity.cli import build_cli
    from anycity.lit import ScaffoldModule

    monkeypatch.setattr("sys.argv", ["anycity"])
    args = lambda run: ["fit", *H.tiny_fit_args(tiny_shards, run, 3)[1:], "--trainer.max_epochs", "100"]  # noqa: E731
    ref, run = tmp_path / "ref", tmp_path / "run"
    build_cli(args(ref))
    step = ScaffoldModule.training_step

    def crash_at_step_3(self, batch, batch_idx):
        if self.global_step == 2:
            raise _Crash
        return step(self, batch, batch_idx)

    with monkeypatch.context() as m:
        m.setattr(ScaffoldModule, "training_step", crash_at_step_3)
        with pytest.raises(_Crash):
            build_cli(args(run))
    cli = build_cli([*args(run), "--ckpt_path", "last"])
    assert cli.trainer.global_step == 3
    last = "checkpoints/last.ckpt"
    diff = H.max_abs_diff(H.params(ref / last), H.params(run / last))
    assert diff == 0.0, f"the resumed run differs from the uninterrupted one by {diff}"


def _toy_trainer(tmp_path, max_steps: int, stop: str | None = None):
    """A one-weight module and a Trainer with a ModelCheckpoint every 2 steps (save_last) and FinalLastCheckpoint;
    ``stop``: ``"exception"`` or ``"sigterm"`` in the third step."""
    import lightning.pytorch as pl
    import torch
    from lightning.pytorch.callbacks import ModelCheckpoint

    from anycity.callbacks.last_checkpoint import FinalLastCheckpoint

    class Toy(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Linear(1, 1)

        def training_step(self, batch, batch_idx):
            if self.global_step == 2 and stop == "exception":
                raise _Crash
            if self.global_step == 2 and stop == "sigterm":
                self.trainer._signal_connector.received_sigterm = True  # what Lightning's SIGTERM handler sets
            return self.w(batch[0]).pow(2).mean()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(100, 1)), batch_size=1)
    cb = ModelCheckpoint(dirpath=tmp_path, save_last=True, save_top_k=0, every_n_train_steps=2)
    trainer = pl.Trainer(max_steps=max_steps, callbacks=[cb, FinalLastCheckpoint()], logger=False,
                         accelerator="cpu", enable_progress_bar=False, enable_model_summary=False)
    return Toy(), data, trainer


@pytest.mark.parametrize("stop", [None, "exception", "sigterm"])
def test_last_ckpt_is_the_final_step_of_a_finished_fit_and_untouched_by_an_interrupted_one(tmp_path, stop):
    """FinalLastCheckpoint: a fit that ends by itself (max_steps 3, a checkpoint every 2 steps) leaves last.ckpt at
    step 3 (Lightning's own end-of-training save writes it only when nothing was saved during the run: step 2). A
    fit stopped in its third step, by an exception or by SIGTERM (which Lightning raises once the step is done),
    goes through on_exception, not on_train_end, and keeps step 2's: the CLI's SIGTERM line names that file."""
    import contextlib

    from lightning.pytorch.utilities.exceptions import SIGTERMException

    model, data, trainer = _toy_trainer(tmp_path, 3, stop)
    raises = {"exception": _Crash, "sigterm": SIGTERMException}.get(stop)
    with pytest.raises(raises) if raises else contextlib.nullcontext():
        trainer.fit(model, data)
    assert H.safe_torch_load(tmp_path / "last.ckpt")["global_step"] == (2 if stop else 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


def test_a_fit_whose_last_step_was_checkpointed_is_not_saved_again_at_its_end(tmp_path):
    """FinalLastCheckpoint saves only where the ModelCheckpoint did not save the final step itself: max_steps 4 with
    a checkpoint every 2 steps writes at steps 2 and 4, not a second, identical save of step 4 (at the paper's size
    each is 14 GB with the optimiser state)."""
    model, data, trainer = _toy_trainer(tmp_path, 4)
    saved, save = [], trainer.save_checkpoint
    trainer.save_checkpoint = lambda *a, **k: saved.append(trainer.global_step) or save(*a, **k)
    trainer.fit(model, data)
    assert saved == [2, 4]
    assert H.safe_torch_load(tmp_path / "last.ckpt")["global_step"] == 4
