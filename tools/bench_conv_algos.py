"""Kernel time and accuracy of the CUDA sparse-convolution algorithms for float32 and float16.

    python tools/bench_conv_algos.py [--grids kitti,dense] [--channels 64,128] [--pillars]

For each BEV grid of benchmarks/bm_sparse.py, kind (SubM 3x3, strided 3x3 s2) and C = Cin = Cout, the
registered op ``sparse_conv`` with its cached map and order, per algorithm:

* ``fp32``: float32 FFMA tiles (exact float32);
* ``tf32``: one TF32 product (``allow_tf32``);
* ``fp16``: float16 operands, float32 accumulation.

``call`` is the benchmark's per-call time (CUDA events around each Python call); ``kernel`` is the GPU
time alone (20 calls captured in a CUDA graph, replayed; per call); ``err`` is max |out - ref| / max
|ref| against the float64 product of the same float32 inputs. ``--pillars`` also times the
Sparse-PointPillars backbone (maps cached, and in a CUDA graph) per precision.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402



def graph_ms(fn, reps: int = 20, replays: int = 30) -> float:
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    g = torch.cuda.CUDAGraph()
    with torch.cuda.graph(g):
        for _ in range(reps):
            fn()
    g.replay()
    times = []
    for _ in range(replays):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        a.record()
        g.replay()
        b.record()
        b.synchronize()
        times.append(a.elapsed_time(b) / reps)
    return statistics.median(times)


def call_ms(fn, runs: int = 200) -> float:
    for _ in range(5):
        fn()
    ev = [(torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)) for _ in range(runs)]
    for a, b in ev:
        a.record()
        fn()
        b.record()
    torch.cuda.synchronize()
    return statistics.median(a.elapsed_time(b) for a, b in ev)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grids", default="drone,kitti,dense")
    ap.add_argument("--channels", default="32,64,128")
    ap.add_argument("--algos", default="fp32,tf32,fp16")
    ap.add_argument("--pillars", action="store_true")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("bench_conv_algos: needs a GPU")
        return 0
    from benchmarks.bm_sparse import GRIDS, bev_sites, pillars_input
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs
    ops = torch.ops.lidarops
    dev = torch.device("cuda")
    old = torch.backends.cuda.matmul.allow_tf32
    print(f"{'grid':6s} {'kind':4s} {'C':>4s} {'algo':7s} {'call':>7s} {'kernel':>7s} {'TFLOP/s':>8s} {'err':>9s}")
    try:
        for gname in filter(None, a.grids.split(",")):
            shape, n = GRIDS[gname]
            idx = bev_sites(shape, n).to(dev)
            for kind in ("subm", "conv"):
                for C in (int(c) for c in a.channels.split(",")):
                    g = torch.Generator().manual_seed(C)
                    f32 = torch.randn(idx.shape[0], C, generator=g).to(dev)
                    w = (torch.randn(C, 9, C, generator=g) / (3 * math.sqrt(C))).to(dev)
                    x = SparseConvTensor(f32, idx, list(shape), 1)
                    km = Fs.build_kernel_map(x, kind, 3, 2 if kind == "conv" else 1, 1, 1)
                    nbr, order = km.neighbors, km.order
                    pairs = int((nbr >= 0).sum())
                    flop = 2.0 * pairs * C * C
                    ref = ops.sparse_conv(f32.double().cpu(), w.double().cpu(), nbr.cpu())
                    scale = ref.abs().max().item()
                    for algo in a.algos.split(","):
                        torch.backends.cuda.matmul.allow_tf32 = algo == "tf32"
                        xf, wf = (f32.half(), w.half()) if algo == "fp16" else (f32, w)
                        fn = lambda: ops.sparse_conv(xf, wf, nbr, order)  # noqa: E731
                        err = (fn().double().cpu() - ref).abs().max().item() / scale
                        t_call, t_kernel = call_ms(fn), graph_ms(fn)
                        print(f"{gname:6s} {kind:4s} {C:4d} {algo:7s} {t_call:7.3f} {t_kernel:7.3f} "
                              f"{flop / t_kernel / 1e9:8.1f} {err:9.2e}", flush=True)
        if a.pillars:
            for algo in a.algos.split(","):
                torch.backends.cuda.matmul.allow_tf32 = algo == "tf32"
                dtype = torch.float16 if algo == "fp16" else torch.float32
                with torch.no_grad():
                    net, _, cached = pillars_input(dev, dtype)
                    t_call = call_ms(lambda: net(cached), runs=50)
                    t_graph = graph_ms(lambda: net(cached), reps=1, replays=50)
                print(f"pillars {algo:7s} maps cached {t_call:6.3f} ms, in a CUDA graph {t_graph:6.3f} ms", flush=True)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    return 0


if __name__ == "__main__":
    sys.exit(main())
