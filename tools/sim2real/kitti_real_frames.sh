#!/usr/bin/env bash
# Six real KITTI training frames (000000-000005: scans, calibration, labels, images) out of OpenPCDet's git
# history (commit 0b243c8, data/kitti/), into a KITTI folder outside git: the yardstick of
# benchmarks/bm_sim2real.py. KITTI's licence (non-commercial, share-alike) forbids committing them here.
#   bash tools/sim2real/kitti_real_frames.sh [OPENPCDET_GIT_DIR] [OUT]
# OPENPCDET_GIT_DIR: a clone or mirror of open-mmlab/OpenPCDet with its history (default .peers/OpenPCDet;
# the agent tools' `fetch github:open-mmlab/OpenPCDet` gives one). OUT defaults to .peers/kitti_real.
set -euo pipefail
src=${1:-.peers/OpenPCDet}
out=${2:-.peers/kitti_real}
commit=0b243c8
git -C "$src" cat-file -e "$commit^{commit}" 2>/dev/null \
  || { echo "$src has no commit $commit (a full clone or mirror of open-mmlab/OpenPCDet is needed)" >&2; exit 2; }
mkdir -p "$out/training" "$out/ImageSets"
for d in velodyne calib label_2 image_2; do
  mkdir -p "$out/training/$d"
  for i in 000000 000001 000002 000003 000004 000005; do
    ext=$([ $d = velodyne ] && echo bin || ([ $d = image_2 ] && echo png || echo txt))
    git -C "$src" show "$commit:data/kitti/training/$d/$i.$ext" > "$out/training/$d/$i.$ext"
  done
done
printf '%s\n' 000000 000001 000002 000003 000004 000005 > "$out/ImageSets/val.txt"
echo "6 real KITTI frames in $out (not for git)"
