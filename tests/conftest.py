"""Fixtures shared by the integration and reliability tests: tiny synthetic shards, built once per session."""

import pytest


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
