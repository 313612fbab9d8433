"""``lidarops tour``: a short tour of the neighbourhood ops on a synthetic LiDAR sweep.

Runs FPS, kNN, ball query and gather the way a PointNet++ set-abstraction layer chains them
(sample centres, find their neighbours, group features), checks each result against the
pure-PyTorch reference on a subsample, and prints a table of sizes, times and checks. It is the
``make demo`` job until the larger demos exist.

The cloud comes from ``lidarops.data.synthetic.Simulator("driving_city")`` when that module is
present, else from :func:`lidar_like_cloud`, a small built-in generator (also used by the
benchmarks) of what a rotating LiDAR sees: ground rings whose density falls with range, boxes
(cars, pedestrians, walls) and clutter.
"""
from __future__ import annotations

import argparse
import math
import statistics
import time
from typing import Callable

import torch
from torch import Tensor

__all__ = ["lidar_like_cloud", "synthetic_sweep", "register", "run"]

_SENSOR_HEIGHT = 1.8  # metres above the ground


def lidar_like_cloud(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> Tensor:
    """A LiDAR-like cloud of exactly ``n`` points, in metres, in the sensor frame.

    About 55 % ground points on 48 rings (beam elevations -25 to -1.5 degrees, sensor 1.8 m above
    the ground, so ring radii run from 3.9 m to 69 m and the density falls with range), 35 % on the
    surfaces of boxes (cars, pedestrians, walls) 5-60 m away, 10 % in Gaussian clutter blobs. Points
    are ordered by azimuth, as a rotating sensor emits them. Deterministic for a given ``seed``.

    Args:
        n (int): number of points, >= 0.
        seed (int): random seed.
        dtype (torch.dtype): floating dtype of the result.

    Returns:
        Tensor[n, 3]: x, y, z coordinates.
    """
    g = torch.Generator().manual_seed(int(seed))

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    n_obj, n_clutter = int(0.35 * n), int(0.10 * n)
    n_ground = n - n_obj - n_clutter
    parts = []

    # ground: equal azimuth sampling per beam, so far rings are sparse
    beams = 48
    elev = torch.linspace(math.radians(-25.0), math.radians(-1.5), beams, dtype=torch.float64)
    ring_r = _SENSOR_HEIGHT / torch.tan(-elev)
    beam = torch.arange(n_ground) % beams
    r = ring_r[beam] * (1.0 + 0.01 * randn(n_ground))
    az = 2 * math.pi * rand(n_ground)
    z = -_SENSOR_HEIGHT + 0.004 * r * torch.cos(az) + 0.03 * randn(n_ground)  # gentle slope
    parts.append(torch.stack([r * torch.cos(az), r * torch.sin(az), z], 1))

    # objects: boxes (length, width, height) at random positions, points spread over their surfaces
    if n_obj:
        kinds = torch.tensor([[4.5, 1.8, 1.6], [0.6, 0.6, 1.8], [20.0, 0.5, 6.0], [2.0, 2.0, 3.0]],
                             dtype=torch.float64)
        n_boxes = 40
        kind = torch.multinomial(torch.tensor([0.5, 0.25, 0.1, 0.15]), n_boxes, replacement=True, generator=g)
        size = kinds[kind] * (0.8 + 0.4 * rand(n_boxes, 3))
        dist = 5.0 + 55.0 * rand(n_boxes)
        ang = 2 * math.pi * rand(n_boxes)
        yaw = 2 * math.pi * rand(n_boxes)
        # nearer and larger boxes get more points, as they would from a sensor
        weight = (size[:, 0] * size[:, 2] + size[:, 1] * size[:, 2]) / dist.square()
        box = torch.multinomial(weight, n_obj, replacement=True, generator=g)
        u = rand(n_obj, 3) - 0.5
        face = torch.randint(0, 3, (n_obj,), generator=g)
        side = torch.where(rand(n_obj) < 0.5, -0.5, 0.5).to(torch.float64)
        u[torch.arange(n_obj), face] = side  # put each point on one face of its box
        local = u * size[box]
        c, s = torch.cos(yaw[box]), torch.sin(yaw[box])
        x = dist[box] * torch.cos(ang[box]) + c * local[:, 0] - s * local[:, 1]
        y = dist[box] * torch.sin(ang[box]) + s * local[:, 0] + c * local[:, 1]
        z = -_SENSOR_HEIGHT + size[box, 2] / 2 + local[:, 2]
        parts.append(torch.stack([x, y, z], 1))

    # clutter: vegetation-like blobs
    if n_clutter:
        blobs = 12
        centre = torch.stack([(8 + 50 * rand(blobs)) * torch.cos(2 * math.pi * rand(blobs)),
                              (8 + 50 * rand(blobs)) * torch.sin(2 * math.pi * rand(blobs)),
                              -_SENSOR_HEIGHT + 1.0 + 2.0 * rand(blobs)], 1)
        blob = torch.randint(0, blobs, (n_clutter,), generator=g)
        parts.append(centre[blob] + randn(n_clutter, 3) * torch.tensor([1.0, 1.0, 0.6], dtype=torch.float64))

    pts = torch.cat(parts) if parts else torch.zeros(0, 3, dtype=torch.float64)
    order = torch.argsort(torch.atan2(pts[:, 1], pts[:, 0]), stable=True)
    return pts[order].to(dtype)


_SIM_CACHE: dict = {}  # seed -> (simulator, list of sweep point tensors)


def _simulated_points(seed: int, min_points: int) -> Tensor:
    """Sweeps 0, 1, ... of the simulator's ``driving_city`` scene ``seed``, concatenated, >= min_points
    (cached per seed, so several sizes cut from one scene cost one simulation)."""
    if seed not in _SIM_CACHE:
        from lidarops.data.synthetic import Simulator  # type: ignore[import-not-found]
        try:
            sim = Simulator("driving_city", seed=seed)
        except TypeError:
            sim = Simulator("driving_city")
        if len(_SIM_CACHE) >= 16:
            _SIM_CACHE.pop(next(iter(_SIM_CACHE)))
        _SIM_CACHE[seed] = (sim, [])
    sim, chunks = _SIM_CACHE[seed]
    while sum(c.shape[0] for c in chunks) < min_points and len(chunks) < 64:
        chunks.append(torch.as_tensor(sim.sweep(len(chunks)).points)[:, :3].to(torch.float32))
    return torch.cat(chunks) if len(chunks) > 1 else chunks[0]


def synthetic_sweep(n: int, seed: int = 0) -> tuple[Tensor, str]:
    """A LiDAR sweep of exactly ``n`` points (float32, (n, 3)) and the name of its source.

    Uses ``lidarops.data.synthetic.Simulator("driving_city", seed=seed)`` when it is importable:
    its sweeps 0, 1, ... are concatenated until there are ``n`` points, then an order-preserving
    random subset of ``n`` is kept. Otherwise :func:`lidar_like_cloud`.
    """
    try:
        import lidarops.data.synthetic  # noqa: F401
        have_sim = True
    except ImportError:
        have_sim = False
    if have_sim and n > 0:
        try:
            pts = _simulated_points(int(seed), int(n))
            if pts.shape[0] >= n:
                g = torch.Generator().manual_seed(int(seed))
                keep = torch.randperm(pts.shape[0], generator=g)[:n].sort().values
                return pts[keep].contiguous(), f'lidarops.data.synthetic.Simulator("driving_city", seed={seed})'
        except Exception as e:  # noqa: BLE001  (a simulator in progress must not break the tour)
            print(f"[lidarops] simulator failed ({type(e).__name__}: {e}); using the built-in generator")
    return lidar_like_cloud(n, seed), "lidarops.tour.lidar_like_cloud (built-in)"


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


def run(device: str | torch.device = "cpu", n: int = 20000, seed: int = 0, check_queries: int = 256) -> int:
    """Run the tour and print its table; returns 0 when every check passes, 1 otherwise."""
    import lidarops
    from lidarops.ops import neighbors as nb

    device = torch.device(device)
    if device.type == "cuda":
        from lidarops import extension
        if not torch.cuda.is_available():
            raise SystemExit("lidarops tour: --device cuda asked for, but torch sees no GPU")
        if not extension.cuda_available():
            raise SystemExit("lidarops tour: this lidarops build has no CUDA kernels "
                             f"({extension.build_info().get('cuda_reason', 'CPU-only build')})")
    if n < 64:
        raise SystemExit(f"lidarops tour: --n must be at least 64, got {n}")

    t0 = time.perf_counter()
    cloud, source = synthetic_sweep(n, seed)
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
    checks = {"fps": _compare("fps", centres_idx, nb._fps_reference(points, K))}
    ref_kd, ref_ki = nb._knn_reference(centres[:, sub_dev], points, k_knn)
    checks["knn"] = _compare("knn", knn_i[:, sub_dev], ref_ki, knn_d[:, sub_dev], ref_kd)
    ref_bd, ref_bi = nb._ball_query_reference(centres[:, sub_dev], points, radius, k_ball)
    checks["ball_query"] = _compare("ball_query", ball_i[:, sub_dev], ref_bi, ball_d[:, sub_dev], ref_bd)
    ref_g = nb._gather_reference(feats.cpu(), ball_i.cpu())
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
          f"checks: pure-PyTorch references (lidarops/ops/neighbors.py); total {time.perf_counter() - t0:.1f} s")
    return 1 if failures else 0


def _main(args: argparse.Namespace) -> int:
    device = args.device
    if device is None:
        import lidarops.ops.neighbors  # noqa: F401  (loads the library through the op wrappers)
        from lidarops import extension
        device = "cuda" if torch.cuda.is_available() and extension.cuda_available() else "cpu"
    return run(device=device, n=args.n, seed=args.seed)


def register(subparsers) -> None:
    """Add the ``tour`` subcommand to the ``lidarops`` command line."""
    p = subparsers.add_parser("tour", help="a short tour of the ops on a synthetic LiDAR sweep",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="default: cuda when available and built, else cpu")
    p.add_argument("--n", type=int, default=20000, help="points in the sweep (default 20000)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the sweep and features")
    p.set_defaults(func=_main)
