# Two commands for a fresh machine with Python 3.11: `make demo` and `make test`.
# Both create .venv on first use from the committed lock (requirements/lock.txt: exact
# versions and hashes) and reinstall only when the lock or pyproject.toml changes, so a
# fresh clone runs exactly the versions CI tested. `make demo` runs pipelines/driving.toml;
# a second run reuses every stage.
#
# `make lock` refreshes the lock on purpose (newest releases within pyproject.toml's
# ranges); `make test-latest` runs the suite against the newest releases without touching
# the lock, in .venv-latest, so drift is found before it reaches CI.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
DEMO   := demo_out

.PHONY: demo test test-fast test-latest lock bench lint clean

LOCK   := requirements/lock.txt
UV     := uv==0.13.9

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# One environment for the demo and the tests: the lock holds the library, every extra the
# README's commands use (dask, onnx, minari) and the test tools.
$(VENV)/.installed: $(LOCK) pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --no-compile --require-hashes --no-deps -r $(LOCK)
	$(BIN)/python -m pip install -q --no-compile --no-deps --no-build-isolation -e .
	@# bytecode on every core (pip compiles file by file: half the install's time); like
	@# pip, a file that does not compile (a package's test data) is skipped, not an error
	-$(BIN)/python -m compileall -q -j 0 $(VENV)/lib > /dev/null
	$(BIN)/python -m pip check
	touch $@

demo: $(VENV)/.installed
	@echo "== the driving case study: MCAP logs -> dataset -> FQI -> simulator + off-policy evaluation -> report"
	$(BIN)/offline-adp run pipelines/driving.toml --runs $(DEMO)/runs

# --dist worksteal: a worker that runs out of tests takes queued ones from the other
# (with the default `load`, tests queued behind a long one waited while a worker idled)
test: $(VENV)/.installed
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2 --dist worksteal

# The unit layer only (no slow or end-to-end tests): under 2 minutes on 2 cores.
test-fast: $(VENV)/.installed
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2 --dist worksteal -m "not slow and not integration"

bench: $(VENV)/.installed
	$(BIN)/python benchmarks/ingest_parquet.py
	$(BIN)/python benchmarks/ingest_mcap.py
	$(BIN)/python benchmarks/fqi_scale.py
	$(BIN)/python benchmarks/car_on_hill.py --seeds 0
	$(BIN)/python benchmarks/compare_algorithms.py --quick
	$(BIN)/python benchmarks/evaluation.py
	$(BIN)/python benchmarks/ope_bootstrap.py --episodes 10000 --horizon 100
	$(BIN)/python benchmarks/dask_scale.py

# The suite against the newest releases pyproject.toml allows (not in CI; the lock stays).
test-latest:
	$(PYTHON) -m venv .venv-latest
	.venv-latest/bin/python -m pip install -q --upgrade --upgrade-strategy eager -e ".[dev]"
	.venv-latest/bin/lint-imports
	.venv-latest/bin/python -m pytest -q -n 2 --dist worksteal

# Refresh the lock on purpose: newest releases within pyproject.toml's ranges, with hashes.
lock:
	$(PYTHON) -m venv .venv-lock
	.venv-lock/bin/python -m pip install -q $(UV)
	.venv-lock/bin/uv pip compile pyproject.toml requirements/build.in --extra dev \
	    --python-version 3.11 --python-platform x86_64-manylinux_2_28 \
	    --generate-hashes --no-header --upgrade -o $(LOCK)

lint: $(VENV)/.installed
	$(BIN)/ruff check .
	$(BIN)/lint-imports

clean:
	rm -rf $(VENV) .venv-latest .venv-lock $(DEMO) .pytest_cache
