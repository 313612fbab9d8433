"""Where the time of an eager call goes: host time, GPU time, launches and host synchronisations.

    python benchmarks/profile_eager.py --device cuda [--frame 000134.bin --calib 000134.txt] [--json]

For each call a user writes (below), two measurements:

* **wall**: the call's median wall time with the GPU drained after it (``time.perf_counter``, as
  ``bm_*.py``'s CUDA events measure it, without the profiler's overhead);
* **profile** (``torch.profiler``, CPU and CUDA activities, 20 calls after warm-up), per call: the GPU's
  busy time (kernels, copies and memsets, summed), the kernels launched, the host reads (device-to-host
  copies, which wait for the GPU) and stream or device synchronisations, and the share of the profiled call's
  host time spent inside PyTorch ops (self CPU time of every op, the CUDA runtime's calls included); the rest
  is Python (modules, argument checks, the library's own code between ops). The profiler slows the host,
  so that share is of the profiled call, not of the wall time.

``GPU busy / wall`` is the share of the call the GPU works; far below 1, the call is bound by the host
(launches, Python, waits on host reads), and a faster kernel would not make it faster.

Calls: ``PointPillars.predict`` eagerly (``eager_predict()``, TF32 and fp16 autocast) and replayed (its CUDA
graph), on a real-scan-sized frame; one SubM 3x3 64 -> 64 layer module of ``lidarops.compat.spconv`` on a new
``SparseConvTensor`` on a new copy of the indices (a new frame: its map built and its sites checked in the call) and on one whose ``indice_dict`` holds the map; the 16-layer
down path of Sparse-PointPillars (maps built); the whole Sparse-PointPillars backbone of the shipped detector
(``BaseBEVBackbone(mode="sparse")``, maps built). With spconv importable, its SubM layer and down path too.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.common import env_meta, fmt_ms, print_table, time_cpu  # noqa: E402

# CUDA runtime / driver calls that wait for the GPU, or copy to the host (and so wait)
SYNC_CALLS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cuStreamSynchronize",
              "cuCtxSynchronize")
LAUNCH_CALLS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                "cudaLaunchCooperativeKernel")


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def _wall_ms(fn, runs: int = 50) -> float:
    """Median wall time of ``fn()`` with the GPU drained after it (a cold call first, untimed)."""
    return time_cpu(lambda: (fn(), _sync()), (), min_runs=runs, max_runs=runs, budget_s=float("inf")).median


def _device_time(e) -> float:
    for name in ("self_device_time_total", "self_cuda_time_total"):
        if hasattr(e, name):
            return float(getattr(e, name))
    return 0.0


def kernel_totals(events, calls: int) -> list[tuple[str, float, float]]:
    """The GPU activities of a profile (kernels, copies, memsets) by name: ``(name, us per call, launches per
    call)``, the longest first."""
    acc: dict[str, list] = {}
    for e in events:
        # a record_function range also appears on the GPU's timeline, as an annotation spanning its kernels
        if str(getattr(e, "device_type", "")).endswith("CUDA") and not getattr(e, "is_user_annotation", False):
            a = acc.setdefault(e.name, [0.0, 0])
            a[0] += e.time_range.elapsed_us()
            a[1] += 1
    return sorted(((n, us / calls, k / calls) for n, (us, k) in acc.items()), key=lambda t: -t[1])


def profile_call(fn, calls: int = 20, top: int = 8) -> dict:
    """One call's profile, per call (module docstring): microseconds and counts."""
    from torch.profiler import ProfilerActivity, profile

    for _ in range(3):
        fn()
    _sync()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
    with profile(activities=activities) as prof:
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        _sync()
        profiled_us = (time.perf_counter() - t) * 1e6 / calls
    gpu_us, host_op_us, launches, syncs, d2h = 0.0, 0.0, 0, 0, 0
    host_ops = []
    for e in prof.events():
        dev = str(getattr(e, "device_type", "")).endswith("CUDA")
        if dev and getattr(e, "is_user_annotation", False):  # a range's span on the GPU's timeline, not work
            continue
        if dev:
            gpu_us += e.time_range.elapsed_us()
            if "DtoH" in e.name or "Device -> Pageable" in e.name or "Device -> Pinned" in e.name:
                d2h += 1
            continue
        if e.name in LAUNCH_CALLS:
            launches += 1
        elif e.name in SYNC_CALLS:
            syncs += 1
    for e in prof.key_averages():
        if str(getattr(e, "device_type", "")).endswith("CPU"):
            host_op_us += e.self_cpu_time_total
            host_ops.append((e.key, e.self_cpu_time_total / calls, e.count / calls))
    top_kernels = kernel_totals(prof.events(), calls)[:top]
    host_ops.sort(key=lambda t: -t[1])
    # the profiler slows the host's side: host shares are of the profiled call, not of the wall time
    return {"gpu_busy_us": gpu_us / calls, "host_in_ops_us": host_op_us / calls,
            "host_in_ops_share": min(host_op_us / calls / profiled_us, 1.0), "profiled_call_us": profiled_us,
            "launches": launches / calls,
            "syncs": syncs / calls, "d2h_copies": d2h / calls,
            "top_kernels": [{"name": n[:90], "us": round(us, 2), "per_call": k} for n, us, k in top_kernels],
            "top_host_ops": [{"name": n[:90], "self_us": round(us, 2), "per_call": round(c, 2)}
                             for n, us, c in host_ops[:top]]}


def detector_calls(frame_path: str | None, calib: str | None):
    from benchmarks.bm_detector import kitti_like_frame, load_model
    from lidarops.models.cuda_graph import precision_mode
    from lidarops.models.pointpillars import eager_predict

    frame = kitti_like_frame(path=frame_path, calib=calib).cuda()
    model = load_model("cuda", "dense")
    batch = {"points": torch.cat([frame.new_zeros(frame.shape[0], 1), frame], 1), "batch_size": 1}
    out = []
    for prec in ("tf32", "fp16"):
        def eager(prec=prec):
            with eager_predict(), torch.no_grad(), precision_mode(prec, "cuda", autocast=True):
                return model.predict(batch)

        def replayed(prec=prec):
            with torch.no_grad(), precision_mode(prec, "cuda", autocast=True):
                return model.predict(batch)

        out += [(f"predict, eager (no graph), {prec}", eager), (f"predict, replayed graph, {prec}", replayed)]
    return out, int(frame.shape[0])


def sparse_calls(dtype=torch.float16):
    import lidarops.compat.spconv as lspconv
    from benchmarks.bm_sparse import GRIDS, _spconv, bev_sites, down_path, sparse_pointpillars
    from lidarops.models.bev_backbone import BaseBEVBackbone
    from lidarops.sparse import SparseConvTensor

    shape, n = GRIDS["kitti"]
    idx = bev_sites(shape, n).cuda()
    feats = torch.randn(idx.shape[0], 64, device="cuda", dtype=dtype)
    out = []
    peers = [("lidarops", lspconv)] + ([("spconv", _spconv())] if _spconv() is not None else [])
    for name, ns in peers:
        layer = ns.SubMConv2d(64, 64, 3, padding=1, bias=False, indice_key="k").cuda().to(dtype).eval()
        down = down_path(sparse_pointpillars(ns).cuda().to(dtype).eval())
        with torch.no_grad():
            first = layer(ns.SparseConvTensor(feats, idx, list(shape), 1))
        cached = ns.SparseConvTensor(feats, idx, list(shape), 1, indice_dict=first.indice_dict)

        def fresh(layer=layer, ns=ns):  # a new frame: a new copy of the indices, its sites never seen
            with torch.no_grad():
                return layer(ns.SparseConvTensor(feats, idx.clone(), list(shape), 1))

        def reuse(layer=layer, cached=cached):
            with torch.no_grad():
                return layer(cached.replace_feature(feats))

        def path(down=down, ns=ns):
            with torch.no_grad():
                return down(ns.SparseConvTensor(feats, idx.clone(), list(shape), 1))

        out += [(f"{name}: SubM 3x3 64->64, map built", fresh), (f"{name}: SubM 3x3 64->64, map reused", reuse),
                (f"{name}: down path, 16 layers, maps built", path)]
    bb = BaseBEVBackbone(64, mode="sparse").cuda().to(dtype).eval()

    def backbone():
        with torch.no_grad():
            return bb(SparseConvTensor(feats, idx.clone(), list(shape), 1))

    out.append(("lidarops: Sparse-PointPillars backbone (down + up), maps built", backbone))
    return out, int(idx.shape[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cuda",), default="cuda")
    ap.add_argument("--frame", default=None, help="a KITTI velodyne .bin scan (default: the simulated frame)")
    ap.add_argument("--calib", default=None)
    ap.add_argument("--only", default="detector,sparse")
    ap.add_argument("--json", default=None, metavar="FILE", help="write the rows here")
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("profile_eager.py profiles CUDA calls; no CUDA device here")
        return 1
    calls = []
    if "detector" in args.only:
        det, points = detector_calls(args.frame, args.calib)
        calls += [(n, f, f"{points} points") for n, f in det]
    if "sparse" in args.only:
        sp, sites = sparse_calls()
        calls += [(n, f, f"KITTI grid, {sites} sites, fp16") for n, f in sp]
    rows = []
    for name, fn, what in calls:
        wall = _wall_ms(fn)
        p = profile_call(fn)
        rows.append({"call": name, "input": what, "wall_ms": round(wall, 4), **p,
                     "gpu_share": round(p["gpu_busy_us"] / (wall * 1e3), 3)})
    print_table(f"eager calls on {env_meta('cuda')['device']}: per call",
                ["call", "wall ms", "GPU busy ms", "GPU/wall", "launches", "host reads", "syncs",
                 "host in ops (profiled)"],
                [[r["call"], fmt_ms(r["wall_ms"]), fmt_ms(r["gpu_busy_us"] / 1e3), f"{r['gpu_share']:.2f}",
                  f"{r['launches']:.0f}", f"{r['d2h_copies']:.0f}", f"{r['syncs']:.0f}",
                  f"{100 * r['host_in_ops_share']:.0f} %"] for r in rows],
                right=tuple(range(1, 8)))
    for r in rows:
        print(f"\n{r['call']}: top kernels (us per call): " + "; ".join(
            f"{k['name'][:60]} {k['us']:.1f} (x{k['per_call']:.0f})" for k in r["top_kernels"][:5]))
        print("  top host ops (self us per call): " + "; ".join(
            f"{k['name'][:50]} {k['self_us']:.1f} (x{k['per_call']:.0f})" for k in r["top_host_ops"][:6]))
    if args.json:
        Path(args.json).write_text(json.dumps({"meta": env_meta("cuda"), "rows": rows}, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
