"""``lidarops tour``: a short tour of the neighbourhood ops on a synthetic LiDAR sweep.

Runs FPS, kNN, ball query and gather the way a PointNet++ set-abstraction layer chains them
(sample centres, find their neighbours, group features), checks each result against the
pure-PyTorch reference on a subsample, and prints a table of sizes, times and checks (``make tour``).
Exit code 0 when every check passes, 1 when one fails, 2 on an error (:mod:`lidarops.cli.errors`).

The cloud comes from ``lidarops.data.synthetic.Simulator("driving_city")``
(:func:`lidarops.data.clouds.simulated_sweep`); the references are :mod:`lidarops.ops.references`.

Examples::

    lidarops tour
    lidarops tour --device cuda --n 200000 --seed 3
"""
from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable

import torch
from torch import Tensor

from lidarops.cli.errors import guarded

__all__ = ["register", "run"]

# ---- the tour ----

def _timeit(fn: Callable[[], object], device: torch.device, runs: int = 5) -> float:
    """Median wall time in ms over ``runs`` calls after one warm-up call."""
    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    fn()
    sync()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _compare(name: str, got_idx: Tensor, ref_idx: Tensor, got_d: Tensor | None = None,
             ref_d: Tensor | None = None) -> tuple[bool, str]:
    got_idx, ref_idx = got_idx.cpu(), ref_idx.cpu()
    if got_idx.shape != ref_idx.shape:
        return False, f"{name}: shape {tuple(got_idx.shape)} != reference {tuple(ref_idx.shape)}"
    bad = (got_idx != ref_idx).nonzero()
    if len(bad):
        where = tuple(bad[0].tolist())
        return False, (f"{name}: {len(bad)} indices differ, first at {where}: "
                       f"{int(got_idx[where])} vs reference {int(ref_idx[where])}")
    if got_d is not None:
        got_d, ref_d = got_d.cpu().double(), ref_d.cpu().double()
        finite = torch.isfinite(ref_d)
        if not torch.equal(finite, torch.isfinite(got_d)):
            return False, f"{name}: padding (+inf) differs from the reference"
        diff = (got_d[finite] - ref_d[finite]).abs()
        if diff.numel() and diff.max() > 0:
            return False, f"{name}: dist2 differs from the reference by up to {float(diff.max()):.3g}"
    return True, "OK"


def run(device: str | torch.device | None = "cpu", n: int = 20000, seed: int = 0, check_queries: int = 256) -> int:
    """Run the tour and print its table; returns 0 when every check passes, 1 otherwise.

    Args:
        device: cpu or cuda; None: cuda when torch sees a GPU and lidarops has its CUDA kernels, else cpu.

    Raises:
        ValueError: ``n`` below 64, or a device this machine or build cannot run on (before anything runs).
    """
    import lidarops
    from lidarops.cli._device import resolve_device
    from lidarops.data.clouds import simulated_sweep
    from lidarops.ops import references as ref

    if isinstance(n, bool) or not isinstance(n, int) or n < 64:
        raise ValueError(f"--n must be an integer >= 64, got {n}")
    device = resolve_device(None if device is None else str(device))

    t0 = time.perf_counter()
    cloud, source = simulated_sweep(n, seed)
    points = cloud.unsqueeze(0).to(device)  # (1, n, 3)
    K = min(1024, max(16, n // 16))  # FPS centres
    k_knn, k_ball, radius, C = 16, 32, 1.0, 32
    feats = torch.randn(1, n, C, generator=torch.Generator().manual_seed(seed)).to(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu ({torch.get_num_threads()} threads)"
    print(f"lidarops {lidarops.__version__} tour: torch {torch.__version__}, device {name}")
    print(f"cloud: {n} points from {source}, extent "
          f"{[round(float(v), 1) for v in (cloud.amax(0) - cloud.amin(0))]} m\n")

    centres_idx = lidarops.fps(points, K)  # (1, K)
    centres = lidarops.gather(points, centres_idx)  # (1, K, 3)
    knn_d, knn_i = lidarops.knn(centres, points, k_knn)
    ball_d, ball_i = lidarops.ball_query(centres, points, radius, k_ball)
    grouped = lidarops.gather(feats, ball_i)  # (1, K, k_ball, C)

    g = torch.Generator().manual_seed(seed + 1)
    sub = torch.randperm(K, generator=g)[:min(check_queries, K)].sort().values
    sub_dev = sub.to(device)
    checks = {"fps": _compare("fps", centres_idx, ref.fps(points, K))}
    ref_kd, ref_ki = ref.knn(centres[:, sub_dev], points, k_knn)
    checks["knn"] = _compare("knn", knn_i[:, sub_dev], ref_ki, knn_d[:, sub_dev], ref_kd)
    ref_bd, ref_bi = ref.ball_query(centres[:, sub_dev], points, radius, k_ball)
    checks["ball_query"] = _compare("ball_query", ball_i[:, sub_dev], ref_bi, ball_d[:, sub_dev], ref_bd)
    ref_g = ref.gather(feats.cpu(), ball_i.cpu())
    checks["gather"] = (torch.equal(grouped.cpu(), ref_g),
                        "OK" if torch.equal(grouped.cpu(), ref_g) else "gather: differs from the reference")

    times = {
        "fps": _timeit(lambda: lidarops.fps(points, K), device),
        "knn": _timeit(lambda: lidarops.knn(centres, points, k_knn), device),
        "ball_query": _timeit(lambda: lidarops.ball_query(centres, points, radius, k_ball), device),
        "gather": _timeit(lambda: lidarops.gather(feats, ball_i), device),
    }
    fill = float((ball_i >= 0).sum(-1).double().mean())
    rows = [
        ("fps", f"points (1, {n}, 3), k={K}", f"idx {tuple(centres_idx.shape)}", "fps"),
        ("knn", f"centres (1, {K}, 3) -> points, k={k_knn}", f"dist2, idx {tuple(knn_i.shape)}", "knn"),
        ("ball_query", f"r={radius} m, k={k_ball} (mean {fill:.1f} hits)", f"dist2, idx {tuple(ball_i.shape)}",
         "ball_query"),
        ("gather", f"features (1, {n}, {C}) by ball idx", f"{tuple(grouped.shape)}", "gather"),
    ]
    what = {"fps": "all", "knn": f"{len(sub)} queries", "ball_query": f"{len(sub)} queries", "gather": "all"}
    header = ("op", "input", "output", "time (ms)", "check vs reference")
    table = [(op, inp, out, f"{times[key]:.2f}",
              f"{'OK' if checks[key][0] else 'FAIL'} ({what[key]})") for op, inp, out, key in rows]
    widths = [max(len(str(r[i])) for r in [header, *table]) for i in range(len(header))]
    fmt = "  ".join(f"{{:>{w}}}" if i == 3 else f"{{:<{w}}}" for i, w in enumerate(widths))
    print(fmt.format(*header).rstrip())
    print("  ".join("-" * w for w in widths))
    for r in table:
        print(fmt.format(*r).rstrip())
    failures = [msg for ok, msg in checks.values() if not ok]
    for msg in failures:
        print(f"FAIL {msg}")
    print(f"\ntimes: median of 5 calls of the validated wrappers after a warm-up; "
          f"checks: float64 pure-PyTorch references (lidarops.ops.references); total {time.perf_counter() - t0:.1f} s")
    return 1 if failures else 0


def _main(args: argparse.Namespace) -> int:
    return run(device=args.device, n=args.n, seed=args.seed)


def register(subparsers) -> None:
    """Add the ``tour`` subcommand to the ``lidarops`` command line."""
    p = subparsers.add_parser("tour", help="a short tour of the ops on a synthetic LiDAR sweep",
                              description="A short tour of the neighbourhood ops (FPS, kNN, ball query, gather) on a "
                                          "simulated LiDAR sweep, each result checked against its pure-PyTorch "
                                          "reference; exit code 1 when a check fails.")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="default: cuda when available and built, else cpu")
    p.add_argument("--n", type=int, default=20000, help="points in the sweep (default 20000)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the sweep and features")
    p.set_defaults(func=guarded("tour", _main))
