#!/usr/bin/env bash
# The fuzz suite's CUDA cases with a hypothesis profile (default long: 2,000 examples per test), each
# process under compute-sanitizer (default memcheck), the tests spread over JOBS processes (default 8).
# For the GPU machine, after `make build`:
#   bash tools/fuzz_cuda.sh [PROFILE [TOOL]]      e.g. bash tools/fuzz_cuda.sh long memcheck
# Environment: JOBS, FUZZ_TIMEOUT (seconds per process, default 520), LOGS (default /tmp/fuzz_cuda),
# K (pytest -k expression, default cuda), SHARDS (default 1: run each test in SHARDS processes, each with
# its own --hypothesis-seed and 1/SHARDS of the examples; JOBS is then ignored: one process per shard).
# Prints one line per process (its tests' pytest summary and the sanitizer's error summary), exits
# nonzero when a test failed, the sanitizer reported an error or a process ran out of time.
set -uo pipefail
profile=${1:-long} tool=${2:-memcheck} jobs=${JOBS:-8} logs=${LOGS:-/tmp/fuzz_cuda}
PY=${PYTHON:-python3}
mkdir -p "$logs"
shards=${SHARDS:-1}
mapfile -t ids < <(HYPOTHESIS_PROFILE=$profile "$PY" -m pytest tests/fuzz -q --collect-only -k "${K:-cuda}" \
  -p no:cacheprovider 2>/dev/null | grep '::')
[ ${#ids[@]} -gt 0 ] || { echo "no CUDA fuzz tests collected"; exit 2; }
[ "$shards" -gt 1 ] && jobs=$(( ${#ids[@]} * shards ))
echo "[fuzz_cuda] ${#ids[@]} tests, profile $profile, $shards shard(s) each, $tool, $jobs processes"
pids=()
for ((j = 0; j < jobs; j++)); do
  group=() seed=()
  if [ "$shards" -gt 1 ]; then
    group=("${ids[$(( j / shards ))]}") seed=(--hypothesis-seed=$(( j % shards + 1 )))
  else
    for ((i = j; i < ${#ids[@]}; i += jobs)); do group+=("${ids[$i]}"); done
  fi
  [ ${#group[@]} -gt 0 ] || continue
  (HYPOTHESIS_PROFILE=$profile FUZZ_SHARDS=$shards OMP_NUM_THREADS=2 timeout ${FUZZ_TIMEOUT:-520} \
    compute-sanitizer --tool "$tool" --error-exitcode 9 "$PY" -m pytest -q -p no:cacheprovider "${seed[@]}" \
    "${group[@]}" > "$logs/$j.log" 2>&1
   echo "exit $?" >> "$logs/$j.log") &
  pids+=($!)
done
wait "${pids[@]}"
status=0
for ((j = 0; j < jobs; j++)); do
  [ -f "$logs/$j.log" ] || continue
  rc=$(tail -1 "$logs/$j.log" | sed 's/exit //')
  summary=$(grep -E "passed|failed|error" "$logs/$j.log" | grep -v "ERROR SUMMARY" | tail -1)
  san=$(grep -E "ERROR SUMMARY|RACECHECK SUMMARY|hazards" "$logs/$j.log" | tail -1)
  echo "[fuzz_cuda] process $j: exit $rc; $summary; $san"
  [ "$rc" = 0 ] || { status=1; grep -E "^(FAILED|ERROR)|Falsifying|=========     " "$logs/$j.log" | head -20; }
done
exit $status
