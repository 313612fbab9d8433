#!/usr/bin/env bash
# CAS-Net's experiments in one GPU-machine session (issue 37; docs/casnet.md quotes the results):
#   bash tools/casnet/device_session.sh classify   # CUDA tests + sanitizer, PointNet, CAS-Net at D = 2..32, the table
#   bash tools/casnet/device_session.sh detect     # CAS-Net in front of pointpillars_synth at D = 2, 4, 8, Table I
# In front of the real-scan detector: REALISM=kitti DET_CONFIG=configs/casnet/casnet_pointpillars_synth_real.yaml
# DET_TASK=pointpillars_synth_real TABLE_ARGS="--detector pointpillars_synth_real --config <the same> ..." (the
# training and held-out frames made with --realism kitti).
# The anchored head (ours): CAS_SET="MODEL.HEAD anchored" (classify), DET_SET="MODEL.HEAD anchored" and
# TABLE_ARGS="--casnet-dedup 1 --chunked-fps --anchored-init --whole" (detect).
# classify builds the object-set cache in data/objects with 15 processes (or finds it there: `lidarops train --config
# configs/casnet/pointnet_objects.yaml` builds it, about 6 minutes on 2 cores). Set LIDAROPS_SO=.devbuild to
# reuse a CUDA build carried from an earlier session (.devbuild/_C*.so, same machine kind); otherwise it builds.
# Everything printed goes to $OUT/casnet.log; at most 8 files come back, so checkpoints travel as one tar.
set -uo pipefail
what=${1:-classify}
OUT=${OUT:-/tmp/casnet-out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/casnet.log") 2>&1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[casnet] $1 ($(( $(date +%s) - t0 )) s)"; }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
if [ -n "${LIDAROPS_SO:-}" ] && ls "$LIDAROPS_SO"/_C*.so >/dev/null 2>&1; then
  cp "$LIDAROPS_SO"/_C*.so "$LIDAROPS_SO"/_build_info.json lidarops/ 2>/dev/null
  stamp "carried CUDA build"
else
  make build > /tmp/build.log 2>&1 || { tail -40 /tmp/build.log; tail -40 build/build.log; exit 1; }
  stamp "lidarops built"
  if [ -n "${SAVE_SO:-}" ]; then  # bring the build back for later sessions (one file <= 16 MiB)
    tar cJf "$OUT/devbuild.tar.xz" lidarops/_C*.so lidarops/_build_info.json && ls -la "$OUT/devbuild.tar.xz"
  fi
fi
python3 -c "import lidarops.extension as e; e.load(); print('with_cuda', e.cuda_available())"
L="python3 -m lidarops"

cuda_tests() {  # the CAS-Net tests on CUDA (LIDAROPS_TEST_REQUIRE_CUDA: a skipped CUDA case fails), then memcheck
  LIDAROPS_TEST_REQUIRE_CUDA=1 OMP_NUM_THREADS=2 timeout 400 python3 -m pytest -q -p no:cacheprovider -rfE \
    tests/models/test_casnet.py tests/models/test_casnet_anchored.py tests/models/test_casnet_losses.py tests/models/test_offset_attention.py \
    tests/models/test_samplers.py tests/models/test_pointnet.py tests/models/test_casnet_pointnet.py \
    tests/models/test_casnet_pointpillars.py tests/fuzz/test_fuzz_casnet*.py > /tmp/cuda_tests.log 2>&1
  echo "[casnet] CUDA tests exit $?" >> /tmp/cuda_tests.log
  timeout 300 compute-sanitizer --tool memcheck --error-exitcode 9 python3 -m pytest -q -p no:cacheprovider \
    tests/models/test_casnet.py tests/models/test_casnet_anchored.py tests/models/test_offset_attention.py tests/models/test_samplers.py \
    -k "cuda and not slow" -x > /tmp/sanitizer.log 2>&1
  echo "[casnet] compute-sanitizer memcheck exit $?" >> /tmp/sanitizer.log
}

if [ "$what" = classify ]; then
  cuda_tests & tests_pid=$!
  export OMP_NUM_THREADS=1
  RUNS=/tmp/runs; mkdir -p $RUNS
  PN_EPOCHS=${PN_EPOCHS:-40}
  $L train --config configs/casnet/pointnet_objects.yaml --data data/objects --out $RUNS/pointnet \
    --epochs $PN_EPOCHS --workers 15 --eval-every 10 --no-progress \
    --set OPTIMIZATION.DECAY_STEP_LIST "[15, 25, 35]" > $RUNS/pointnet.log 2>&1
  grep -E "accuracy|finished|stopped|Error" $RUNS/pointnet.log | tail -5
  stamp "PointNet"
  # CAS-Net at every ratio, full and fast, side by side on the one GPU; each stops with a checkpoint in time
  CAS_MIN=${CAS_MIN:-4.5}; CAS_EPOCHS=${CAS_EPOCHS:-30}; CAS_LR=${CAS_LR:-0.0005}; CAS_BATCH=${CAS_BATCH:-32}
  pids=()
  for D in ${RATIOS:-2 4 8 16 32}; do for V in ${VARIANTS:-full fast}; do
    $L train --config configs/casnet/casnet_pointnet_objects.yaml --data data/objects --out $RUNS/cas_d${D}_$V \
      --epochs $CAS_EPOCHS --batch-size $CAS_BATCH --lr $CAS_LR --workers 1 --eval-every 0 --no-progress \
      --max-minutes $CAS_MIN --set MODEL.RATIO $D MODEL.VARIANT $V MODEL.TASK_CHECKPOINT $RUNS/pointnet/final.pth \
      OPTIMIZATION.DECAY_STEP_LIST "[20]" ${CAS_SET:-} > $RUNS/cas_d${D}_$V.log 2>&1 & pids+=($!)
  done; done
  for p in "${pids[@]}"; do wait $p; done
  for f in $RUNS/cas_*.log; do echo "$(basename $f): $(grep -E 'finished|stopped|Error' $f | tail -1)"; done
  stamp "CAS-Net runs"
  ckpts=()
  for d in $RUNS/cas_d*; do
    c=$d/final.pth; [ -f $c ] || c=$d/latest.pth; [ -f $c ] && ckpts+=($c)
  done
  timeout 200 python3 tools/casnet/classification_table.py --pointnet $RUNS/pointnet/final.pth --casnet "${ckpts[@]}" \
    --data data/objects --device cuda --out "$OUT/casnet_classification.json" --plot "$OUT/casnet_classification.png"
  stamp "table"
  # what comes back: the PointNet and each CAS-Net alone (no optimizer state), the logs
  mkdir -p /tmp/ship
  python3 -m lidarops.models.weights $RUNS/pointnet/final.pth /tmp/ship/pointnet_objects.pth
  for c in "${ckpts[@]}"; do  # each CAS-Net alone (CASNet.save): its PointNet is the one above
    python3 -c "import sys, torch; from lidarops.models.casnet import load_casnet
ck = torch.load(sys.argv[1], weights_only=False)
load_casnet(sys.argv[1]).save(sys.argv[2], task='pointnet_objects', model_config_of_run=ck['model_config'],
                              train_command=ck.get('train_command'), epoch=ck.get('epoch'), it=ck.get('it'))" \
      $c /tmp/ship/$(basename $(dirname $c)).pth
  done
  tail -n 3 $RUNS/*.log > /tmp/ship/train_logs.txt
  for d in $RUNS/*/; do cp $d/log.csv /tmp/ship/$(basename $d)_log.csv 2>/dev/null; done
  tar cf "$OUT/casnet_classification_runs.tar" -C /tmp/ship . && ls -la "$OUT/casnet_classification_runs.tar"
  if [ -f benchmarks/bm_casnet.py ] && [ -z "${NO_BM:-}" ]; then
    timeout 150 python3 benchmarks/bm_casnet.py --device cuda --json 2>&1 | tail -40
    cp benchmarks/results/cuda-*.json "$OUT/" 2>/dev/null
    stamp "bm_casnet"
  fi
  wait $tests_pid
  cat /tmp/cuda_tests.log | tail -25; tail -6 /tmp/sanitizer.log
  stamp "done"
fi

if [ "$what" = detect ]; then
  export OMP_NUM_THREADS=2
  if [ -n "${RUN_TESTS:-}" ]; then cuda_tests & tests_pid=$!; fi
  if [ -n "${DEBUG_TESTS:-}" ]; then  # full tracebacks of chosen tests, beside the rest
    (LIDAROPS_TEST_REQUIRE_CUDA=1 timeout 300 python3 -m pytest -q -p no:cacheprovider -rfE --tb=long $DEBUG_TESTS \
      > "$OUT/debug_tests.log" 2>&1; echo "exit $?" >> "$OUT/debug_tests.log") & debug_pid=$!
  fi
  if [ -n "${CLASSIFY_RUNS:-}" ]; then  # the classification table again from carried runs (dedup rows too)
    (mkdir -p /tmp/cr && tar xf "$CLASSIFY_RUNS" -C /tmp/cr
     $L train --config configs/casnet/pointnet_objects.yaml --data data/objects --out /tmp/objset --workers 12 \
       --epochs 1 --max-steps 1 --no-progress > /tmp/objset.log 2>&1  # builds the object-set cache
     timeout 300 python3 tools/casnet/classification_table.py --pointnet /tmp/cr/pointnet_objects.pth \
       --casnet /tmp/cr/cas_d*.pth --data data/objects --device cuda --out "$OUT/casnet_classification.json" \
       --plot "$OUT/casnet_classification.png" > /tmp/cls_table.log 2>&1; tail -30 /tmp/cls_table.log) & cls_pid=$!
  fi
  $L data synth --scenario driving_city driving_highway --frames ${TRAIN_FRAMES:-400 200} --seed 0 \
    --val-fraction 0 --out /tmp/synth --workers 16 --no-progress ${REALISM:+--realism $REALISM} > /tmp/synth.log 2>&1 \
    || tail /tmp/synth.log
  $L data synth --scenario driving_city driving_highway --frames ${VAL_FRAMES:-100 100} --seed 5000 \
    --val-fraction 0 --out /tmp/val --workers 16 --no-progress ${REALISM:+--realism $REALISM} > /tmp/val.log 2>&1 \
    || tail /tmp/val.log
  stamp "data"
  RUNS=/tmp/runs; mkdir -p $RUNS; pids=()
  # each run: name:D:dedup[:variant[:lr]]; DET_SET adds --set pairs to every run (e.g. "MODEL.HEAD anchored")
  for run in ${DET_RUNS:-"d2:2:False" "d4:4:False" "d8:8:False" "d8_dedup:8:True"}; do
    IFS=: read name D dedup variant lr <<< "$run"
    $L train --config ${DET_CONFIG:-configs/casnet/casnet_pointpillars_synth.yaml} --data /tmp/synth --out $RUNS/det_$name \
      --epochs ${DET_EPOCHS:-4} --workers 3 --eval-every 0 --no-progress --gt-database-frames 300 \
      --max-minutes ${DET_MIN:-4} ${lr:+--lr $lr} --set MODEL.RATIO $D MODEL.DEDUP $dedup MODEL.VARIANT ${variant:-full} \
      ${DET_SET:-} > $RUNS/det_$name.log 2>&1 & pids+=($!)
  done
  for p in "${pids[@]}"; do wait $p; done
  for f in $RUNS/det_*.log; do echo "$(basename $f): $(grep -E 'finished|stopped|Error' $f | tail -1)"; done
  stamp "CAS-Net detection runs"
  mkdir -p /tmp/ship
  for d in $RUNS/det_*; do
    c=$d/final.pth; [ -f $c ] || c=$d/latest.pth
    [ -f $c ] && python3 -c "import sys, torch; from lidarops.models.casnet import load_casnet
ck = torch.load(sys.argv[1], weights_only=False)
load_casnet(sys.argv[1]).save(sys.argv[2], task=sys.argv[3], model_config_of_run=ck['model_config'],
                              train_command=ck.get('train_command'), epoch=ck.get('epoch'), it=ck.get('it'))" \
      $c /tmp/ship/casnet_$(basename $d).pth ${DET_TASK:-pointpillars_synth}
    cp $d/log.csv /tmp/ship/$(basename $d)_log.csv 2>/dev/null
  done
  tail -n 4 $RUNS/*.log > /tmp/ship/train_logs.txt
  tar cf "$OUT/casnet_detection_runs.tar" -C /tmp/ship . && ls -la "$OUT/casnet_detection_runs.tar"
  timeout ${TABLE_TIMEOUT:-200} python3 tools/casnet/detection_table.py --data /tmp/val --casnet /tmp/ship/casnet_det_*.pth \
    --ratios 1 2 4 8 --device cuda --out "$OUT/casnet_detection.json" --plot "$OUT/casnet_detection.png" ${TABLE_ARGS:-}
  stamp "table"
  if [ -n "${BM:-}" ]; then
    timeout ${BM_TIMEOUT:-150} python3 benchmarks/bm_casnet.py --device cuda --json --results-dir "$OUT" 2>&1 | tail -45
    stamp "bm_casnet"
  fi
  [ -n "${cls_pid:-}" ] && { wait $cls_pid; stamp "classification table"; }
  if [ -n "${tests_pid:-}" ]; then
    wait $tests_pid; cp /tmp/cuda_tests.log /tmp/sanitizer.log "$OUT/"; tail -4 /tmp/cuda_tests.log; tail -4 /tmp/sanitizer.log
  fi
  [ -n "${debug_pid:-}" ] && { wait $debug_pid; tail -5 "$OUT/debug_tests.log"; }
  stamp "done"
fi
