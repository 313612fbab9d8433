#!/usr/bin/env bash
# One GPU-machine session: build with CUDA, run the whole test suite (one pytest per file, so that a
# crash in one file does not hide the others), compute-sanitizer on the kernel tests, then benchmarks.
# Everything printed goes to $OUT/run.log (the device tool returns at most 8 files); benchmark JSON
# results are copied to $OUT. Usage (from the repository root):
#   bash tools/device_run.sh [tests|bench|all]
# Environment: TESTS (test files, default tests/test_*.py tests/*/test_*.py), TEST_K (a pytest -k expression for them), TEST_TIMEOUT (per file),
# TEST_JOBS (files run at once), SANITIZER_PLAN, SANITIZER_K (run beside the tests), SANITIZER_TIMEOUT, BENCHES, BENCH_TIMEOUT, LIDAROPS_SKIP_BUILD=1 (reuse lidarops/_C*.so), PRE (a command
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
  grep -E "^\[make\]" /tmp/build.log | head -20   # the compiler's output is in build/build.log
  grep -E "^\[lidarops\]|error|warning: .*lidarops" build/build.log 2>/dev/null | head -60
  [ $rc -ne 0 ] && { tail -60 /tmp/build.log; tail -60 build/build.log; echo "[device_run] BUILD FAILED"; exit 1; }
fi
echo "[device_run] build: $(( $(date +%s) - start )) s"
python3 -c "import lidarops.extension as e; e.load(); print('with_cuda', e.cuda_available())"
[ -n "${PRE:-}" ] && { echo "[device_run] PRE: $PRE"; bash -c "$PRE"; echo "[device_run] PRE exit $?"; }
sanitize() {  # compute-sanitizer on CUDA kernel tests; SANITIZER_PLAN="tool:file,file tool:file@k+expr ..."
  mkdir -p /tmp/san; local i=0
  for entry in ${SANITIZER_PLAN:-memcheck:tests/ops/test_neighbors.py racecheck:tests/ops/test_neighbors.py}; do
    local tool=${entry%%:*} files=${entry#*:} k=${SANITIZER_K:-cuda and not slow}; i=$((i + 1))
    if [[ $files == *@* ]]; then k=${files#*@}; k=${k//+/ }; files=${files%%@*}; fi  # tool:files@k+expr
    timeout ${SANITIZER_TIMEOUT:-240} compute-sanitizer --tool $tool --error-exitcode 9 python3 -m pytest -q \
      -p no:cacheprovider ${files//,/ } -k "$k" -x > /tmp/san/$i-$tool.log 2>&1
    echo "[device_run] compute-sanitizer $tool on $files exit $?" >> /tmp/san/$i-$tool.log
    tail -8 /tmp/san/$i-$tool.log
  done
}
run_test_file() {  # one pytest per file, its output to /tmp/tlogs/<file>.log
  local f=$1 s=$(date +%s) log=/tmp/tlogs/$(echo ${1#tests/} | tr / _ | sed 's/\.py$//').log
  LIDAROPS_TEST_REQUIRE_CUDA=1 timeout ${TEST_TIMEOUT:-300} python3 -X faulthandler -m pytest "$f" -q -rfE \
    -p no:cacheprovider ${TEST_K:+-k "$TEST_K"} 2>&1 \
    | grep -v -E "site-packages/(_pytest|pluggy)/|frozen runpy|^Extension modules" | tail -40 > $log
  echo "[device_run] $f exit ${PIPESTATUS[0]} in $(( $(date +%s) - s )) s" >> $log
  cat $log  # whole, as each file finishes
}
export -f run_test_file
if [ "$what" = tests ] || [ "$what" = all ]; then
  start=$(date +%s); rm -rf /tmp/tlogs /tmp/san; mkdir -p /tmp/tlogs
  san_pid=
  if command -v compute-sanitizer >/dev/null && [ -z "${NO_SANITIZER:-}" ]; then sanitize & san_pid=$!; fi
  # TEST_JOBS files at a time (GPU shared; OpenMP threads split between them)
  jobs=${TEST_JOBS:-1}; export OMP_NUM_THREADS=$(( 16 / jobs > 1 ? 16 / jobs : 1 ))
  files=$(ls -S ${TESTS:-tests/test_*.py tests/*/test_*.py} 2>/dev/null)  # largest first
  [ -n "$files" ] && printf '%s\n' $files | xargs -P $jobs -I{} bash -c 'run_test_file {}'
  grep -h "exit .* in .* s$" /tmp/tlogs/*.log  # the summary
  unset OMP_NUM_THREADS
  echo "[device_run] tests: $(( $(date +%s) - start )) s"
  if [ -n "$san_pid" ]; then wait $san_pid
    echo "[device_run] tests + sanitizer: $(( $(date +%s) - start )) s"; fi
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
