# Two entry points (see README): `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean install

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch first, pinned: the local CPU wheel (an unpinned torch pulls CUDA packages)
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/torchslq demo

# two workers (pytest-xdist) on 2 cores: about 6 minutes with numba's cache warm, 10 on a
# fresh clone, two thirds of that compiling the kernels (cached for later runs)
test: $(STAMP)
	$(PY) -m pytest -n 2 tests

LINT_PATHS := torchslq tests examples benchmarks reproductions

lint: $(STAMP)
	$(VENV)/bin/ruff check $(LINT_PATHS)
	$(VENV)/bin/ruff format --check $(LINT_PATHS)

bench: $(STAMP)
	# mpc declares numpy<2 but runs on numpy 2: install it without its pins, the rest normally
	$(PY) -m pip install -q --no-deps mpc
	$(PY) -m pip install -q scipy crocoddyl casadi
	$(PY) benchmarks/lq_kernel.py
	$(PY) benchmarks/slq.py
	$(PY) benchmarks/peers.py

clean:
	rm -rf $(VENV) runs build *.egg-info
