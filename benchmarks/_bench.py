"""What the benchmarks share: a positive-count argparse type and a child-process runner whose failure prints the
child's own one-line error. Imported as ``_bench``: a benchmark's folder is ``sys.path[0]`` when it runs.
Not a benchmark itself (nothing runs on import or as a script)."""

from __future__ import annotations

import argparse
import subprocess


def positive_int(text: str) -> int:
    """argparse ``type=`` for counts (steps, repeats, threads, views, samples): a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {value}")
    return value


def run_child(cmd: list[str], what: str, **kwargs) -> str:
    """Run ``cmd`` and return its stdout; if it fails, stop with one line: ``what``, the exit code and the
    child's last stderr line (its own one-line error, or a traceback's last line)."""
    res = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    if res.returncode != 0:
        lines = [line for line in res.stderr.splitlines() if line.strip()]
        raise SystemExit(f"{what} failed (exit {res.returncode}): "
                         f"{lines[-1].strip() if lines else 'no error output'}")
    return res.stdout
