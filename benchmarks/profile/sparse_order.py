"""Whether a kernel map's row order (``KernelMap.order``: the rows sorted by their offset masks, about five
launches when a map is built) pays for itself. Eager calls, each on a new copy of the indices (maps built in
the call): the SubM 3x3 64 -> 64 module and the 16-layer down path, each layer run with the order ("always", as
when a map made it at construction), without it ("never"), and with the library's rule (``KernelMap.layer_order``:
from a map's ``ORDER_FROM_CALL``-th layer call on, "call 2" and "call 3"; SparseSequential runs the fused SubM
layers after a block's first as one call); and the kernels alone: the
whole Sparse-PointPillars backbone with its maps cached, replayed as a CUDA graph, with and without the order.

    python benchmarks/profile/sparse_order.py
"""
from __future__ import annotations

import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_sparse import (GRIDS, _graphed, bev_sites, down_path, pillars_input, precision,  # noqa: E402
                                  sparse_pointpillars)
from benchmarks.common import time_call  # noqa: E402
from lidarops.compat import spconv as lspconv  # noqa: E402
from lidarops.sparse import tensor as sparse_tensor  # noqa: E402

LIBRARY = sparse_tensor.KernelMap.layer_order
LIBRARY_FROM = sparse_tensor.ORDER_FROM_CALL
# what a layer runs with: the order made for every layer (as when maps made it at construction), never, or the
# library's own rule from a map's second or third layer call on: (layer_order, ORDER_FROM_CALL)
POLICIES = {"always": (lambda self: self.order, LIBRARY_FROM), "never": (lambda self: self._order, LIBRARY_FROM),
            "call 2": (LIBRARY, 2), "call 3": (LIBRARY, 3)}


def use(policy) -> None:
    sparse_tensor.KernelMap.layer_order, sparse_tensor.ORDER_FROM_CALL = policy


def main() -> int:
    print("eager calls on a new copy of the indices, ms (medians): SubM + map | down path, per order policy")
    print(f"{'grid':6s} {'prec':5s} " + " ".join(f"{'SubM ' + p:>13s}" for p in POLICIES) + " "
          + " ".join(f"{'down ' + p:>13s}" for p in POLICIES))
    for gname, (shape, n) in GRIDS.items():
        idx = bev_sites(shape, n).cuda()
        for mode in ("tf32", "fp16"):
            with precision(mode) as dtype, torch.no_grad():
                feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
                layer = lspconv.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(dtype).eval()
                down = down_path(sparse_pointpillars(lspconv).cuda().to(dtype).eval())
                cells = []
                for fn in (layer, down):
                    for policy in POLICIES.values():
                        use(policy)
                        cells.append(time_call(lambda f: fn(lspconv.SparseConvTensor(f, idx.clone(), list(shape), 1)),
                                               (feats,), "cuda").median)
                use((LIBRARY, LIBRARY_FROM))
                print(f"{gname:6s} {mode:5s} " + " ".join(f"{c:13.3f}" for c in cells))
    print("the whole Sparse-PointPillars backbone (KITTI grid, 15k pillars), maps cached, CUDA graph, ms: "
          "order / no order")
    for mode in ("tf32", "fp16"):
        with precision(mode) as dtype, torch.no_grad():
            cells = []
            for policy in (POLICIES["always"], POLICIES["never"]):
                use(policy)
                net, x, cached = pillars_input("cuda", dtype)
                cells.append(_graphed(net, cached, x.features).median)
            use((LIBRARY, LIBRARY_FROM))
            print(f"  {mode:5s} " + " ".join(f"{c:8.3f}" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
