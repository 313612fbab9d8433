"""Speed of the LiDAR simulator (lidarops.data.synthetic): rays per second and time per sweep.

Usage::

    python benchmarks/bm_data.py               # all scenarios, 5 sweeps each
    python benchmarks/bm_data.py --json        # and merge the rows into benchmarks/results/<cpu>.json
    python benchmarks/bm_data.py --repeat 10 --scenarios driving_city
    LIDAROPS_DATA_NATIVE=0 python benchmarks/bm_data.py   # the NumPy ray caster
    python -m benchmarks.bm_data

For every scenario it reports the first sweep of a fresh simulator (scene generation included) and
the median of later sweeps (cache cleared, so every ray is cast again), in wall-clock and CPU
seconds, and the ray-casting throughput (rays cast / CPU second).  Wall time includes whatever else
the machine is doing; CPU time is the better number on a shared machine (CPU time adds up all threads;
run with ``OMP_WAIT_POLICY=PASSIVE`` so that idle OpenMP threads do not spin).  The header names the ray
caster used (native kernel or NumPy, see lidarops.data._raycast); the native one is loaded before any
timing, so the first sweep does not include importing torch. ``--json`` writes section ``"data"`` of
the CPU's results file; rows are replaced per ray caster, so a NumPy-caster run
(``LIDAROPS_DATA_NATIVE=0``) and a native one sit side by side.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

if __package__ in (None, ""):  # run as a script: import lidarops from this checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from lidarops.data._raycast import raycast_backend  # noqa: E402
from lidarops.data.synthetic import SCENARIOS, Simulator  # noqa: E402


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def bench(scenario: str, repeat: int, seed: int = 0) -> dict:
    (sim, frame0), wall0, cpu0 = _timed(lambda: (lambda s: (s, s.sweep(0)))(Simulator(scenario, seed=seed)))
    walls, cpus, rays, points = [], [], [], []
    for i in range(1, repeat + 1):
        sim._cache.clear()  # cast every ray again
        frame, wall, cpu = _timed(lambda: sim.sweep(i))
        walls.append(wall)
        cpus.append(cpu)
        rays.append(frame.meta["rays"])
        points.append(frame.num_points)
    cpu_med = statistics.median(cpus)
    return {
        "scenario": scenario,
        "sensor": sim.sensor.name,
        "rays": int(statistics.median(rays)),
        "points": int(statistics.median(points)),
        "first_wall": wall0,
        "first_cpu": cpu0,
        "wall": statistics.median(walls),
        "cpu": cpu_med,
        "rays_per_s": statistics.median(rays) / cpu_med,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="sweeps per scenario after the first (default 5)")
    parser.add_argument("--scenarios", nargs="*", default=sorted(SCENARIOS))
    parser.add_argument("--json", action="store_true", help="merge the rows into benchmarks/results/<cpu>.json")
    args = parser.parse_args()
    backend = raycast_backend()  # loads the native kernel (and torch) before anything is timed
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load average {load:.1f}, "
          f"ray caster: {backend}")
    header = f"{'scenario':16s} {'sensor':8s} {'rays':>7s} {'points':>7s} {'1st sweep (wall/cpu)':>21s} " \
             f"{'sweep (wall/cpu)':>17s} {'rays/s (cpu)':>13s}"
    print(header)
    print("-" * len(header))
    rows = []
    for scenario in args.scenarios:
        r = bench(scenario, args.repeat)
        print(f"{r['scenario']:16s} {r['sensor']:8s} {r['rays']:7d} {r['points']:7d} "
              f"{r['first_wall']:9.3f}/{r['first_cpu']:.3f} s {r['wall']:8.3f}/{r['cpu']:.3f} s {r['rays_per_s']:13,.0f}")
        rows.append({"op": "simulator_sweep", "caster": backend, "sweeps": args.repeat, **r})
    sim = Simulator("drone_bridge", seed=0)
    _, wall, cpu = _timed(lambda: list(sim.slices(0.0, 1.0, 0.01)))
    print(f"\ndrone_bridge stream: 100 slices of 10 ms in {wall:.3f} s wall / {cpu:.3f} s cpu "
          f"({1.0 / cpu:.1f}x real time)")
    rows.append({"op": "simulator_stream", "caster": backend, "scenario": "drone_bridge", "slices": 100,
                 "wall": wall, "cpu": cpu, "real_time_factor": 1.0 / cpu})
    if args.json:
        from benchmarks.common import env_meta, write_results
        print(f"wrote {write_results('data', 'cpu', rows, env_meta('cpu'), replace_by='caster')}")


if __name__ == "__main__":
    main()
