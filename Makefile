# uncertsplat developer commands. `make setup` is idempotent.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH_VERSION ?= 2.13.0
PYTEST_ARGS ?=

.PHONY: setup test test-all lint demo bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install -q torch==$(TORCH_VERSION)
	$(BIN)/pip install -q -e '.[dev]'
	@# build the native CPU kernels now (a few seconds) rather than on the first render; never fatal
	$(BIN)/python -c "from uncertsplat import native; print('kernels:', native.describe('cpu'))"
	touch $@

setup: $(VENV)/.installed

test: setup
	OMP_NUM_THREADS=2 $(BIN)/python -m pytest -q -m "not slow" $(PYTEST_ARGS)

test-all: setup
	OMP_NUM_THREADS=2 $(BIN)/python -m pytest -q $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check uncertsplat tests benchmarks examples

demo: setup
	$(BIN)/uncertsplat run pipelines/demo.toml -o demo_out

bench: setup
	$(BIN)/python benchmarks/bench_render.py

clean:
	rm -rf $(VENV) build *.egg-info
