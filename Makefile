# uncertsplat developer commands. `make setup` is idempotent.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH_VERSION ?= 2.13.0
PYTEST_ARGS ?=

.PHONY: setup test test-all test-fake-cuda lint demo bench clean

$(BIN)/python:
	@$(PY) -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null || { echo "uncertsplat needs Python 3.11 or newer; '$(PY)' is $$($(PY) --version 2>&1 || echo missing). Install one and run e.g. 'make PY=python3.11 $(MAKECMDGOALS)'." >&2; exit 1; }
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install -q torch==$(TORCH_VERSION)
	$(BIN)/pip install -q -e '.[dev]'
	@# build the native CPU kernels now (a few seconds) rather than on the first render; never fatal
	$(BIN)/python -c "from uncertsplat import native; print('kernels:', native.describe('cpu'))"
	touch $@

setup: $(VENV)/.installed

# The tests run in TEST_WORKERS processes of one thread each (pytest-xdist; a module's tests stay in one process so
# its trained fixtures are built once): on 2 cores 6 min instead of 12 for one process of 2 threads, since much of
# a test's time is Python, process start-up and waiting, which one thread per core overlaps. The threaded paths of
# the native kernels are checked by tests that set the thread count themselves. TEST_WORKERS=0: one process.
TEST_WORKERS ?= 2
TEST_THREADS := $(if $(filter 0,$(TEST_WORKERS)),2,1)
TEST_XDIST := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

test: setup
	OMP_NUM_THREADS=$(TEST_THREADS) $(BIN)/python -m pytest -q $(TEST_XDIST) -m "not slow" $(PYTEST_ARGS)

test-all: setup
	OMP_NUM_THREADS=$(TEST_THREADS) $(BIN)/python -m pytest -q $(TEST_XDIST) $(PYTEST_ARGS)

# The tests of the tensor code once more with CUDA emulated on the CPU (tests/fake_cuda.py, --device fake-cuda):
# a CPU tensor, a CPU generator or host access (.numpy(), data_ptr) in a CUDA computation fails here, without a
# GPU; numerics, memory and CUDA kernels it cannot check. ~3 min on 2 cores. One process, as the emulator collects
# the session's findings and fails the run on any; two threads, as in `make test TEST_WORKERS=0`.
FAKE_CUDA_TESTS ?= tests/unit/test_fake_cuda.py tests/e2e/test_cuda_paths.py tests/unit/test_mc.py \
	tests/unit/test_scores.py tests/unit/test_consistency.py tests/unit/test_view_frames.py \
	tests/unit/test_binning.py tests/unit/test_ause.py tests/unit/test_calibration.py tests/unit/test_nll.py \
	tests/unit/test_tails.py tests/unit/test_metrics_image.py tests/unit/test_metrics_depth.py \
	tests/unit/test_prune_mask.py tests/unit/test_render_api.py tests/numerics/test_render_parity.py \
	tests/numerics/test_render_extremes.py tests/numerics/test_render_position_var.py \
	tests/numerics/test_render_gradcheck.py \
	tests/unit/test_residual.py::TestColourPosterior::test_the_block_form_on_the_device

test-fake-cuda: setup
	OMP_NUM_THREADS=2 $(BIN)/python -m pytest -q -p no:xdist --device fake-cuda $(FAKE_CUDA_TESTS) $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check uncertsplat tests benchmarks examples

demo: setup
	$(BIN)/uncertsplat run pipelines/demo.toml -o demo_out

bench: setup
	$(BIN)/python benchmarks/bench_render.py

clean:
	rm -rf $(VENV) build *.egg-info
