# rangeseg developer commands. `make run` and `make test` work from a fresh clone.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint bench reproduce sample-data clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,bench]"
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/rangeseg run sample_data -o out --overwrite

test: $(STAMP)
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check rangeseg_cli tests benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_pipeline.py

reproduce: $(STAMP)
	$(BIN)/python benchmarks/reproduce_paper.py

clean:
	rm -rf out .pytest_cache
