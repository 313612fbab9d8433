"""``lidarops eval``: KITTI's object evaluation (AP R11 / R40 of bbox, BEV, 3D and AOS) of a folder of result
files against a folder of label files.

Examples::

    lidarops eval --results det/data --labels data/synth/training/label_2 --split data/synth/ImageSets/val.txt
    lidarops eval --results det/data --labels kitti/training/label_2 --classes Car --json car_ap.json

Every frame listed (by ``--split``, else every result file) needs a result file; a frame without
detections needs an empty one, as in KITTI's own evaluation.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from lidarops.cli.errors import CliError, guarded

__all__ = ["register", "evaluate_results", "match_summary"]


def evaluate_results(args: argparse.Namespace) -> int:
    """Scores a folder of KITTI result files against label files; prints the AP table."""
    from lidarops.eval import kitti as kitti_eval

    results_dir, labels_dir = Path(args.results), Path(args.labels)
    if not all(name.strip() for name in args.classes):
        raise CliError(f"--classes holds an empty class name: {args.classes}")
    for p, what in ((results_dir, "--results"), (labels_dir, "--labels")):
        if not p.is_dir():
            raise CliError(f"{what} {p} is not a folder")
    if args.split:
        split = Path(args.split)
        if not split.is_file():
            raise CliError(f"--split {split} not found")
        try:
            text = split.read_bytes().decode("utf-8-sig")
        except UnicodeDecodeError as e:
            raise CliError(f"--split {split}: not a text file of frame ids (byte {e.start} is not UTF-8 text)") from None
        ids = [line.strip() for line in text.splitlines() if line.strip()]
    else:
        ids = sorted(p.stem for p in results_dir.glob("*.txt"))
    if not ids:
        where = f"--split {args.split} lists none" if args.split else f"{results_dir} holds no result files"
        raise CliError(f"no frames to score: {where}")
    missing = [i for i in ids if not (results_dir / f"{i}.txt").is_file()]
    if missing:
        raise CliError(f"{len(missing)} frame(s) have no result file in {results_dir} (e.g. {missing[0]}.txt); "
                       "a frame without detections needs an empty file")
    gt = kitti_eval.read_annos(labels_dir, ids)
    dt = kitti_eval.read_annos(results_dir, ids)
    text, results = kitti_eval.evaluate(gt, dt, args.classes)
    print(text)
    for name in args.classes:
        # KITTI's convention scores a class without labels 0 AP: say why rather than leave a bare 0
        if not any((np.char.lower(a["name"].astype(str)) == name.lower()).any() for a in gt):
            print(f"lidarops eval: note: the labels hold no {name} object, so its AP is 0 by KITTI's convention",
                  file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


def match_summary(gt_annos: list, dt_annos: list, names: Sequence[str]) -> str:
    """Found / labelled objects per class at KITTI's 3D overlap (0.7 Car, 0.5 others), every labelled
    object counted whatever its difficulty: the line a few frames are better read by than an AP (below 41
    objects of a class, R40 cannot reach 100).

    Args:
        gt_annos, dt_annos: per-frame KITTI annotation dicts (:mod:`lidarops.eval.kitti`), the detections
            with ``score``.
        names: the classes to count.
    """
    import lidarops
    from lidarops.eval.kitti import iou_boxes

    def lidar_boxes(anno, keep):
        return iou_boxes(anno["location"][keep], anno["dimensions"][keep], anno["rotation_y"][keep])

    parts = []
    for name in names:
        need = 0.7 if name in ("Car", "Van", "Truck", "Bus") else 0.5
        found = labelled = spare = 0
        for gt, dt in zip(gt_annos, dt_annos):
            g, d = gt["name"] == name, dt["name"] == name
            labelled += int(g.sum())
            if not (g.any() and d.any()):
                spare += int(d.sum())
                continue
            iou = lidarops.box_iou_3d(lidar_boxes(gt, g), lidar_boxes(dt, d)).numpy()  # (gts, detections)
            taken = np.zeros(iou.shape[0], bool)
            for j in np.argsort(-dt["score"][d], kind="stable"):  # the best detections take their gts first
                cand = np.where(taken, -1.0, iou[:, j])
                i = int(np.argmax(cand))
                if cand[i] >= need:
                    taken[i] = True
                    found += 1
                else:
                    spare += 1
        parts.append(f"{name}: {found} of {labelled} labelled found (3D IoU >= {need}), {spare} other detections")
    return "matches: " + "; ".join(parts)


def register(subparsers) -> None:
    """Adds ``eval`` to the ``lidarops`` parser."""
    e = subparsers.add_parser("eval", help="score KITTI result files against labels (KITTI AP)",
                              description="KITTI's object evaluation (AP R11/R40 of bbox, BEV, 3D, AOS) of a "
                                          "folder of result files against a folder of label files.")
    e.add_argument("--results", required=True, help="folder of <id>.txt result files (16 fields)")
    e.add_argument("--labels", required=True, help="folder of <id>.txt label files (label_2)")
    e.add_argument("--split", default=None, help="file listing the frame ids (default: every result file)")
    e.add_argument("--classes", nargs="+", default=["Car", "Pedestrian", "Cyclist"])
    e.add_argument("--json", default=None, help="also write the results dict here")
    e.set_defaults(func=guarded("eval", evaluate_results))
