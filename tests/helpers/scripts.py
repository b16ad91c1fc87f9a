"""Load a file of ``scripts/`` or ``benchmarks/`` as a module, so that tests call its ``main`` and helpers
in-process."""

import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[2]


def load_script(name: str, folder: str = "scripts") -> ModuleType:
    """``<folder>/<name>.py`` (``scripts`` or ``benchmarks``) as a fresh module (not registered in ``sys.modules``)."""
    spec = importlib.util.spec_from_file_location(f"{name}_{folder}", ROOT / folder / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def anycity_in_process(cmd: str, args: list[str], row: str) -> None:
    """A stand-in for ``scripts/stage2_tables.py``'s ``_anycity``: the row's ``anycity CMD ARGS`` in this process
    (each launch of its own would cost its imports, ~8 s on 2 cores)."""
    from anycity.cli import main

    assert main([cmd, *args]) == 0, f"row {row}: anycity {cmd} failed"
