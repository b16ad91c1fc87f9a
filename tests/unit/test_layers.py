"""The import rules of docs/design.md ("Imports point down only"), read from the source with ``ast``: every import,
also one inside a function, goes to a lower layer, and each optional or heavy dependency stays in its modules."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "anycity"

# A package may import packages of a lower rank only (and itself). Keep in step with docs/design.md.
RANK = {
    "structures": 0, "atomic": 0, "safe_load": 0,
    "anycity": 1, "geometry": 1,  # "anycity": the package's own __init__ (re-exports structures)
    "render": 2, "models": 2, "losses": 2, "metrics": 2,
    "export": 3,
    "city": 4, "viewer": 4,
    "data": 5,  # the photo loader orders photos with anycity.city.plan
    "callbacks": 6,
    "lit": 7,
    "cli_sources": 8,  # the command line read before the parse
    "cli": 9,
}
# third-party package -> the modules (or packages) that may import it; LAZY: only inside a function there, so that
# importing the module works without the package (an optional extra) or stays fast (the front door)
CONFINED = {
    "lightning": ("anycity.lit", "anycity.callbacks", "anycity.cli", "anycity.safe_load"),
    "pytorch_lightning": (),
    "gsplat": ("anycity.render.gsplat_backend",),
    "diffusers": ("anycity.models.video_prior",),
    "numba": ("anycity.render.cpu_backend", "anycity.render._cpu_project", "anycity.render._cpu_raster"),
    "viser": ("anycity.viewer.server",),
    "imageio_ffmpeg": ("anycity.viewer.video",),
}
LAZY = {("lightning", "anycity.safe_load"), ("lightning", "anycity.cli"), ("gsplat", "anycity.render.gsplat_backend"),
        ("diffusers", "anycity.models.video_prior"), ("viser", "anycity.viewer.server"),
        ("imageio_ffmpeg", "anycity.viewer.video")}
NUMBA_MODULES = CONFINED["numba"]  # they import numba when imported: other modules import them lazily


def _module_name(path: Path) -> str:
    parts = path.relative_to(SRC.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, bool, int]]:
    """``(imported module, at module level, line)`` for every import in ``path``, relative ones resolved."""
    module, tree = _module_name(path), ast.parse(path.read_text(), str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((a.name, top, child.lineno) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")[: len(package.split(".")) - child.level + 1]
                    name = ".".join(base + ([child.module] if child.module else []))
                else:
                    name = child.module
                found.extend((f"{name}.{a.name}" if name.startswith("anycity") else name, top, child.lineno)
                             for a in child.names)
            visit(child, top and not isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))

    visit(tree, True)
    return found


def _package(module: str) -> str:
    """``anycity.render.api`` -> ``render``; ``anycity`` -> ``anycity``; ``anycity.cli`` -> ``cli``."""
    return module.split(".")[1] if "." in module else module


def _within(module: str, owners: tuple[str, ...]) -> bool:
    return any(module == o or module.startswith(o + ".") for o in owners)


FILES = sorted(SRC.rglob("*.py"))


def test_every_package_has_a_layer():
    assert {_package(_module_name(f)) for f in FILES} <= RANK.keys()


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(SRC)))
def test_imports_point_down(path):
    module = _module_name(path)
    bad = []
    for name, top, line in _imports(path):
        root = name.split(".")[0]
        if root == "anycity":
            target = _package(name)
            target = target if target in RANK else "anycity"  # `from anycity import Gaussians`
            src = _package(module)
            if target != src and RANK[target] >= RANK[src]:
                bad.append(f"line {line}: {src} (layer {RANK[src]}) imports {name} (layer {RANK[target]})")
            if top and _within(name, NUMBA_MODULES) and not _within(module, NUMBA_MODULES):
                bad.append(f"line {line}: {name} needs numba (the optional [cpu] extra); import it inside a function")
        elif root in CONFINED:
            if not _within(module, CONFINED[root]):
                bad.append(f"line {line}: {root} is imported outside {', '.join(CONFINED[root]) or 'the package'}")
            elif top and any(_within(module, (m,)) for r, m in LAZY if r == root):
                bad.append(f"line {line}: {root} is imported at module level; import it inside the function")
    assert not bad, f"{module}: " + "; ".join(bad)


def test_the_checker_sees_violations(tmp_path, monkeypatch):
    """A lazy upward import and a module-level optional import are both found (the rules are not vacuous)."""
    pkg = tmp_path / "anycity"
    (pkg / "geometry").mkdir(parents=True)
    (pkg / "models").mkdir()
    upward = pkg / "geometry" / "bad.py"
    upward.write_text("def f():\n    from anycity.lit.base import AnyCityModule\n")
    eager = pkg / "models" / "video_prior.py"
    eager.write_text("import diffusers\n")
    monkeypatch.setattr(sys.modules[__name__], "SRC", pkg)
    with pytest.raises(AssertionError, match=r"geometry \(layer 1\) imports anycity.lit.base.AnyCityModule"):
        test_imports_point_down(upward)
    with pytest.raises(AssertionError, match="diffusers is imported at module level"):
        test_imports_point_down(eager)
