#!/usr/bin/env bash
# Aerial-PointPillars on the simulator's `avia` realism profile (issue 40) in one GPU-machine call:
#   LIDAROPS_SO=<folder holding _C*.so> bash tools/sim2real/aerial_device_session.sh
# 1. the training frames of the shipped model's recipe made with `--realism avia` (4,500 drone frames, seeds 0 and
#    1000; RAY_FRAMES="750 750": ray-cast frames of seeds 2000 and 3000 beside them, so the model keeps the ray-cast
#    scenes), and two held-out sets of 300 (seeds 5000 and 6000): the profile's, and the ray-cast frames of before;
# 2. the shipped aerial_pointpillars fine-tuned on them (EPOCHS, LR, at most MAX_MINUTES);
# 3. `lidarops detect` of the shipped and the fine-tuned model on both held-out sets (KITTI AP, whole view;
#    DETECT_RUNS: model:set pairs, the last run first to be left out when time is short).
# Back under $OUT: aerial_pointpillars.pth (float16, with its recipe and evaluation), aerial_eval_*.json,
# aerial_train_log.csv, aerial.log. Dry run on a CPU: DEVICE=cpu NO_BUILD=1 PY=.venv/bin/python FRAMES="8 8"
#   HELD_OUT="4 4" EPOCHS=1 WORKERS=2 BATCH=2 OUT=/tmp/aer_dry bash tools/sim2real/aerial_device_session.sh
set -uo pipefail
OUT=${OUT:-/tmp/aerial-out}; mkdir -p "$OUT"
exec > >(tee -a "$OUT/aerial.log") 2>&1
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
PY=${PY:-python3}; L="$PY -m lidarops"; DEVICE=${DEVICE:-cuda}
REALISM=${REALISM:-avia}; FRAMES=${FRAMES:-"2250 2250"}; HELD_OUT=${HELD_OUT:-"150 150"}
EPOCHS=${EPOCHS:-10}; LR=${LR:-0.001}; MAX_MINUTES=${MAX_MINUTES:-5}; BATCH=${BATCH:-8}; WORKERS=${WORKERS:-14}
CONFIG=configs/pointpillars/aerial_pointpillars_drone.yaml
t0=$(date +%s); stamp() { echo "[aerial] $1 ($(( $(date +%s) - t0 )) s)"; }

if [ -z "${NO_BUILD:-}" ]; then
  if [ -n "${LIDAROPS_SO:-}" ] && ls "$LIDAROPS_SO"/_C*.so > /dev/null 2>&1; then
    cp "$LIDAROPS_SO"/_C*.so "$LIDAROPS_SO"/_build_info.json lidarops/ 2>/dev/null
  else
    make build > /tmp/build.log 2>&1 || { tail -40 /tmp/build.log; exit 1; }
  fi
  $PY -c "import lidarops.extension as e; e.load(); print('with_cuda', e.cuda_available())"
  stamp "lidarops"
fi

synth() {  # synth OUT SEED VAL_FRACTION FRAMES... [--realism R]
  local out=$1 seed=$2 vf=$3; shift 3
  $L data synth --scenario drone_bridge drone_lock --seed $seed --val-fraction $vf --out $out --workers 16 \
    --no-progress "$@" > $out.log 2>&1 || { tail -20 $out.log; exit 1; }
  tail -1 $out.log
}
if [ -n "${RAY_FRAMES:-}" ]; then  # the profile's scenes and ray-cast ones (data synth: one --realism per scenario)
  $L data synth --scenario drone_bridge drone_lock drone_bridge drone_lock --seed 0 --val-fraction 0.1112 --out /tmp/aer \
    --workers 16 --no-progress --frames $FRAMES $RAY_FRAMES --realism $REALISM $REALISM none none > /tmp/aer.log 2>&1 \
    || { tail -20 /tmp/aer.log; exit 1; }
  tail -1 /tmp/aer.log
else
  synth /tmp/aer 0 0.1112 --frames $FRAMES --realism $REALISM
fi
synth /tmp/aer_ho 5000 1.0 --frames $HELD_OUT --realism $REALISM
synth /tmp/aer_ho_ray 5000 1.0 --frames $HELD_OUT
stamp "data"

rm -rf /tmp/aer_run  # a machine still warm from an earlier call keeps its run: the trainer would refuse the folder
$L train --config $CONFIG --data /tmp/aer --out /tmp/aer_run --amp bf16 --batch-size $BATCH --workers $WORKERS \
  --epochs $EPOCHS --eval-every 0 --lr $LR --pretrained-model aerial_pointpillars --max-minutes $MAX_MINUTES \
  --device $DEVICE --no-progress > /tmp/aer_train.log 2>&1
grep -E "^(finished|stopped)|moderate AP|Error|error:" /tmp/aer_train.log
ck=/tmp/aer_run/final.pth; [ -f $ck ] || ck=/tmp/aer_run/latest.pth
ev=$(ls /tmp/aer_run/eval_epoch_*.json 2>/dev/null | sort -V | tail -1)
$PY -m lidarops.models.weights $ck "$OUT/aerial_pointpillars.pth" ${ev:+"$ev"} > /dev/null
cp /tmp/aer_run/log.csv "$OUT/aerial_train_log.csv" 2>/dev/null
stamp "fine-tuned ($(ls -la "$OUT/aerial_pointpillars.pth" | awk '{print $5}') bytes)"

# model:held-out set pairs (the shipped model on the ray-cast frames of these seeds is in docs/train.md)
for run in ${DETECT_RUNS:-shipped:aer_ho tuned:aer_ho tuned:aer_ho_ray shipped:aer_ho_ray}; do
  model=${run%%:*}; ho=${run#*:}
  c=aerial_pointpillars; [ $model = tuned ] && c="$OUT/aerial_pointpillars.pth"
  $L detect /tmp/$ho --split val --checkpoint $c --out /tmp/det_${model}_$ho --device $DEVICE --no-progress \
    --png 0 --print-frames 0 > /tmp/det_${model}_$ho.log 2>&1
  cp /tmp/det_${model}_$ho/eval.json "$OUT/aerial_eval_${model}_$ho.json" 2>/dev/null
  echo "[aerial] $model on $ho:"; grep -iE "Drone|AP" /tmp/det_${model}_$ho.log | head -8
  stamp "$model on $ho"
done
if [ -n "${STREAM_CHECK:-}" ]; then  # SSCATeR streaming detection with the new model on the profile's scene
  $L stream --checkpoint "$OUT/aerial_pointpillars.pth" --scenario drone_lock --realism $REALISM --seconds 0.5 \
    --device $DEVICE --json "$OUT/aerial_stream.json" > /tmp/aer_stream.log 2>&1; echo "[aerial] stream exit $?"
  tail -4 /tmp/aer_stream.log
  stamp "stream"
fi
stamp "done"
