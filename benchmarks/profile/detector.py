"""Where the GPU time of PointPillars frames goes, stage by stage, in the graphed inference
(:class:`lidarops.models.GraphedPointPillars`): the graph's body run eagerly under torch.profiler, each
stage in a ``record_function`` range, kernel time summed per stage; then the top kernels, and the
graph's replay time for comparison.

    python benchmarks/profile/detector.py [--precision fp16] [--runs 20] [--batch 16] [--whole-scan] [--optimize]
        [--cudnn-benchmark]

``--batch B`` profiles B frames per call (the batched graph the index build replays); ``--whole-scan`` takes
the whole simulated sweep (what ``bm_index_build`` writes to disk) instead of the camera's view. ``--optimize``
profiles the :func:`~lidarops.models.cuda_graph.inference_copy` that ``GraphedPointPillars(optimize=True)`` and
``predict`` under fp16 autocast replay; ``--cudnn-benchmark`` lets cuDNN time its algorithms for each shape
(``torch.backends.cudnn.benchmark``) instead of choosing them by its heuristics.
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_detector import kitti_like_frame, load_model  # noqa: E402
from benchmarks.profile_eager import kernel_totals  # noqa: E402
from lidarops.models.cuda_graph import (GraphedPointPillars, inference_copy, padded_inference,  # noqa: E402
                                        precision_mode)

STAGES = ("voxelize", "pfn", "scatter", "backbone", "head", "decode", "postprocess")


def body(model, points, precision, rows=None):
    """``points (B, N, 4)``: :func:`lidarops.models.cuda_graph.padded_inference` (its stages are profiler ranges)."""
    with torch.no_grad(), precision_mode(precision):
        return padded_inference(model, points, rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", default="fp16", choices=("fp32", "tf32", "fp16"))
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--batch", type=int, default=1, help="frames per call")
    ap.add_argument("--whole-scan", action="store_true", help="the whole sweep, not the camera's view")
    ap.add_argument("--all-rows", action="store_true", help="pillar rows for every frame's capacity, not a quarter "
                                                            "more than the frames need (the index build's sizing)")
    ap.add_argument("--optimize", action="store_true", help="the inference copy (BatchNorm folded, channels-last)")
    ap.add_argument("--cudnn-benchmark", action="store_true", help="cuDNN times its algorithms per shape")
    args = ap.parse_args(argv)
    torch.backends.cudnn.benchmark = args.cudnn_benchmark
    if args.whole_scan:
        from lidarops.data.synthetic import Simulator

        frame = torch.from_numpy(Simulator("driving_city", seed=0).sweep(0).points[:, :4]).float().cuda()
    else:
        frame = kitti_like_frame().cuda()
    frames = frame[None].repeat(args.batch, 1, 1)
    model = load_model("cuda", "dense")
    body_model = inference_copy(model) if args.optimize else model
    needed = int(body(body_model, frames, args.precision)["pillars"])
    rows = None if args.all_rows else -(-(needed + needed // 4 + 1) // 8192) * 8192
    for _ in range(5):
        body(body_model, frames, args.precision, rows)
    torch.cuda.synchronize()
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(args.runs):
            body(body_model, frames, args.precision, rows)
        torch.cuda.synchronize()
    per_stage = {s: 0.0 for s in STAGES}
    for e in prof.events():
        # the host's range (its kernels' time); the same range also appears on the GPU's timeline as an
        # annotation whose span includes the gaps between its kernels: not counted
        if e.name in per_stage and str(e.device_type).endswith("CPU"):
            per_stage[e.name] += e.device_time_total / args.runs / 1e3
    total = sum(per_stage.values())
    print(f"{args.batch} frame(s) of {frame.shape[0]} points ({needed} pillars, {rows or 'all'} rows), "
          f"{args.precision}{', optimized copy' if args.optimize else ''}"
          f"{', cudnn.benchmark' if args.cudnn_benchmark else ''}: GPU kernel time per call by stage (ms)")
    for s, t in per_stage.items():
        print(f"  {s:12s} {t:7.3f}  {100 * t / total:4.0f}%")
    print(f"  {'total':12s} {total:7.3f}")
    print("kernels by GPU time per call (us, launches per call):")
    for name, us, n in kernel_totals(prof.events(), args.runs)[:30]:
        print(f"  {us:8.1f} x{n:4.0f}  {name[:110]}")
    graphed = GraphedPointPillars(model, capacity=int(frame.shape[0]), precision=args.precision, batch_size=args.batch,
                                  max_pillars=rows, optimize=args.optimize)
    for _ in range(5):
        graphed([frame] * args.batch)
    times = []
    for _ in range(50):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        graphed._graph.replay()
        b.record()
        torch.cuda.synchronize()
        times.append(a.elapsed_time(b))
    times.sort()
    med = times[len(times) // 2]
    print(f"graph replay alone (GPU, CUDA events): median {med:.3f} ms per call, {1e3 * args.batch / med:.0f} frames/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
