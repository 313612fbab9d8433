"""What the check of a new frame's sites costs an eager SubM call (the 3x3 64 -> 64 module, each call on a new
copy of the indices, so its map is built and its sites are checked in the call), and where: the library's
deferred read (the check's flags copied to pinned memory, read after the convolution is queued), the read made
at once (the map op raises itself: one blocking host read before the convolution), the deferred path with its
read left out (copy and event made, never waited on) and with neither copy nor event (the flagged map op
alone), and no check (``lidarops.validation(False)``). The diagnostic variants are made by patching private
functions of ``lidarops.sparse.functional`` for the run; they skip the check and are not for use.

Per variant: the median CUDA-event time of a call (``benchmarks.common.time_call``, as ``bm_sparse.py``) and the
host's time per call (``time.perf_counter`` over 200 calls, no synchronisation inside); then the host-side
profile of one default call (``torch.profiler``, CPU ops and CUDA runtime calls by self time).

    python benchmarks/profile/sparse_check.py [--grid kitti] [--precision fp16]
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_sparse import GRIDS, bev_sites, precision  # noqa: E402
from benchmarks.common import time_call  # noqa: E402
from lidarops.compat import spconv as lspconv  # noqa: E402
from lidarops.ops.validation import validation  # noqa: E402
from lidarops.sparse import functional as Fs  # noqa: E402

_BUILD, _PENDING = Fs._build_kernel_map, Fs._PendingSitesCheck


class _NoRead(_PENDING):
    """Copy and event made, never waited on (diagnostic: no check)."""

    def finish(self) -> None:
        pass


class _Nothing:
    """Neither copy nor event (diagnostic: the flagged map op alone, no check)."""

    def __init__(self, flags, x, shape):
        pass

    def finish(self) -> None:
        pass


def _at_once(*args, defer):
    return _BUILD(*args, defer=False)


@contextlib.contextmanager
def variant(name: str):
    """Patch the private pieces a variant changes, restore them after."""
    if name == "at once":
        Fs._build_kernel_map = _at_once
    elif name == "deferred, no read":
        Fs._PendingSitesCheck = _NoRead
    elif name == "flagged map only":
        Fs._PendingSitesCheck = _Nothing
    try:
        with validation(name != "no check"):
            yield
    finally:
        Fs._build_kernel_map, Fs._PendingSitesCheck = _BUILD, _PENDING


VARIANTS = ("deferred (library)", "at once", "deferred, no read", "flagged map only", "no check")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", default="kitti", choices=sorted(GRIDS))
    ap.add_argument("--precision", default="fp16", choices=("tf32", "fp16"))
    ap.add_argument("--calls", type=int, default=200)
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("needs a GPU")
        return 1
    shape, n = GRIDS[args.grid]
    idx = bev_sites(shape, n).cuda()
    with precision(args.precision) as dtype, torch.no_grad():
        feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
        layer = lspconv.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(dtype).eval()
        copies = [idx.clone() for _ in range(args.calls)]

        def call(f, i=0):
            return layer(lspconv.SparseConvTensor(f, copies[i % len(copies)], list(shape), 1))

        print(f"SubM 3x3 64 -> 64 with its map built, {args.grid} grid ({idx.shape[0]} sites), {args.precision}")
        print(f"{'variant':22s} {'CUDA events':>12s} {'host / call':>12s}")
        for name in VARIANTS:
            with variant(name):
                ev = time_call(lambda f: layer(lspconv.SparseConvTensor(f, idx.clone(), list(shape), 1)), (feats,),
                               "cuda").median
                hosts = []
                for _ in range(5):
                    copies = [idx.clone() for _ in range(args.calls)]  # new tensors: never checked before
                    torch.cuda.synchronize()
                    t0 = time.perf_counter()
                    for i in range(args.calls):
                        call(feats, i)
                    hosts.append((time.perf_counter() - t0) / args.calls * 1e3)
                    torch.cuda.synchronize()
                print(f"{name:22s} {ev:9.3f} ms {sorted(hosts)[2]:9.3f} ms")
        copies = [idx.clone() for _ in range(20)]
        for i in range(10):
            call(feats, i)
        torch.cuda.synchronize()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                                torch.profiler.ProfilerActivity.CUDA]) as prof:
            for i in range(10, 20):
                call(feats, i)
            torch.cuda.synchronize()
        print("one default call's host side (10 calls, torch.profiler, by self CPU time):")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=22))
    return 0


if __name__ == "__main__":
    sys.exit(main())
