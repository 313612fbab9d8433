"""Benchmark PointPillars end to end on one frame already in device memory.

    python benchmarks/bm_detector.py --device cuda --json      # GPU: dense/sparse x fp32/TF32/fp16, eager and graph
    python benchmarks/bm_detector.py --device cpu               # CPU latency (fp32)

The frame: a simulated ``driving_city`` sweep cropped to KITTI's camera field of view and PointPillars'
range (about 20k points). Stages: voxelize -> PFN -> scatter -> backbone -> head -> decode -> NMS, with
the shipped weights when present (``lidarops/weights``), else seeded random weights with BatchNorm
statistics from a few frames (the time does not depend on the values, except NMS on the number of boxes).

* **eager**: ``model.predict(batch)`` as a user writes it (validation, voxelization with its host read,
  every launch, post-processing with its host reads), median over many calls, CUDA events.
* **graph** (dense backbone, CUDA): :class:`lidarops.models.GraphedPointPillars` as a user calls it:
  the frame copied into the graph's input, one replay of padded voxelization, network, decode, score
  threshold and NMS (``postprocess_padded``), the number of boxes read back and the detections sliced.
  The sparse backbone builds its kernel maps with host reads, so it has no graph row.
* **stages**: CUDA events between the stages of one eager call (their GPU time, not counting host gaps).
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.common import env_meta, fmt_ms, print_table, time_call, write_results  # noqa: E402
import lidarops  # noqa: E402
from lidarops import extension  # noqa: E402
from lidarops.models.pointpillars import PointPillars  # noqa: E402
from lidarops.models.postprocess import postprocess  # noqa: E402
from lidarops.models.cuda_graph import GraphedPointPillars, precision_mode  # noqa: E402

PRECISIONS = ("fp32", "tf32", "fp16")


def kitti_like_frame(seed: int = 0) -> torch.Tensor:
    """A driving_city sweep in KITTI's camera field of view and the PointPillars range: (N, 4)."""
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask
    from lidarops.data.synthetic import Simulator

    pts = Simulator("driving_city", seed=seed).sweep(0).points
    keep = kitti_fov_mask(pts, KittiCalib.default())
    keep &= (pts[:, 0] >= 0) & (pts[:, 0] < 69.12) & (np.abs(pts[:, 1]) < 39.68) & (pts[:, 2] >= -3) & (pts[:, 2] < 1)
    return torch.from_numpy(pts[keep])


def load_model(device: str, mode: str) -> PointPillars:
    try:
        from lidarops.models import weights

        model = weights.load("pointpillars_synth", map_location=device)
        if model.config.backbone_mode != mode:
            cfg = model.config.to_dict()
            cfg["backbone_mode"] = mode
            state = model.state_dict()
            model = PointPillars(cfg)
            model.load_weights(state)
    except (ImportError, FileNotFoundError, AttributeError):
        torch.manual_seed(0)
        cfg = PointPillars().config.to_dict()
        cfg["backbone_mode"] = mode
        model = PointPillars(cfg)
    return model.to(device).eval()


def stage_times(model: PointPillars, batch: dict, precision: str, runs: int = 30, autocast: bool = True
                ) -> dict[str, float]:
    """Median GPU time of each stage of one eager call (CUDA events between the stages)."""
    from lidarops.sparse import SparseConvTensor

    names = ("voxelize", "pfn", "scatter", "backbone", "head", "decode", "nms")
    acc = {n: [] for n in names}
    cfg = model.config
    for _ in range(runs + 3):
        ev = [torch.cuda.Event(enable_timing=True) for _ in range(len(names) + 1)]
        with torch.no_grad(), precision_mode(precision, "cuda", autocast=autocast):
            ev[0].record()
            voxels, num, coords = model.voxelize(batch["points"], 1)
            ev[1].record()
            feats = model.vfe(voxels, num, coords)
            ev[2].record()
            if cfg.backbone_mode == "dense":
                x = model.map_to_bev(feats, coords, 1)
            else:
                nx, ny, _ = cfg.grid_size
                x = SparseConvTensor(feats, coords[:, [0, 2, 3]].int().contiguous(), [ny, nx], 1)
            ev[3].record()
            x = model.backbone_2d(x)
            ev[4].record()
            raw = model.dense_head(x)
            ev[5].record()
            cls, boxes = model.dense_head.decode(raw)
            ev[6].record()
            postprocess(cls, boxes, cfg)
            ev[7].record()
        torch.cuda.synchronize()
        for i, n in enumerate(names):
            acc[n].append(ev[i].elapsed_time(ev[i + 1]))
    return {n: float(np.median(v[3:])) for n, v in acc.items()}


def run(device: str, modes=("dense", "sparse"), precisions=PRECISIONS) -> list[dict]:
    rows = []
    frame = kitti_like_frame().to(device)
    # channels_last was slower than the default layout on the H200 (docs/notes/boxes-and-detector.md)
    variants = [(mode, precision, "contiguous") for mode in modes
                for precision in (precisions if device == "cuda" else ("fp32",))]
    for mode, precision, fmt in variants:
        model = load_model(device, mode)
        half = mode == "sparse" and precision == "fp16"
        if half:
            model = model.half()
        batch = {"points": torch.cat([frame.new_zeros(frame.shape[0], 1), frame], 1), "batch_size": 1}
        if half:
            batch["points"] = batch["points"].half()

        def eager(b):
            with precision_mode(precision, device, autocast=not half):
                return model.predict(b)

        t = time_call(eager, (batch,), torch.device(device), budget_s=2.0, rotate=False)
        kept = len(eager(batch)[0]["scores"])
        row = {"op": "pointpillars", "backbone": mode, "precision": precision, "impl": "eager",
               "memory_format": fmt,
               "points": int(frame.shape[0]), "boxes": kept, **t.as_dict()}
        if device == "cuda":
            row["stages_ms"] = stage_times(model, batch, precision, autocast=not half)
        rows.append(row)
        if device == "cuda" and mode == "dense":
            # capacity = the frame's points (the padded tensors as small as they can be), and a capacity
            # a user would set for any KITTI scan (the pillar rows then reach the config's max_voxels_test)
            for capacity in (int(frame.shape[0]), 150_000):
                impl = "graph" if capacity == frame.shape[0] else f"graph, capacity {capacity // 1000}k"
                try:
                    graphed = GraphedPointPillars(model, capacity=capacity, precision=precision)
                    t = time_call(graphed, (frame,), torch.device(device), budget_s=2.0, rotate=False)
                    got = graphed(frame)
                    same = torch.equal(got["labels"], eager(batch)[0]["labels"])
                    rows.append({"op": "pointpillars", "backbone": mode, "precision": precision, "impl": impl,
                                 "memory_format": fmt, "points": int(frame.shape[0]), "capacity": capacity,
                                 "boxes": len(got["scores"]), "same_labels_as_eager": same, **t.as_dict()})
                except Exception as e:  # noqa: BLE001  (reported, not blanked)
                    rows.append({"op": "pointpillars", "backbone": mode, "precision": precision, "impl": impl,
                                 "memory_format": fmt, "status": f"error: {type(e).__name__}: {e}"})
    for r in rows:
        r.setdefault("status", "ok")
        r["device"] = device
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--json", action="store_true", help="merge results into benchmarks/results/<device>.json")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not (torch.cuda.is_available() and extension.cuda_available()):
        print("no CUDA device or lidarops without CUDA kernels")
        return 1
    rows = run(args.device)
    table = []
    for r in rows:
        stages = r.get("stages_ms")
        share = ""
        if stages:
            total = sum(stages.values())
            share = "  ".join(f"{k} {100 * v / total:.0f}%" for k, v in stages.items())
        table.append([r["backbone"], r["precision"], r.get("memory_format", ""), r["impl"], fmt_ms(r.get("median_ms")), r.get("boxes", ""),
                      share if r["status"] == "ok" else r["status"]])
    print_table(f"PointPillars end to end on {env_meta(args.device).get('device', args.device)}",
                ["backbone", "precision", "layout", "call", "median ms", "boxes", "GPU time by stage / status"],
                table, right=(4, 5))
    if args.json:
        print(f"wrote {write_results('detector', args.device, rows, env_meta(args.device), replace_by=None)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
