"""SLURM's time-limit signal (SIGUSR1, Lightning's SLURMEnvironment with auto_requeue) saves ``hpc_ckpt_N.ckpt`` at
the next safe point of the fit (``anycity.callbacks.requeue``): a signal that lands between ``optimizer.step()``
and Lightning counting the batch used to save the weights of step k with the step count of k-1, so the resumed run
trained that batch twice. In-process (about 4 s a fit): the signal is sent from inside the optimiser step, as the
reviewer's ``r6_hpc_midstep.py`` did, and the run resumed from the file must end bit for bit where an uninterrupted
run ends."""

import os
import signal

import pytest

from anycity.cli import build_cli
from anycity.lit.scaffold import ScaffoldModule

from .harness import max_abs_diff, params, safe_torch_load, tiny_fit_args

SLURM = dict(SLURM_NTASKS="1", SLURM_JOB_NAME="anycity-test", SLURM_JOB_ID="12345", SLURM_NNODES="1",
             SLURM_NTASKS_PER_NODE="1", SLURM_PROCID="0", SLURM_LOCALID="0", SLURM_NODEID="0",
             SLURM_NODELIST="localhost", SLURM_JOB_NODELIST="localhost")


@pytest.fixture(autouse=True)
def _argv(monkeypatch):
    monkeypatch.setattr("sys.argv", ["anycity"])


def _fit(shards, run, steps, extra=()):
    build_cli([*tiny_fit_args(shards, run, steps), *extra])


def test_a_time_limit_signal_inside_the_optimiser_step_resumes_bit_for_bit(tiny_shards, tmp_path, monkeypatch):
    _fit(tiny_shards, tmp_path / "ref", 3)

    requeued = []
    monkeypatch.setattr("lightning.pytorch.trainer.connectors.signal_connector.call",
                        lambda cmd, **kw: requeued.append(cmd) or 0)  # the stand-in scontrol
    for k, v in SLURM.items():
        monkeypatch.setenv(k, v)
    step = ScaffoldModule.optimizer_step
    sent = []

    def optimizer_step(self, *a, **k):
        out = step(self, *a, **k)
        if self.global_step == 1 and not sent:  # the 2nd step: weights updated, the step not yet counted
            sent.append(os.kill(os.getpid(), signal.SIGUSR1))
        return out

    monkeypatch.setattr(ScaffoldModule, "optimizer_step", optimizer_step)
    _fit(tiny_shards, tmp_path / "run", 3)
    monkeypatch.undo()
    assert sent and requeued == [["scontrol", "requeue", "12345"]]
    hpc = tmp_path / "run" / "hpc_ckpt_1.ckpt"
    ckpt = safe_torch_load(hpc)
    state = ckpt["optimizer_states"][0]["state"]
    adamw_steps = {int(s["step"]) for s in state.values()}
    # one state: the weights, AdamW's moments, the step count and the LR schedule all after step 2
    assert (ckpt["global_step"], adamw_steps, ckpt["lr_schedulers"][0]["last_epoch"]) == (2, {2}, 2)

    monkeypatch.setattr("sys.argv", ["anycity"])
    _fit(tiny_shards, tmp_path / "resumed", 3, ["--ckpt_path", str(hpc)])
    ref, resumed = (tmp_path / r / "checkpoints" / "last.ckpt" for r in ("ref", "resumed"))
    assert safe_torch_load(resumed)["global_step"] == 3
    assert max_abs_diff(params(ref), params(resumed)) == 0.0


def test_a_time_limit_signal_during_validation_saves_when_validation_ends(tiny_shards, tmp_path, monkeypatch):
    requeued = []
    monkeypatch.setattr("lightning.pytorch.trainer.connectors.signal_connector.call",
                        lambda cmd, **kw: requeued.append(cmd) or 0)
    for k, v in SLURM.items():
        monkeypatch.setenv(k, v)
    validation_step, sent = ScaffoldModule.validation_step, []

    def in_validation(self, *a, **k):
        if not self.trainer.sanity_checking and not sent:
            sent.append(os.kill(os.getpid(), signal.SIGUSR1))
        return validation_step(self, *a, **k)

    monkeypatch.setattr(ScaffoldModule, "validation_step", in_validation)
    _fit(tiny_shards, tmp_path / "run", 3, ["--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1"])
    monkeypatch.undo()
    # saved when the validation after step 2 ended, not at the end of step 3
    assert sent and requeued == [["scontrol", "requeue", "12345"]]
    assert safe_torch_load(tmp_path / "run" / "hpc_ckpt_1.ckpt")["global_step"] == 2
    assert not (tmp_path / "run" / "hpc_ckpt_2.ckpt").exists()


def test_the_fit_trainer_ends_with_the_requeue_callback(tiny_shards, tmp_path):
    """After the checkpoint callbacks (its save holds theirs of the same step), and this Lightning has the internals
    it uses (else it warns and leaves Lightning's handler)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from anycity.callbacks import RequeueAtSafePoint
    from anycity.callbacks.requeue import missing_private_api

    trainer = build_cli(tiny_fit_args(tiny_shards, tmp_path / "run", 1)[1:], run=False).trainer
    assert isinstance(trainer.callbacks[-1], RequeueAtSafePoint) and isinstance(trainer.callbacks[-2], ModelCheckpoint)
    assert missing_private_api(trainer) == []


def _stub_trainer(accumulates):
    """The trainer internals RequeueAtSafePoint reads (one rank under SLURM's auto_requeue): Lightning's
    save-and-requeue records its calls, and the epoch loop's ``_should_accumulate`` answers from ``accumulates``."""
    from types import SimpleNamespace

    from lightning.fabric.plugins.environments import SLURMEnvironment

    saves = []
    steps = iter(accumulates)
    return SimpleNamespace(
        world_size=1, _accelerator_connector=SimpleNamespace(cluster_environment=SLURMEnvironment(auto_requeue=True)),
        _signal_connector=SimpleNamespace(_slurm_sigusr_handler_fn=lambda signum, frame: saves.append(signum)),
        fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(_should_accumulate=lambda: next(steps)))), saves


def test_a_time_limit_signal_waits_for_the_batch_that_steps_the_optimiser():
    """With gradient accumulation the checkpoint was also due after a batch that only accumulates: the saved state
    then lost the gradients gathered so far, and the resumed run stepped on fewer batches."""
    from lightning.pytorch.trainer.connectors.signal_connector import _HandlersCompose

    from anycity.callbacks import RequeueAtSafePoint

    trainer, saves = _stub_trainer([True, False])  # batch 1 accumulates, batch 2 steps
    cb, before = RequeueAtSafePoint(), signal.getsignal(signal.SIGUSR1)
    try:
        signal.signal(signal.SIGUSR1, _HandlersCompose([trainer._signal_connector._slurm_sigusr_handler_fn]))
        cb.on_train_start(trainer, None)
        assert cb._active and signal.getsignal(signal.SIGUSR1) == cb._on_signal
        os.kill(os.getpid(), signal.SIGUSR1)  # only noted
        assert saves == []
        cb.on_train_batch_end(trainer, None, None, None, 0)
        assert saves == []  # the batch only accumulated: no save yet
        cb.on_train_batch_end(trainer, None, None, None, 1)
        assert saves == [signal.SIGUSR1]  # the batch that steps: one save and requeue
    finally:
        cb.teardown(trainer, None, "fit")
        signal.signal(signal.SIGUSR1, before)


def test_a_sigusr1_handler_lightning_did_not_install_is_left_alone():
    """The callback took SIGUSR1 over whatever handler was in place; it replaces Lightning's own only, so a user's
    handler keeps the signal and the callback stays inactive."""
    from lightning.pytorch.trainer.connectors.signal_connector import _HandlersCompose

    from anycity.callbacks import RequeueAtSafePoint

    trainer, saves = _stub_trainer([False])
    before = signal.getsignal(signal.SIGUSR1)

    def mine(signum, frame):
        pass

    try:
        signal.signal(signal.SIGUSR1, mine)
        cb = RequeueAtSafePoint()
        cb.on_sanity_check_start(trainer, None)
        cb.on_train_start(trainer, None)
        assert signal.getsignal(signal.SIGUSR1) is mine and not cb._active
        cb._on_signal(signal.SIGUSR1, None)
        cb.on_train_batch_end(trainer, None, None, None, 0)
        assert saves == []  # inactive: it never saves on Lightning's behalf
        # the same trainer with Lightning's handler in place: taken over (the stub is complete)
        signal.signal(signal.SIGUSR1, _HandlersCompose([trainer._signal_connector._slurm_sigusr_handler_fn]))
        cb = RequeueAtSafePoint()
        cb.on_train_start(trainer, None)
        assert cb._active and signal.getsignal(signal.SIGUSR1) == cb._on_signal
    finally:
        signal.signal(signal.SIGUSR1, before)


def test_a_requeued_fit_without_ckpt_path_resumes_from_its_hpc_checkpoint(tiny_shards, tmp_path, monkeypatch):
    """A plain ``srun anycity fit`` requeued by Lightning's auto-requeue (no ``--ckpt_path``): Lightning resumes it
    from RUN/hpc_ckpt_N.ckpt by itself, so anycity must treat it as a resume too. It took it for a fresh fit: the
    run's own checkpoints/ went aside as checkpoints.1 after the first batch, and the network was built outside
    ``resuming()`` (``pretrained``/``init_from`` read again)."""
    import functools
    import shutil

    from anycity.lit import base

    run = tmp_path / "run"
    _fit(tiny_shards, run, 2)
    shutil.copy(run / "checkpoints" / "last.ckpt", run / "hpc_ckpt_1.ckpt")  # what the time-limit signal saved
    shutil.copy(run / "checkpoints" / "last.ckpt", run / "hpc_ckpt_0.ckpt")  # an older one: the largest N is read
    for k, v in SLURM.items():
        monkeypatch.setenv(k, v)
    built_resuming, init = [], ScaffoldModule.__init__

    @functools.wraps(init)  # its signature stays the one the CLI parses
    def record(self, *a, **k):
        built_resuming.append(base._RESUMING.get())
        init(self, *a, **k)

    monkeypatch.setattr(ScaffoldModule, "__init__", record)
    cli = build_cli(tiny_fit_args(tiny_shards, run, 4))  # the requeued job: the same command
    assert sorted(p.name for p in run.iterdir() if p.name.startswith("checkpoints")) == ["checkpoints"]
    assert safe_torch_load(run / "checkpoints" / "last.ckpt")["global_step"] == 4
    assert built_resuming == [True]
    assert cli.config["fit"]["ckpt_path"] == str(run / "hpc_ckpt_1.ckpt")


def test_the_hpc_checkpoint_resumed_from_is_the_largest_n_and_only_under_slurm_or_when_asked(tmp_path, monkeypatch):
    """What Lightning's ``_parse_ckpt_path`` would resume a fit from by itself, found before the network is built."""
    from anycity.cli import hpc_resume_path

    for n in (2, 10):
        (tmp_path / f"hpc_ckpt_{n}.ckpt").write_bytes(b"x")
    trainer = {"default_root_dir": str(tmp_path)}
    assert hpc_resume_path(trainer, "hpc") == str(tmp_path / "hpc_ckpt_10.ckpt")  # by N, not by name
    for k in SLURM:
        monkeypatch.delenv(k, raising=False)
    assert hpc_resume_path(trainer, None) is None  # not under SLURM: a fresh fit
    for k, v in SLURM.items():
        monkeypatch.setenv(k, v)
    assert hpc_resume_path(trainer, None) == str(tmp_path / "hpc_ckpt_10.ckpt")
    assert hpc_resume_path(trainer, str(tmp_path / "other.ckpt")) is None  # a named checkpoint is what is resumed
    monkeypatch.chdir(tmp_path)
    assert hpc_resume_path({"default_root_dir": None}, None) == str(tmp_path / "hpc_ckpt_10.ckpt")  # cwd, as Lightning
