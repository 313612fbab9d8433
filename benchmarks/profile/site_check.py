"""What a new frame's site check costs an eager SubM call on CUDA, piece by piece. Each call starts from a new copy
of the indices (a new frame, KITTI grid, 15,000 sites): the copy alone; the copy and the kernel map without a
check, with the check read at once (one blocking host read), and with the check read later (a word the map's
last kernel writes into pinned host memory, read by ticket as a layer reads it); then the SubM 3x3 64 -> 64 module with its map built: the library's path
(check read after the convolution is queued), the check read at once, and no check (``validation(False)``).
Medians per call (CUDA events, calls back to back), then the CUDA runtime calls of each path (torch.profiler).

    python benchmarks/profile/site_check.py
"""
from __future__ import annotations

import contextlib
import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_sparse import GRIDS, _spconv, bev_sites, precision  # noqa: E402
from benchmarks.common import _CudaClock, time_cuda_interleaved, time_interleaved  # noqa: E402
from lidarops.compat import spconv as lspconv  # noqa: E402
from lidarops.ops.validation import validation  # noqa: E402
from lidarops.sparse import functional as Fs  # noqa: E402


@contextlib.contextmanager
def check_read_at_once():
    """The layers' maps built with the check read before the map's last launch (no deferred read)."""
    original = Fs._kernel_map_for

    def at_once(*args, defer=False, **kw):
        return original(*args, **kw)
    Fs._kernel_map_for = at_once
    try:
        yield
    finally:
        Fs._kernel_map_for = original


def _device_flags() -> str:
    """cudaGetDeviceFlags of the current device (the scheduling policy of host waits), through the CUDA runtime
    torch loaded."""
    import ctypes
    import glob
    lib = None
    for path in ["libcudart.so"] + sorted(glob.glob(os.path.join(os.path.dirname(torch.__file__), "..", "nvidia", "*",
                                                                   "lib", "libcudart.so*"))):
        try:
            lib = ctypes.CDLL(path)
            break
        except OSError:
            continue
    if lib is None:
        return "(libcudart not found)"
    flags = ctypes.c_uint(0)
    err = lib.cudaGetDeviceFlags(ctypes.byref(flags))
    names = {0: "auto", 1: "spin", 2: "yield", 4: "blocking sync"}
    return f"{flags.value:#x} (schedule {names.get(flags.value & 7, flags.value & 7)}, error {err})"


class _IdleClock(_CudaClock):
    """CUDA events recorded on an idle GPU: a synchronisation before each start event, so that no call waits for the
    work the call before it left queued."""

    def __init__(self):
        super().__init__(torch.device("cuda"))
        self.n = 0

    def event(self):
        ev = super().event()
        self.n += 1
        if self.n % 2 == 0:  # (start, end) pairs: only the start waits
            return ev
        record = ev.record

        def synced_record(*a, **kw):
            torch.cuda.synchronize()
            return record(*a, **kw)
        ev.record = synced_record
        return ev


def main() -> int:
    ops = torch.ops.lidarops
    shape, n = GRIDS["kitti"]
    idx = bev_sites(shape, n).cuda()
    geo = (1, list(shape), [3, 3], [1, 1], [1, 1], [1, 1], False)

    def copy(i):
        return i.clone()

    def map_unchecked(i):
        return ops.sparse_kernel_map(i.clone(), i, *geo, False, 0)

    def map_checked(i):
        return ops.sparse_kernel_map(i.clone(), i, *geo, True, 0)

    def map_deferred(i):
        j = i.clone()
        nbr, ticket = ops.sparse_kernel_map_deferred(j, i, *geo, 0)
        Fs._settle((j, ticket, 1, shape))
        return nbr

    with precision("fp16") as dtype, torch.no_grad():
        feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
        layer = lspconv.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(dtype).eval()

        def subm(f, i, mode):
            x = lspconv.SparseConvTensor(f, i.clone(), list(shape), 1)
            if mode == "off":
                with validation(False):
                    return layer(x)
            if mode == "at once":
                with check_read_at_once():
                    return layer(x)
            return layer(x)

        calls = {"copy": (copy, (idx,)), "map, no check": (map_unchecked, (idx,)),
                 "map, check read at once": (map_checked, (idx,)), "map, check read later": (map_deferred, (idx,)),
                 "SubM, library (check read after the conv)": (subm, (feats, idx, "library")),
                 "SubM, check read at once": (subm, (feats, idx, "at once")),
                 "SubM, no check": (subm, (feats, idx, "off"))}
        times = time_interleaved(list(calls.values()), torch.device("cuda"), budget_s=1.0, max_runs=400)
        print(f"{torch.cuda.get_device_name()}, KITTI grid, {idx.shape[0]} sites, fp16; ms per call (median)")
        for name, t in zip(calls, times):
            print(f"  {name:45s} {t.median:.4f}" if hasattr(t, "median") else f"  {name:45s} {t!r}")
        sp = _spconv()
        print(f"  CUDA device flags: {_device_flags()}")
        # interleaved with spconv's call, as bm_sparse times them: back to back, and each from an idle GPU
        if sp is not None:
            peer = sp.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(dtype).eval()

            def spconv_subm(f, i):
                return peer(sp.SparseConvTensor(f, i.clone(), list(shape), 1))
            trio = [calls["SubM, library (check read after the conv)"], calls["SubM, no check"],
                    (spconv_subm, (feats, idx))]
            for how, clock in (("back to back", None), ("each from an idle GPU", _IdleClock())):
                t = time_cuda_interleaved(trio, clock=clock, budget_s=1.0, max_runs=400)
                print(f"  interleaved with spconv, {how}: library / no check / spconv = "
                      + " / ".join(f"{x.median:.4f}" for x in t)
                      + f" ms; spconv / library {t[2].median / t[0].median:.2f}x")
                print(f"  CUDA device flags: {_device_flags()}")
        from torch.profiler import ProfilerActivity, profile
        for name, (fn, args) in calls.items():
            for _ in range(5):
                fn(*args)
            torch.cuda.synchronize()
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                for _ in range(20):
                    fn(*args)
                torch.cuda.synchronize()
            rows = sorted(((e.key, e.self_cpu_time_total / 20, e.count / 20) for e in prof.key_averages()
                           if e.self_cpu_time_total > 0), key=lambda r: -r[1])[:9]
            print(f"{name}: " + "; ".join(f"{k[:40]} {us:.1f} us x{c:g}" for k, us, c in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
