# Two commands for a fresh machine with Python 3.11: `make demo` and `make test`.
# Both create .venv on first use and reinstall only when pyproject.toml changes.
# `make demo` runs pipelines/driving.toml; a second run reuses every stage.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
DEMO   := demo_out

.PHONY: demo test test-fast bench lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(VENV)/.installed: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $@ $(VENV)/.installed

demo: $(VENV)/.installed
	@echo "== the driving case study: MCAP logs -> dataset -> FQI -> simulator + off-policy evaluation -> report"
	$(BIN)/offline-adp run pipelines/driving.toml --runs $(DEMO)/runs

test: $(VENV)/.installed-dev
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2

# The unit layer only (no slow or end-to-end tests): under 2 minutes on 2 cores.
test-fast: $(VENV)/.installed-dev
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -q -n 2 -m "not slow and not integration"

bench: $(VENV)/.installed-dev
	$(BIN)/python benchmarks/ingest_parquet.py
	$(BIN)/python benchmarks/ingest_mcap.py
	$(BIN)/python benchmarks/fqi_scale.py
	$(BIN)/python benchmarks/car_on_hill.py --seeds 0
	$(BIN)/python benchmarks/compare_algorithms.py --quick
	$(BIN)/python benchmarks/evaluation.py
	$(BIN)/python benchmarks/dask_scale.py

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check offline_adp tests benchmarks
	$(BIN)/lint-imports

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
