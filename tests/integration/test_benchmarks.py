"""The benchmarks' arguments and guards, in-process with fakes (no benchmark runs): a foreign ``--root`` survives
data.py, a child's one-line error reaches the user, unknown cases and non-positive counts stop in one line, the
memory count keeps diffusers' float32 modules, and the peer ratio is printed only where it compares like with
like."""

import queue
import subprocess
import sys

import pytest
import torch
from helpers.scripts import ROOT, load_script


@pytest.fixture
def bench(monkeypatch):
    """Loads ``benchmarks/<name>.py`` with its folder on ``sys.path`` (as when it runs as a script)."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))

    def load(name: str, *argv: str):
        monkeypatch.setattr(sys, "argv", [f"{name}.py", *argv])
        return load_script(name, "benchmarks")
    return load


def _one_line_error(capsys, exc) -> str:
    """The message a ``SystemExit`` printed (argparse's on stderr, or its own), checked to be one line."""
    msg = exc.value.code if isinstance(exc.value.code, str) else capsys.readouterr().err.strip().splitlines()[-1]
    assert "\n" not in msg and "Traceback" not in msg
    return msg


# 1. data.py --root


def test_data_foreign_root_is_left_alone(bench, tmp_path, capsys):
    user = tmp_path / "data"  # e.g. `--root data` for `--root data/bench-448`
    (user / "synth").mkdir(parents=True)
    (user / "synth" / "my_shard.tar").write_text("precious")
    (user / "notes.txt").write_text("precious")
    m = bench("data", "--root", str(user), "--skip-synth")
    m.synth = lambda *a, **k: pytest.fail("synth ran in a folder the benchmark did not make")
    with pytest.raises(SystemExit) as exc:
        m.main()
    msg = _one_line_error(capsys, exc)
    assert msg.startswith(f"--root {user}:") and "bench_data.json" in msg and "leave --root out" in msg
    assert (user / "notes.txt").read_text() == "precious" and (user / "synth" / "my_shard.tar").exists()


def test_data_rebuilds_only_its_own_folders(bench, tmp_path, monkeypatch):
    m = bench("data")
    made = []

    def fake_synth(out, *a):
        made.append(out)
        out.mkdir(parents=True, exist_ok=True)
        return 1.0
    monkeypatch.setattr(m, "bench_synth", fake_synth)
    ours = tmp_path / "ours"
    ours.mkdir()
    (ours / m.MARKER).write_text("{}")
    (ours / "index.json").write_text("not json")  # an older schema: rebuilt, as the default folder is
    m.prepare_root(ours, default=False)
    m.prepare_root(tmp_path / "new", default=False)
    (tmp_path / "default").mkdir()
    (tmp_path / "default" / "old.tar").write_text("")
    m.prepare_root(tmp_path / "default", default=True)
    assert made == [ours, tmp_path / "new", tmp_path / "default"]
    assert (tmp_path / "new" / m.MARKER).is_file()


def test_data_photos_go_to_a_temporary_folder_and_the_read_size_is_the_stored_one(bench, tmp_path, monkeypatch,
                                                                                     capsys):
    m = bench("data", "--skip-synth", "--root", str(tmp_path / "shards"), "--samples", "2")
    monkeypatch.chdir(tmp_path)
    folders = []
    monkeypatch.setattr(m, "prepare_root", lambda root, default: None)
    monkeypatch.setattr(m, "stored_size", lambda root: "320x240")
    monkeypatch.setattr(m, "bench_read", lambda *a: (1.0, 1.0))
    monkeypatch.setattr(m, "bench_photos", lambda folder: folders.append(folder) or (1.0, 2.0, 40.0))
    m.main()
    out = capsys.readouterr().out
    assert "stored at 320x240" in out and "views at 448x448, " not in out
    assert len(folders) == 1 and not folders[0].exists() and not (tmp_path / "data").exists()


# 2. a child's error


def _failing_run(line: str):
    def run(cmd, check=False, **kw):
        err = f"Traceback (most recent call last):\n  ...\n{line}\n"
        res = subprocess.CompletedProcess(cmd, 1, stdout="", stderr=err)
        if check:
            raise subprocess.CalledProcessError(1, cmd, res.stdout, res.stderr)
        return res
    return run


@pytest.mark.parametrize("script, argv, line, named", [
    ("city", ["--views", "40", "--chunk", "8", "--overlap", "8", "--threads", "1"],
     "ValueError: overlap 8 must be smaller than chunk 8; lower --overlap", "40 photos"),
    ("render", ["--cold-compile"], "ModuleNotFoundError: No module named 'numba'", "--cold-compile"),
])
def test_a_child_process_error_is_shown_in_one_line(bench, monkeypatch, capsys, script, argv, line, named):
    m = bench(script, *argv)
    monkeypatch.setattr(subprocess, "run", _failing_run(line))
    with pytest.raises(SystemExit) as exc:
        m.main()
    msg = _one_line_error(capsys, exc)
    assert named in msg and msg.endswith(line)


# 3. and 4. argument validation


class _FakeContext:
    """A ``multiprocessing`` context whose processes put a made-up row instead of rendering."""

    Queue = queue.Queue

    class Process:
        def __init__(self, target, args):
            self.args, self.exitcode = args, 0

        def start(self):
            case, backend, *_, q, _device = self.args
            q.put(dict(case=case, backend=backend, n=1, size="1x1", overlaps=0.0, int_overlaps=0.0, fwd_ms=100.0,
                       fwdbwd_ms=200.0, peak_rss_mb=1.0))

        def join(self):
            pass


def test_render_unknown_case_is_refused(bench, monkeypatch, capsys):
    m = bench("render", "--cases", "10k,10K", "--backends", "torch", "--threads", "1", "--repeats", "1")
    monkeypatch.setattr(m.mp, "get_context", lambda *a: pytest.fail("cases ran"))
    with pytest.raises(SystemExit) as exc:
        m.main()
    assert exc.value.code == 2
    msg = _one_line_error(capsys, exc)
    assert "--cases" in msg and "'10K'" in msg and "10k, 100k, 800k" in msg


@pytest.mark.parametrize("name, argv, option", [
    ("train_step", ["--steps", "0"], "--steps"),
    ("inference", ["--repeats", "0"], "--repeats"),
    ("render", ["--repeats", "-1"], "--repeats"),
    ("render", ["--threads", "two"], "--threads"),
    ("data", ["--samples", "0"], "--samples"),
    ("city", ["--views", "48", "0"], "--views"),
])
def test_counts_must_be_positive(bench, monkeypatch, capsys, name, argv, option):
    m = bench(name, *argv)
    monkeypatch.setattr(torch, "set_num_threads", lambda n: pytest.fail(f"{name} ran with {argv}"))
    if hasattr(m, "mp"):
        monkeypatch.setattr(m.mp, "get_context", lambda *a: pytest.fail(f"{name} ran with {argv}"))
    if hasattr(m, "read_index"):
        monkeypatch.setattr(m, "read_index", lambda *a: pytest.fail(f"{name} ran with {argv}"))
    if name == "city":
        monkeypatch.setattr(subprocess, "run", lambda *a, **k: pytest.fail(f"{name} ran with {argv}"))
    with pytest.raises(SystemExit) as exc:
        m.main()
    assert exc.value.code == 2
    msg = _one_line_error(capsys, exc)
    assert f"argument {option}" in msg and "whole number >= 1" in msg


# 5. memory.py


def test_memory_keeps_diffusers_float32_modules(bench):
    m = bench("memory")

    class Tiny(torch.nn.Module):
        _keep_in_fp32_modules = ["norm"]

        def __init__(self):
            super().__init__()
            self.proj = torch.nn.Linear(2, 2)
            self.norm = torch.nn.LayerNorm(2)
            self.block = torch.nn.ModuleDict({"norm": torch.nn.LayerNorm(2), "normal": torch.nn.Linear(2, 2)})

    net = m.keep_fp32_modules(Tiny().to(torch.bfloat16))
    dtypes = {n: p.dtype for n, p in net.named_parameters()}
    assert {n for n, d in dtypes.items() if d == torch.float32} == {
        "norm.weight", "norm.bias", "block.norm.weight", "block.norm.bias"}
    assert dtypes["proj.weight"] == dtypes["block.normal.weight"] == torch.bfloat16


# 6. render.py's peer ratio


@pytest.mark.parametrize("threads, shown", [("1", False), ("2", True)])
def test_render_peer_ratio_only_at_its_thread_count(bench, monkeypatch, capsys, threads, shown):
    m = bench("render", "--cases", "100k", "--backends", "torch", "--threads", threads, "--repeats", "1")
    monkeypatch.setattr(m.mp, "get_context", lambda *a: _FakeContext)
    m.main()
    out = capsys.readouterr().out
    assert ("faster fwd+bwd than gsplat-pytorch (2287 ms at 2 threads" in out) == shown
    assert ("no gsplat-pytorch ratio" in out) != shown
