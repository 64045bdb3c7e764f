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

ARC := sample_data/arc

# The synthetic samples at the paper's settings; each real frame with its camera's
# preset, intrinsics and empty-tote frame (README, "Your own camera in five minutes").
run: $(STAMP)
	$(BIN)/rangeseg run sample_data/synthetic -o out/synthetic --overwrite
	$(BIN)/rangeseg run $(ARC)/suction-scene.depth.png --preset tenth-mm-depth \
	    --intrinsics $(ARC)/suction-camera-intrinsics.txt \
	    --background $(ARC)/empty/suction-background.depth.png -o out/arc --overwrite
	$(BIN)/rangeseg run $(ARC)/bin-scene.depth.png --preset tenth-mm-depth \
	    --intrinsics $(ARC)/bin-camera-intrinsics.txt \
	    --background $(ARC)/empty/bin-background.depth.png -o out/arc-bin --overwrite

test: $(STAMP)
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check rangeseg_cli tests benchmarks docs
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
