"""``lidarops eval``: KITTI's object evaluation (AP R11 / R40 of bbox, BEV, 3D and AOS) of a folder of result
files against a folder of label files.

Examples::

    lidarops eval --results det/data --labels data/synth/training/label_2 --split data/synth/ImageSets/val.txt
    lidarops eval --results det/data --labels kitti/training/label_2 --classes Car --json car_ap.json
    lidarops eval --results aerial/data --labels drones/training/label_2 --classes Drone --whole-view

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

__all__ = ["register", "evaluate_results", "match_summary", "counted", "ap_headline"]


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
    _check_sides(gt, dt, labels_dir, results_dir, ids)
    if args.whole_view:  # no image: BEV and 3D, every object (a drone's Avia sees far beyond a camera)
        gt = [kitti_eval.whole_view_annos(a) for a in gt]
        dt = [kitti_eval.whole_view_annos(a) for a in dt]
    text, results = kitti_eval.evaluate(gt, dt, args.classes)
    print(text)
    made = results_dir.parent / "detect.json"  # written by lidarops detect beside its data/ folder
    if made.is_file():
        try:
            trained = set(json.loads(made.read_text()).get("frames_of_the_model_recipe") or ())
        except (OSError, ValueError, AttributeError):
            trained = set()
        scored = [i for i in ids if i in trained]
        if scored:
            print(f"lidarops eval: warning: {len(scored)} of the {len(ids)} frames scored are frames the model was "
                  f"trained or validated on ({made} says so): the AP measures memory, not detection",
                  file=sys.stderr)
    for name in args.classes:
        # KITTI's convention scores a class without labels 0 AP: say why rather than leave a bare 0
        if not any((np.char.lower(a["name"].astype(str)) == name.lower()).any() for a in gt):
            print(f"lidarops eval: note: the labels hold no {name} object, so its AP is 0 by KITTI's convention",
                  file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


def _check_sides(gt: list, dt: list, labels_dir: Path, results_dir: Path, ids: Sequence[str]) -> None:
    """Refuses label files given as results (no score column) and result files given as labels, naming the
    folder and the first such file: the evaluator would otherwise fail on a missing field."""
    for annos, folder, flag, want in ((dt, results_dir, "--results", True), (gt, labels_dir, "--labels", False)):
        for anno, frame_id in zip(annos, ids):
            if len(anno["name"]) and ("score" in anno) != want:
                what = "label files (15 fields, no score)" if want else "result files (16 fields, with a score)"
                raise CliError(f"{flag} {folder} holds {what}: {folder / (frame_id + '.txt')}; "
                               f"{'--results takes detections' if want else '--labels takes the ground truth'}"
                               " (are --results and --labels swapped?)")


def counted(anno: dict, point_cloud_range: Sequence[float] | None = None) -> np.ndarray:
    """Which labelled objects of a frame a summary counts: those in one of KITTI's difficulties (a 2D box
    >= 25 px high, truncation <= 0.5, occlusion <= 2: the objects AP is computed on; without image boxes,
    as :func:`lidarops.eval.kitti.whole_view_annos` leaves them, occlusion alone) and, with
    ``point_cloud_range``, whose centre lies inside the model's range in x and y (it cannot see others)."""
    n = len(anno["name"])
    if n == 0:
        return np.zeros(0, bool)
    keep = (anno["truncated"] <= 0.5) & (anno["occluded"] <= 2)
    if "bbox" in anno:
        keep &= anno["bbox"][:, 3] - anno["bbox"][:, 1] >= 25
    if point_cloud_range is not None:
        x, y = anno["location"][:, 2], -anno["location"][:, 0]  # camera frame -> x forward, y left
        x0, y0, _, x1, y1, _ = point_cloud_range
        keep &= (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    return keep


def match_summary(gt_annos: list, dt_annos: list, names: Sequence[str],
                  point_cloud_range: Sequence[float] | None = None) -> str:
    """Found / labelled objects per class at KITTI's 3D overlap (0.7 Car, 0.5 others), counting the labelled
    objects :func:`counted` keeps (in a KITTI difficulty and, given it, the model's range): the line a few
    frames are better read by than an AP (below 41 objects of a class, R40 cannot reach 100).

    Args:
        gt_annos, dt_annos: per-frame KITTI annotation dicts (:mod:`lidarops.eval.kitti`), the detections
            with ``score``.
        names: the classes to count.
        point_cloud_range: the model's range (x0, y0, z0, x1, y1, z1), or None for no range limit.
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
            g, d = (gt["name"] == name) & counted(gt, point_cloud_range), dt["name"] == name
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
        parts.append(f"{name}: {found} of {labelled} found (3D IoU >= {need}), {spare} other detections")
    where = " in range and a KITTI difficulty" if point_cloud_range is not None else " in a KITTI difficulty"
    return f"matches (labelled objects{where}): " + "; ".join(parts)


def ap_headline(results: dict, names: Sequence[str], frames: int, recorded: dict | None = None,
                counts: dict | None = None) -> str:
    """A few lines of the AP that matter (3D and BEV, R40, strict overlaps) per class, with the number of
    objects scored at moderate difficulty (``counts``: :func:`lidarops.eval.kitti.count_difficulties`) and the
    model's own recorded evaluation beside them when there is one."""
    rows = [f"KITTI AP (R40, %) on {frames} frame(s), 3D easy / moderate / hard, BEV moderate:"]
    for name in names:
        get = [results.get(f"{name}_3d_{d}_R40") for d in ("easy", "moderate", "hard")]
        bev = results.get(f"{name}_bev_moderate_R40")
        if None in get or bev is None:
            continue
        line = f"  {name:<11} 3D {get[0]:5.1f} / {get[1]:5.1f} / {get[2]:5.1f}   BEV {bev:5.1f}"
        n = (counts or {}).get(name, {}).get("moderate")
        if n is not None:
            # R40 samples 40 recall positions: with fewer objects a perfect detector still scores below 100
            line += f"   {n:4d} moderate objects" + ("  (too few for R40: read the found line)" if n < 41 else "")
        mine = (recorded or {}).get(f"{name}_3d_moderate_R40")
        if mine is not None:
            line += f"   (recorded when trained: {mine:.1f})"
        rows.append(line)
    return "\n".join(rows)


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
    e.add_argument("--whole-view", action="store_true",
                   help="score the sensor's whole view, not a camera's: no image boxes (BEV and 3D only, no minimum "
                        "height in pixels), truncation 0, no DontCare regions; for models that see beyond the camera "
                        "(aerial_pointpillars)")
    e.set_defaults(func=guarded("eval", evaluate_results))
