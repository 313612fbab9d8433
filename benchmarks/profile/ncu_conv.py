"""One sparse-convolution layer per algorithm, for Nsight Compute (ncu) to profile.

    ncu --clock-control none --kernel-name regex:conv_fwd -o report python benchmarks/profile/ncu_conv.py \
        [--grid dense] [--kind subm] [--channels 128] [--algos fp32,3xtf32,tf32,fp16]

Each algorithm's layer runs twice (warm-up, then the profiled call); the switches are those of
benchmarks/profile/conv_algos.py.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", default="dense")
    ap.add_argument("--kind", default="subm")
    ap.add_argument("--channels", type=int, default=128)
    ap.add_argument("--algos", default="fp32,3xtf32,tf32,fp16")
    a = ap.parse_args(argv)
    from benchmarks.bm_sparse import GRIDS, bev_sites
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs
    from benchmarks.profile.conv_algos import use_algo
    dev = torch.device("cuda")
    shape, n = GRIDS[a.grid]
    idx = bev_sites(shape, n).to(dev)
    C = a.channels
    g = torch.Generator().manual_seed(C)
    f32 = torch.randn(idx.shape[0], C, generator=g).to(dev)
    w = (torch.randn(C, 9, C, generator=g) / (3 * math.sqrt(C))).to(dev)
    km = Fs.build_kernel_map(SparseConvTensor(f32, idx, list(shape), 1), a.kind, 3, 2 if a.kind == "conv" else 1, 1, 1)
    pairs = int((km.neighbors >= 0).sum())
    print(f"{a.grid} {a.kind} C={C}: {km.neighbors.shape[0]} output rows, {pairs} pairs", flush=True)
    for algo in a.algos.split(","):
        dt = use_algo(algo)
        xf, wf = f32.to(dt), w.to(dt)
        for _ in range(2):
            torch.ops.lidarops.sparse_conv(xf, wf, km.neighbors, km.order)
        torch.cuda.synchronize()
        print(algo, "done", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
