# Two entry points for a fresh machine with Python 3.11:
#   make demo   -> creates .venv if missing, installs diffcontact, runs the demo
#   make test   -> creates .venv if missing, installs diffcontact[dev], runs the tests
# torch is pinned through constraints.txt to the 2.13.0 CPU wheel of this machine;
# elsewhere pass CONSTRAINTS= (empty) to let pip choose any recent torch.

PYTHON ?= python3.11
VENV ?= .venv
CONSTRAINTS ?= constraints.txt
PIP_C := $(if $(CONSTRAINTS),-c $(CONSTRAINTS),)
PY := $(VENV)/bin/python

.PHONY: demo test test-slow lint bench reproduce compare clean

$(VENV)/.base: pyproject.toml $(CONSTRAINTS)
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q $(PIP_C) -e .
	touch $@

$(VENV)/.dev: $(VENV)/.base
	$(PY) -m pip install -q $(PIP_C) -e ".[dev]"
	touch $@

demo: $(VENV)/.base
	$(VENV)/bin/diffcontact demo

test: $(VENV)/.dev
	$(PY) -m pytest -q

test-slow: $(VENV)/.dev
	$(PY) -m pytest -q -m slow

lint: $(VENV)/.dev
	$(VENV)/bin/ruff check src tests benchmarks experiments
	$(VENV)/bin/ruff format --check src tests benchmarks experiments

bench: $(VENV)/.dev
	$(PY) benchmarks/run.py

# the paper's learning tables (docs/results.md): about 45 minutes on 2 CPU cores
reproduce: $(VENV)/.base
	$(PY) experiments/reproduce.py --out runs/repro --doc docs/results.md

# the comparison of all models on BP5-e, CP3 and Gyro (docs/experiments.md, docs/results.md)
compare: $(VENV)/.base
	$(PY) experiments/compare.py models --tasks BP5-e CP3 Gyro --out runs/compare \
		--doc docs/results.md --jobs 2

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache .ruff_cache
