"""A write that dies midway (full disk, kill) leaves the old file or none under the final name, and no temp file.

Covers the ``anycity export`` writers (``scene.ply``, ``.splat``, COLMAP text, ``transforms.json``, ``scale.json``)
and its output folder as a whole, the city merge's streamed ``scene.ply`` (:class:`anycity.city.PlyStream`) and the
city spill folder.
"""

from __future__ import annotations

import errno
import io
import os
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
import traceback

import pytest
import torch
from helpers.faults import fail_writes_midway

from anycity.city import ChunkedScene, PlyStream
from anycity.export import save_cameras, save_ply
from anycity.export.cli import export
from anycity.export.formats import save_colmap, save_scale, save_splat, save_transforms
from anycity.export.views import save_view_pngs
from anycity.structures import Gaussians


def _gaussians(n: int) -> Gaussians:
    gen = torch.Generator().manual_seed(0)
    return Gaussians(torch.randn(1, n, 3, generator=gen), torch.randn(1, n, 4, generator=gen),
                     torch.rand(1, n, 3, generator=gen) + 0.01, torch.rand(1, n, generator=gen),
                     torch.randn(1, n, 4, 3, generator=gen))


def _files(root) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def _cams(v: int = 3):
    return torch.eye(4).repeat(v, 1, 1).double(), torch.tensor([[40.0, 0, 24], [0, 40, 16], [0, 0, 1]]).repeat(v, 1, 1)


WRITERS = {
    "scene.ply": lambda d: save_ply(_gaussians(20), d / "scene.ply"),
    "scene.splat": lambda d: save_splat(_gaussians(20), d / "scene.splat"),
    "points3D.txt": lambda d: save_colmap(d / "sparse" / "0", *_cams(), 48, 32, ["a", "b", "c"], _gaussians(20)),
    "transforms.json": lambda d: save_transforms(d / "transforms.json", *_cams(), 48, 32, ["a", "b", "c"]),
    "scale.json": lambda d: save_scale(d / "scale.json", 2.5, "splat"),
}


@pytest.mark.parametrize("name", list(WRITERS))
def test_export_write_failing_midway_leaves_no_file_under_the_final_name(tmp_path, monkeypatch, name):
    fail_writes_midway(monkeypatch, name)
    with pytest.raises(OSError, match=f"disk full writing .*{name}") as e:
        WRITERS[name](tmp_path)
    monkeypatch.undo()
    for frame, _ in traceback.walk_tb(e.value.__traceback__):  # the error keeps the writer's buffers: none may
        for buf in [v for v in frame.f_locals.values() if isinstance(v, io.BytesIO)]:  # still be exported, else
            buf.close()  # freeing it (the garbage collector, later, anywhere) raises BufferError
    left = _files(tmp_path)
    assert not [f for f in left if name in f], left  # neither the final name nor a temp file
    if name == "points3D.txt":  # the model's other files were written whole before it
        assert left == ["sparse/0/cameras.txt", "sparse/0/images.txt"]
    else:
        assert left == []
    WRITERS[name](tmp_path)  # a re-run writes it
    assert name in "\n".join(_files(tmp_path))


def _stream(path, **kw) -> PlyStream:
    s = PlyStream(path, **kw)
    s.write(_gaussians(30))
    return s


def test_ply_stream_close_fsyncs_the_file_before_its_rename_and_the_folder_after(tmp_path, monkeypatch):
    final, real_fsync, calls = tmp_path / "scene.ply", os.fsync, []

    def fsync(fd):
        st = os.fstat(fd)
        calls.append((stat.S_ISDIR(st.st_mode) and st.st_ino == tmp_path.stat().st_ino, st.st_size, final.exists()))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    _stream(final).close()
    size = final.stat().st_size
    assert (False, size, False) in calls  # the whole file's data is on disk before it takes the final name
    assert any(is_dir and exists for is_dir, _, exists in calls)  # then the folder holding the new name
    assert _files(tmp_path) == ["scene.ply"]


def test_ply_stream_exception_before_close_keeps_the_old_file_and_no_temp(tmp_path):
    final = tmp_path / "scene.ply"
    final.write_bytes(b"previous run")
    with pytest.raises(RuntimeError, match="killed"), _stream(final):
        raise RuntimeError("killed")
    assert final.read_bytes() == b"previous run" and _files(tmp_path) == ["scene.ply"]


def test_ply_stream_disk_full_in_close_leaves_no_file(tmp_path, monkeypatch):
    s = _stream(tmp_path / "scene.ply")

    def copy_half(src, dst, *a):
        dst.write(src.read()[:100])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(shutil, "copyfileobj", copy_half)
    with pytest.raises(OSError, match=r"disk full writing .*scene\.ply"):
        s.close()
    assert _files(tmp_path) == []


def test_city_spill_of_a_killed_run_is_hidden_and_removed_by_the_next_run(tmp_path):
    plan, names, K = [[0, 1, 2], [1, 2, 3]], ["a", "b", "c", "d"], torch.eye(3).expand(3, 3, 3)
    out = tmp_path / "flight"
    killed = ChunkedScene(plan, names, (2, 2), out=out)
    killed.add(0, _gaussians(12), torch.eye(4).expand(3, 4, 4), K)  # then SIGKILL: no finish, no close
    left = _files(tmp_path)
    assert left and all(f.startswith(".") for f in left), left  # nothing that looks like a finished output
    with pytest.warns(UserWarning, match="removing the spill folder an interrupted run left"):
        rerun = ChunkedScene(plan, names, (2, 2), out=out)
    assert _files(tmp_path) == [] and rerun.spill.parent == tmp_path
    rerun.close()
    assert list(tmp_path.iterdir()) == []


def _predict_folder(root):
    d = root / "pred" / "sceneA"
    save_ply(_gaussians(20), d / "scene.ply")
    save_cameras(d / "cameras.json", *_cams(), 48, 32)
    save_view_pngs(d, "inputs", torch.rand(3, 3, 32, 48), range(3))
    return d


def test_an_export_that_dies_midway_leaves_no_out_folder_and_the_rerun_needs_no_overwrite(tmp_path, monkeypatch):
    src, out = _predict_folder(tmp_path), tmp_path / "o"
    fail_writes_midway(monkeypatch, "points3D.txt")  # the colmap export's last file, after scale.json and images/
    with pytest.raises(OSError, match="disk full writing"):
        export(src, "colmap", out)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pred"]  # no out folder, no staging folder
    assert export(src, "colmap", out) == out / "sparse" / "0"  # not refused as "not empty"
    assert _files(out) == ["images/000.png", "images/001.png", "images/002.png", "scale.json",
                           "sparse/0/cameras.txt", "sparse/0/images.txt", "sparse/0/points3D.txt"]


def test_the_staging_folder_a_killed_export_left_is_dropped_and_an_empty_out_is_filled(tmp_path):
    src, out = _predict_folder(tmp_path), tmp_path / "o"
    killed = tmp_path / ".o.partial"  # what SIGKILL during the export leaves: hidden, never an --out folder
    (killed / "sparse").mkdir(parents=True)
    (killed / "scale.json").write_text("{}")
    assert export(src, "splat", out) == out / "scene.splat"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "pred"]
    assert _files(out) == ["scale.json", "scene.splat"]
    (tmp_path / "empty").mkdir()  # an existing empty --out folder is written into, not refused
    assert export(src, "ply", tmp_path / "empty") == tmp_path / "empty" / "scene.ply"
    assert _files(tmp_path / "empty") == ["scale.json", "scene.ply"]
    (tmp_path / "f").write_text("x")
    with pytest.raises(FileExistsError, match="f is a file, not a folder; pass --out NEW_DIR"):
        export(src, "splat", tmp_path / "f")


def test_an_export_killed_midway_leaves_only_its_hidden_staging_folder(tmp_path):
    src, out = _predict_folder(tmp_path), tmp_path / "o"
    code = textwrap.dedent(f"""
        import os, signal
        import anycity.export.formats as formats
        from anycity.export.cli import export
        formats.save_colmap = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)  # after scale.json and images/
        export({str(src)!r}, "colmap", {str(out)!r})
    """)
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == -signal.SIGKILL
    assert sorted(p.name for p in tmp_path.iterdir()) == [".o.partial", "pred"]
    # it died with files written, in its own stage <pid>-<hex>-<host>/
    assert any(f.endswith("/scale.json") for f in _files(tmp_path / ".o.partial"))
    export(src, "colmap", out)  # the rerun is not refused and drops the staging folder
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "pred"] and "sparse/0/points3D.txt" in _files(out)
