# hdrig: `make run` and `make test` work on a fresh machine with only Python 3.11 (README, CONTRACT.md).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= results

.PHONY: install run test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The main job on the embedded defaults: the seed model under a sine voltage, replayed, summarized.
run: install
	@mkdir -p $(OUT)
	$(BIN)/hdrig model show seed
	$(BIN)/hdrig simulate --model seed --input sine:amp=2,freq=0.5 --duration 10 --out $(OUT)/seed-sine.parquet
	$(BIN)/hdrig simulate --model seed --input ramp:slope=0.1 --duration 20 --out $(OUT)/seed-ramp.csv
	$(BIN)/hdrig simulate --model seed --input-file $(OUT)/seed-sine.parquet --out $(OUT)/seed-sine-replay.csv
	@echo "results are in $(abspath $(OUT))"

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test: lint
	$(BIN)/pytest -q

bench: install
	$(BIN)/python bench/bench_simulator.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache *.egg-info
