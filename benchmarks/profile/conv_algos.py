"""Kernel time and accuracy of the CUDA sparse-convolution algorithms for float32 and float16.

    python benchmarks/profile/conv_algos.py [--grids kitti,dense] [--channels 64,128] [--pillars] [--splits auto,1,2]

For each BEV grid of benchmarks/bm_sparse.py, kind (SubM 3x3, strided 3x3 s2) and C = Cin = Cout, the
registered op ``sparse_conv`` with its cached map and order, per algorithm:

* ``fp32``: float32 FFMA tiles (exact float32);
* ``3xtf32``: float32 as three TF32 tensor-core products (the op's ``algo="3xtf32"``);
* ``tf32``: one TF32 product (``allow_tf32``);
* ``fp16``: float16 operands, float32 accumulation.

``call`` is the benchmark's per-call time (``benchmarks.common.time_cuda``: CUDA events around each
Python call, the inputs rotated over copies so that they come from memory, not L2); ``kernel`` is the
GPU time alone (20 calls on the same inputs captured in a CUDA graph, replayed; per call); ``err`` is
max |out - ref| / max |ref| against the float64 product of the same float32 inputs. ``--pillars`` also times the
Sparse-PointPillars backbone (maps cached, and in a CUDA graph) per precision; ``--layers`` times each
of its convolutions alone (kernel time, on the backbone's own maps and channels) and their sum
weighted by how often each occurs. ``--splits`` forces the offset splits of the single layers and of
``--layers`` (the op's ``splits``; the backbone of ``--pillars`` keeps its own). ``--ceiling`` adds, per
layer (the single layers, and the backbone's with ``--layers``), cuBLAS on the dense GEMM of the same useful work (rows x (pairs per row x Cin)
times (. x Cout), operands already gathered) in float32 and in TF32: what the vendor's GEMM takes on
that work with no gather at all.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

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


def use_algo(algo: str) -> tuple:
    """Sets torch's TF32 switch for one algorithm; returns the operands' dtype and the op's ``algo``."""
    torch.backends.cuda.matmul.allow_tf32 = algo == "tf32"
    return (torch.float16 if algo == "fp16" else torch.float32), ("3xtf32" if algo == "3xtf32" else "auto")


def set_algo(net: torch.nn.Module, algo: str) -> None:
    """The kernel choice of every sparse convolution of a network."""
    from lidarops.sparse.nn import SparseConvolution
    for m in net.modules():
        if isinstance(m, SparseConvolution):
            m.algo = algo


# the Sparse-PointPillars backbone's convolutions: map key, Cin, Cout, how many use that map and channels
BACKBONE = [("down0", 64, 64, 1), ("subm0", 64, 64, 3), ("down1", 64, 128, 1), ("subm1", 128, 128, 5),
            ("up1", 128, 128, 1), ("down2", 128, 256, 1), ("subm2", 256, 256, 5), ("up2", 256, 128, 1)]


def dense_gemm_ms(rows: int, pairs: int, cin: int, cout: int, tf32: bool) -> float:
    """cuBLAS time of the dense product with the useful multiply-adds of a layer (its ``pairs`` input rows
    folded into ``rows`` rows of K = pairs / rows * Cin, rounded to a multiple of 4)."""
    k = max(4, round(pairs / rows * cin / 4) * 4)
    g = torch.Generator().manual_seed(rows)
    a = torch.randn(rows, k, generator=g).cuda()
    b = torch.randn(k, cout, generator=g).cuda()
    old = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = tf32
    try:
        return graph_ms(lambda: torch.mm(a, b))
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old


def backbone_layers(algos, dev, ceiling: bool = False, splits: int = 0) -> None:
    from benchmarks.bm_sparse import pillars_input
    with torch.no_grad():
        _, _, cached = pillars_input(dev, torch.float32)
    maps = cached.indice_dict
    n_in = {"down0": cached.features.shape[0]}
    n_in.update(subm0=maps["subm0"].neighbors.shape[0], down1=maps["subm0"].neighbors.shape[0],
                subm1=maps["subm1"].neighbors.shape[0], up1=maps["subm1"].neighbors.shape[0],
                down2=maps["subm1"].neighbors.shape[0], subm2=maps["subm2"].neighbors.shape[0],
                up2=maps["subm2"].neighbors.shape[0])
    extra = ["mm_fp32", "mm_tf32"] if ceiling else []
    print(f"{'layer':6s} {'rows':>6s} {'Cin':>4s} {'Cout':>4s} {'x':>2s} "
          + " ".join(f"{al:>9s}" for al in [*algos, *extra]))
    total = dict.fromkeys([*algos, *extra], 0.0)
    for key, cin, cout, count in BACKBONE:
        km = maps[key]
        nbr, order = km.neighbors, km.order
        g = torch.Generator().manual_seed(cin + cout)
        x32 = torch.randn(n_in[key], cin, generator=g).to(dev)
        w32 = (torch.randn(cout, nbr.shape[1], cin, generator=g) / math.sqrt(9 * cin)).to(dev)
        cells = []
        for algo in algos:
            dt, op_algo = use_algo(algo)
            xf, wf = x32.to(dt), w32.to(dt)
            t = graph_ms(lambda: torch.ops.lidarops.sparse_conv(xf, wf, nbr, order, op_algo, splits))  # noqa: B023
            total[algo] += count * t
            cells.append(f"{t:9.3f}")
        for col in extra:
            t = dense_gemm_ms(nbr.shape[0], int((nbr >= 0).sum()), cin, cout, tf32=col == "mm_tf32")
            total[col] += count * t
            cells.append(f"{t:9.3f}")
        print(f"{key:6s} {nbr.shape[0]:6d} {cin:4d} {cout:4d} {count:2d} " + " ".join(cells), flush=True)
    print(f"{'sum':6s} {'':6s} {'':4s} {'':4s} {'':2s} " + " ".join(f"{total[al]:9.3f}" for al in total), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grids", default="drone,kitti,dense")
    ap.add_argument("--channels", default="32,64,128")
    ap.add_argument("--algos", default="fp32,3xtf32,tf32,fp16")
    ap.add_argument("--pillars", action="store_true")
    ap.add_argument("--layers", action="store_true")
    ap.add_argument("--ceiling", action="store_true", help="cuBLAS on each layer's dense GEMM (mm_fp32, mm_tf32)")
    ap.add_argument("--splits", default="auto",
                    help="offset splits to time, comma-separated: auto (the library's choice) or a number "
                         "(the op's splits)")
    a = ap.parse_args(argv)
    for sp in a.splits.split(","):
        if len(a.splits.split(",")) > 1:
            print(f"--- offset splits: {sp}", flush=True)
        run(a, 0 if sp == "auto" else int(sp))
    return 0


def run(a, splits: int = 0) -> None:
    if not torch.cuda.is_available():
        print("conv_algos: needs a GPU")
        return
    from benchmarks.bm_sparse import GRIDS, bev_sites, pillars_input
    from benchmarks.common import time_cuda
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs
    ops = torch.ops.lidarops
    dev = torch.device("cuda")
    old = torch.backends.cuda.matmul.allow_tf32
    print(f"{'grid':6s} {'kind':4s} {'C':>4s} {'algo':9s} {'call':>7s} {'kernel':>7s} {'TFLOP/s':>8s} {'err':>9s}")
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
                        dt, op_algo = use_algo(algo)
                        xf, wf = f32.to(dt), w.to(dt)
                        fn = lambda: ops.sparse_conv(xf, wf, nbr, order, op_algo, splits)  # noqa: E731
                        err = (fn().double().cpu() - ref).abs().max().item() / scale
                        t_call = time_cuda(lambda *args: ops.sparse_conv(*args),
                                           (xf, wf, nbr, order, op_algo, splits)).median
                        t_kernel = graph_ms(fn)
                        print(f"{gname:6s} {kind:4s} {C:4d} {algo:9s} {t_call:7.3f} {t_kernel:7.3f} "
                              f"{flop / t_kernel / 1e9:8.1f} {err:9.2e}", flush=True)
                    for tf32 in (False, True) if a.ceiling else ():
                        t_kernel = dense_gemm_ms(nbr.shape[0], pairs, C, C, tf32)
                        name = "mm_tf32" if tf32 else "mm_fp32"
                        print(f"{gname:6s} {kind:4s} {C:4d} {name:9s} {'':>7s} {t_kernel:7.3f} "
                              f"{flop / t_kernel / 1e9:8.1f}", flush=True)
        if a.layers:
            backbone_layers(a.algos.split(","), dev, a.ceiling, splits)
        if a.pillars:
            for algo in a.algos.split(","):
                dtype, op_algo = use_algo(algo)
                with torch.no_grad():
                    net, _, cached = pillars_input(dev, dtype)
                    set_algo(net, op_algo)
                    t_call = call_ms(lambda: net(cached), runs=50)
                    t_graph = graph_ms(lambda: net(cached), reps=1, replays=50)
                print(f"pillars {algo:9s} maps cached {t_call:6.3f} ms, in a CUDA graph {t_graph:6.3f} ms", flush=True)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old


if __name__ == "__main__":
    sys.exit(main())
