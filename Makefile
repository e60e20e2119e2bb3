# Two commands on a fresh machine with Python 3.11+:
#   make demo   -- the main job: the demo on the simulated rig
#   make test   -- lint and the whole test suite
# Fast loop while editing (leaves out the tests marked slow):
#   .venv/bin/python -m pytest -m "not slow"
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo test lint bench clean

$(BIN)/activate: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,figures]'
	touch $(BIN)/activate

demo: $(BIN)/activate
	$(BIN)/multislit demo --out demo-output

test: $(BIN)/activate
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/python -m pytest -q

bench: $(BIN)/activate
	$(BIN)/python benchmarks/bench_speed.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache
