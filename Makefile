# The two commands a newcomer needs: `make demo` and `make test`.
# Both create .venv and install the project into it on first use.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench mutants clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/mocap-labeler demo

test: $(STAMP)
	bash scripts/ensure-mosquitto.sh
	bash scripts/ensure-chromium.sh
	$(BIN)/python -m pytest -q -n auto --maxprocesses 4 --durations=25

lint: $(STAMP)
	$(BIN)/ruff check labeler_service offline tests benchmarks
	$(BIN)/ruff format --check labeler_service offline tests benchmarks
	$(BIN)/mypy labeler_service offline

bench: $(STAMP)
	$(BIN)/python benchmarks/acceptance.py --out reports/acceptance.json
	$(BIN)/python benchmarks/bench_labeler.py --frames 10000
	$(BIN)/mocap-labeler bench latency --subjects 10 --rate 360 --seconds 20 --transport udp --json

# a curated mutation check (scripts/mutant_list.py): one JSON line, >= 90 % must be killed
mutants: $(STAMP)
	bash scripts/ensure-mosquitto.sh
	$(BIN)/python scripts/mutants.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
