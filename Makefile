# Two commands do all set-up on a fresh machine:
#   make smoke   a small end-to-end study on CPU (clothgap pipeline --preset smoke)
#   make test    the test suite (what CI runs)
# Each creates or reuses .venv, installing system and Python packages first.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
# The project's CPU machines carry a local torch 2.13.0 CPU wheel; elsewhere pip
# takes a recent release from the index.
TORCH_SPEC ?= torch==2.13.0
OUT    ?= runs/smoke
STAMP  := $(VENV)/.installed

.PHONY: smoke test env clean-env gpu-bundle

smoke: $(STAMP)
	$(VENV)/bin/clothgap pipeline --preset smoke --out $(OUT)

test: $(STAMP)
	$(VENV)/bin/pytest -q

env: $(STAMP)

$(STAMP): pyproject.toml scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PIP) install -q "$(TORCH_SPEC)" || $(PIP) install -q torch
	$(PIP) install -q -e ".[dev]"
	$(PY) -c "import clothgap, sim, render, learn, eval; print('clothgap environment ready')"
	touch $(STAMP)

# The GPU machine's packages in parts (../shared/gpu/README.md) and the simulation's Warp kernels compiled for
# it ahead of time (.gpu/warp-aot: carry it with the last part's call).
gpu-bundle: $(STAMP)
	bash ../shared/gpu/bundle.sh av==16.0.1
	$(PY) scripts/gpu/warp_aot.py

clean-env:
	rm -rf $(VENV)
