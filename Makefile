# rangeseg developer commands. `make run` and `make test` work from a fresh clone.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint bench tradeoffs reproduce sample-data clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test,bench,dask]"
	touch $(STAMP)

# The synthetic samples at the paper's settings; the real frame with its own settings.
run: $(STAMP)
	$(BIN)/rangeseg run sample_data/synthetic -o out/synthetic --overwrite
	$(BIN)/rangeseg run sample_data/arc --config sample_data/arc/suction.toml -o out/arc --overwrite

test: $(STAMP)
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check rangeseg_cli tests benchmarks
	$(BIN)/mypy

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_pipeline.py

# Time and correct detections of each step beyond the paper turned off alone (~20 min).
tradeoffs: $(STAMP)
	$(BIN)/python benchmarks/tradeoffs.py

reproduce: $(STAMP)
	$(BIN)/python benchmarks/reproduce_paper.py

# The paper's test objects (Sec. VI, Figs. 10-13) at noise 0, 1, 2 with ground truth.
sample-data: $(STAMP)
	$(BIN)/rangeseg synth sample_data/synthetic --scenes part1,cup,part2,cube-holes --noise 0,1,2 --seed 1990 --size 128x128

clean:
	rm -rf out .pytest_cache
