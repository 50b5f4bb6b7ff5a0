# hdrig: `make run` and `make test` work on a fresh machine with only Python 3.11 (README, docs/INTERFACE.md).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= results

.PHONY: install run test lint bench clean serve lock

# Installs go through uv with constraints.txt, the lock of every dependency of every extra (README,
# "Installing"): exact versions on every machine, and no resolver search at install time.
UV_VERSION  := 0.13.9
CONSTRAINTS := constraints.txt
UV_INSTALL   = $(BIN)/uv pip install --quiet --python $(BIN)/python -c $(CONSTRAINTS)

$(STAMP): pyproject.toml $(CONSTRAINTS)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet uv==$(UV_VERSION)
	$(UV_INSTALL) -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

# The main job on the embedded defaults: the characterization campaign on the simulated rig (each run
# stored under $HDRIG_HOME, here results/store unless set, its line printed as it lands), then a fit of
# the seed model to those runs with the validation report.
HOME_DIR = $${HDRIG_HOME:-$(abspath $(OUT))/store}
run: install
	@mkdir -p $(OUT)
	HDRIG_HOME="$(HOME_DIR)" $(BIN)/hdrig run campaign --rig configs/rigs/sim.yaml
	@echo "runs: $(HOME_DIR)/runs/<id>/ (data.parquet; artifacts/: tables, results.json, plots/)"
	HDRIG_HOME="$(HOME_DIR)" $(BIN)/hdrig fit --data latest --model seed --out $(OUT)/fitted-seed.yaml \
	  --report $(OUT)/fit-report -q
	@echo "fitted model: $(abspath $(OUT))/fitted-seed.yaml; report: $(abspath $(OUT))/fit-report/report.md"

# The REST service and browser page on the simulated rig paced to the wall clock (runs play live);
# an admin key is printed on first start.
serve: install
	HDRIG_HOME="$(HOME_DIR)" $(BIN)/hdrig serve --rig configs/rigs/sim-live.yaml

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy && $(BIN)/lint-imports

# The fleet's tests run on real parts (PostgreSQL, an S3 API, a Dask cluster): the `fleet` extra installs
# their Python side, so CI never skips them (.ci/run installs Debian's postgresql).
FLEET_STAMP := $(VENV)/.installed-fleet
$(FLEET_STAMP): $(STAMP)
	$(UV_INSTALL) -e '.[dev,fleet]'
	touch $(FLEET_STAMP)

test: lint $(FLEET_STAMP)
	$(BIN)/pytest -q

# Benchmarks print their figures beside the targets (docs/BENCHMARKS.md keeps the latest); the SINDy
# baseline of the gap benchmark needs the `bench` extra.
bench: install
	$(UV_INSTALL) -e '.[dev,bench,fleet]'
	$(BIN)/python bench/bench_simulator.py
	$(BIN)/python bench/bench_campaign.py
	$(BIN)/python bench/bench_identify.py
	$(BIN)/python bench/bench_compensation.py
	$(BIN)/python bench/bench_daq.py
	$(BIN)/python bench/bench_canopen.py
	$(BIN)/python bench/bench_gaps.py
	$(BIN)/python bench/bench_service.py
	$(BIN)/python bench/bench_endurance.py
	$(BIN)/python bench/bench_thermal_trend.py
	$(BIN)/python bench/bench_compensation_thermal.py
	$(BIN)/python bench/bench_fleet.py

# Renews the lock after a change of pyproject.toml's dependencies (--upgrade: the newest allowed versions).
# One universal file for every extra and platform; commit it with the change that asked for it.
lock: install
	$(BIN)/uv pip compile pyproject.toml --all-extras --universal --python-version 3.11 --upgrade \
	  --quiet -o $(CONSTRAINTS)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache *.egg-info
