"""What a transposed map pays for reading its output count. An upsampling layer whose kernel is its stride (the
Sparse-PointPillars deblocks: 1 x 1 / 1, 2 x 2 / 2, 4 x 4 / 4) on sites a layer made reaches N K output sites,
which the library then knows without reading them back from the device ("blocks"); "counted" forces the count
to be read, as before. The whole Sparse-PointPillars backbone (KITTI grid, 15k pillars) eager, each call on a new
copy of the indices (every map built in the call), the two interleaved in rounds, beside dense cuDNN.

    python benchmarks/profile/sparse_upsample.py [--rounds 5]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_sparse import GRIDS, bev_sites, dense_pointpillars, precision, sparse_pointpillars  # noqa: E402
from benchmarks.common import time_call  # noqa: E402
from lidarops.compat import spconv as lspconv  # noqa: E402

OPS = torch.ops.lidarops


def _counted(op):
    """The out-indices op with the vouch for checked sites dropped: every transposed map reads its count."""
    def call(*args):
        return op(*args[:11], False)
    return call


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    shape, n = GRIDS["kitti"]
    idx = bev_sites(shape, n, sensor=(shape[0] / 2, 0)).cuda()
    blocks_op = OPS.sparse_conv_out_indices
    counted_op = _counted(blocks_op)
    print(f"Sparse-PointPillars backbone, {idx.shape[0]} pillars on {shape[0]} x {shape[1]}, eager, maps built, "
          f"ms (median of each round; {args.rounds} rounds)")
    print(f"{'prec':5s} {'blocks':>8s} {'counted':>8s} {'dense':>8s}  rounds: blocks / counted")
    for mode in ("tf32", "fp16"):
        with precision(mode) as dtype, torch.no_grad():
            feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
            net = sparse_pointpillars(lspconv).cuda().to(dtype).eval()
            dense = dense_pointpillars().cuda().to(dtype).eval()
            x_dense = lspconv.SparseConvTensor(feats, idx, list(shape), 1).dense()
            got = {"blocks": [], "counted": [], "dense": []}
            for _ in range(args.rounds):
                for name, op in (("blocks", blocks_op), ("counted", counted_op)):
                    OPS.sparse_conv_out_indices = op
                    try:
                        got[name].append(time_call(
                            lambda f: net(lspconv.SparseConvTensor(f, idx.clone(), list(shape), 1)), (feats,),
                            "cuda").median)
                    finally:
                        OPS.sparse_conv_out_indices = blocks_op
                got["dense"].append(time_call(dense, (x_dense,), "cuda").median)
            med = {k: statistics.median(v) for k, v in got.items()}
            rounds = " ".join(f"{b:.3f}/{c:.3f}" for b, c in zip(got["blocks"], got["counted"]))
            print(f"{mode:5s} {med['blocks']:8.3f} {med['counted']:8.3f} {med['dense']:8.3f}  {rounds}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
