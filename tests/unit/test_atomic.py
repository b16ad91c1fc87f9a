"""anycity.atomic: temp names that Lightning's HPC-resume scan ignores, kept permissions, concurrent writers."""

import os
import stat
import threading
from pathlib import Path
from types import SimpleNamespace

import pytest

from anycity.atomic import atomic_open, atomic_path, atomic_write_bytes


def _leftover(path):
    """What a SIGKILL during the write of ``path`` leaves: its temp file, with part of the data."""
    with pytest.raises(KeyboardInterrupt), atomic_open(path) as f:
        name = f.name
        raise KeyboardInterrupt  # the write is abandoned, then its temp file is put back as a kill leaves it
    with open(name, "wb") as f:
        f.write(b"half")
    return name


def test_a_killed_hpc_save_leaves_nothing_lightnings_resume_scan_reads(tmp_path):
    from lightning.pytorch.trainer.connectors.checkpoint_connector import _CheckpointConnector

    (tmp_path / "hpc_ckpt_1.ckpt").write_bytes(b"ckpt")
    tmp = _leftover(tmp_path / "hpc_ckpt_2.ckpt")  # killed while writing the next preemption checkpoint
    connector = _CheckpointConnector(SimpleNamespace(default_root_dir=str(tmp_path)))
    assert connector._hpc_resume_path == str(tmp_path / "hpc_ckpt_1.ckpt")  # was hpc_ckpt_2<pid>.ckpt: not found
    assert _CheckpointConnector.hpc_save_path(tmp_path) == str(tmp_path / "hpc_ckpt_2.ckpt")
    assert os.path.dirname(tmp) == str(tmp_path) and "ckpt" not in os.path.basename(tmp)


def test_stale_temp_files_are_listed_and_removed(tmp_path):
    from anycity.atomic import remove_stale_temp_files, stale_temp_files

    (tmp_path / "last.ckpt").write_bytes(b"ckpt")
    (tmp_path / ".anycity-tmp-notours").write_bytes(b"x")  # not the pattern: kept
    killed = Path(_leftover(tmp_path / "last.ckpt"))
    with atomic_path(tmp_path / "video.mp4") as live:  # being written now: not stale
        live.write_bytes(b"v")
        assert live.suffix == ".mp4" and stale_temp_files(tmp_path) == [killed]
    left = [killed, live.with_name(live.name)]
    left[1].write_bytes(b"v")  # as if that write had been killed too
    assert stale_temp_files(tmp_path, min_age_s=3600) == []
    assert sorted(remove_stale_temp_files(tmp_path)) == sorted(left)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".anycity-tmp-notours", "last.ckpt", "video.mp4"]


@pytest.mark.parametrize("mode", [0o600, 0o664])
def test_replacing_a_file_keeps_its_permissions(tmp_path, mode):
    for write in (lambda p, b: atomic_write_bytes(p, b), _write_via_path):
        p = tmp_path / "last.ckpt"
        p.write_bytes(b"old")
        os.chmod(p, mode)
        write(p, b"new")
        assert p.read_bytes() == b"new" and stat.S_IMODE(p.stat().st_mode) == mode


def _write_via_path(p, data):
    with atomic_path(p) as t:
        t.write_bytes(data)


def test_threads_writing_one_path_do_not_collide(tmp_path):
    p, errors = tmp_path / "f.bin", []

    def write(i):
        try:
            for _ in range(20):
                atomic_write_bytes(p, bytes([65 + i]) * 200_000)
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(repr(e))

    threads = [threading.Thread(target=write, args=(i,)) for i in range(4)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert errors == []
    assert len(set(p.read_bytes())) == 1 and [q.name for q in tmp_path.iterdir()] == ["f.bin"]
