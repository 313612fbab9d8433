"""Where a stream push's time goes on the host: PillarStream.push alone, as a trained detector's stream runs it.

    python benchmarks/profile/stream_push.py [--device cuda] [--checkpoint aerial_pointpillars] [--steps 200]

Feeds the scene of the checkpoint's first training frames (its realism profile) in 10 ms slices to the stream of
``SSCATeRPointPillars.from_detector`` (the detector's slots, capacity and overflow rule), with the slices already
on the device, to two streams in turn, one pushing as a CUDA graph (``cuda_graph=True``, the default) and one
eagerly, and prints each push's wall time per step (it ends in a read of its figures, so its wall time is what a
step waits for), then ``torch.profiler``'s top host ops over ``--profile-steps`` pushes of each and the device's
kernel time in them.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from benchmarks.bm_sscater import _checkpoint_path, _first_scenario, stream_realism  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoint", default="aerial_pointpillars")
    ap.add_argument("--scenario", default=None)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--profile-steps", type=int, default=50)
    a = ap.parse_args()
    from lidarops.data.synthetic import Simulator
    from lidarops.models import load_model
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    dev = torch.device(a.device)
    scenario = a.scenario or _first_scenario(a.checkpoint)
    det = load_model(_checkpoint_path(a.checkpoint), map_location=dev).eval()
    from lidarops.stream import PillarStream
    s0 = SSCATeRPointPillars.from_detector(det, device=dev).stream
    streams = {name: PillarStream(s0.grid, s0.window, s0.max_points_per_pillar, s0.max_pillars, device=dev,
                                  overflow=s0.overflow, cuda_graph=graph)
               for name, graph in (("graph", True), ("eager", False))}
    sim = Simulator(scenario, seed=0, realism=stream_realism(a.checkpoint, scenario, None))
    n = 10 + a.steps + a.profile_steps
    feed = []
    for k in range(n):
        p, t = sim.stream(k * 0.01, (k + 1) * 0.01)
        feed.append((torch.from_numpy(p).to(dev), torch.from_numpy(t).to(dev)))
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    ms = {name: [] for name in streams}
    for k in range(10 + a.steps):
        for name, stream in streams.items():
            sync()
            t0 = time.perf_counter()
            stream.push(*feed[k], now=(k + 1) * 0.01)
            sync()
            if k >= 10:
                ms[name].append(1e3 * (time.perf_counter() - t0))
    for name, v in ms.items():
        v.sort()
        print(f"{scenario}: push ({name}), {a.steps} steps, ms: mean {statistics.fmean(v):.3f} median "
              f"{statistics.median(v):.3f} p95 {v[int(0.95 * (len(v) - 1))]:.3f} max {v[-1]:.3f}; active pillars "
              f"{streams[name].num_active}")
    for name, stream in streams.items():
        _profile(stream, name, feed, 10 + a.steps, n, dev, a.profile_steps, sync)


def _profile(stream, name, feed, first, n, dev, s, sync) -> None:
    acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with torch.profiler.profile(activities=acts) as prof:
        for k in range(first, n):
            stream.push(*feed[k], now=(k + 1) * 0.01)
        sync()
    ka = prof.key_averages()
    print(f"==== {name}")
    print("== top host ops by self CPU time (us per push)")
    for e in sorted(ka, key=lambda e: e.self_cpu_time_total, reverse=True)[:30]:
        print(f"{e.key[:64]:64s} calls/push {e.count / s:6.1f}  self {e.self_cpu_time_total / s:8.1f}  "
              f"total {e.cpu_time_total / s:8.1f}")
    if dev.type == "cuda":
        print("== device time by kernel (us per push)")
        rows = [e for e in ka if getattr(e, "self_device_time_total", 0) > 0]
        for e in sorted(rows, key=lambda e: e.self_device_time_total, reverse=True)[:15]:
            print(f"{e.key[:64]:64s} calls/push {e.count / s:6.1f}  device {e.self_device_time_total / s:8.1f}")
        print(f"device total per push: {sum(e.self_device_time_total for e in rows) / s:.1f} us")


if __name__ == "__main__":
    main()
