# Two entry points: `make reproduce` (set up + run the default benchmark) and `make test`.
# Both create .venv on first use and reinstall only when requirements.txt or pyproject.toml change.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2
STAMP  := $(VENV)/.installed

# Numba's compile cache lives inside the checkout, so only the first run in a clone compiles (and
# `python -m trace3d.warm` does that first run over $(CORES) processes).
export NUMBA_CACHE_DIR := $(CURDIR)/.numba_cache
export OMP_WAIT_POLICY := PASSIVE
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: setup reproduce test lint dry-run clean-results

setup: $(STAMP)

$(STAMP): requirements.txt pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# The HTML report (tables, plots, captions) is written after the run, from what the run produced.
reproduce: $(STAMP)
	$(BIN)/python -m trace3d.warm --jobs $(CORES)
	$(BIN)/snakemake --cores $(CORES) --show-failed-logs reproduce
	$(BIN)/snakemake --cores 1 reproduce --report results/report.html

# The kernels are compiled first, over $(CORES) processes (trace3d/warm.py), so that no test compiles one;
# then the suite runs on $(CORES) pytest-xdist workers, the whole-DAG runs taking turns on one of them
# (their xdist_group; tests/conftest.py).
test: $(STAMP)
	$(BIN)/python -m trace3d.warm --jobs $(CORES)
	$(BIN)/python -m pytest -q -n $(CORES) --dist loadgroup tests

# ruff (its rules in pyproject.toml's [tool.ruff]) over the Python, then Snakemake's own lint of the rules
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/snakemake --lint

dry-run: $(STAMP)
	$(BIN)/snakemake -n reproduce

clean-results:
	find results -mindepth 1 -maxdepth 1 ! -name README.md -exec rm -rf {} +
