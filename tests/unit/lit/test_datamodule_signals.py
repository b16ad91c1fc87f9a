"""DataLoader workers of AerialDataModule ignore SIGUSR1 and keep torch's own SIGTERM handler: only the main process
answers SLURM's signals, a process that leaves a loader unfinished still exits, and a worker its loader ends exits
quietly."""

import pickle
import signal
import subprocess
import sys
from types import SimpleNamespace

import torch

from anycity.lit.datamodule import AerialDataModule


class _ReportSignals(torch.utils.data.IterableDataset):
    def __iter__(self):
        yield torch.tensor([signal.getsignal(signal.SIGUSR1) is signal.SIG_IGN])


def _lightning_like_handler(signum, frame):  # what a forked worker would otherwise inherit
    raise AssertionError("a DataLoader worker ran the main process's signal handler")


def _dm(root):
    for split in ("train", "val", "test"):
        (root / f"{split}-000000.tar").touch()  # building a loader reads no shard
    pattern = str(root / "{}-000000.tar")
    return AerialDataModule(train_shards=pattern.format("train"), val_shards=pattern.format("val"),
                            test_shards=pattern.format("test"), image_size=(32, 32), num_context=2, num_dense=0,
                            num_targets=1, num_workers=2, epoch_samples=8, batch_size=1)


def test_every_loader_gives_its_workers_a_picklable_init_that_ignores_slurm_signals(tmp_path):
    dm = _dm(tmp_path)
    loaders = [dm.train_dataloader(), dm.val_dataloader(), dm.test_dataloader()]
    total = SimpleNamespace(processed=3)  # a resumed fit (Lightning's restored loop progress): the _SkipFirst loader
    dm.trainer = SimpleNamespace(fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=SimpleNamespace(
        total=total))))
    loaders.append(dm.train_dataloader())
    assert loaders[-1].dataset.batches == 3
    old = {s: signal.signal(s, _lightning_like_handler) for s in (signal.SIGUSR1, signal.SIGTERM)}
    try:
        for loader in loaders:
            init = pickle.loads(pickle.dumps(loader.worker_init_fn))  # spawned workers get it pickled
            seen = list(torch.utils.data.DataLoader(_ReportSignals(), batch_size=None, num_workers=1,
                                                    worker_init_fn=init))
            assert [t.tolist() for t in seen] == [[True]]
        assert signal.getsignal(signal.SIGUSR1) is _lightning_like_handler  # the main process keeps its handler
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def test_a_worker_its_loader_terminates_exits_quietly():
    """The init reset SIGTERM to its default action, replacing torch's worker handler (exit 0 when the loader's
    process sends it): workers then died by the signal, and torch printed 'DataLoader worker killed by signal:
    Terminated' at exit. Lightning's handler, inherited at fork, must not run in the worker either."""
    code = """
import itertools, os, signal, torch
from anycity.lit.datamodule import worker_init_fn
class Forever(torch.utils.data.IterableDataset):
    def __iter__(self):
        return (torch.zeros(1) for _ in itertools.count())
def lightning_like(signum, frame):
    os._exit(3)
signal.signal(signal.SIGTERM, lightning_like)
it = iter(torch.utils.data.DataLoader(Forever(), batch_size=None, num_workers=1, worker_init_fn=worker_init_fn()))
next(it)
w = it._workers[0]
os.kill(w.pid, signal.SIGTERM)
w.join(20)
print("worker exit code", w.exitcode, flush=True)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "worker exit code 0" in out.stdout, (out.stdout, out.stderr[-2000:])
    assert "killed by signal" not in out.stderr, out.stderr[-2000:]


def test_the_init_runs_an_earlier_worker_init_fn_too():
    from anycity.lit.datamodule import worker_init_fn

    calls = []
    old = {s: signal.getsignal(s) for s in (signal.SIGUSR1, signal.SIGTERM)}
    try:
        worker_init_fn(calls.append)(3)  # called in this process: restore its handlers after
        assert calls == [3] and signal.getsignal(signal.SIGUSR1) is signal.SIG_IGN
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def test_a_process_that_leaves_a_loader_unfinished_still_exits():
    """torch ends a loader's workers with SIGTERM at exit: workers that ignored it kept pytest alive for minutes."""
    code = """
import itertools, torch
from anycity.lit.datamodule import worker_init_fn
class Forever(torch.utils.data.IterableDataset):
    def __iter__(self):
        return (torch.zeros(1) for _ in itertools.count())
it = iter(torch.utils.data.DataLoader(Forever(), batch_size=None, num_workers=2, worker_init_fn=worker_init_fn()))
next(it)
print("done", flush=True)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "done" in out.stdout, out.stderr[-2000:]
