"""mmdetection3d's demo KITTI frame 000008 (``demo/data/kitti/``: scan and annotation pickle) as KITTI files
(velodyne, calib, label_2) in a KITTI folder outside git, beside the frames of kitti_real_frames.sh.

    python tools/sim2real/mmdet3d_demo_frame.py MMDET3D_GIT_DIR OUT

The pickle is mmdetection3d 1.x's info format (plain dicts and lists): camera boxes ``(x, y, z, l, h, w, ry)``
with KITTI's bottom-centre origin, labels Pedestrian 0, Cyclist 1, Car 2, DontCare -1.
"""
from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path

NAMES = {0: "Pedestrian", 1: "Cyclist", 2: "Car", -1: "DontCare"}


def show(repo: str, path: str) -> bytes:
    return subprocess.run(["git", "-C", repo, "show", f"HEAD:{path}"], check=True, capture_output=True).stdout


def row(m) -> str:
    return " ".join(f"{v:.12e}" for r in m[:3] for v in r[:4])


def main(repo: str, out: str) -> int:
    split = Path(out) / "training"
    for d in ("velodyne", "calib", "label_2"):
        (split / d).mkdir(parents=True, exist_ok=True)
    (split / "velodyne" / "000008.bin").write_bytes(show(repo, "demo/data/kitti/000008.bin"))
    info = pickle.loads(show(repo, "demo/data/kitti/000008.pkl"))["data_list"][0]  # plain dicts from a public repo
    images, lidar = info["images"], info["lidar_points"]
    r0 = images["R0_rect"]
    calib = [f"P{k}: {row(images[f'CAM{k}']['cam2img'])}" for k in range(4)]
    calib.append("R0_rect: " + " ".join(f"{v:.12e}" for r in r0[:3] for v in r[:3]))
    calib.append(f"Tr_velo_to_cam: {row(lidar['Tr_velo_to_cam'])}")
    calib.append(f"Tr_imu_to_velo: {row(lidar['Tr_imu_to_velo'])}")
    (split / "calib" / "000008.txt").write_text("\n".join(calib) + "\n")
    lines = []
    for inst in info["instances"]:
        x, y, z, l, h, w, ry = inst["bbox_3d"]
        name = NAMES[inst["bbox_label_3d"]]
        lines.append(f"{name} {inst['truncated']:.2f} {inst['occluded']} {inst['alpha']:.2f} "
                     + " ".join(f"{v:.2f}" for v in inst["bbox"])
                     + f" {h:.2f} {w:.2f} {l:.2f} {x:.2f} {y:.2f} {z:.2f} {ry:.2f}")
    (split / "label_2" / "000008.txt").write_text("\n".join(lines) + "\n")
    ids = Path(out) / "ImageSets" / "val.txt"
    have = ids.read_text().split() if ids.is_file() else []
    ids.parent.mkdir(parents=True, exist_ok=True)
    ids.write_text("\n".join(sorted(set(have) | {"000008"})) + "\n")
    print(f"frame 000008 ({len(lines)} labels) in {split}")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
