"""The README's Python examples run as written, and what the docs name exists."""

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
DOCS = [README, *sorted((ROOT / "docs").glob("*.md")), ROOT / "tests" / "reliability" / "README.md"]
# repository paths the docs point at: configs/..., scripts/x.py, docs/x.md, docker/..., benchmarks/..., tests/...
PATH = re.compile(r"(?<![\w/.-])((?:configs|scripts|benchmarks|docs|docker|tests|src)/[\w./-]*[\w/])")
NAME = re.compile(r"`(anycity(?:\.\w+)+)`")  # `anycity.module.attribute`


def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README has no python example"
    for code in blocks:
        exec(compile(code, str(README), "exec"), {})


def _resolves(dotted: str) -> bool:
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_name_what_exists(doc):
    text = doc.read_text()
    paths = {p.rstrip(".") for p in PATH.findall(text)}
    missing = sorted(p for p in paths if not (ROOT / p).exists())
    missing += sorted(n for n in set(NAME.findall(text)) if not _resolves(n))
    assert not missing, f"{doc.relative_to(ROOT)} names what does not exist: {missing}"
