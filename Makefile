# Two commands on a fresh machine with Python 3.11+:
#   make demo   -- the main job: the demo on the simulated rig
#   make test   -- lint and the whole test suite
# Fast loop while editing (leaves out the tests marked slow):
#   .venv/bin/python -m pytest -m "not slow"
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin

.PHONY: demo test lint bench clean chromium

$(BIN)/activate: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test,figures]'
	$(BIN)/python -c "import multislit; multislit.compile_kernels()"  # Numba, cached on disk
	touch $(BIN)/activate

demo: $(BIN)/activate
	$(BIN)/multislit demo --out demo-output

# The view's browser test needs Chromium (Debian's package); installed when missing, as root
# or through sudo where there is one.
chromium:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; elif command -v sudo >/dev/null 2>&1; then SUDO=sudo; \
	  else echo "chromium missing and no root: the browser test will be skipped"; exit 0; fi; \
	  command -v apt-get >/dev/null 2>&1 || { echo "no apt-get: the browser test will be skipped"; exit 0; }; \
	  $$SUDO apt-get update -qq && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }

test: $(BIN)/activate chromium
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/python -m pytest -q -n 2 --dist loadfile  # two processes, a test file each

bench: $(BIN)/activate
	$(BIN)/python benchmarks/bench_speed.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache
