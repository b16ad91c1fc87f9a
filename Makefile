# anycity: the commands a newcomer runs. See README.md.
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip

.PHONY: setup test test-floors test-all bench lint quickstart stage2-prior clean docker docker-cpu docker-check gpu-check

setup:
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	@# torch first: the local CPU build here; a CUDA torch already installed on a GPU machine stays.
	@$(PY) -c "import torch" 2>/dev/null || $(PIP) install -q torch==2.13.0
	$(PIP) install -q -e ".[dev,wan,cpu]"

# One pytest worker per CPU core (pytest-xdist), each test process on one thread (tests/conftest.py): on 2 cores
# the suite takes about two thirds of the time one process on both cores does.
PYTEST_WORKERS ?= auto
test:
	$(PY) -m pytest -m "not slow" -n $(PYTEST_WORKERS) --dist worksteal tests

# The suite on the oldest dependencies pyproject.toml allows (.ci/floors.txt), in its own venv; not in CI (~10 min).
# The oldest Python too: make test-floors FLOORS_PYTHON=python3.10 FLOORS_VENV=.venv-floors310 (torch 2.13 for 3.10
# is not on this disk: pip downloads PyPI's CUDA build, 4.6 GB installed, which runs the suite on the CPU).
# The oldest torch too: make test-floors FLOORS_TORCH=2.5.1 FLOORS_VENV=.venv-floors-t25 (PyPI's CUDA build, 5.9 GB
# installed, on the CPU). A venv holding another torch gets FLOORS_TORCH installed over it.
FLOORS_VENV ?= .venv-floors
FLOORS_PYTHON ?= python3
FLOORS_TORCH ?= 2.13.0
test-floors:
	@test -x $(FLOORS_VENV)/bin/python || $(FLOORS_PYTHON) -m venv $(FLOORS_VENV)
	@$(FLOORS_VENV)/bin/python -c "import sys, torch; sys.exit(torch.__version__.split('+')[0] != '$(FLOORS_TORCH)')" \
		2>/dev/null || $(FLOORS_VENV)/bin/python -m pip install -q torch==$(FLOORS_TORCH)
	$(FLOORS_VENV)/bin/python -m pip install -q -e ".[dev,wan,cpu]" -c .ci/floors.txt
	$(FLOORS_VENV)/bin/python -m pytest -m "not slow" -n $(PYTEST_WORKERS) --dist worksteal tests

test-all:
	$(PY) -m pytest tests

quickstart:
	$(PY) scripts/quickstart.py

# Beyond the paper (docs/stage2.md, "Taking the prior's pose"), after `make quickstart`: pretrain the pose prior once
# (about 18 min), then the prior_mix rows of scripts/stage2_tables.py on the quickstart's Stage I (about 10 min).
runs/pose_prior.pt:
	$(PY) scripts/pose_prior.py --data data/quickstart --out $@

stage2-prior: runs/pose_prior.pt
	$(PY) scripts/stage2_tables.py --rows prior_mix,prior_mix_unordered --pose_prior runs/pose_prior.pt --out runs/stage2_prior

bench:
	@for f in benchmarks/[!_]*.py; do echo "== $$f"; $(PY) $$f || exit 1; done

lint:
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/hadolint docker/Dockerfile

clean:
	rm -rf runs .pytest_cache

# Cluster (docs/cluster.md): the CUDA image, its CPU variant, a real CPU build + run here, the first-GPU check.
IMAGE ?= anycity
docker:
	docker build -f docker/Dockerfile -t $(IMAGE):cuda .

docker-cpu:
	docker build -f docker/Dockerfile -t $(IMAGE):cpu --build-arg BASE=python:3.11-slim \
		--build-arg WITH_GSPLAT=0 --build-arg EXTRAS=wan,cpu .

docker-check:
	bash docker/check.sh

gpu-check:
	$(PY) scripts/gpu_check.py
