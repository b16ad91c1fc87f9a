"""Two processes writing one folder at once (two ``anycity predict`` of one photo folder, two ``anycity export`` to one
``--out``): every folder published, or kept and named, is one run's complete copy."""

import multiprocessing as mp
import re
import time
from pathlib import Path

import pytest

from anycity.atomic import atomic_write_bytes, staged_folder

FILES = 12


def _write(out: str, tag: str, barrier, results) -> None:
    """A tiny staged write (``FILES`` files, some in a subfolder, as predict's ``renders/``) that waits at
    ``barrier`` until the other writer has started too."""
    try:
        with staged_folder(out) as stage:
            barrier.wait(timeout=60)
            for i in range(FILES):
                atomic_write_bytes(stage / ("renders" if i % 2 else "") / f"{i:03d}.bin", tag.encode())
                time.sleep(0.005)
        results.put((tag, "published", ""))
    except Exception as e:  # noqa: BLE001 - the parent checks what each writer saw
        results.put((tag, type(e).__name__, str(e)))


def _tags(folder: Path) -> tuple[int, set[str]]:
    files = [p for p in folder.rglob("*") if p.is_file()]
    return len(files), {p.read_text() for p in files}


@pytest.mark.parametrize("round_", range(3))
def test_two_processes_staging_one_folder_publish_one_complete_copy_and_keep_the_other(tmp_path, round_):
    ctx = mp.get_context("fork")
    out, barrier, results = tmp_path / "scene", ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_write, args=(str(out), tag, barrier, results)) for tag in "AB"]
    [p.start() for p in procs]
    got = sorted(results.get(timeout=120) for _ in procs)
    [p.join(timeout=60) for p in procs]
    outcomes = sorted(kind for _, kind, _ in got)
    assert outcomes == ["FileExistsError", "published"], got
    winner = next(tag for tag, kind, _ in got if kind == "published")
    loser, message = next((tag, msg) for tag, kind, msg in got if kind == "FileExistsError")
    assert _tags(out) == (FILES, {winner})  # complete, and one run's only
    m = re.fullmatch(rf"{re.escape(str(out))} appeared while this run wrote it \(another run\?\); this run's "
                     r"complete copy is kept as (\S+)", message)
    assert m, message
    assert _tags(Path(m[1])) == (FILES, {loser})
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([Path(m[1]).name, "scene"])  # no stage left
