#!/usr/bin/env bash
# CounterNet's experiments (issue 38) in two GPU-machine calls of at most 10 minutes each, build included
# (docs/counternet.md quotes the results):
#   SAVE_SO=1 bash tools/counternet/device_session.sh train
#       dense driving_city frames (seed 0); CN (pt 1), CN_pt (pt 4), CN_pt_o (pt 4, delta 0.2) and CN_nocount (pt 1,
#       count loss weight 0) trained side by side on the one GPU, their epochs sized from a throughput probe so
#       that all four finish by TRAIN_END s; back come <name>.pth.xz (float16 weights, one file each: the 16 MiB
#       limit per file), devbuild.tar.xz (SAVE_SO=1), counternet_train_logs.tar.xz and counternet.log.
#   bash tools/counternet/device_session.sh all   # train, then eval on what it wrote, in one call (set TRAIN_END,
#       DET_END, CALL_LIMIT to share the call's time)
#   CKPTS=runs/counternet_device LIDAROPS_SO=runs/counternet_device/devbuild.tar.xz \
#       bash tools/counternet/device_session.sh eval
#       (carry runs/counternet_device, ignored by /runs/, holding the .pth.xz files and devbuild.tar.xz of train)
#       the same training frames again (seeded: identical files) and 600 held-out frames (seed 5000); CUDA tests
#       and compute-sanitizer memcheck in the background; PointPillars (configs/counternet/pointpillars_road7.yaml:
#       the seven classes, CounterNet's augmentations) trained on the training frames until DET_END s;
#       tools/counternet/evaluate.py (every counter, model selection, the seed's metrics), results_table.py;
#       benchmarks/bm_counternet.py.
# REALISM=kitti (either command): every frame made with `data synth --realism kitti` (issue 40: the shipped models
#   retrained on the simulator's realism profile).
# LIDAROPS_SO: a devbuild.tar.xz of an earlier call (used when csrc/ and setup.py are unchanged) or a folder
# holding _C*.so (used as is); otherwise lidarops is built (~100 s). Everything printed goes to $OUT/counternet.log.
# Dry run on a CPU (every command line, tiny): DEVICE=cpu NO_BUILD=1 PY=.venv/bin/python TRAIN_FRAMES=12 \
#   VAL_FRACTION=0.25 BATCH=2 PROBE_STEPS=2 EPOCHS_MAX=1 ... (tools/counternet/README.md: the two dry runs).
set -uo pipefail
what=${1:-train}
OUT=${OUT:-/tmp/counternet-out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/counternet.log") 2>&1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
DEVICE=${DEVICE:-cuda}; PY=${PY:-python3}; HERE=tools/counternet; L="$PY -m lidarops"
CALL_LIMIT=${CALL_LIMIT:-590}                # seconds this call may take (the device's limit is 600)
t0=$(date +%s)
now() { echo $(( $(date +%s) - t0 )); }
stamp() { echo "[counternet] $1 ($(now) s)"; }
minutes_until() { awk -v s=$(( $1 - $(now) )) 'BEGIN { if (s < 30) s = 30; printf "%.2f", s / 60 }'; }
csrc_hash() { find csrc setup.py -type f -print0 | LC_ALL=C sort -z | xargs -0 sha256sum | sha256sum | cut -c1-16; }
echo "[counternet] $what on $DEVICE: $(date -u +%FT%TZ), $(nproc) cores"
[ "$DEVICE" = cuda ] && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader

# ---------------------------------------------------------------------------------------------- lidarops' build
check_so() { $PY -c "import lidarops.extension as e; e.load(); import sys; c = e.cuda_available(); print('with_cuda', c)
sys.exit(0 if c or '$DEVICE' != 'cuda' else 3)"; }
have_so=
if [ -n "${NO_BUILD:-}" ]; then
  have_so=1; stamp "NO_BUILD: lidarops as built here"
elif [ -n "${LIDAROPS_SO:-}" ]; then
  if [ -f "$LIDAROPS_SO" ]; then
    rm -rf /tmp/devbuild && mkdir -p /tmp/devbuild && tar xJf "$LIDAROPS_SO" -C /tmp/devbuild
    if [ "$(cat /tmp/devbuild/csrc.sha256 2>/dev/null)" = "$(csrc_hash)" ]; then
      cp /tmp/devbuild/lidarops/_C*.so /tmp/devbuild/lidarops/_build_info.json lidarops/ && have_so=1
    else
      echo "[counternet] $LIDAROPS_SO was built from other sources (csrc/, setup.py changed): building"
    fi
  elif ls "$LIDAROPS_SO"/_C*.so >/dev/null 2>&1; then
    cp "$LIDAROPS_SO"/_C*.so "$LIDAROPS_SO"/_build_info.json lidarops/ 2>/dev/null; have_so=1
  fi
  [ -n "$have_so" ] && { check_so || { have_so=; rm -f lidarops/_C*.so; echo "[counternet] carried build unusable"; }; }
  [ -n "$have_so" ] && stamp "carried CUDA build"
fi
so_pid=
if [ -z "$have_so" ]; then
  make build > /tmp/build.log 2>&1 || { tail -40 /tmp/build.log; tail -40 build/build.log; exit 1; }
  stamp "lidarops built"
  check_so || exit 1
  if [ -n "${SAVE_SO:-}" ]; then  # brings the build back for the next call (one file, about 3 MB)
    csrc_hash > /tmp/csrc.sha256
    (tar cf - lidarops/_C*.so lidarops/_build_info.json -C /tmp csrc.sha256 | xz -T4 -6 > "$OUT/devbuild.tar.xz") &
    so_pid=$!
  fi
fi

# ---------------------------------------------------------------------------------------------- shared settings
TRAIN_FRAMES=${TRAIN_FRAMES:-2400}; TRAIN_SEED=${TRAIN_SEED:-0}; VAL_FRACTION=${VAL_FRACTION:-0.05}
VAL_FRAMES=${VAL_FRAMES:-600}; VAL_SEED=${VAL_SEED:-5000}; SYNTH_WORKERS=${SYNTH_WORKERS:-15}
TRAIN_DATA=/tmp/cn_train; VAL_DATA=/tmp/cn_val
BATCH=${BATCH:-8}; AMP=${AMP:-bf16}
RUNS=${RUNS:-"CN:1:0.0:1.0 CN_pt:4:0.0:1.0 CN_pt_o:4:0.2:1.0 CN_nocount:1:0.0:0.0"}   # name:pt:delta:count weight
CN_CONFIG=configs/counternet/counternet_synth.yaml

synth_train() {  # the training frames: a pure function of the command (any number of workers), made once a call
  local args="--frames $TRAIN_FRAMES --seed $TRAIN_SEED --val-fraction $VAL_FRACTION${REALISM:+ --realism $REALISM}"
  if [ "$(cat $TRAIN_DATA/.synth_args 2>/dev/null)" = "$args" ]; then echo "[counternet] training frames already made"; return; fi
  $L data synth --scenario driving_city --object-counts dense $args \
    --out $TRAIN_DATA --workers $SYNTH_WORKERS --no-progress > /tmp/synth_train.log 2>&1 \
    || { tail -20 /tmp/synth_train.log; exit 1; }
  tail -1 /tmp/synth_train.log
  echo "$args" > $TRAIN_DATA/.synth_args
}

probe_fps() {  # the slowest "frames/s per process" of the probe logs given (empty when none parsed)
  for f in "$@"; do sed -n 's/.* \([0-9][0-9.]*\) frames\/s per process.*/\1/p' "$f" | tail -1; done | sort -g | head -1
}

epochs_for() {  # epochs_for FPS SECONDS FRAMES MAX: what fits, at 80 % of the probe's rate, in [1, MAX]
  awk -v f="${1:-0}" -v s="$2" -v n="$3" -v hi="$4" \
    'BEGIN { e = int(0.8 * f * s / n); if (e < 1) e = 1; if (e > hi) e = hi; print e }'
}

gpu_watch() {  # GPU utilisation and memory every 10 s (is the training GPU- or data-bound?)
  [ "$DEVICE" = cuda ] || return 0
  nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader -l 10 > "$1" 2>&1 &
  watch_pid=$!
}

gpu_summary() {
  [ -n "${watch_pid:-}" ] && kill "$watch_pid" 2>/dev/null
  [ -f "$1" ] && awk -F, '{ gsub(/[ %]/, "", $2); if ($2 != "") { s += $2; n++ } }
    END { if (n) printf "[counternet] GPU utilisation: mean %.0f %% over %d samples\n", s / n, n }' "$1"
}

# ================================================================================================ train
if [ "$what" = train ] || [ "$what" = all ]; then
  TRAIN_END=${TRAIN_END:-520}          # the trainings end by then (s since the start), leaving ~70 s to ship
  CN_WORKERS=${CN_WORKERS:-3}; PROBE_STEPS=${PROBE_STEPS:-30}; EPOCHS_MAX=${EPOCHS_MAX:-40}
  export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
  synth_train
  stamp "training data"
  n_train=$(wc -l < $TRAIN_DATA/ImageSets/train.txt)
  train_cn() {  # train_cn NAME PT DELTA CW OUTDIR EPOCHS [more flags]
    local name=$1 pt=$2 delta=$3 cw=$4 dir=$5 ep=$6; shift 6
    $L train --config $CN_CONFIG --data $TRAIN_DATA --out $dir --epochs $ep --batch-size $BATCH --amp $AMP \
      --workers $CN_WORKERS --eval-every 0 --no-progress --device $DEVICE "$@" \
      --set MODEL.COUNT_HEAD.PARTITIONS $pt MODEL.COUNT_HEAD.OVERLAP $delta MODEL.COUNT_HEAD.COUNT_WEIGHT $cw
  }
  EPOCHS=${EPOCHS:-}
  if [ -z "$EPOCHS" ]; then  # the four side by side for PROBE_STEPS steps: their rate sizes the real runs
    rm -rf /tmp/cn_probe; mkdir -p /tmp/cn_probe; pids=()
    for run in $RUNS; do
      IFS=: read name pt delta cw <<< "$run"
      train_cn $name $pt $delta $cw /tmp/cn_probe/$name 1 --max-steps $PROBE_STEPS > /tmp/cn_probe/$name.log 2>&1 & pids+=($!)
    done
    for p in "${pids[@]}"; do wait $p; done
    fps=$(probe_fps /tmp/cn_probe/*.log)
    grep -h "frames/s per process\|Error" /tmp/cn_probe/*.log | sed 's/^/  probe: /'
    left=$(( TRAIN_END - $(now) - 30 ))  # 30 s: start-up, the closing evaluation and checkpoints
    EPOCHS=$(epochs_for "$fps" $left $n_train $EPOCHS_MAX)
    stamp "probe: ${fps:-?} frames/s per run, 4 runs side by side -> $EPOCHS epochs of $n_train frames in $left s"
  fi
  RUNS_DIR=/tmp/cn_runs; rm -rf $RUNS_DIR; mkdir -p $RUNS_DIR; pids=()
  gpu_watch /tmp/gpu_train.log
  MAXMIN=$(minutes_until $(( TRAIN_END - 10 )))
  for run in $RUNS; do
    IFS=: read name pt delta cw <<< "$run"
    train_cn $name $pt $delta $cw $RUNS_DIR/$name $EPOCHS --max-minutes $MAXMIN > $RUNS_DIR/$name.log 2>&1 & pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  gpu_summary /tmp/gpu_train.log
  for f in $RUNS_DIR/*.log; do
    echo "$(basename $f .log): $(grep -E '^(finished|stopped)|counting accuracy|Error|error:' $f | tr '\n' ' ')"
  done
  stamp "CounterNet runs ($EPOCHS epochs, --max-minutes $MAXMIN)"
  mkdir -p /tmp/ship; ship_pids=()
  for run in $RUNS; do
    name=${run%%:*}; d=$RUNS_DIR/$name
    c=$d/final.pth; [ -f $c ] || c=$d/latest.pth
    [ -f $c ] || { echo "[counternet] $name: no checkpoint"; continue; }
    ev=$(ls $d/eval_epoch_*.json 2>/dev/null | sort -V | tail -1)
    $PY -m lidarops.models.weights $c /tmp/ship/$name.pth ${ev:+"$ev"} > /dev/null \
      && (xz -T4 -6 -c /tmp/ship/$name.pth > "$OUT/$name.pth.xz") & ship_pids+=($!)
  done
  for p in "${ship_pids[@]}"; do wait $p; done
  ls -la "$OUT"/*.pth.xz
  (cd $RUNS_DIR && tar cJf "$OUT/counternet_train_logs.tar.xz" *.log */train.log */log.csv */eval_epoch_*.json \
    -C /tmp $(cd /tmp && ls gpu_train.log cn_probe/*.log 2>/dev/null) 2>/dev/null)
  stamp "shipped"
  [ -n "$so_pid" ] && { wait $so_pid; ls -la "$OUT/devbuild.tar.xz"; }
  stamp "done"
fi

# ================================================================================================ eval
if [ "$what" = eval ] || [ "$what" = all ]; then
  [ "$what" = all ] && CKPTS=${CKPTS:-$OUT}  # all: the checkpoints train just wrote
  CKPTS=${CKPTS:-runs/counternet_device}
  DET=${DET:-1}; DET_CONFIG=${DET_CONFIG:-configs/counternet/pointpillars_road7.yaml}
  DET_END=${DET_END:-380}; DET_WORKERS=${DET_WORKERS:-10}; DET_AMP=${DET_AMP:-bf16}
  GTDB=${GTDB:-0}  # frames of the gt-sampling database, for a DET_CONFIG with gt sampling (~30 ms a frame)
  DET_PROBE_STEPS=${DET_PROBE_STEPS:-30}; DET_EPOCHS_MAX=${DET_EPOCHS_MAX:-40}; DET_VAL_FRAMES=${DET_VAL_FRAMES:-120}
  SELECT=${SELECT:-"CN CN_pt CN_pt_o"}; FIT_FRAMES=${FIT_FRAMES:-400}; SCORE_THRESH=${SCORE_THRESH:-"0.5 0.3"}
  EVAL_WORKERS=${EVAL_WORKERS:-8}; EVAL_TIMEOUT=${EVAL_TIMEOUT:-170}
  TESTS=${TESTS:-1}; TEST_TIMEOUT=${TEST_TIMEOUT:-180}; SAN_TIMEOUT=${SAN_TIMEOUT:-120}
  BM=${BM:-1}; BM_ARGS=${BM_ARGS:-}; BM_TIMEOUT=${BM_TIMEOUT:-100}
  export OMP_NUM_THREADS=${OMP_NUM_THREADS:-2} OPENBLAS_NUM_THREADS=1
  mkdir -p /tmp/cn_ckpt
  for f in $CKPTS/*.pth.xz; do [ -f "$f" ] && xz -dc "$f" > /tmp/cn_ckpt/$(basename "$f" .xz); done
  for f in $CKPTS/*.pth; do [ -f "$f" ] && cp "$f" /tmp/cn_ckpt/; done
  cn_args=()
  for run in $RUNS; do
    name=${run%%:*}; [ -f /tmp/cn_ckpt/$name.pth ] && cn_args+=("$name=/tmp/cn_ckpt/$name.pth")
  done
  echo "[counternet] CounterNets: ${cn_args[*]:-none found in $CKPTS}"
  sel=(); for n in $SELECT; do [ -f /tmp/cn_ckpt/$n.pth ] && sel+=("$n"); done
  [ ${#sel[@]} -ge 2 ] || sel=()  # a selection needs two models
  synth_train
  $L data synth --scenario driving_city --object-counts dense --frames $VAL_FRAMES --seed $VAL_SEED --val-fraction 0 \
    --out $VAL_DATA --workers $SYNTH_WORKERS --no-progress ${REALISM:+--realism $REALISM} > /tmp/synth_val.log 2>&1 \
    || { tail -20 /tmp/synth_val.log; exit 1; }
  tail -1 /tmp/synth_val.log
  stamp "training and held-out data"

  cuda_tests() {  # the CounterNet and counting tests (LIDAROPS_TEST_REQUIRE_CUDA: a skipped CUDA case fails), memcheck
    local req=0; [ "$DEVICE" = cuda ] && req=1
    LIDAROPS_TEST_REQUIRE_CUDA=$req timeout $TEST_TIMEOUT $PY -m pytest -q -p no:cacheprovider -rfE \
      tests/models/test_counternet.py tests/models/test_counternet_selection.py tests/models/test_counting.py \
      tests/eval/test_counting.py tests/fuzz/test_fuzz_counting.py tests/fuzz/test_fuzz_counting_parts.py \
      tests/query/test_counter_source.py ${TESTS_ARGS:-} > /tmp/cn_tests.log 2>&1
    echo "[counternet] tests exit $?" >> /tmp/cn_tests.log
    $PY $HERE/cuda_smoke.py $DEVICE > /tmp/cn_smoke.log 2>&1
    echo "[counternet] cuda_smoke exit $?" >> /tmp/cn_smoke.log
    if [ "$DEVICE" = cuda ] && command -v compute-sanitizer > /dev/null; then
      timeout $SAN_TIMEOUT compute-sanitizer --tool memcheck --error-exitcode 9 $PY $HERE/cuda_smoke.py cuda \
        > /tmp/cn_sanitizer.log 2>&1
      echo "[counternet] compute-sanitizer memcheck, cuda_smoke.py: exit $?" >> /tmp/cn_sanitizer.log
      timeout $SAN_TIMEOUT compute-sanitizer --tool memcheck --error-exitcode 9 $PY -m pytest -q -p no:cacheprovider \
        tests/models/test_counting.py -k "cuda and not slow" -x >> /tmp/cn_sanitizer.log 2>&1
      echo "[counternet] compute-sanitizer memcheck, tests/models/test_counting.py -k cuda: exit $?" >> /tmp/cn_sanitizer.log
    else
      echo "[counternet] memcheck skipped (device $DEVICE, compute-sanitizer: $(command -v compute-sanitizer || echo none))" \
        > /tmp/cn_sanitizer.log
    fi
  }
  tests_pid=
  [ "$TESTS" = 1 ] && { cuda_tests & tests_pid=$!; }

  det_ckpt=
  if [ "$DET" = 1 ]; then
    det_train() {  # det_train OUTDIR EPOCHS [more flags]
      local dir=$1 ep=$2; shift 2
      $L train --config $DET_CONFIG --data $TRAIN_DATA --out $dir --epochs $ep --batch-size $BATCH --amp $DET_AMP \
        --workers $DET_WORKERS --eval-every 0 --max-val-frames $DET_VAL_FRAMES --no-progress --device $DEVICE \
        "${gtdb_flag[@]}" "$@"
    }
    gtdb_flag=(); [ "$GTDB" -gt 0 ] && gtdb_flag=(--gt-database-frames $GTDB)
    n_train=$(wc -l < $TRAIN_DATA/ImageSets/train.txt)
    DET_EPOCHS=${DET_EPOCHS:-}
    if [ -z "$DET_EPOCHS" ]; then
      rm -rf /tmp/det_probe
      det_train /tmp/det_probe 1 --max-steps $DET_PROBE_STEPS > /tmp/det_probe.log 2>&1
      fps=$(probe_fps /tmp/det_probe.log)
      grep -h "frames/s per process\|Error" /tmp/det_probe.log | sed 's/^/  probe: /'
      # start-up, the gt database (~30 ms a frame), the closing KITTI evaluation and checkpoints
      left=$(( DET_END - $(now) - 35 - GTDB * 3 / 100 ))
      DET_EPOCHS=$(epochs_for "$fps" $left $n_train $DET_EPOCHS_MAX)
      stamp "detector probe: ${fps:-?} frames/s -> $DET_EPOCHS epochs of $n_train frames in $left s"
    fi
    gpu_watch /tmp/gpu_det.log
    MAXMIN=$(minutes_until $(( DET_END - 15 - GTDB * 3 / 100 )))
    det_train /tmp/det_run $DET_EPOCHS --max-minutes $MAXMIN > /tmp/det_run.log 2>&1
    gpu_summary /tmp/gpu_det.log
    grep -E "^(finished|stopped)|moderate AP|Error|error:" /tmp/det_run.log
    det_ckpt=/tmp/det_run/final.pth; [ -f $det_ckpt ] || det_ckpt=/tmp/det_run/latest.pth
    [ -f $det_ckpt ] || { echo "[counternet] the detector left no checkpoint"; det_ckpt=; }
    stamp "PointPillars detector ($DET_EPOCHS epochs, --max-minutes $MAXMIN)"
  fi

  timeout $EVAL_TIMEOUT $PY $HERE/evaluate.py --val $VAL_DATA --train $TRAIN_DATA --fit-frames $FIT_FRAMES \
    ${cn_args[0]:+--counternet "${cn_args[@]}"} ${sel[0]:+--select "${sel[@]}"} \
    ${det_ckpt:+--detector $det_ckpt --detector-config $DET_CONFIG} \
    --score-thresh $SCORE_THRESH --device $DEVICE --batch $BATCH --workers $EVAL_WORKERS \
    --out "$OUT/counternet_results.json" --counts "$OUT/counternet_counts.npz"
  echo "[counternet] evaluate.py exit $?"
  [ -f "$OUT/counternet_results.json" ] && $PY $HERE/results_table.py "$OUT/counternet_results.json" \
    --out "$OUT/counternet_tables.md" && echo "[counternet] wrote $OUT/counternet_tables.md"
  stamp "evaluation"
  if [ -n "$det_ckpt" ] && [ -n "${SHIP_DET:-1}" ]; then  # the detector alone (float16), for docs and reruns
    $PY -m lidarops.models.weights $det_ckpt "$OUT/pointpillars_synth_road7.pth" > /dev/null
  fi
  ship_logs() {
    mkdir -p /tmp/cn_logs; cp /tmp/det_run.log /tmp/det_probe.log /tmp/gpu_det.log /tmp/cn_tests.log /tmp/cn_smoke.log \
      /tmp/cn_sanitizer.log /tmp/synth_train.log /tmp/synth_val.log /tmp/cn_logs/ 2>/dev/null
    cp /tmp/det_run/log.csv /tmp/cn_logs/det_log.csv 2>/dev/null
    cp /tmp/det_run/eval_epoch_*.json /tmp/cn_logs/ 2>/dev/null
    tar cJf "$OUT/counternet_eval_logs.tar.xz" -C /tmp/cn_logs .
  }
  ship_logs
  if [ -n "$tests_pid" ]; then
    wait $tests_pid  # before the benchmark: the sanitizer's kernels would share the GPU with its timings
    tail -4 /tmp/cn_tests.log; tail -3 /tmp/cn_smoke.log; grep -E "ERROR SUMMARY|exit" /tmp/cn_sanitizer.log
    stamp "tests"
  fi
  if [ "$BM" = 1 ] && [ $(( CALL_LIMIT - $(now) )) -gt $BM_TIMEOUT ]; then
    timeout $BM_TIMEOUT $PY benchmarks/bm_counternet.py --device $DEVICE --json --results-dir "$OUT" $BM_ARGS
    echo "[counternet] bm_counternet exit $?"
    stamp "bm_counternet"
  elif [ "$BM" = 1 ]; then
    echo "[counternet] bm_counternet skipped: $(( CALL_LIMIT - $(now) )) s left, it may take $BM_TIMEOUT"
  fi
  ship_logs
  ls -la "$OUT"
  stamp "done"
fi
