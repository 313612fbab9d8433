"""Benchmark lidarops.voxelize on a LiDAR-like sweep (tests/voxelize_data.py), against a
pure-PyTorch implementation of the same semantics measured in the same run (and spconv's
PointToVoxel when it is installed: the CUDA machine's spconv bundle).

    python benchmarks/bm_voxelize.py                 # CPU, and CUDA when available
    python benchmarks/bm_voxelize.py --device cuda --json

Times are medians (torch.utils.benchmark on CPU, CUDA events on GPU) of the whole call, host sync
included (the wrapper reads the voxel count once). ``--json`` merges the table into
``benchmarks/results/<device>.json`` under the key ``"voxelize"``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

import lidarops  # noqa: E402
from voxelize_data import KITTI_PILLARS, KITTI_SECOND, lidar_sweep  # noqa: E402

CONFIGS = {
    # name: (grid, max_points_per_voxel, max_voxels); capacities of OpenPCDet's KITTI configs (test)
    "pillars 0.16 m (PointPillars)": (KITTI_PILLARS, 32, 40_000),
    "voxels 0.05x0.05x0.1 m (SECOND)": (KITTI_SECOND, 5, 40_000),
}


def torch_voxelize(points, voxel_size, point_range, P, M):
    """Pure-PyTorch voxelization with lidarops' semantics (first-seen voxels, input order within a
    voxel, drop beyond capacity): the baseline one writes without a custom op."""
    dev = points.device
    ct = torch.float64 if points.dtype == torch.float64 else torch.float32
    p = points[:, :3].to(ct)
    lo = torch.tensor(point_range[:3], dtype=ct, device=dev)
    hi = torch.tensor(point_range[3:], dtype=ct, device=dev)
    vs = torch.tensor(voxel_size, dtype=ct, device=dev)
    dims = torch.tensor([round((point_range[a + 3] - point_range[a]) / voxel_size[a]) for a in range(3)], device=dev)
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
    gen = PointToVoxel(vsize_xyz=list(cfg["voxel_size"]), coors_range_xyz=list(cfg["point_range"]),
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


def time_fn(fn, device, reps=30):
    for _ in range(3):
        fn()
    if device == "cuda":
        times = []
        for _ in range(reps):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            torch.cuda.synchronize()
            times.append(a.elapsed_time(b))
        return statistics.median(times)
    from torch.utils.benchmark import Timer
    m = Timer("fn()", globals={"fn": fn}, num_threads=torch.get_num_threads()).blocked_autorange(min_run_time=1.0)
    return m.median * 1e3


def run(device: str, n: int):
    pts = torch.from_numpy(lidar_sweep(n, seed=0)).to(device)
    rows = []
    for name, (cfg, P, M) in CONFIGS.items():
        vs, pr = cfg["voxel_size"], cfg["point_range"]
        res = lidarops.voxelize(pts, vs, pr, P, M, overflow="drop")
        ours = res.voxels, res.coords, res.num_points
        base = torch_voxelize(pts, vs, pr, P, M)
        same = all(torch.equal(a, b) for a, b in zip(ours, base))
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
        peer = spconv_peer(device, cfg, P, M)
        same_spconv = None
        if peer is not None:
            entries["spconv PointToVoxel"] = lambda: peer(pts)
            from lidarops.compat.spconv_utils import PointToVoxel as LidaropsPointToVoxel
            face = LidaropsPointToVoxel(list(vs), list(pr), 4, M, P, device=torch.device(device), overflow="drop")
            same_spconv = same_voxel_sets(face(pts), peer(pts))  # the face reproduces spconv's range rule
        times = {k: time_fn(f, device) for k, f in entries.items()}
        ref = times["lidarops.voxelize"]
        for k, t in times.items():
            rows.append({"config": name, "impl": k, "ms": t, "ratio_vs_lidarops": t / ref, "points": n,
                         "voxels": res.info.num_voxels, "dropped": res.num_dropped,
                         "same_as_lidarops": {"pure PyTorch": same, "spconv PointToVoxel": same_spconv}.get(k)})
    return rows


def device_name(device: str) -> str:
    if device == "cuda":
        return torch.cuda.get_device_name().replace(" ", "_")
    return f"cpu-{platform.machine()}-{torch.get_num_threads()}threads"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda", "all"], default="all")
    ap.add_argument("--points", type=int, default=120_000)
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (default: torch's choice)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or torch.cuda.is_available()]
    for device in devices:
        rows = run(device, args.points)
        print(f"\n{device_name(device)}: {args.points} points, torch {torch.__version__}")
        print(f"{'config':34s} {'implementation':36s} {'ms':>9s} {'x lidarops':>10s}")
        for r in rows:
            note = "" if r["same_as_lidarops"] is None else ("  (same output)" if r["same_as_lidarops"] else "  (DIFFERENT)")
            if r["impl"] == "spconv PointToVoxel" and r["same_as_lidarops"] is not None:
                note = "  (same voxels and counts)" if r["same_as_lidarops"] else "  (DIFFERENT voxels or counts)"
            print(f"{r['config']:34s} {r['impl']:36s} {r['ms']:9.3f} {r['ratio_vs_lidarops']:10.2f}{note}")
        print("voxels / dropped: " + ", ".join(f"{r['config']}: {r['voxels']} / {r['dropped']}"
                                              for r in rows if r["impl"] == "lidarops.voxelize"))
        if args.json:
            path = os.path.join(ROOT, "benchmarks", "results", f"{device_name(device)}.json")
            os.makedirs(os.path.dirname(path), exist_ok=True)
            data = {}
            if os.path.exists(path):
                with open(path) as f:
                    data = json.load(f)
            data["voxelize"] = {"torch": torch.__version__, "rows": rows}
            with open(path, "w") as f:
                json.dump(data, f, indent=1)
            print(f"wrote {path}")


if __name__ == "__main__":
    main()
