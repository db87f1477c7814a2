# Two entry points: `make reproduce` (set up + run the default benchmark) and `make test`.
# Both create .venv on first use and reinstall only when requirements.txt or pyproject.toml change.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CORES  ?= 2
STAMP  := $(VENV)/.installed

# Numba's compile cache lives inside the checkout, so only the first run in a clone compiles (and
# `python -m trace3d.tooling.warm` does that first run over $(CORES) processes).
export NUMBA_CACHE_DIR := $(CURDIR)/.numba_cache
export OMP_WAIT_POLICY := PASSIVE
export PATH := $(CURDIR)/$(BIN):$(PATH)

.PHONY: setup reproduce geometry fern test lint dry-run clean-results

setup: $(STAMP)

$(STAMP): requirements.txt pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.txt
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

# The paper's tables first: target `paper_tables` (Tables 2, 3, 5 of the paper's own rows, config `paper_rows`,
# at lift seed 0) and an HTML report of them, Tables 2 and 3 printed; then the rest of the grid
# (the study's mask models, oracle and seeds, the official protocol, robustness) and the report again
# over everything. `trace3d progress` (in another terminal, in this folder) says where the run is.
# The jobs start from fork servers (trace3d/tooling/forkserver.py; FORKSERVER=0 turns them off): they have
# imported the steps and loaded the kernels once, which every job would do again (docs/performance.md).
reproduce: $(STAMP)
	$(BIN)/python -m trace3d.tooling.warm --jobs $(CORES)
	$(WITH_FORKSERVER) \
	$(BIN)/snakemake --cores $(CORES) --show-failed-logs paper_tables; \
	$(BIN)/snakemake --cores 1 paper_tables --report results/report.html; \
	cat results/tables/paper/table2.md results/tables/paper/table3.md; \
	echo "Tables 2 and 3 of the paper's rows above (results/tables/paper/, report: results/report.html); now the rest of the grid."; \
	$(BIN)/snakemake --cores $(CORES) --show-failed-logs reproduce; \
	$(BIN)/snakemake --cores 1 reproduce --report results/report.html

# The fork servers of one recipe (its lines joined into one shell): started in a private temporary folder,
# named by TRACE3D_FORKSERVER for the commands that follow (TRACE3D_TEST_FORKSERVER for the tests:
# tests/workflow/conftest.py), stopped when the shell leaves, whether the commands succeeded or not. If
# they fail to start, the jobs run as without them.
FORKSERVER ?= 1
ifeq ($(FORKSERVER),1)
WITH_FORKSERVER = set -e; fork=$$(mktemp -d); \
	trap '$(BIN)/python -m trace3d.tooling.forkserver stop "$$fork/s" >/dev/null; rm -rf "$$fork"' EXIT; \
	export TRACE3D_FORKSERVER="$$fork/s" TRACE3D_TEST_FORKSERVER="$$fork/s"; \
	$(BIN)/python -m trace3d.tooling.forkserver start "$$fork/s" || true;
else
WITH_FORKSERVER = set -e; export TRACE3D_TEST_FORKSERVER=off;
endif

# Without ground truth or SAM (docs/masks.md, docs/capture.md): the default rooms with masks from the fitted
# geometry (config/geometry.yaml; the default run's fits, made first if absent), and the LLFF fern capture
# (config/fern.yaml; data_root ../shared/captures, else `make fern FERN_ROOT=/path/to/captures`).
GEOMETRY_EVALS := $(foreach k,0 1 2 3,$(foreach v,full both_off both_off_ignore both_off_coarse both_off_coarse01,results/room$(k)@geometry/$(v)/eval))
FERN_ROOT ?= ../shared/captures
geometry: $(STAMP)
	$(BIN)/python -m trace3d.tooling.warm --jobs $(CORES)
	$(BIN)/snakemake --cores $(CORES) --show-failed-logs --configfile=config/geometry.yaml -- $(GEOMETRY_EVALS)

fern: $(STAMP)
	$(BIN)/python -m trace3d.tooling.warm --jobs $(CORES)
	$(BIN)/snakemake --cores $(CORES) --show-failed-logs --configfile=config/fern.yaml --config data_root=$(FERN_ROOT) -- reproduce

# The kernels are compiled first, over $(CORES) processes (trace3d/tooling/warm.py), so that no test compiles one;
# then the suite runs on $(CORES) pytest-xdist workers, the whole-DAG runs taking turns on one of them
# (their xdist_group; tests/conftest.py).
# The whole-DAG tests' jobs start from fork servers (tests/workflow/conftest.py; FORKSERVER=0: without).
test: $(STAMP)
	$(BIN)/python -m trace3d.tooling.warm --jobs $(CORES)
	$(WITH_FORKSERVER) unset TRACE3D_FORKSERVER; \
	$(BIN)/python -m pytest -q -n $(CORES) --dist loadgroup --durations=20 tests

# ruff (its rules in pyproject.toml's [tool.ruff]) over the Python, then Snakemake's own lint of the rules
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/snakemake --lint

dry-run: $(STAMP)
	$(BIN)/snakemake -n reproduce

clean-results:
	find results -mindepth 1 -maxdepth 1 ! -name README.md -exec rm -rf {} +
