# Two commands for a fresh machine with Python 3.11: `make demo` and `make test`.
# Both create .venv on first use and reinstall only when pyproject.toml changes.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
DEMO   := demo_out

.PHONY: demo test bench lint clean

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
	@echo "== simulate: demonstrations + exploration on the path_tracking driving problem, as a raw Parquet log"
	$(BIN)/offline-adp simulate path_tracking --format parquet --out $(DEMO)/logs/path_tracking.parquet \
		--demonstrations 100 --exploration 100 --seed 0 --overwrite --quiet
	@echo "== ingest: raw log + spec -> validated dataset directory"
	$(BIN)/offline-adp ingest parquet $(DEMO)/logs/path_tracking.parquet \
		--spec $(DEMO)/logs/path_tracking.spec.toml --out $(DEMO)/dataset --overwrite --quiet
	@echo "== inspect"
	$(BIN)/offline-adp inspect $(DEMO)/dataset

test: $(VENV)/.installed-dev
	$(BIN)/python -m pytest -q

bench: $(VENV)/.installed-dev
	$(BIN)/python benchmarks/ingest_parquet.py
	$(BIN)/python benchmarks/ingest_mcap.py
	$(BIN)/python benchmarks/fqi_scale.py
	$(BIN)/python benchmarks/car_on_hill.py --seeds 0
	$(BIN)/python benchmarks/compare_algorithms.py --quick
	$(BIN)/python benchmarks/evaluation.py

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check offline_adp tests benchmarks

clean:
	rm -rf $(VENV) $(DEMO) .pytest_cache
