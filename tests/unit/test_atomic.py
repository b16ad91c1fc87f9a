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


def test_a_failed_atomic_path_write_leaves_no_temp_file(tmp_path):
    """When the writer fails inside ``atomic_path``, its half-written temp file is removed and ``path`` never
    appears: the folder is as before."""
    with pytest.raises(RuntimeError, match="writer failed"), atomic_path(tmp_path / "v.mp4") as t:
        t.write_bytes(b"half a video")
        raise RuntimeError("writer failed")
    assert list(tmp_path.iterdir()) == []


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


def _tree(root) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_two_writers_of_one_staged_folder_each_publish_or_keep_a_complete_copy(tmp_path):
    """Two runs of one folder interleaved: B's start deleted A's half-written ``.scene.partial``, A went on into a
    re-created one and published a scene without its ``scene.ply`` (exit 0)."""
    import re
    from contextlib import ExitStack

    from anycity.atomic import staged_folder

    out = tmp_path / "scene"
    with ExitStack() as a_stack:
        a = a_stack.enter_context(staged_folder(out))  # writer A starts
        atomic_write_bytes(a / "scene.ply", b"A-ply")
        b_cm = staged_folder(out)
        b = b_cm.__enter__()  # writer B starts while A writes
        atomic_write_bytes(a / "sub" / "cameras.json", b"A-cams")
        atomic_write_bytes(b / "scene.ply", b"B-ply")
    assert _tree(out) == {"scene.ply": b"A-ply", "sub/cameras.json": b"A-cams"}  # A's, complete
    atomic_write_bytes(b / "sub" / "cameras.json", b"B-cams")
    with pytest.raises(FileExistsError, match=r"scene appeared while this run wrote it \(another run\?\); this "
                                              r"run's complete copy is kept as .*/\.scene\.kept-\d+-[0-9a-f]{8}$") as e:
        b_cm.__exit__(None, None, None)
    kept = Path(re.search(r"kept as (\S+)$", str(e.value))[1])
    assert _tree(kept) == {"scene.ply": b"B-ply", "sub/cameras.json": b"B-cams"}  # B's, complete, not dropped
    assert _tree(out) == {"scene.ply": b"A-ply", "sub/cameras.json": b"A-cams"}
    assert sorted(p.name for p in tmp_path.iterdir()) == [kept.name, "scene"]  # both stages gone
    with staged_folder(tmp_path / "next") as c:  # a later run of another folder leaves the kept copy alone
        atomic_write_bytes(c / "f", b"c")
    assert kept.is_dir()


def test_a_stage_removed_while_written_is_one_line_not_silently_recreated(tmp_path):
    import shutil

    from anycity.atomic import staged_folder

    out = tmp_path / "scene"
    with pytest.raises(FileNotFoundError, match=r"this run's unfinished copy of .*scene was removed while it was "
                                                r"written \(by another program\?\); nothing is published"):
        with staged_folder(out) as stage:
            atomic_write_bytes(stage / "scene.ply", b"ply")
            shutil.rmtree(stage)
            atomic_write_bytes(stage / "renders" / "000.png", b"png")
    assert not out.exists() and not stage.exists()
    with pytest.raises(FileNotFoundError, match="nothing is published"):  # re-created by someone's mkdir -p
        with staged_folder(out) as stage:
            shutil.rmtree(stage)
            stage.mkdir(parents=True)
            (stage / "half").write_bytes(b"")
    assert not out.exists()


def test_a_write_straight_into_a_removed_stage_names_the_stage_not_a_raw_errno(tmp_path):
    """The stage's own folder, not a sub-folder: no mkdir runs that would notice, so the stage mark is checked."""
    import shutil

    from anycity.atomic import staged_folder

    out = tmp_path / "scene"
    with pytest.raises(FileNotFoundError, match=r"this run's unfinished copy of .*scene was removed while it was "
                                                r"written"):
        with staged_folder(out) as stage:
            shutil.rmtree(stage)
            atomic_write_bytes(stage / "scene.ply", b"ply")
    assert not out.exists() and not stage.exists()


def test_only_the_stages_of_runs_that_no_longer_run_are_dropped(tmp_path):
    import socket
    import subprocess
    import sys

    from anycity.atomic import staged_folder

    out, box = tmp_path / "scene", tmp_path / ".scene.partial"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = socket.gethostname()
    killed = box / f"{int(dead.stdout)}-0123abcd-{host}"  # what a killed run leaves
    live = box / f"{os.getpid()}-89abcdef-{host}"  # another live writer of this host (its pid runs)
    remote = box / f"{int(dead.stdout)}-0123abcd-another-host.example"  # a writer on another machine
    for d in (killed, live, remote):
        (d / "sub").mkdir(parents=True)
        (d / "sub" / "f").write_bytes(b"x")
    (box / "scale.json").write_text("{}")  # an older anycity's stage: its files directly in .scene.partial
    with staged_folder(out) as stage:
        atomic_write_bytes(stage / "f", b"mine")
    assert _tree(out) == {"f": b"mine"}
    assert sorted(p.name for p in box.iterdir()) == sorted([live.name, remote.name])
