"""Fixtures shared by the integration and reliability tests: tiny synthetic shards, built once per session (per
pytest-xdist worker)."""

import os

import pytest

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs one worker per core: one torch thread each (and in the processes the tests start, which
    # inherit this), or torch's pool would put two threads on every core. The fused CPU kernels follow torch's
    # count; NUMBA_NUM_THREADS stays as it is, so tests that set 2 threads still get them. Set before torch loads.
    for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_var, "1")
# torch's own libgomp reads its wait policy when torch loads (the fused CPU renderer's setting reaches only numba's
# libgomp): after a first fused render, a worker's later torch work ran 5x slower beside one busy process (a 5 s test
# took 25-32 s), shrinking every timing margin. Tests only: with 2 torch threads a training step is 2x slower passive
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@pytest.fixture(scope="session", autouse=True)
def _tmpdir_in_pytest_folder(tmp_path_factory):
    """Point $TMPDIR at pytest's own (rotated) folder, so what the code under test leaves there by design (the
    skip logs a run names in its messages) does not pile up in the machine's /tmp run after run."""
    old = os.environ.get("TMPDIR")
    os.environ["TMPDIR"] = str(tmp_path_factory.mktemp("tmpdir"))
    yield
    if old is None:
        os.environ.pop("TMPDIR", None)
    else:
        os.environ["TMPDIR"] = old


@pytest.fixture(autouse=True)
def _no_state_leaks_between_tests():
    """Restore what an in-process run changes for the rest of its worker, so that no test's outcome depends on which
    tests pytest-xdist handed that worker before it: a fit with ``--trainer.deterministic true`` leaves torch's
    deterministic algorithms on (slower, and some ops refuse), LightningCLI's seeding leaves ``PL_GLOBAL_SEED`` and
    ``PL_SEED_WORKERS`` in the environment and moves the global RNG."""
    import torch

    env, rng = dict(os.environ), torch.get_rng_state()
    deterministic, warn_only = torch.are_deterministic_algorithms_enabled(), \
        torch.is_deterministic_algorithms_warn_only_enabled()
    yield
    torch.use_deterministic_algorithms(deterministic, warn_only=warn_only)
    torch.set_rng_state(rng)
    if dict(os.environ) != env:
        os.environ.clear()
        os.environ.update(env)


@pytest.fixture(scope="session")
def tiny_shards(tmp_path_factory):
    """3 synthetic cities x 8 views at 32x32 (train/val/test one scene each)."""
    from anycity.data.cli import data_main

    out = tmp_path_factory.mktemp("shards")
    rc = data_main(["synth", "--out", str(out), "--scenes", "3", "--views", "8", "--size", "32x32", "--workers", "1"])
    assert rc in (0, None)
    return out


@pytest.fixture(scope="session")
def ddp_shards(tmp_path_factory):
    """30 cities x 8 views at 32x32 (24 train, 3 val, 3 test scenes) for the two-process tests (DDP, SLURM)."""
    from helpers.ddp_probe import make_shards

    return make_shards(tmp_path_factory.mktemp("ddp_shards"))
