"""Compare two OpenPCDet data roots prepared by prepare_kitti.py (one with OpenPCDet's own ops, one with
lidarops.compat.pcdet): the infos (every field, including each object's ``num_points_in_gt``, which
``points_in_boxes_cpu`` counts) and the ground-truth database (its entries and every object's points).

    python tools/upstream/openpcdet/compare_infos.py ROOT_A ROOT_B [--out report.json]
"""
from __future__ import annotations

import argparse
import json
import pickle
import sys
from pathlib import Path

import numpy as np


def same(a, b) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        if not (isinstance(b, np.ndarray) and a.shape == b.shape and a.dtype == b.dtype):
            return False
        return bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"))
    return a == b


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    report = {}
    for name in ("kitti_infos_train.pkl", "kitti_infos_val.pkl", "kitti_dbinfos_train.pkl"):
        a = pickle.loads((args.a / name).read_bytes())
        b = pickle.loads((args.b / name).read_bytes())
        report[name] = same(a, b)
    a = pickle.loads((args.a / "kitti_infos_train.pkl").read_bytes())
    b = pickle.loads((args.b / "kitti_infos_train.pkl").read_bytes())
    na = np.concatenate([i["annos"]["num_points_in_gt"] for i in a])
    nb = np.concatenate([i["annos"]["num_points_in_gt"] for i in b])
    report["objects"] = int(na.size)
    report["num_points_in_gt_differing"] = int((na != nb).sum()) if na.shape == nb.shape else None
    files_a = sorted((args.a / "gt_database").glob("*.bin"))
    differing = [f.name for f in files_a if not (args.b / "gt_database" / f.name).is_file()
                 or (args.b / "gt_database" / f.name).read_bytes() != f.read_bytes()]
    report["gt_database_files"] = len(files_a)
    report["gt_database_files_differing"] = len(differing)
    ok = all(report[n] for n in ("kitti_infos_train.pkl", "kitti_infos_val.pkl", "kitti_dbinfos_train.pkl")) \
        and not differing and len(files_a) == len(list((args.b / "gt_database").glob("*.bin")))
    report["same"] = ok
    print(f"infos and gt database, OpenPCDet's ops vs lidarops faces: {'the same' if ok else 'DIFFERENT'} {report}")
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
