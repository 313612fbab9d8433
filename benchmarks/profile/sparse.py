"""Where the Sparse-PointPillars backbone of benchmarks/bm_sparse.py spends its GPU time (maps cached).

    python benchmarks/profile/sparse.py [--precision fp32|tf32|fp16] [--calls 10] [--host]

Prints the top kernels by device time per forward (torch.profiler), on the KITTI grid with 15,000
pillars, every kernel map cached, as the benchmark's "maps cached" column runs it. ``--host`` also
prints where the host time of an eager forward goes: its wall time, the ops and CUDA runtime calls
by self CPU time, and the Python functions by own time (cProfile).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--precision", default="fp32", choices=["fp32", "tf32", "fp16"])
    ap.add_argument("--calls", type=int, default=10)
    ap.add_argument("--host", action="store_true")
    a = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("profile/sparse: needs a GPU")
        return 0
    from benchmarks.bm_sparse import pillars_input, precision
    dev = torch.device("cuda")
    with precision(a.precision) as dtype, torch.no_grad():
        net, _, x = pillars_input(dev, dtype)
        for _ in range(3):
            net(x)
        torch.cuda.synchronize()
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                                torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(a.calls):
                net(x)
            torch.cuda.synchronize()
    ka = prof.key_averages()
    # device time of the kernels and copies themselves (the ops that launch them report it again)
    total = sum(e.time_range.elapsed_us() for e in prof.events()
                if e.device_type == torch.autograd.DeviceType.CUDA) / 1e3 / a.calls
    print(f"== {a.precision}: {total:.3f} ms of device time per forward; top kernels (ms per forward)")
    for e in sorted(ka, key=lambda e: e.self_device_time_total, reverse=True)[:15]:
        if e.self_device_time_total:
            print(f"{e.key[:70]:70s} calls {e.count / a.calls:5.1f}  {e.self_device_time_total / 1e3 / a.calls:7.3f}")
    if a.host:
        host_profile(a.precision, a.calls)
    return 0


def host_profile(prec: str, calls: int) -> None:
    import cProfile
    import pstats
    import time
    from benchmarks.bm_sparse import pillars_input, precision
    dev = torch.device("cuda")
    with precision(prec) as dtype, torch.no_grad():
        net, _, x = pillars_input(dev, dtype)
        for _ in range(5):
            net(x)
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(calls):
            net(x)
        t_host = (time.perf_counter() - t0) / calls
        torch.cuda.synchronize()
        t_all = (time.perf_counter() - t0) / calls
        print(f"== {prec} eager forward: {t_host * 1e3:.3f} ms of host time per call "
              f"({t_all * 1e3:.3f} ms with the GPU drained)")
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            for _ in range(calls):
                net(x)
            torch.cuda.synchronize()
        print("ops and runtime calls by self CPU time (ms per forward, calls per forward)")
        for e in sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)[:20]:
            print(f"  {e.key[:60]:60s} {e.count / calls:6.1f} {e.self_cpu_time_total / 1e3 / calls:8.3f}")
        pr = cProfile.Profile()
        pr.enable()
        for _ in range(calls):
            net(x)
        pr.disable()
        torch.cuda.synchronize()
    pstats.Stats(pr).sort_stats("tottime").print_stats(15)


if __name__ == "__main__":
    sys.exit(main())
