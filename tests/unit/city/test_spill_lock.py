"""A second run of the same scene must not delete the spill folder of a run that is still writing it."""

import os
import subprocess
import sys
import textwrap

import pytest
import torch

from anycity.city import ChunkedScene
from anycity.city.scene import work_dir
from anycity.structures import Gaussians

PLAN, NAMES = [[0, 1, 2], [1, 2, 3]], ["a", "b", "c", "d"]

HOLDER = textwrap.dedent("""
    import sys, torch
    from anycity.city import ChunkedScene
    from anycity.structures import Gaussians
    scene = ChunkedScene([[0, 1, 2], [1, 2, 3]], ["a", "b", "c", "d"], (2, 2), out=sys.argv[1])
    g = Gaussians(torch.zeros(1, 12, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, 12, 4), torch.ones(1, 12, 3),
                  torch.ones(1, 12), torch.zeros(1, 12, 1, 3))
    scene.add(0, g, torch.eye(4).expand(3, 4, 4), torch.eye(3).expand(3, 3, 3))
    print("ready", flush=True)
    sys.stdin.readline()  # running until the test kills it
""")


def _holder(out):
    """Another process running chunk 0 of ``out``'s city, started and waiting."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


@pytest.mark.skipif(sys.platform == "win32", reason="flock is POSIX")
def test_a_concurrent_run_of_the_same_scene_is_refused_and_leaves_the_first_ones_spill(tmp_path):
    """The second run removed the hidden spill folder as if a killed run had left it: the first run's chunks
    went, and it then merged the second run's chunk files or failed in finish."""
    out = tmp_path / "flight"
    proc = _holder(out)
    try:
        spill = work_dir(out)
        before = sorted(p.name for p in spill.iterdir())
        assert before == ["chunk_00000.pt"]
        with pytest.raises(ValueError, match=r"flight: another anycity predict is writing this scene \(its spill "
                                             r"folder .*\.flight\.anycity_city_work is in use\); wait for it to "
                                             r"end, or pass another --export\.out_dir$"):
            ChunkedScene(PLAN, NAMES, (2, 2), out=out)
        assert sorted(p.name for p in spill.iterdir()) == before  # the running one's chunks are kept
    finally:
        proc.kill()
        proc.wait()
    # killed: the kernel dropped its lock, so its spill is a leftover the next run removes
    with pytest.warns(UserWarning, match="removing the spill folder an interrupted run left"):
        rerun = ChunkedScene(PLAN, NAMES, (2, 2), out=out)
    assert list(rerun.spill.iterdir()) == []
    rerun.close()
    assert list(tmp_path.iterdir()) == []


def test_a_closed_scenes_folder_is_free_for_the_next_run(tmp_path):
    out = tmp_path / "flight"
    first = ChunkedScene(PLAN, NAMES, (2, 2), out=out)
    g = Gaussians(torch.zeros(1, 12, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, 12, 4), torch.ones(1, 12, 3),
                  torch.ones(1, 12), torch.zeros(1, 12, 1, 3))
    first.add(0, g, torch.eye(4).expand(3, 4, 4), torch.eye(3).expand(3, 3, 3))
    first.close()
    first.close()  # twice: as finish and then the export's drop do
    second = ChunkedScene(PLAN, NAMES, (2, 2), out=out)  # no warning: nothing was left
    assert list(second.spill.iterdir()) == []
    second.close()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (a device whose writes fail ENOSPC)")
def test_a_full_disk_while_spilling_a_chunk_names_the_file_and_the_bytes(tmp_path, monkeypatch):
    """torch.save straight to the spill file failed ENOSPC as ``RuntimeError: [enforce fail at inline_container.cc]``,
    so predict printed a traceback instead of the CLI's one-line disk-full error (an OSError naming the file)."""
    import errno

    import anycity.atomic

    scene = ChunkedScene(PLAN, NAMES, (2, 2), out=tmp_path / "flight")
    spill = scene.spill
    (spill / "chunk_00000.pt").symlink_to("/dev/full")  # where the spill file goes: the full disk
    real = anycity.atomic.temp_name

    def on_the_full_disk(folder, suffix=""):  # as is the temp file a crash-safe write puts beside it
        if os.path.samefile(folder, spill):
            full = real(folder, suffix)
            full.symlink_to("/dev/full")
            return full
        return real(folder, suffix)

    monkeypatch.setattr(anycity.atomic, "temp_name", on_the_full_disk)
    g = Gaussians(torch.zeros(1, 12, 3), torch.tensor([1.0, 0, 0, 0]).expand(1, 12, 4), torch.ones(1, 12, 3),
                  torch.ones(1, 12), torch.zeros(1, 12, 1, 3))
    with pytest.raises(OSError, match=r"disk full writing .*chunk_00000\.pt: \d+ bytes needed; free space on ") as e:
        scene.add(0, g, torch.eye(4).expand(3, 4, 4), torch.eye(3).expand(3, 3, 3))
    assert e.value.errno == errno.ENOSPC and 0 not in scene.spilled
    assert sorted(p.name for p in spill.iterdir()) == ["chunk_00000.pt"]  # no temp file left
    scene.close()
