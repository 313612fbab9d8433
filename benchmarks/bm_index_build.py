"""Benchmark building a frame index with the detector (or CounterNet, ``--source counter``) as the counter: frames/s from KITTI-format ``.bin``
scans on disk, reading included, and each stage's share (reading the scans, counting, writing the parts;
within counting: the host time of the copy to the device, of the network with its post-processing and of the
read-back; on CUDA the copies run on a side stream beside the network, and what they hide is not counted).

    python benchmarks/bm_index_build.py --device cuda --frames 3000 --batch 16 --workers 12 \\
        --precision default,fp32,tf32,fp16 --json
    python benchmarks/bm_index_build.py --device cpu --frames 16 --distinct 4 --workers 0 --batch 1,4

The scans: ``--distinct`` simulated frames (held-out seed) written as KITTI velodyne files, copied to make
``--frames`` files (every file read from disk by the build). Rows: one per (mode, precision, batch, workers), plus the loop
a user writes first (one frame per call, read in the same process) as the baseline. Each row is a whole
``build_index`` into a fresh index, as ``lidarops index build --source detector`` runs it, after one
warm-up build of 2 batches, for each ``--precision`` (``default``: torch's settings, as the command without
``--precision``; ``fp32``, ``tf32``, ``fp16``: ``DetectorSource(precision=...)``) and ``--mode`` (``eager``: each
batch as eager calls; ``graph``: as one replayed CUDA graph, the command's default on CUDA). ``--json`` merges the rows
into ``benchmarks/results/<device>.json`` under ``"query_build"``. Target (issue 36): >= 500 frames/s on one
H100/H200. ``--source counter`` counts with the shipped ``counternet_road7`` (``CounterSource``);
``--mode graph-optimized`` records the graph of a BatchNorm-folded, channels-last copy (``optimize=True``).
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.common import env_meta, print_table, write_results  # noqa: E402


def write_scans(folder: Path, frames: int, distinct: int) -> list[int]:
    from lidarops.conventions import HELD_OUT_SEED
    from lidarops.data.formats.kitti import write_velodyne
    from lidarops.data.synthetic import SyntheticFrames

    velodyne = folder / "velodyne"
    velodyne.mkdir(parents=True, exist_ok=True)
    sim = SyntheticFrames("driving_city", num_frames=distinct, seed=HELD_OUT_SEED + 77)
    firsts = [write_velodyne(velodyne / f"{i:06d}.bin", sim[i].points) for i in range(distinct)]
    for i in range(distinct, frames):
        shutil.copyfile(firsts[i % distinct], velodyne / f"{i:06d}.bin")
    return list(range(frames))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--frames", type=int, default=3000)
    p.add_argument("--distinct", type=int, default=64)
    p.add_argument("--batch", default="8,16,32", help="frames per detector call, comma-separated")
    p.add_argument("--workers", default="8", help="DataLoader processes, comma-separated")
    p.add_argument("--precision", default="default",
                   help="the network's arithmetic, comma-separated: default (torch's settings), fp32, tf32, fp16")
    p.add_argument("--baseline-frames", type=int, default=200, help="frames of the one-at-a-time baseline")
    p.add_argument("--mode", default=None, help="eager, graph or both, comma-separated: each batch as eager calls "
                                                 "or as one replayed CUDA graph (default: both on CUDA, eager on CPU)")
    p.add_argument("--source", choices=["detector", "counter"], default="detector",
                   help="the shipped PointPillars (default) or the shipped CounterNet counternet_road7")
    p.add_argument("--data", type=Path, help="folder for the scans (default: a temporary one)")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    modes = (args.mode or ("eager,graph" if args.device.startswith("cuda") else "eager")).split(",")
    if any(m not in ("eager", "graph", "graph-optimized") for m in modes) or \
            (any(m.startswith("graph") for m in modes) and args.device == "cpu"):
        p.error(f"--mode: {args.mode!r}: eager, graph and graph-optimized, comma-separated; graph needs --device cuda")
    precisions = args.precision.split(",")
    for precision in precisions:
        if precision not in ("default", "fp32", "tf32", "fp16"):
            p.error(f"--precision: {precision!r} is not one of default, fp32, tf32, fp16")
        if precision == "fp16" and args.device == "cpu":
            p.error("--precision fp16 needs --device cuda (float16 on the CPU is far slower than float32)")

    from lidarops.cli.query import _KittiLoader
    from lidarops.data.formats.kitti import KittiDataset
    from lidarops.models import load_model, weights
    from lidarops.query.build import CounterSource, DetectorSource, build_index

    tmp = Path(tempfile.mkdtemp(prefix="bm_index_"))
    data = args.data or tmp / "kitti"
    if not (data / "velodyne" / f"{args.frames - 1:06d}.bin").is_file():
        print(f"writing {args.frames} scans ({args.distinct} distinct) to {data}", flush=True)
        write_scans(data, args.frames, args.distinct)
    kitti = KittiDataset(data)
    names = kitti.ids[:args.frames]
    ids = [int(n) for n in names]
    load = _KittiLoader(kitti, names, needs_labels=False)
    model = load_model(weights.path("counternet_road7" if args.source == "counter" else weights.DEFAULT))
    model = model.to(args.device).eval()
    points = sum(os.path.getsize(data / "velodyne" / f"{n}.bin") for n in names[:args.distinct]) / 16 / args.distinct

    def run(batch: int, workers: int, n: int, label: str, precision: str = "default", mode: str = "eager") -> dict:
        kw = dict(precision=None if precision == "default" else precision, graph=mode.startswith("graph"),
                  optimize=mode == "graph-optimized")
        source = CounterSource(model, **kw) if args.source == "counter" else DetectorSource(model, 0.5, **kw)
        build_index(tmp / "warm", ids[:2 * batch], load, source, batch=batch, workers=workers)  # warm-up
        shutil.rmtree(tmp / "warm")
        source.stage_seconds = dict.fromkeys(source.stage_seconds, 0.0)
        report = build_index(tmp / "idx", ids[:n], load, source, batch=batch, workers=workers,
                             part_frames=1024)
        shutil.rmtree(tmp / "idx")
        count = report.stage_seconds["count"] or 1e-9
        row = {"op": f"index_build_{args.source}", "case": label if args.source == "detector" else f"counter: {label}", "frames": n, "batch": batch, "workers": workers,
               "precision": precision, "mode": mode,
               "points_per_frame": round(points), "frames_per_s": round(report.frames_per_second, 1),
               **{f"share_{k}": round(v / report.seconds, 3) for k, v in report.stage_seconds.items()},
               **{f"count_share_{k}": round(v / count, 3) for k, v in source.stage_seconds.items()}}
        within = ", ".join(f"{k} {100 * v / count:.0f} %" for k, v in source.stage_seconds.items())
        print(f"{label}: {row['frames_per_s']} frames/s ({report.shares()}; counting: {within})", flush=True)
        return row

    rows = [run(1, 0, min(args.baseline_frames, args.frames), "one frame per call, read in-process")]
    for mode in modes:
        for precision in precisions:
            for workers in (int(w) for w in args.workers.split(",")):
                for batch in (int(b) for b in args.batch.split(",")):
                    label = f"batch {batch}, {workers} workers" + ("" if precision == "default" else f", {precision}") \
                        + {"eager": "", "graph": ", CUDA graph", "graph-optimized": ", CUDA graph, optimized"}[mode]
                    rows.append(run(batch, workers, args.frames, label, precision, mode))
    keys = ["case", "frames_per_s", "share_load", "share_count", "share_write", "count_share_to_device",
            "count_share_predict", "count_share_read_back"]
    print_table(f"index build, {args.source} source, {args.device}", keys, [[r[k] for k in keys] for r in rows],
                right=range(1, len(keys)))
    if args.json:
        meta = env_meta(args.device)
        meta["scenario"] = "driving_city"
        print("results:", write_results("query_build", args.device, rows, meta, replace_by="case"))
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
