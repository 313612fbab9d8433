"""Benchmark lidarops.voxelize on a LiDAR-like sweep (tests/helpers/voxelize.py), against a
pure-PyTorch implementation of the same semantics measured in the same run (and spconv's
PointToVoxel when it is installed: the CUDA machine's spconv bundle).

    python benchmarks/bm_voxelize.py                 # CPU, and CUDA when available
    python benchmarks/bm_voxelize.py --device cuda --json
    python benchmarks/bm_voxelize.py --device cpu --quick   # smoke test (20k points, short budget)

Times are medians of the whole call, host sync included (the wrapper reads the voxel count once;
``padded=True`` does not), with the timers of ``benchmarks/common.py``: on CPU every implementation's
calls interleaved, each with the same warm-up and run count; on CUDA CUDA events, the same warm-up and
a fixed run count for each. Like is compared with like: spconv's ``PointToVoxel`` module call against
lidarops' ``PointToVoxel`` face (``lidarops.compat.spconv_utils``, the same call shape), the pure-PyTorch
baseline against ``lidarops.voxelize``. ``--json`` merges the rows into
``benchmarks/results/<device>.json``, section ``"voxelize"``; an implementation that fails has its
error in ``status``, not a blank.
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

import lidarops  # noqa: E402
from benchmarks.common import (  # noqa: E402
    env_meta, fmt_ms, fmt_ratio, print_table, short_status, time_cpu_interleaved, time_cuda, write_results)
from helpers.voxelize import KITTI_PILLARS, KITTI_SECOND, lidar_sweep  # noqa: E402

SECTION = "voxelize"
CUDA_RUNS = 50  # every implementation gets this many timed calls on CUDA

CONFIGS = {
    # name: (grid, max_points_per_voxel, max_voxels); capacities of OpenPCDet's KITTI configs (test)
    "pillars 0.16 m (PointPillars)": (KITTI_PILLARS, 32, 40_000),
    "voxels 0.05x0.05x0.1 m (SECOND)": (KITTI_SECOND, 5, 40_000),
}


def torch_voxelize(points, voxel_size, point_cloud_range, P, M):
    """Pure-PyTorch voxelization with lidarops' semantics (first-seen voxels, input order within a
    voxel, drop beyond capacity): the baseline one writes without a custom op."""
    dev = points.device
    ct = torch.float64 if points.dtype == torch.float64 else torch.float32
    p = points[:, :3].to(ct)
    lo = torch.tensor(point_cloud_range[:3], dtype=ct, device=dev)
    hi = torch.tensor(point_cloud_range[3:], dtype=ct, device=dev)
    vs = torch.tensor(voxel_size, dtype=ct, device=dev)
    dims = torch.tensor([round((point_cloud_range[a + 3] - point_cloud_range[a]) / voxel_size[a]) for a in range(3)], device=dev)
    c = torch.floor((p - lo) / vs)
    ok = ((p >= lo) & (p < hi) & (c >= 0) & (c < dims)).all(1)
    idx = torch.nonzero(ok).squeeze(1)
    c = c[idx].long()
    key = (c[:, 2] * dims[1] + c[:, 1]) * dims[0] + c[:, 0]
    skey, order = torch.sort(key, stable=True)
    uniq, inverse, counts = torch.unique_consecutive(skey, return_inverse=True, return_counts=True)
    starts = torch.cumsum(counts, 0) - counts
    first = idx[order[starts]]                      # first point of each voxel (stable sort)
    rank = torch.empty_like(first)
    rank[torch.argsort(first)] = torch.arange(first.numel(), device=dev)
    slot = torch.arange(skey.numel(), device=dev) - starts[inverse]
    voxel = rank[inverse]
    keep = (voxel < M) & (slot < P)
    V = min(int(uniq.numel()), M)
    out = points.new_zeros((V, P, points.shape[1]))
    out[voxel[keep], slot[keep]] = points[idx[order[keep]]]
    kept = rank < M
    coords = torch.empty((V, 3), dtype=torch.int32, device=dev)
    u = uniq[kept]
    coords[rank[kept]] = torch.stack([u // (dims[0] * dims[1]), u // dims[0] % dims[1], u % dims[0]], 1).int()
    num = torch.empty(V, dtype=torch.int32, device=dev)
    num[rank[kept]] = counts[kept].clamp(max=P).int()
    return out, coords, num


def spconv_peer(device, cfg, P, M):
    try:
        from spconv.pytorch.utils import PointToVoxel
    except ImportError:
        return None
    gen = PointToVoxel(vsize_xyz=list(cfg["voxel_size"]), coors_range_xyz=list(cfg["point_cloud_range"]),
                       num_point_features=4, max_num_voxels=M, max_num_points_per_voxel=P, device=torch.device(device))
    return lambda pts: gen(pts)


def same_voxel_sets(ours, theirs) -> bool:
    """Same voxels with the same point counts, in any order (spconv's CUDA order is arbitrary; when
    max_voxels is not exceeded the set of voxels and the counts do not depend on it)."""
    def canon(coords, num):
        coords = coords.long().cpu()
        key = (coords[:, 0] * 2**21 + coords[:, 1]) * 2**21 + coords[:, 2]
        order = torch.argsort(key)
        return coords[order], num.long().cpu()[order]
    a, b = canon(ours[1], ours[2]), canon(theirs[1], theirs[2])
    return all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, b))


def _error(e: BaseException) -> str:
    msg = str(e).strip().splitlines()[0][:160] if str(e).strip() else ""
    return f"error: {type(e).__name__}: {msg}"


def _time_all(entries: dict, device: str, budget_s: float) -> dict:
    """Timing (or an "error: ..." status) per implementation: the same warm-up and run count for each."""
    if device == "cuda":
        out = {}
        for k, f in entries.items():
            try:
                out[k] = time_cuda(f, (), min_runs=CUDA_RUNS, max_runs=CUDA_RUNS, budget_s=budget_s, rotate=False)
            except Exception as e:  # noqa: BLE001  (reported in the row)
                out[k] = _error(e)
        return out
    timings = time_cpu_interleaved([(f, ()) for f in entries.values()], budget_s=budget_s)
    return {k: (_error(t) if isinstance(t, BaseException) else t) for k, t in zip(entries, timings)}


def run(device: str, n: int, budget_s: float = 1.0) -> list[dict]:
    """The rows of one device: per config and implementation, its timing or its error."""
    pts = torch.from_numpy(lidar_sweep(n, seed=0)).to(device)
    rows = []
    for name, (cfg, P, M) in CONFIGS.items():
        vs, pr = cfg["voxel_size"], cfg["point_cloud_range"]
        res = lidarops.voxelize(pts, vs, pr, P, M, overflow="drop")
        ours = res.voxels, res.coords, res.num_points
        base = torch_voxelize(pts, vs, pr, P, M)
        same = {"pure PyTorch": all(torch.equal(a, b) for a, b in zip(ours, base))}
        entries = {
            "lidarops.voxelize": lambda: lidarops.voxelize(pts, vs, pr, P, M, overflow="drop"),
            "pure PyTorch": lambda: torch_voxelize(pts, vs, pr, P, M),
        }
        if device == "cpu":
            for method in ("dense", "hash"):
                entries[f"lidarops.voxelize method={method}"] = (
                    lambda m=method: lidarops.voxelize(pts, vs, pr, P, M, overflow="drop", method=m))
        else:
            entries["lidarops.voxelize padded=True"] = (
                lambda: lidarops.voxelize(pts, vs, pr, P, M, overflow="drop", padded=True))
        from lidarops.compat.spconv_utils import PointToVoxel as LidaropsPointToVoxel
        face = LidaropsPointToVoxel(list(vs), list(pr), 4, M, P, device=torch.device(device), overflow="drop")
        entries["lidarops PointToVoxel (compat face)"] = lambda: face(pts)
        peer = spconv_peer(device, cfg, P, M)
        if peer is not None:
            entries["spconv PointToVoxel"] = lambda: peer(pts)
            try:  # the face reproduces spconv's range rule
                same["spconv PointToVoxel"] = same_voxel_sets(face(pts), peer(pts))
            except Exception:  # noqa: BLE001  (the timing reports the error)
                same["spconv PointToVoxel"] = None
        times = _time_all(entries, device, budget_s)
        # each row's reference: the lidarops call of the same shape
        refs = {"spconv PointToVoxel": "lidarops PointToVoxel (compat face)"}
        for k, t in times.items():
            ref = times.get(refs.get(k, "lidarops.voxelize"))
            row = {"op": f"{name}/{k}", "config": name, "impl": k, "points": n, "voxels": res.info.num_voxels,
                   "dropped": res.num_dropped, "same_as_lidarops": same.get(k),
                   "ratio_vs": refs.get(k, "lidarops.voxelize")}
            if isinstance(t, str):
                row.update(status=t, median_ms=None, ratio=None)
            else:
                row.update(status="ok", **t.as_dict())
                row["ratio"] = t.median / ref.median if not isinstance(ref, (str, type(None))) else None
            rows.append(row)
    return rows


def print_rows(rows: list[dict], title: str) -> None:
    table = []
    for r in rows:
        note = ""
        if r["same_as_lidarops"] is not None:
            note = "same output" if r["same_as_lidarops"] else "DIFFERENT"
            if r["impl"] == "spconv PointToVoxel":
                note = "same voxels and counts" if r["same_as_lidarops"] else "DIFFERENT voxels or counts"
        time_cell = fmt_ms(r["median_ms"]) if r["median_ms"] is not None else short_status(r["status"])
        table.append([r["config"], r["impl"], time_cell, r.get("runs", ""), fmt_ratio(r["ratio"]),
                      r["ratio_vs"] if r["impl"] not in ("lidarops.voxelize",) else "", note])
    print_table(title, ["config", "implementation", "ms", "runs", "ratio", "ratio against", "output"], table,
                right=(2, 3, 4))
    for r in rows:
        if r["status"].startswith("error"):
            print(f"  {r['config']}, {r['impl']}: {r['status']}")
    print("voxels / dropped: " + ", ".join(f"{r['config']}: {r['voxels']} / {r['dropped']}"
                                          for r in rows if r["impl"] == "lidarops.voxelize"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda", "all"], default="all")
    ap.add_argument("--points", type=int, default=None, help="points per sweep (default 120,000; 20,000 with --quick)")
    ap.add_argument("--quick", action="store_true", help="smoke test: a small sweep and a short budget")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (default: torch's choice)")
    ap.add_argument("--json", action="store_true", help="merge the rows into benchmarks/results/<device>.json")
    ap.add_argument("--results-dir", default=None, help="folder of the result files (default benchmarks/results)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    points = args.points or (20_000 if args.quick else 120_000)
    budget_s = 0.1 if args.quick else 1.0
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or torch.cuda.is_available()]
    for device in devices:
        rows = run(device, points, budget_s)
        meta = env_meta(device)
        print_rows(rows, f"\n{meta['device']}: {points} points, torch {torch.__version__} (ratio: impl / reference)")
        if args.json:
            meta["points"] = points
            path = write_results(SECTION, device, rows, meta, replace_by=None, results_dir=args.results_dir)
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
