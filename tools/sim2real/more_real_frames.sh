#!/usr/bin/env bash
# Eight more real KITTI training frames with their labels and calibration, from other public repositories'
# history, into the yardstick folder of benchmarks/bm_sim2real.py (outside git: KITTI's licence forbids
# committing them). Run after tools/sim2real/kitti_real_frames.sh.
#   bash tools/sim2real/more_real_frames.sh MIRRORS [OUT]
# MIRRORS holds git clones or mirrors named owner+name/repo (the agent tools' `fetch github:owner/name` makes
# them under /work/.mirror): sshaoshuai+PointRCNN (pull request 217, commit af3a8ee: 000006-000010, full
# scans), isl-org+Open3D-ML (pull request 654, commit ea297bc: 004139, 004747) and zhulf0804+PointPillars
# (commit 620e6b0: 000134, cropped to the camera's view). 000008 replaces mmdetection3d's cropped copy: the
# same scan, whole, with KITTI's own label file. OUT defaults to .peers/kitti_real.
set -euo pipefail
mirrors=${1:?give the folder of the mirrors (e.g. /work/.mirror)}
out=${2:-.peers/kitti_real}
mkdir -p "$out/training/velodyne" "$out/training/label_2" "$out/training/calib" "$out/ImageSets"
take() {  # take REPO COMMIT ID VELODYNE LABEL CALIB
  local git="$mirrors/$1/repo"
  git -C "$git" cat-file -e "$2^{commit}" 2>/dev/null \
    || { echo "$git has no commit $2 (fetch github:${1/+//} with its pull requests)" >&2; exit 2; }
  git -C "$git" show "$2:$4" > "$out/training/velodyne/$3.bin"
  git -C "$git" show "$2:$5" > "$out/training/label_2/$3.txt"
  git -C "$git" show "$2:$6" > "$out/training/calib/$3.txt"
  echo "$3"
}
new=()
for i in 000006 000007 000008 000009 000010; do
  d=data/KITTI/training
  new+=("$(take sshaoshuai+PointRCNN af3a8eeff5faa63a29b718fffd1d4a82120102de $i $d/velodyne/$i.bin \
           $d/label_2/$i.txt $d/calib/$i.txt)")
done
for i in 004139 004747; do
  d=examples/demo_data/KITTI/training
  new+=("$(take isl-org+Open3D-ML ea297bcee9bcfe7b3717f5f2684f166560b6ebb6 $i $d/velodyne/$i.bin \
           $d/label_2/$i.txt $d/calib/$i.txt)")
done
d=pointpillars/dataset/demo_data/val
new+=("$(take zhulf0804+PointPillars 620e6b0d07e4cb37b7b0114f26b934e8be92a0ba 000134 $d/000134.bin \
         $d/000134_gt.txt $d/000134.txt)")
# the frames already there (000000-000005) and the new ones, once each, in order
{ cat "$out/ImageSets/val.txt" 2>/dev/null || true; printf '%s\n' "${new[@]}"; } | sort -u > "$out/ImageSets/val.tmp"
mv "$out/ImageSets/val.tmp" "$out/ImageSets/val.txt"
echo "$(wc -l < "$out/ImageSets/val.txt") real KITTI frames in $out (not for git)"
