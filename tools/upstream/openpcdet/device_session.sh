#!/usr/bin/env bash
# The OpenPCDet checks in one GPU-machine session (README.md here says what each step shows):
#   bash tools/upstream/openpcdet/device_session.sh [checks|train|all]
# train's variables: FRAMES ("600 300": driving_city, driving_highway), EPOCHS, BATCH, WORKERS, AMP (none|fp16),
# SEEDS (lidarops trains once per seed), SBS_FRAMES; NO_OPS_BUILD=1 runs OpenPCDet on lidarops' faces;
# SAVE_SO=1 brings lidarops' CUDA build back as devbuild.tar.xz
# Needs, carried with the tree: .peers/openpcdet-src (git archive of OpenPCDet's pcdet/ tools/ setup.py, and
# COMMIT), .peers/wheels (its pure-Python needs: README.md lists them), .peers/spconv_site.tar.xz
# (../shared/tools/spconv-bundle.sh). Everything printed goes to $OUT/openpcdet.log; reports to $OUT.
set -uo pipefail
what=${1:-all}
OUT=${OUT:-/tmp/openpcdet-out}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/openpcdet.log") 2>&1
SRC=$PWD/.peers/openpcdet-src
HERE=tools/upstream/openpcdet
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16} PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[openpcdet] $1 ($(( $(date +%s) - t0 )) s)"; }
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
make build > /tmp/build.log 2>&1 || { tail -40 /tmp/build.log; tail -40 build/build.log; exit 1; }
stamp "lidarops built"
if [ -n "${SAVE_SO:-}" ]; then  # bring the CUDA build back for later sessions (one file <= 16 MiB)
  tar cJf "$OUT/devbuild.tar.xz" lidarops/_C*.so lidarops/_build_info.json && ls -la "$OUT/devbuild.tar.xz"
fi
peers=$(bash $HERE/peer_setup.sh) || exit 1  # its Python needs into /tmp/site, its ops built (unless NO_OPS_BUILD)
eval "$peers"
stamp "OpenPCDet ready${NO_OPS_BUILD:+ (its ops not built)}"

if [ "$what" = checks ] || [ "$what" = all ]; then
  python3 -X faulthandler $HERE/ops_parity.py "$SRC" --out "$OUT/ops_parity.json"
  stamp "ops parity"
  python3 -m lidarops data synth --frames 8 --out /tmp/sbs --workers 8 --no-progress
  python3 $HERE/side_by_side.py --openpcdet "$SRC" --frames /tmp/sbs/training --out "$OUT/side_by_side.json" \
    --dump /tmp/sbs_own.pt 2>&1 | grep -v -i warn
  python3 $HERE/side_by_side.py --openpcdet "$SRC" --frames /tmp/sbs/training --faces --out "$OUT/side_by_side_faces.json" \
    --dump /tmp/sbs_faces.pt 2>&1 | grep -v -i warn
  python3 -c "
import torch
a, b = torch.load('/tmp/sbs_own.pt'), torch.load('/tmp/sbs_faces.pt')
same = all(torch.equal(x[k], y[k]) for x, y in zip(a, b) for k in x)
print(f'OpenPCDet PointPillar inference, its own ops vs lidarops faces: {len(a)} frames, identical outputs: {same}')"
  stamp "side by side"
  python3 -m lidarops data synth --frames 64 --out /tmp/steps_own --workers 16 --seed 7100 --no-progress
  cp -r /tmp/steps_own /tmp/steps_faces
  python3 $HERE/prepare_kitti.py "$SRC" /tmp/steps_own --workers 16 > /tmp/prep_own.log 2>&1 || tail -30 /tmp/prep_own.log
  python3 $HERE/prepare_kitti.py "$SRC" /tmp/steps_faces --workers 16 --faces > /tmp/prep_faces.log 2>&1 || tail -30 /tmp/prep_faces.log
  tail -1 /tmp/prep_own.log; tail -1 /tmp/prep_faces.log
  python3 $HERE/compare_infos.py /tmp/steps_own /tmp/steps_faces --out "$OUT/infos_own_vs_faces.json"
  python3 $HERE/train_steps.py "$SRC" /tmp/steps_own --out "$OUT/train_steps_own.json" > /tmp/ts_own.log 2>&1 || tail -30 /tmp/ts_own.log
  python3 $HERE/train_steps.py "$SRC" /tmp/steps_own --faces --out "$OUT/train_steps_faces.json" > /tmp/ts_faces.log 2>&1 || tail -30 /tmp/ts_faces.log
  python3 $HERE/compare_steps.py "$OUT/train_steps_own.json" "$OUT/train_steps_faces.json"
  stamp "training steps"
fi

if [ "$what" = train ] || [ "$what" = all ]; then
  FRAMES=${FRAMES:-"600 300"} EPOCHS=${EPOCHS:-3} BATCH=${BATCH:-8} WORKERS=${WORKERS:-12} AMP=${AMP:-none} SEEDS=${SEEDS:-0}
  python3 -m lidarops data synth --scenario driving_city driving_highway --frames $FRAMES --seed 7000 \
    --val-fraction 0.1 --out /tmp/bm_data --workers 16 --no-progress
  python3 $HERE/prepare_kitti.py "$SRC" /tmp/bm_data --workers 16 ${NO_OPS_BUILD:+--faces} > /tmp/prep_bm.log 2>&1 || { tail -30 /tmp/prep_bm.log; exit 1; }
  tail -1 /tmp/prep_bm.log
  stamp "training data"
  ops=own faces=
  [ -n "${NO_OPS_BUILD:-}" ] && { ops=faces; faces=--faces; echo "[openpcdet] its ops not built: they are lidarops faces"; }
  [ $ops = own ] && { python3 $HERE/cpu_op_probe.py "$SRC" || { ops=faces; faces=--faces
    echo "[openpcdet] its CPU box IoU failed: its pipeline runs on lidarops faces"; }; }
  timeout ${BM_TIMEOUT:-100000} python3 benchmarks/bm_train.py --data /tmp/bm_data --vs-openpcdet "$SRC" --epochs $EPOCHS --batch-size $BATCH \
    --workers $WORKERS --amp $AMP --seeds $SEEDS --out /tmp/bm_train --json --openpcdet-ops $ops
  cp /tmp/bm_train/bm_train.json /tmp/bm_train/bm_train_partial.json "$OUT/" 2>/dev/null  # the logs as one file: at most 8 come back
  (cd /tmp/bm_train && tar cJf "$OUT/bm_train_logs.tar.xz" *.log lidarops_run_seed*/train.log lidarops_run_seed*/log.csv \
    eval_*/eval.json 2>/dev/null)
  cp benchmarks/results/cuda-*.json "$OUT/" 2>/dev/null
  stamp "training comparison"
  ck=$(ls "$SRC"/output/kitti_models/pointpillar_lidarops_bm/*/ckpt/checkpoint_epoch_$EPOCHS.pth | head -1)
  python3 $HERE/side_by_side.py --openpcdet "$SRC" --frames /tmp/bm_data/training --max-frames ${SBS_FRAMES:-16} $faces \
    --pcdet-checkpoint "$ck" --cfg "$SRC/tools/cfgs/kitti_models/pointpillar_lidarops_bm.yaml" \
    --score-thresh 0.05 --out "$OUT/side_by_side_openpcdet_checkpoint.json"
  stamp "OpenPCDet's checkpoint in lidarops"
fi
