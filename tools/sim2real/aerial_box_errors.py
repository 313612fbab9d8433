"""Where the Aerial-PointPillars' boxes go wrong: for each labelled drone with points in the model's range, the
best-overlapping detection (bird's-eye IoU >= 0.25, score >= --score) and its errors (centre in the ground plane,
height of the centre, length / width / height), on held-out frames of the `avia` realism profile and ray-cast ones.

    python tools/sim2real/aerial_box_errors.py --frames 30 --out benchmarks/results/aerial_box_errors_cpu.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def errors(model, realism, frames: int, seed: int, score: float) -> dict:
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.ops.boxes import box_iou_bev

    lo, hi = np.array(model.config.point_cloud_range[:3]), np.array(model.config.point_cloud_range[3:])
    rows, drones = [], 0
    for scenario in ("drone_bridge", "drone_lock"):
        source = SyntheticFrames(scenario, num_frames=frames, seed=seed, realism=realism)
        for i in range(frames):
            frame = source[i]
            seen = (frame.num_points_in_box >= 2) & ((frame.boxes[:, :3] >= lo) & (frame.boxes[:, :3] <= hi)).all(1)
            gt, pts = frame.boxes[seen].astype(np.float32), frame.num_points_in_box[seen]
            drones += len(gt)
            points = torch.from_numpy(frame.points.astype(np.float32))
            with torch.no_grad():
                pred = model.predict({"points": torch.nn.functional.pad(points, (1, 0)), "batch_size": 1})[0]
            boxes = pred["boxes"][pred["scores"] >= score]
            if not len(gt) or not len(boxes):
                continue
            iou = box_iou_bev(torch.from_numpy(gt), boxes)
            best, j = iou.max(1)
            for g in np.flatnonzero(best.numpy() >= 0.25):
                b, t = boxes[j[g]].numpy(), gt[g]
                rows.append({"iou_bev": float(best[g]), "points": int(pts[g]),
                             "centre_xy": float(np.hypot(*(b[:2] - t[:2]))), "dz": float(b[2] - t[2]),
                             "dl": float(b[3] - t[3]), "dw": float(b[4] - t[4]), "dh": float(b[5] - t[5])})
    out = {"realism": realism, "frames": 2 * frames, "drones": drones, "matched": len(rows)}
    if rows:
        for key in ("iou_bev", "centre_xy", "dz", "dl", "dw", "dh"):
            v = np.array([r[key] for r in rows])
            out[key] = {"median": round(float(np.median(v)), 3), "mean": round(float(v.mean()), 3),
                        "p10": round(float(np.percentile(v, 10)), 3), "p90": round(float(np.percentile(v, 90)), 3)}
    return out


def main(argv=None) -> int:
    from lidarops.models import weights

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", default="aerial_pointpillars")
    p.add_argument("--frames", type=int, default=30, help="frames per scenario and kind")
    p.add_argument("--seed", type=int, default=5000)
    p.add_argument("--score", type=float, default=0.2)
    p.add_argument("--out", default=None)
    args = p.parse_args(argv)
    torch.set_num_threads(2)
    model = weights.load(args.checkpoint) if args.checkpoint in weights.available() else None
    if model is None:
        from lidarops.models import load_model

        model = load_model(args.checkpoint).eval()
    t0 = time.perf_counter()
    report = {"checkpoint": args.checkpoint, "seed": args.seed, "score": args.score,
              "kinds": [errors(model, r, args.frames, args.seed, args.score) for r in ("avia", None)]}
    report["seconds"] = round(time.perf_counter() - t0, 1)
    for k in report["kinds"]:
        print(f"{k['realism'] or 'ray-cast'}: {k['matched']} of {k['drones']} drones matched (BEV IoU >= 0.25); "
              + "; ".join(f"{key} median {k[key]['median']:+.3f} (p10 {k[key]['p10']:+.3f}, p90 {k[key]['p90']:+.3f})"
                          for key in ("iou_bev", "centre_xy", "dz", "dl", "dw", "dh") if key in k))
    if args.out:
        Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
