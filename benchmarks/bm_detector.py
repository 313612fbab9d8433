"""Benchmark PointPillars end to end on one frame already in device memory.

    python benchmarks/bm_detector.py --device cuda --json      # GPU: dense/sparse x fp32/TF32/fp16, eager and graph
    python benchmarks/bm_detector.py --device cpu               # CPU latency (fp32)
    python benchmarks/bm_detector.py --frame 000134.bin --calib 000134.txt   # a real KITTI scan, camera view
    python benchmarks/bm_detector.py --vs-openpcdet .peers/openpcdet-src     # OpenPCDet's PointPillar, same run

The frame: a simulated ``driving_city`` sweep cropped to KITTI's camera field of view and PointPillars'
range (about 20k points). Stages: voxelize -> PFN -> scatter -> backbone -> head -> decode -> NMS, with
the shipped weights when present (``lidarops/weights``), else seeded random weights with BatchNorm
statistics from a few frames (the time does not depend on the values, except NMS on the number of boxes).

* **eager**: ``model.predict(batch)`` as a user writes it, median over many calls, CUDA events. On CUDA with
  the dense backbone that call replays a CUDA graph of the whole inference from its second call on
  (``lidarops.models.pointpillars.PREDICT_CUDA_GRAPH``); **eager, no graph** is the same call inside
  ``eager_predict()``: validation, voxelization with its host read, every launch, post-processing with its host
  reads. On the CPU ``predict`` runs an inference copy of the model (BatchNorm and padding folded,
  channels-last: ``PREDICT_CPU_COPY``); **eager, the model itself** is the call inside ``eager_predict()``.
* **graph of the model itself** (fp16): ``predict`` under fp16 autocast replays a graph of an optimized copy
  (BatchNorm folded, channels-last: ``lidarops.models.cuda_graph.OPTIMIZE_UNDER_AUTOCAST``); this row turns
  that off, replaying a graph of the model's own modules.
* **batched predict**: ``model.predict`` on a batch of 16 distinct frames (frames per second).
* **graph** (dense backbone, CUDA): :class:`lidarops.models.GraphedPointPillars` as a user calls it:
  the frame copied into the graph's input, one replay of padded voxelization, network, decode, score
  threshold and NMS (``postprocess_padded``), the number of boxes read back and the detections sliced; with its
  default pillar rows (one per point of capacity) and, optimized, with ``max_pillars`` as ``predict`` sizes it.
  The sparse backbone builds its kernel maps with host reads, so it has no graph row.
* **stages**: CUDA events between the stages of one eager call (their GPU time, not counting host gaps).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from benchmarks.common import env_meta, fmt_ms, print_table, time_call, write_results  # noqa: E402
import lidarops  # noqa: E402
from lidarops import extension  # noqa: E402
from lidarops.models.pointpillars import PointPillars  # noqa: E402
from lidarops.models.postprocess import postprocess  # noqa: E402
from lidarops.models.cuda_graph import GraphedPointPillars, precision_mode  # noqa: E402

PRECISIONS = ("fp32", "tf32", "fp16")


def kitti_like_frame(seed: int = 0, path: str | None = None, calib: str | None = None) -> torch.Tensor:
    """A driving_city sweep (or the KITTI velodyne scan ``path``, with its ``calib`` file) in KITTI's camera field
    of view and the PointPillars range: (N, 4)."""
    from lidarops.data.formats.kitti import KittiCalib, kitti_fov_mask, read_calib
    from lidarops.data.synthetic import Simulator

    if path is None:
        pts = Simulator("driving_city", seed=seed).sweep(0).points
    else:
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    keep = kitti_fov_mask(pts, read_calib(calib) if calib else KittiCalib.default())
    keep &= (pts[:, 0] >= 0) & (pts[:, 0] < 69.12) & (np.abs(pts[:, 1]) < 39.68) & (pts[:, 2] >= -3) & (pts[:, 2] < 1)
    return torch.from_numpy(pts[keep])


def load_model(device: str, mode: str, checkpoint: str | None = None) -> PointPillars:
    """The shipped model run with ``mode``'s backbone, or the model in ``checkpoint`` (a PointPillars
    trained with that backbone, e.g. ``pointpillars_synth_sparse.yaml``'s)."""
    if checkpoint is not None:
        from lidarops.models import load_model as load

        model = load(checkpoint, map_location=device)
        if not isinstance(model, PointPillars) or model.config.backbone_mode != mode:
            raise ValueError(f"{checkpoint}: not a PointPillars with the {mode} backbone")
        return model.to(device).eval()
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


def run(device: str, modes=("dense", "sparse"), precisions=PRECISIONS, frame: torch.Tensor | None = None,
        frame_name: str = "driving_city seed 0", batched: int = 16,
        sparse_checkpoint: str | None = None) -> list[dict]:
    from lidarops.models.pointpillars import eager_predict

    rows = []
    frame = (kitti_like_frame() if frame is None else frame).to(device)
    many = [kitti_like_frame(seed).to(device) for seed in range(batched)] if device == "cuda" else []
    # channels_last was slower than the default layout on the H200 (docs/notes/boxes-and-detector.md)
    variants = [(mode, precision, "contiguous") for mode in modes
                for precision in (precisions if device == "cuda" else ("fp32",))]
    for mode, precision, fmt in variants:
        checkpoint = sparse_checkpoint if mode == "sparse" else None
        model = load_model(device, mode, checkpoint)
        trained = "pointpillars_synth" + (f" ({mode}-trained: {os.path.basename(checkpoint)})" if checkpoint else
                                          "" if mode == "dense" else " (dense-trained weights)")
        half = mode == "sparse" and precision == "fp16"
        if half:
            model = model.half()
        batch = {"points": torch.cat([frame.new_zeros(frame.shape[0], 1), frame], 1), "batch_size": 1}
        if half:
            batch["points"] = batch["points"].half()

        def eager(b):
            with precision_mode(precision, device, autocast=not half):
                return model.predict(b)

        def no_graph(b):
            with eager_predict():
                return eager(b)

        def exact_graph(b):  # fp16: predict's graph of the model itself instead of its optimized copy
            from lidarops.models import cuda_graph

            old, cuda_graph.OPTIMIZE_UNDER_AUTOCAST = cuda_graph.OPTIMIZE_UNDER_AUTOCAST, False
            try:
                return eager(b)
            finally:
                cuda_graph.OPTIMIZE_UNDER_AUTOCAST = old

        calls = [("eager", eager)]
        if mode == "dense":  # predict without its graph (CUDA) or its inference copy (CPU): the model itself
            calls.append(("eager, no graph" if device == "cuda" else "eager, the model itself (no inference copy)",
                          no_graph))
        if device == "cuda" and mode == "dense" and precision == "fp16":
            calls.append(("eager, graph of the model itself (not optimized)", exact_graph))
        for impl, fn in calls:
            t = time_call(fn, (batch,), torch.device(device), budget_s=2.0, rotate=False)
            kept = len(fn(batch)[0]["scores"])
            row = {"op": "pointpillars", "backbone": mode, "precision": precision, "impl": impl,
                   "memory_format": fmt, "frame": frame_name, "points": int(frame.shape[0]), "boxes": kept,
                   "weights": trained, **t.as_dict()}
            if device == "cuda" and impl == "eager, no graph" or (device == "cuda" and mode == "sparse"):
                row["stages_ms"] = stage_times(model, batch, precision, autocast=not half)
            rows.append(row)
        if many and mode == "dense":
            big = {"points": torch.cat([F.pad(f, (1, 0), value=float(b)) for b, f in enumerate(many)]),
                   "batch_size": len(many)}
            t = time_call(eager, (big,), torch.device(device), budget_s=2.0, rotate=False)
            rows.append({"op": "pointpillars", "backbone": mode, "precision": precision,
                         "impl": f"batched predict ({len(many)} frames)", "memory_format": fmt,
                         "frame": f"driving_city seeds 0-{len(many) - 1}", "points": int(sum(len(f) for f in many)),
                         "boxes": sum(len(d["scores"]) for d in eager(big)),
                         "frames_per_s": round(len(many) * 1000.0 / t.median, 1), **t.as_dict()})
        if device == "cuda" and mode == "dense":
            # capacity = the frame's points (the padded tensors as small as they can be), and a capacity
            # a user would set for any KITTI scan (the pillar rows then reach the config's max_voxels_test)
            # and the optimized graph with the pillar rows predict would give it (its frame's pillars, a quarter
            # to spare, a power of two) instead of one per point
            from lidarops.models.cuda_graph import _predict_rows
            from lidarops.models.pointpillars import voxelize_frames

            n = int(frame.shape[0])
            with torch.no_grad():
                sized = _predict_rows(int(voxelize_frames(batch["points"], 1, model.config, False)[0].shape[0]), n)
            for capacity, optimize, pillars in ((n, False, None), (150_000, False, None), (n, True, None),
                                                (n, True, sized)):
                impl = "graph" if capacity == frame.shape[0] else f"graph, capacity {capacity // 1000}k"
                impl += ", optimize (BatchNorm folded, channels-last)" if optimize else ""
                impl += f", max_pillars {pillars}" if pillars else ""
                try:
                    graphed = GraphedPointPillars(model, capacity=capacity, precision=precision, optimize=optimize,
                                                  max_pillars=pillars)
                    t = time_call(graphed, (frame,), torch.device(device), budget_s=2.0, rotate=False)
                    got = graphed(frame)
                    same = torch.equal(got["labels"], eager(batch)[0]["labels"])
                    rows.append({"op": "pointpillars", "backbone": mode, "precision": precision, "impl": impl,
                                 "memory_format": fmt, "frame": frame_name, "points": int(frame.shape[0]),
                                 "capacity": capacity,
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
    ap.add_argument("--frame", default=None, help="a KITTI velodyne .bin scan instead of the simulated frame")
    ap.add_argument("--calib", default=None, help="its KITTI calib .txt (default: KITTI's usual one)")
    ap.add_argument("--modes", default="dense,sparse")
    ap.add_argument("--precisions", default=",".join(PRECISIONS))
    ap.add_argument("--sparse-checkpoint", default=None, metavar="FILE",
                    help="the sparse rows' model: a PointPillars trained with the sparse backbone (default: the "
                         "shipped dense-trained weights run sparse, a different detector)")
    ap.add_argument("--vs-openpcdet", default=None, metavar="SRC",
                    help="also time OpenPCDet's PointPillar (an OpenPCDet tree with its ops built) on the same frame "
                         "and weights (benchmarks/openpcdet_peer.py)")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not (torch.cuda.is_available() and extension.cuda_available()):
        print("no CUDA device or lidarops without CUDA kernels")
        return 1
    frame = kitti_like_frame(path=args.frame, calib=args.calib) if args.frame else None
    name = os.path.basename(args.frame) if args.frame else "driving_city seed 0"
    rows = run(args.device, tuple(args.modes.split(",")), tuple(args.precisions.split(",")), frame, name,
               sparse_checkpoint=args.sparse_checkpoint)
    if args.vs_openpcdet:
        from benchmarks.openpcdet_peer import openpcdet_rows
        from lidarops.models import weights

        for tf32 in (True, False):
            for r in openpcdet_rows(Path(args.vs_openpcdet), kitti_like_frame() if frame is None else frame,
                                    Path(weights.path("pointpillars_synth")), tf32=tf32):
                rows.append({"frame": name, **r})
    table = []
    for r in rows:
        stages = r.get("stages_ms")
        share = ""
        if stages:
            total = sum(stages.values())
            share = "  ".join(f"{k} {100 * v / total:.0f}%" for k, v in stages.items())
        table.append([r.get("backbone", ""), r.get("precision", ""), r.get("memory_format", ""),
                      r.get("impl", "") + (f" {r['stage']}" if r.get("stage") else ""),
                      fmt_ms(r.get("median_ms")), r.get("boxes", ""),
                      share if r["status"] == "ok" else r["status"]])
    print_table(f"PointPillars end to end on {env_meta(args.device).get('device', args.device)}",
                ["backbone", "precision", "layout", "call", "median ms", "boxes", "GPU time by stage / status"],
                table, right=(4, 5))
    if args.json:
        # the rows of other frames stay: a real scan's run does not erase the simulated frame's
        print(f"wrote {write_results('detector', args.device, rows, env_meta(args.device), replace_by='frame')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
