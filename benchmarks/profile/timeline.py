"""The timeline of one eager sparse call on CUDA, started from an idle GPU as a new frame's call is: the host's ops
and CUDA runtime calls and the GPU's kernels and copies, in time order from the call's start, so that a wait (a host
read, a polled check) and the GPU's idle gaps show where they fall. Cases: the SubM 3x3 64 -> 64 module and the
16-layer down path of bm_sparse's Sparse-PointPillars, each on a new copy of the indices (KITTI grid, 15,000 sites),
with the library's site check and under ``validation(False)``. First the median wall time per call from an idle GPU
(host clock, a synchronisation before and after each call), then each case's timeline (torch.profiler; its own
overhead stretches the host's side).

    python benchmarks/profile/timeline.py [--precision fp16] [--case subm|down|all] [--rows 400]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, ROOT)

from benchmarks.bm_sparse import GRIDS, bev_sites, down_path, precision, sparse_pointpillars  # noqa: E402
from lidarops.compat import spconv as lspconv  # noqa: E402
from lidarops.ops.validation import validation  # noqa: E402

_RUNTIME = ("cuda", "cu")  # runtime and driver calls: cudaLaunchKernel, cuLaunchKernelEx, cudaStreamQuery, ...


def _idle_wall_ms(fn, runs: int = 50) -> float:
    for _ in range(5):
        fn()
    times = []
    for _ in range(runs):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _timeline(fn, rows: int) -> list[str]:
    """One call's events from the start of its marker: host ops at the top of the stack, runtime calls, and device
    activity, each as start offset, side, duration and name."""
    from torch.profiler import ProfilerActivity, profile, record_function
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        with record_function("## call"):
            fn()
        torch.cuda.synchronize()
    events = prof.events()
    start = next(e.time_range.start for e in events if e.name == "## call")
    out = []
    for e in sorted(events, key=lambda e: e.time_range.start):
        if e.name == "## call":
            continue
        on_gpu = e.device_type == torch.autograd.DeviceType.CUDA
        parent = e.cpu_parent
        top = parent is None or parent.name == "## call"
        if not on_gpu and not (top or e.name.startswith(_RUNTIME)):
            continue
        side = "gpu " if on_gpu else ("host" if top else "  rt")
        out.append(f"  {e.time_range.start - start:9.1f} us  {side}  {e.time_range.elapsed_us():7.1f} us  "
                   f"{e.name[:90]}")
    if len(out) > rows:
        out = out[:rows] + [f"  ... {len(out) - rows} more"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--precision", default="fp16", choices=["fp32", "tf32", "fp16"])
    ap.add_argument("--case", default="all", choices=["subm", "down", "all"])
    ap.add_argument("--rows", type=int, default=400)
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("profile/timeline: needs a GPU")
        return 0
    shape, n = GRIDS["kitti"]
    idx = bev_sites(shape, n).cuda()
    with precision(a.precision) as dtype, torch.no_grad():
        feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
        nets = {}
        if a.case in ("subm", "all"):
            nets["SubM 3x3 64 -> 64"] = lspconv.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(
                dtype).eval()
        if a.case in ("down", "all"):
            nets["down path, 16 layers"] = down_path(sparse_pointpillars(lspconv).cuda().to(dtype).eval())
        cases = {}
        for name, net in nets.items():
            for checks in (True, False):
                def call(net=net, checks=checks):
                    with validation(checks):
                        return net(lspconv.SparseConvTensor(feats, idx.clone(), list(shape), 1))
                cases[f"{name}, {'site check' if checks else 'validation(False)'}"] = call
        print(f"{torch.cuda.get_device_name()}, KITTI grid, {idx.shape[0]} sites, {a.precision}: median wall time per "
              "call from an idle GPU")
        for name, fn in cases.items():
            print(f"  {name:45s} {_idle_wall_ms(fn):.4f} ms")
        for name, fn in cases.items():
            print(f"\n== {name}: start offset, side (host op, runtime call, gpu), duration, name")
            print("\n".join(_timeline(fn, a.rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
