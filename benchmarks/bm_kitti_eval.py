"""Speed of the KITTI evaluation (lidarops.eval.kitti.evaluate) on a KITTI-val-sized set.

Usage::

    python benchmarks/bm_kitti_eval.py                      # 3769 frames, ~15 gts and ~20 detections each
    python benchmarks/bm_kitti_eval.py --frames 500 --seed 1
    python benchmarks/bm_kitti_eval.py --json               # merge into benchmarks/results/<device>.json
    python benchmarks/bm_kitti_eval.py --json out.json      # or write this run's rows to out.json

The annotations come from the test data generator (tests/helpers/kitti.py, seeded): Cars, Pedestrians,
Cyclists, Vans, Persons sitting, Trucks and DontCare regions, jittered detections and false positives.
Rows: the whole evaluation (3 classes, the bbox / bev / 3d / aos metrics, strict and loose overlaps, as
OpenPCDet runs it after each epoch), its two halves (checking the annotations and computing every IoU;
the matching passes and AP curves), and the evaluation of single metrics. CPU wall time, median over
runs after a warm-up run (benchmarks/common.py).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from benchmarks.common import env_meta, print_table, time_cpu, write_results  # noqa: E402
from helpers.kitti import random_annos  # noqa: E402
from lidarops.eval import kitti  # noqa: E402

CLASSES = ("Car", "Pedestrian", "Cyclist")


def run(frames: int, seed: int, num_gt: int, num_dt: int, budget_s: float) -> tuple[list[dict], dict]:
    t0 = time.perf_counter()
    gts, dts = random_annos(frames, seed=seed, num_gt=num_gt, num_dt=num_dt)
    gen_s = time.perf_counter() - t0
    sizes = {"frames": frames, "gts": sum(len(a["name"]) for a in gts), "detections": sum(len(a["name"]) for a in dts),
             "generate_s": round(gen_s, 3)}

    def setup():
        return kitti._Evaluation(gts, dts, CLASSES, kitti.METRICS)

    cases = [
        ("evaluate: all metrics", lambda: kitti.evaluate(gts, dts, CLASSES)),
        ("  annotations + IoUs", setup),
        ("evaluate: 3d only", lambda: kitti.evaluate(gts, dts, CLASSES, metrics=("3d",))),
        ("evaluate: bev only", lambda: kitti.evaluate(gts, dts, CLASSES, metrics=("bev",))),
        ("evaluate: bbox + aos", lambda: kitti.evaluate(gts, dts, CLASSES, metrics=("bbox", "aos"))),
    ]
    rows = []
    for name, fn in cases:
        timing = time_cpu(fn, (), min_runs=3, max_runs=10, budget_s=budget_s, slow_single_s=60.0)
        rows.append({"op": "kitti_eval", "case": name.strip(), **sizes, **timing.as_dict()})
    # the matching half: the whole evaluation less its setup
    full, part = rows[0]["median_ms"], rows[1]["median_ms"]
    rows.insert(2, {"op": "kitti_eval", "case": "matching + AP (difference)", **sizes,
                    "median_ms": round(full - part, 3), "iqr_ms": None, "runs": None, "input_sets": 1})
    return rows, sizes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3769, help="frames (default 3769, KITTI val)")
    ap.add_argument("--gts", type=int, default=15, help="ground truths per frame, on average")
    ap.add_argument("--dets", type=int, default=20, help="detections per frame, on average")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget", type=float, default=10.0, help="seconds of timed runs per case")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (default: torch's choice)")
    ap.add_argument("--json", nargs="?", const="", default=None, metavar="PATH",
                    help="write the rows to PATH, or without PATH into benchmarks/results/<device>.json")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    rows, sizes = run(args.frames, args.seed, args.gts, args.dets, args.budget)
    meta = env_meta("cpu")
    print(f"# {meta['device']}, torch {meta['torch']}, {meta['threads']} threads")
    print_table(f"KITTI evaluation of {sizes['frames']} frames ({sizes['gts']} gts, {sizes['detections']} detections; "
                f"classes {', '.join(CLASSES)}; strict and loose overlaps)",
                ["case", "median s", "IQR s", "runs"],
                [[r["case"], f"{r['median_ms'] / 1e3:.3f}", "" if r["iqr_ms"] is None else f"{r['iqr_ms'] / 1e3:.3f}",
                  r["runs"] or ""] for r in rows], right=(1, 2, 3))
    if args.json is not None:
        if args.json:
            Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
            print(f"wrote {args.json}")
        else:
            print(f"wrote {write_results('kitti_eval', 'cpu', rows, meta, replace_by=None)}")


if __name__ == "__main__":
    main()
