"""Where the GPU time of one PointPillars frame goes, stage by stage, in the graphed inference
(:class:`lidarops.models.GraphedPointPillars`): the graph's body run eagerly under torch.profiler, each
stage in a ``record_function`` range, kernel time summed per stage; then the top kernels, and the
graph's replay time for comparison.

    python benchmarks/profile/detector.py [--precision fp16] [--runs 20]
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

import lidarops  # noqa: E402
from benchmarks.bm_detector import kitti_like_frame, load_model  # noqa: E402
from lidarops.models.postprocess import postprocess_padded  # noqa: E402
from lidarops.models.cuda_graph import GraphedPointPillars, precision_mode  # noqa: E402
from lidarops.ops.voxelize import voxelize  # noqa: E402

STAGES = ("voxelize", "pfn", "scatter", "backbone", "head", "decode", "postprocess")


def body(model, points, precision):
    cfg = model.config
    rf = torch.profiler.record_function
    with torch.no_grad(), precision_mode(precision), lidarops.validation(False):
        with rf("voxelize"):
            v, c, n = voxelize(points, cfg.voxel_size, cfg.point_cloud_range, cfg.max_points_per_voxel,
                               cfg.max_voxels_test, overflow="drop", padded=True)
            coords = torch.cat([(c[:, :1] >= 0).to(c.dtype) - 1, c], 1)
        with rf("pfn"):
            feats = model.vfe(v, n, coords)
        with rf("scatter"):
            x = model.map_to_bev(feats, coords, 1)
        with rf("backbone"):
            x = model.backbone_2d(x)
        with rf("head"):
            raw = model.dense_head(x)
        with rf("decode"):
            cls, boxes = model.dense_head.decode(raw)
        with rf("postprocess"):
            return postprocess_padded(cls, boxes, cfg)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--precision", default="fp16", choices=("fp32", "tf32", "fp16"))
    ap.add_argument("--runs", type=int, default=20)
    args = ap.parse_args(argv)
    frame = kitti_like_frame().cuda()
    model = load_model("cuda", "dense")
    for _ in range(5):
        body(model, frame, args.precision)
    torch.cuda.synchronize()
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(args.runs):
            body(model, frame, args.precision)
        torch.cuda.synchronize()
    per_stage = {s: 0.0 for s in STAGES}
    for e in prof.events():
        if e.name in per_stage:
            per_stage[e.name] += e.device_time_total / args.runs / 1e3
    total = sum(per_stage.values())
    print(f"{frame.shape[0]} points, {args.precision}: GPU kernel time per frame by stage (ms)")
    for s, t in per_stage.items():
        print(f"  {s:12s} {t:7.3f}  {100 * t / total:4.0f}%")
    print(f"  {'total':12s} {total:7.3f}")
    print(prof.key_averages().table(sort_by="device_time_total", row_limit=25))
    graphed = GraphedPointPillars(model, capacity=int(frame.shape[0]), precision=args.precision)
    for _ in range(5):
        graphed(frame)
    times = []
    for _ in range(50):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        graphed._graph.replay()
        b.record()
        torch.cuda.synchronize()
        times.append(a.elapsed_time(b))
    times.sort()
    print(f"graph replay alone (GPU, CUDA events): median {times[len(times) // 2]:.3f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
