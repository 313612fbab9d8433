#!/usr/bin/env bash
# Trains the shipped PointPillars (lidarops/weights/pointpillars_synth.pth): the data recipe, the training
# command and the export, in one script (docs/detector.md quotes it).
#   bash tools/train_pointpillars_synth.sh OUT_DIR            # environment: GPUS (1), EPOCHS, BATCH, WORKERS, DATA
#   REALISM=kitti bash tools/train_pointpillars_synth.sh OUT  # the real-scan model: data with --realism kitti,
#                                                             # configs/pointpillars/pointpillars_synth_real.yaml
#                                                             # (or a profile with fields changed:
#                                                             # REALISM=kitti:crossing_groups=0.6,crossing_cyclists=0.2)
#   SPARSE=1 bash tools/train_pointpillars_synth.sh OUT       # Sparse-PointPillars on the same data and recipe:
#                                                             # configs/pointpillars/pointpillars_synth_sparse.yaml
#   RESUME=1 ... (same OUT)                                   # continue OUT/run from latest.pth, on the data
#                                                             # already in DATA when it is complete
#   PRETRAINED=FILE LR=0.001 EPOCHS=10 REALISM=kitti ...      # fine-tune FILE (a checkpoint or a shipped name)
#                                                             # on the recipe's data, at peak learning rate LR
# Runs on the GPU machine; writes OUT_DIR/run (checkpoints, log.csv, evaluations) and
# OUT_DIR/pointpillars_synth.pth (float16 weights with their config, recipe, command and evaluation).
set -euo pipefail
OUT=${1:-runs/pointpillars_synth}
GPUS=${GPUS:-1}; EPOCHS=${EPOCHS:-20}; BATCH=${BATCH:-8}; DATA=${DATA:-/tmp/synth${REALISM:+_$REALISM}}
NAME=pointpillars_synth${REALISM:+_real}${SPARSE:+_sparse}
[ -n "${REALISM:-}" ] && [ -n "${SPARSE:-}" ] && { echo "REALISM and SPARSE: no config trains both" >&2; exit 2; }
WORKERS=${WORKERS:-$(( $(nproc) / GPUS - 2 ))}
s=$(date +%s)
# 3,600 frames: driving_city 2,400 and driving_highway 1,200, each its own scene; 500 held out for val
# (RESUME=1 on a machine that still holds the data: made once, not again)
if [ -z "${RESUME:-}" ] || [ ! -f "$DATA/recipe.json" ]; then
  python3 -m lidarops data synth --scenario driving_city driving_highway --frames 2400 1200 --seed 0 \
      --val-fraction 0.1389 --workers "$(nproc)" --out "$DATA" --no-progress ${REALISM:+--realism $REALISM}
fi
echo "[train] data: $(( $(date +%s) - s )) s"
TRAIN=(--config configs/pointpillars/$NAME.yaml --data "$DATA" --out "$OUT/run" --amp bf16 --batch-size "$BATCH"
       --workers "$WORKERS" --epochs "$EPOCHS" --eval-every 5 --gt-database-frames 1000 --no-progress
       ${MAX_MINUTES:+--max-minutes $MAX_MINUTES} ${RESUME:+--resume} ${PRETRAINED:+--pretrained-model $PRETRAINED}
       ${LR:+--lr $LR})
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1   # the DataLoader workers' numpy/torch: one thread each
if [ "$GPUS" -gt 1 ]; then
    torchrun --standalone --nproc_per_node="$GPUS" -m lidarops train "${TRAIN[@]}"
else
    python3 -m lidarops train "${TRAIN[@]}"
fi
echo "[train] total: $(( $(date +%s) - s )) s"
last=$(ls "$OUT"/run/eval_epoch_*.json 2>/dev/null | sort -V | tail -1 || true)
if [ -f "$OUT/run/final.pth" ]; then
    python3 -m lidarops.models.weights "$OUT/run/final.pth" "$OUT/$NAME.pth" ${last:+"$last"}
fi
