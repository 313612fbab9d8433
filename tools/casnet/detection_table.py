"""CAS-Net's Table I re-measured: the frozen PointPillars (the shipped ``pointpillars_synth``) on every frame of
a KITTI-format folder, fed 1/D of each frame's field-of-view points by random sampling, FPS and trained
CAS-Nets, at D = 1, 2, 4, 8: moderate mAP (3D and BEV, R40 and R11) and the sampling time per frame; a JSON
report and a plot (issue 37, docs/casnet.md).

    python tools/casnet/detection_table.py --data /tmp/val --casnet casnet_det_d2.pth casnet_det_d4.pth \\
        casnet_det_d8.pth --ratios 1 2 4 8 --device cuda --out casnet_detection.json --plot casnet_detection.png

Every sampler keeps the same budget, ``n // D`` points of a frame of ``n`` (D = 1: every point, the
reference). CAS-Net runs as :class:`lidarops.models.casnet.CASNetSampler` does behind ``lidarops detect
--sampler casnet``: segments of ``m * D`` points (8,192), the most confident distinct picks. Each CAS-Net file
(``CASNet.save``; a training checkpoint of ``CASNetPointPillars`` works too) is used at the ratio it was
trained for, ``8192 // num_out``. Times: the sampling call per frame, synchronised, median over the frames.
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def run(detector, sampler, ratio: int, frames: list, device) -> dict:
    """Detections of every frame behind one sampler, their KITTI metrics and the sampling times."""
    from lidarops.eval.kitti import KittiEvaluator
    from lidarops.train.data import frame_meta, move_to_device

    preds, metas, times, kept_n, in_n, distinct = [], [], [], [], [], []
    with torch.no_grad():
        for batch in frames:
            on_device = move_to_device(batch, device)
            points = on_device["points"]
            xyzi = points[:, 1:].unsqueeze(0)
            n = xyzi.shape[1]
            if ratio > 1 and n:
                _sync(device)
                t = time.perf_counter()
                idx = sampler(xyzi, max(1, n // ratio))[0]
                _sync(device)
                times.append(time.perf_counter() - t)
                idx = idx[idx >= 0]
                distinct.append(int(torch.unique(idx).numel()))
                points = points[idx]
            in_n.append(n)
            kept_n.append(points.shape[0])
            out = detector({"points": points, "batch_size": 1})
            preds += [move_to_device(p, torch.device("cpu")) for p in detector.postprocess(out, None)]
            metas += frame_meta(batch, 1)
    metrics, _ = KittiEvaluator(detector.config.class_names)(preds, metas)
    names = detector.config.class_names
    row = {"frames": len(frames), "points_in_mean": statistics.mean(in_n), "points_kept_mean": statistics.mean(kept_n),
           "distinct_kept_mean": statistics.mean(distinct) if distinct else statistics.mean(kept_n),
           "sample_ms_median": 1e3 * statistics.median(times) if times else 0.0,
           "sample_ms_mean": 1e3 * statistics.mean(times) if times else 0.0}
    for metric in ("3d", "bev"):
        for r in ("R40", "R11"):
            per = {c: metrics.get(f"{c}_{metric}_moderate_{r}") for c in names}
            row[f"{metric}_moderate_{r}"] = per
            vals = [v for v in per.values() if v is not None]
            row[f"mAP_{metric}_moderate_{r}"] = statistics.mean(vals) if vals else None
    return row


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    styles = {"random": ("tab:orange", "o", "-"), "fps": ("tab:blue", "s", "-"), "chunked fps": ("tab:cyan", "s", "-"),
              "anchored, untrained": ("grey", "x", ":"), "casnet": ("tab:green", "^", "-"),
              "casnet, whole cloud": ("tab:red", "v", "-"), "casnet fast": ("tab:olive", "^", "--"),
              "casnet fast, whole cloud": ("tab:purple", "v", "--")}

    def family(method: str) -> str:  # one line per sampler kind: the checkpoints' labels say full or fast only
        return re.sub(r" \(([^)]*)\)", lambda m: " fast" if "fast" in m.group(1) else "", method)

    ref = next((r for r in report["rows"] if r["ratio"] == 1), None)
    for ax, key, title in ((axes[0], "mAP_3d_moderate_R40", "moderate 3D mAP (R40)"),
                           (axes[1], "mAP_bev_moderate_R40", "moderate BEV mAP (R40)")):
        if ref is not None:
            ax.axhline(ref[key], color="grey", ls="--", lw=1, label=f"all points ({ref[key]:.1f})")
        methods = sorted({family(r["method"]) for r in report["rows"] if r["ratio"] > 1})
        for method in methods:
            colour, marker, line = styles.get(method, (None, "d", "-"))
            pts = sorted((r["ratio"], r[key]) for r in report["rows"]
                         if family(r["method"]) == method and r["ratio"] > 1)
            if pts:
                ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=marker, color=colour, ls=line, label=method)
        ax.set_xscale("log", base=2)
        ax.set_xticks([d for d in report["ratios"] if d > 1], [str(d) for d in report["ratios"] if d > 1])
        ax.set_xlabel("sampling ratio D")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"{Path(report.get('detector', 'pointpillars_synth')).stem} behind each sampler, {report['frames']} "
                 f"frames of {Path(report['data']).name} ({report['device']})",
                 fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    from lidarops.config import load_config
    from lidarops.data.detection import DetectionConfig, KittiDetectionDataset, collate_batch
    from lidarops.models import weights
    from lidarops.models.casnet import CASNet, CASNetSampler, load_casnet
    from lidarops.models.samplers import ChunkedFPSSampler, FPSSampler, RandomSampler

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", help="a KITTI-format folder (every frame of --split)")
    p.add_argument("--split", default=None, help="an ImageSets name (default: train and val together)")
    p.add_argument("--casnet", nargs="*", default=[], help="CAS-Net files, one per ratio")
    p.add_argument("--detector", default="pointpillars_synth", help="a shipped name or a checkpoint")
    p.add_argument("--config", default=str(ROOT / "configs/casnet/casnet_pointpillars_synth.yaml"),
                   help="its DATA_CONFIG is the detector's pipeline (field of view, range)")
    p.add_argument("--ratios", type=int, nargs="+", default=[1, 2, 4, 8])
    p.add_argument("--segment-points", type=int, default=8192)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--casnet-dedup", type=int, choices=(0, 1), default=0,
                   help="0: CAS-Net's raw picks, the most confident first, repeats allowed (the paper); 1: distinct")
    p.add_argument("--chunked-fps", action="store_true",
                   help="also FPS in chunks of --segment-points (the paper's FPS)")
    p.add_argument("--anchored-init", action="store_true",
                   help="also an untrained anchored-head CAS-Net at each ratio (where its training starts: FPS "
                        "per segment)")
    p.add_argument("--whole", action="store_true",
                   help="also each anchored-head CAS-Net on the whole cloud (no segments), beside its segmented row")
    p.add_argument("--out")
    p.add_argument("--plot", default=None)
    p.add_argument("--replot", default=None, metavar="JSON", help="only redraw --plot from a report of this script")
    args = p.parse_args(argv)
    if args.replot:
        if not args.plot:
            p.error("--replot needs --plot")
        plot(json.loads(Path(args.replot).read_text()), Path(args.plot))
        return 0
    if not args.data or not args.out:
        p.error("--data and --out are required (unless --replot)")
    device = torch.device(args.device)
    detector_path = Path(args.detector) if Path(args.detector).is_file() else weights.path(args.detector)
    from lidarops.models import load_model

    detector = load_model(detector_path).eval().to(device)
    data_cfg = DetectionConfig.from_openpcdet(load_config(args.config)["DATA_CONFIG"])
    splits = [args.split] if args.split else [s for s in ("train", "val")
                                               if (Path(args.data) / "ImageSets" / f"{s}.txt").is_file()]
    frames = []
    for split in splits:
        ds = KittiDetectionDataset(args.data, split, detector.config.class_names, data_cfg, training=False)
        frames += [collate_batch([ds[i]]) for i in range(len(ds))]
    frames = frames[:args.max_frames] if args.max_frames else frames
    casnets = []  # (ratio, label, path, model): the ratio each was trained for
    for path in args.casnet:
        model = load_casnet(path, device)
        casnets.append((args.segment_points // model.num_out, Path(path).stem, path, model))
    report = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "frames": len(frames), "data": str(args.data), "splits": splits, "detector": str(args.detector),
              "ratios": args.ratios, "command": " ".join(sys.argv), "rows": []}
    for ratio in args.ratios:
        samplers = [("all points", None, None)] if ratio == 1 else \
            [("random", RandomSampler(args.seed), None), ("fps", FPSSampler(), None)]
        if ratio > 1 and args.chunked_fps:
            samplers.append(("chunked fps", ChunkedFPSSampler(args.segment_points), None))
        if ratio > 1 and args.anchored_init:
            torch.manual_seed(args.seed)
            init = CASNet(args.segment_points // ratio, head="anchored").eval().to(device)
            samplers.append(("anchored, untrained", CASNetSampler(init, ratio=ratio, max_points=args.segment_points,
                                                                  dedup=bool(args.casnet_dedup)), None))
        for r, label, path, model in casnets:
            if r == ratio > 1:
                name = "casnet" if sum(c[0] == ratio for c in casnets) == 1 else f"casnet ({label})"
                samplers.append((name, CASNetSampler(model, ratio=ratio, max_points=args.segment_points,
                                                     dedup=bool(args.casnet_dedup)), str(path)))
                if args.whole and model.head_kind == "anchored":
                    samplers.append((f"{name}, whole cloud", CASNetSampler(model, dedup=bool(args.casnet_dedup),
                                                                           whole=True), str(path)))
        for name, sampler, path in samplers:
            row = {"method": name, "ratio": ratio, "checkpoint": path, **run(detector, sampler, ratio, frames, device)}
            report["rows"].append(row)
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(report, indent=1))  # row by row: a cut-short run keeps its rows
            print(f"D={ratio} {name:<24} mAP 3D R40 {row['mAP_3d_moderate_R40']:6.2f}  R11 {row['mAP_3d_moderate_R11']:6.2f}"
                  f"  BEV R40 {row['mAP_bev_moderate_R40']:6.2f}  kept {row['points_kept_mean']:8.0f} ({row['distinct_kept_mean']:.0f} distinct) of "
                  f"{row['points_in_mean']:8.0f}  sampling {row['sample_ms_median']:.2f} ms/frame", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1))
    if args.plot:
        plot(report, Path(args.plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
