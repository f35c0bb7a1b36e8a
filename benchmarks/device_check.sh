#!/usr/bin/env bash
# The CUDA checks (see BENCHMARKS.md, "CUDA"): the test suite with --device cuda, then the demo pipeline with
# --device cuda. Run from the repository root with a python3 whose torch has CUDA (e.g. `PATH=.venv/bin:$PATH` after
# installing a CUDA build of torch there); on a bare machine our other dependencies can come as wheels in .whl:
#   device run: bash benchmarks/device_check.sh        (carry .whl; results under $OUT)
# TEST_PATHS=... runs only those tests, SKIP_DEMO=1 leaves the demo out, DEMO_S / TEST_S bound each part,
# CONCURRENT=1 runs the demo beside the tests (the device time of one part instead of two; the demo's timings then
# share the CPU cores with the tests' workers, WORKERS of them).
set -u
OUT=${OUT:-/tmp/device_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if ! python3 -c "import pydantic, pycolmap, OpenImageIO" 2>/dev/null && compgen -G ".whl/*.whl" >/dev/null; then
  # a bare machine: our dependencies arrive as wheels (the device tool's carry)
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  export PYTHONPATH=/tmp/site
fi
python3 -c "import uncertsplat" 2>/dev/null \
  || python3 -m pip install -q --no-index --no-deps --no-build-isolation -e . >/dev/null 2>&1 || exit 1
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null; nproc;
  python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name() if torch.cuda.is_available() else 'no CUDA')"; } \
  | tee "$OUT/machine.txt"
TEST_S=${TEST_S:-270}
DEMO_S=${DEMO_S:-250}
WORKERS=${WORKERS:-12}
run_demo() {
  local t0=$SECONDS
  timeout "$DEMO_S" python3 -m uncertsplat run pipelines/demo.toml -o /tmp/demo --device cuda >"$OUT/demo.log" 2>&1
  echo "demo rc=$? seconds=$((SECONDS - t0))" >>"$OUT/demo_rc.txt"
}
demo_pid=
if [ "${CONCURRENT:-0}" = 1 ] && [ "${SKIP_DEMO:-0}" != 1 ]; then
  run_demo &
  demo_pid=$!
fi
t0=$SECONDS
PER_TEST=$(python3 -c "import pytest_timeout" 2>/dev/null && echo "--timeout 150")
OMP_NUM_THREADS=1 timeout "$TEST_S" python3 -m pytest -q -m 'not slow' --device cuda -n "$WORKERS" $PER_TEST \
  -p no:cacheprovider ${PYTEST_EXTRA:-} ${TEST_PATHS:-} >"$OUT/tests.log" 2>&1
echo "tests rc=$? seconds=$((SECONDS - t0))" | tee -a "$OUT/machine.txt"
grep -E "^(FAILED|ERROR)|passed|failed" "$OUT/tests.log" | tail -25
[ "${SKIP_DEMO:-0}" = 1 ] && exit 0
if [ -n "$demo_pid" ]; then wait "$demo_pid"; else run_demo; fi
tee -a "$OUT/machine.txt" <"$OUT/demo_rc.txt"
tail -30 "$OUT/demo.log"
cp /tmp/demo/train/train_summary.json "$OUT/" 2>/dev/null
cp /tmp/demo/train/eval/metrics.json "$OUT/train_eval_metrics.json" 2>/dev/null
cp /tmp/demo/prune/prune.json "$OUT/" 2>/dev/null
cp /tmp/demo/reconstruct/reconstruct_report.json "$OUT/" 2>/dev/null
