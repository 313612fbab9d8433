#!/usr/bin/env bash
# One GPU-machine session: build with CUDA, run the whole test suite (one pytest per file, so that a
# crash in one file does not hide the others), compute-sanitizer on the kernel tests, then benchmarks.
# Everything printed goes to $OUT/run.log (the device tool returns at most 8 files); benchmark JSON
# results are copied to $OUT. Usage (from the repository root):
#   bash tools/device_run.sh [tests|bench|all] [pytest -k expression for the sanitizer]
# Environment: TESTS (test files, default tests/test_*.py), TEST_K (a pytest -k expression for them), TEST_TIMEOUT (per file), SANITIZER_TIMEOUT,
# SANITIZER_TESTS, BENCHES, BENCH_TIMEOUT, LIDAROPS_SKIP_BUILD=1 (reuse lidarops/_C*.so), PRE (a command
# run after the build, e.g. a diagnostic).
set -uo pipefail
what=${1:-all}
OUT=${OUT:-/tmp/lidarops-out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/run.log") 2>&1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
if [ -f .peers/spconv_site.tar.xz ] && [ ! -d /tmp/site/spconv ]; then
  mkdir -p /tmp/site && tar xJf .peers/spconv_site.tar.xz -C /tmp/site
fi
[ -d /tmp/site/spconv ] && export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv
start=$(date +%s)
if [ -n "${LIDAROPS_SKIP_BUILD:-}" ] && ls lidarops/_C*.so >/dev/null 2>&1; then
  echo "[device_run] reusing the built extension"
else
  make build > /tmp/build.log 2>&1; rc=$?
  grep -E "^\[lidarops\]|error|warning: .*lidarops" /tmp/build.log | head -60
  [ $rc -ne 0 ] && { tail -60 /tmp/build.log; echo "[device_run] BUILD FAILED"; exit 1; }
fi
echo "[device_run] build: $(( $(date +%s) - start )) s"
python3 -c "import lidarops.extension as e; e.load(); print('with_cuda', e.cuda_available())"
[ -n "${PRE:-}" ] && { echo "[device_run] PRE: $PRE"; bash -c "$PRE"; echo "[device_run] PRE exit $?"; }
if [ "$what" = tests ] || [ "$what" = all ]; then
  start=$(date +%s)
  for f in ${TESTS:-tests/test_*.py}; do
    s=$(date +%s)
    LIDAROPS_TEST_REQUIRE_CUDA=1 timeout ${TEST_TIMEOUT:-300} python3 -X faulthandler -m pytest "$f" -q -rfE \
      -p no:cacheprovider ${TEST_K:+-k "$TEST_K"} 2>&1 \
      | grep -v -E "site-packages/(_pytest|pluggy)/|frozen runpy|^Extension modules" | tail -40
    echo "[device_run] $f exit ${PIPESTATUS[0]} in $(( $(date +%s) - s )) s"
  done
  echo "[device_run] tests: $(( $(date +%s) - start )) s"
  if command -v compute-sanitizer >/dev/null && [ -z "${NO_SANITIZER:-}" ]; then
    start=$(date +%s)
    for tool in ${SANITIZER_TOOLS:-memcheck racecheck}; do
      timeout ${SANITIZER_TIMEOUT:-240} compute-sanitizer --tool $tool --error-exitcode 9 python3 -m pytest -q \
        -p no:cacheprovider ${SANITIZER_TESTS:-tests/test_neighbors.py} -k "${2:-cuda and not slow}" -x 2>&1 | tail -6
      echo "[device_run] compute-sanitizer $tool exit ${PIPESTATUS[0]}"
    done
    echo "[device_run] sanitizer: $(( $(date +%s) - start )) s"
  fi
fi
if [ "$what" = bench ] || [ "$what" = all ]; then
  start=$(date +%s)
  for bm in ${BENCHES:-bm_neighbors bm_voxelize bm_sparse}; do
    timeout ${BENCH_TIMEOUT:-200} python3 benchmarks/$bm.py --device cuda --json 2>&1 | tail -60
  done
  cp benchmarks/results/*.json "$OUT/" 2>/dev/null
  echo "[device_run] bench: $(( $(date +%s) - start )) s"
fi
exit 0
