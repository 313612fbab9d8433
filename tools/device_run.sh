#!/usr/bin/env bash
# One GPU-machine session: build with CUDA, run the whole test suite, compute-sanitizer on the kernel
# tests, then benchmarks. Writes logs and results under $OUT. Usage (from the repository root):
#   bash tools/device_run.sh [tests|bench|all] [pytest -k expression for the sanitizer]
set -uo pipefail
what=${1:-all}
OUT=${OUT:-/tmp/lidarops-out}
mkdir -p "$OUT"
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
if [ -f .peers/spconv_site.tar.xz ] && [ ! -d /tmp/site/spconv ]; then
  mkdir -p /tmp/site && tar xJf .peers/spconv_site.tar.xz -C /tmp/site
fi
[ -d /tmp/site/spconv ] && export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv | tee "$OUT/gpu.txt"
start=$(date +%s)
[ -n "${LIDAROPS_SKIP_BUILD:-}" ] && ls lidarops/_C*.so >/dev/null 2>&1 || make build 2>&1 | tee "$OUT/build.log" | grep -E "^\[lidarops\]|error|Error" | head -40
echo "[device_run] build: $(( $(date +%s) - start )) s"
python3 -c "import lidarops.extension as e; e.load(); print('with_cuda', e.cuda_available())"
if [ "$what" = tests ] || [ "$what" = all ]; then
  start=$(date +%s)
  LIDAROPS_TEST_REQUIRE_CUDA=1 timeout ${TEST_TIMEOUT:-420} python3 -m pytest tests -q -rfE -p no:cacheprovider --junitxml="$OUT/junit.xml" 2>&1 | tee "$OUT/tests.log" | tail -40
  echo "[device_run] tests: $(( $(date +%s) - start )) s"
  if command -v compute-sanitizer >/dev/null; then
    start=$(date +%s)
    for tool in memcheck racecheck; do
      timeout ${SANITIZER_TIMEOUT:-240} compute-sanitizer --tool $tool --error-exitcode 9 python3 -m pytest -q -p no:cacheprovider \
        tests/test_neighbors.py -k "${2:-cuda and not slow}" -x 2>&1 | tee "$OUT/sanitizer_$tool.log" | tail -5
      echo "[device_run] compute-sanitizer $tool exit ${PIPESTATUS[0]}"
    done
    echo "[device_run] sanitizer: $(( $(date +%s) - start )) s"
  fi
fi
if [ "$what" = bench ] || [ "$what" = all ]; then
  start=$(date +%s)
  for bm in ${BENCHES:-bm_neighbors bm_voxelize bm_sparse}; do
    timeout ${BENCH_TIMEOUT:-200} python3 benchmarks/$bm.py --device cuda --json 2>&1 | tee "$OUT/$bm.log" | tail -40
  done
  cp benchmarks/results/*.json "$OUT/" 2>/dev/null
  echo "[device_run] bench: $(( $(date +%s) - start )) s"
fi
cp lidarops/_C*.so lidarops/_build_info.json "$OUT/" 2>/dev/null
exit 0
