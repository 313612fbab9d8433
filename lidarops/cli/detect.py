"""``lidarops train``, ``lidarops detect`` and ``lidarops eval``: the detector from the command line.

Examples::

    lidarops data synth --scenario driving_city driving_highway --frames 2000 1000 --workers 16 --out data/synth
    lidarops train --config configs/pointpillars_synth.yaml --data data/synth --out runs/pp --amp bf16
    torchrun --standalone --nproc_per_node=2 -m lidarops train --config ... --out runs/pp2   # 2 GPUs
    lidarops detect data/synth/training/velodyne/000123.bin --out det/        # the shipped model
    lidarops detect --scenario driving_city --frames 20 --checkpoint runs/pp/final.pth --out det/
    lidarops eval --results det/data --labels data/synth/training/label_2 --split data/synth/ImageSets/val.txt
"""
from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["register", "train", "detect", "evaluate_results"]


class CliError(Exception):
    """An error reported as one line (exit code 2)."""


def _guarded(name: str, fn):
    def run(args: argparse.Namespace) -> int:
        from lidarops.models.config import ConfigError

        try:
            return fn(args)
        except (CliError, FileNotFoundError, FileExistsError, NotADirectoryError, ValueError, ConfigError,
                ImportError) as e:
            print(f"lidarops {name}: error: {e}", file=sys.stderr)
            return 2

    return run


# ---------------------------------------------------------------------------------------------
# train
# ---------------------------------------------------------------------------------------------
def train(args: argparse.Namespace) -> int:
    """Trains a detector from a config (OpenPCDet schema) on a KITTI-format folder."""
    from lidarops.data.detection import DetectionConfig, collate_batch, train_val_datasets
    from lidarops.eval.kitti import KittiEvaluator
    from lidarops.models.config import load_config
    from lidarops.models.detector import PointPillars
    from lidarops.train import TrainConfig, fit

    cfg = load_config(args.config)
    model = PointPillars(cfg)
    data_root = Path(args.data or cfg.get("DATA_CONFIG", {}).get("DATA_PATH", ""))
    if not data_root.exists():
        raise CliError(f"data folder {data_root} not found (give --data, or DATA_CONFIG.DATA_PATH in the config); "
                       "make one with: lidarops data synth --out DIR ...")
    data_cfg = DetectionConfig.from_openpcdet(cfg.get("DATA_CONFIG", {}))
    names = model.config.class_names
    gt_database = None
    if args.gt_database_frames:  # OpenPCDet builds it from every training frame; a subset is quicker
        from lidarops.data.detection import KittiDetectionDataset, build_gt_database

        ids = KittiDetectionDataset(data_root, "train", names, data_cfg).ids[:args.gt_database_frames]
        gt_database = build_gt_database(data_root, ids, names)
    train_set, val_set = train_val_datasets(data_root, names, data_cfg, seed=args.seed or 0, gt_database=gt_database)
    if args.max_train_frames:
        train_set.ids = train_set.ids[:args.max_train_frames]
    if args.max_val_frames and val_set is not None:
        val_set.ids = val_set.ids[:args.max_val_frames]
    overrides = {k: v for k, v in dict(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, amp=args.amp,
                                       num_workers=args.workers, seed=args.seed, eval_every=args.eval_every,
                                       max_minutes=args.max_minutes, max_steps=args.max_steps, device=args.device,
                                       sync_bn=args.sync_bn or None,
                                       progress=False if args.no_progress else None).items()
                 if v is not None}
    config = TrainConfig.from_openpcdet(cfg.get("OPTIMIZATION", {}), **overrides)
    extra = {"model_config": model.config.to_dict(), "class_names": list(names),
             "config_path": str(args.config), "data_recipe": train_set.recipe or {"root": str(data_root)},
             "train_command": "lidarops " + " ".join(shlex.quote(a) for a in sys.argv[1:])}
    result = fit(model, train_set, collate_batch, config, args.out, val_dataset=val_set if len(val_set or []) else None,
                 evaluator=KittiEvaluator(names), resume=args.resume, extra_checkpoint=extra)
    if result.metrics:
        keys = [f"{n}_3d_moderate_R40" for n in names] + [f"{n}_bev_moderate_R40" for n in names]
        print("moderate AP (R40): " + ", ".join(f"{k.replace('_moderate_R40', '')} {result.metrics[k]:.1f}"
                                                  for k in keys if k in result.metrics))
    state = "finished" if result.finished else f"stopped ({result.stop_reason}); continue with --resume"
    print(f"{state}: {result.global_step} steps, {result.frames_per_s_total:.1f} frames/s; {result.checkpoint}")
    return 0


# ---------------------------------------------------------------------------------------------
# detect
# ---------------------------------------------------------------------------------------------
def _load_model(args: argparse.Namespace):
    import torch

    from lidarops.models import weights
    from lidarops.models.detector import PointPillars

    device = args.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise CliError(f"--device {device}: this torch ({torch.__version__}) sees no CUDA device; use --device cpu")
    path = Path(args.checkpoint) if args.checkpoint else weights.path()
    if not path.is_file():
        raise CliError(f"checkpoint {path} not found")
    model = PointPillars.from_checkpoint(path, config=args.config, map_location="cpu").to(device).eval()
    if args.score_thresh is not None:
        if not 0 <= args.score_thresh < 1:  # NaN too
            raise CliError(f"--score-thresh must be in [0, 1) (a sigmoid score), got {args.score_thresh}")
        model.config.score_thresh = float(args.score_thresh)
    return model, device, path


def _frames(args: argparse.Namespace):
    """(frame_id, Frame, calib, label file or None) from a .bin, a KITTI folder or a scenario."""
    from lidarops.data.formats.kitti import KittiCalib, KittiDataset, read_kitti_frame

    if args.scenario:
        from lidarops.data.synthetic import SyntheticFrames

        source = SyntheticFrames(args.scenario, num_frames=args.frames, seed=args.seed)
        for i in range(len(source)):
            yield f"{args.scenario}_{i:06d}", source[i], KittiCalib.default(), None
        return
    if not args.input:
        raise CliError("give a .bin file, a KITTI folder, or --scenario NAME")
    path = Path(args.input)
    if not path.exists():
        raise CliError(f"{path} not found")
    if path.is_file():
        if path.suffix != ".bin":
            raise CliError(f"{path}: expected a KITTI velodyne .bin file or a folder")
        frame = read_kitti_frame(path)
        label = path.parent.parent / "label_2" / f"{path.stem}.txt"
        yield path.stem, frame, frame.meta.get("calib") or KittiCalib.default(), label if label.is_file() else None
        return
    data = KittiDataset(path, image_set=args.split)
    for i in range(min(len(data), args.frames) if args.frames else len(data)):
        frame = data[i]
        label = data.split_dir / "label_2" / f"{data.ids[i]}.txt"
        yield data.ids[i], frame, frame.meta.get("calib") or KittiCalib.default(), label if label.is_file() else None


def _fov(points: np.ndarray, calib) -> np.ndarray:
    from lidarops.data.formats.kitti import kitti_fov_mask

    return points[kitti_fov_mask(points, calib)]


def save_detections_png(path: Path, points: np.ndarray, pred: dict, class_names, gt_boxes=None, gt_names=None,
                        title: str = "") -> Path:
    """A bird's-eye view: points, ground-truth boxes (dashed) and detections (solid, with scores)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    from lidarops.data.frame import CLASS_COLORS
    from lidarops.data.viz import new_figure

    fig = new_figure(9.0, 9.0)
    ax = fig.add_subplot(1, 1, 1)
    p = points[(points[:, 0] > -5) & (points[:, 0] < 75) & (np.abs(points[:, 1]) < 42)]
    # grey by height: the ground light, objects and structures darker
    ax.scatter(p[:, 0], p[:, 1], s=0.4, c=p[:, 2], cmap="Greys", vmin=-3.5, vmax=0.0, linewidths=0, rasterized=True)

    def draw(box, color, dashed, text=None):
        c, s = np.cos(box[6]), np.sin(box[6])
        hx, hy = box[3] / 2, box[4] / 2
        corners = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]]) @ np.array([[c, s], [-s, c]]) + box[:2]
        ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor=color, lw=1.0 if dashed else 1.4,
                             linestyle="--" if dashed else "-"))
        if not dashed:
            ax.plot([box[0], box[0] + c * hx], [box[1], box[1] + s * hx], color=color, lw=1.0)
        if text:
            ax.text(box[0] + hx + 0.3, box[1], text, color=color, fontsize=6)

    seen = {}
    for box, name in zip(gt_boxes if gt_boxes is not None else [], gt_names if gt_names is not None else []):
        draw(box, CLASS_COLORS.get(name, "black"), True)
    for box, label, score in zip(pred["boxes"], pred["labels"], pred["scores"]):
        name = class_names[int(label) - 1]
        seen[name] = CLASS_COLORS.get(name, "black")
        draw(box, seen[name], False, f"{score:.2f}")
    ax.plot([0], [0], marker="^", color="black", markersize=6)
    ax.set_xlim(-2, 72)
    ax.set_ylim(-40, 40)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, forward)")
    ax.set_ylabel("y (m, left)")
    handles = [Line2D([0], [0], color=c, lw=2, label=n) for n, c in sorted(seen.items())]
    handles += [Line2D([0], [0], color="gray", lw=1, ls="--", label="ground truth"),
                Line2D([0], [0], color="gray", lw=1.4, label="detection (score)")]
    ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.85)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def detect(args: argparse.Namespace) -> int:
    """Runs a detector on frames; prints boxes, writes KITTI result files and BEV pictures, and scores
    them when the frames have labels."""
    import torch

    from lidarops.data.formats.kitti import boxes_to_kitti_labels, kitti_fov_mask, read_label, write_label
    from lidarops.eval import kitti as kitti_eval

    model, device, ckpt = _load_model(args)
    names = model.config.class_names
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; give a folder")
    gt_annos, dt_annos, shown = [], [], 0
    labelled = True
    for frame_id, frame, calib, label in _frames(args):
        points = frame.points if args.no_fov else _fov(frame.points, calib)
        batch = {"points": torch.from_numpy(np.concatenate([np.zeros((len(points), 1), np.float32), points], 1))
                 .to(device), "batch_size": 1}
        pred = {k: v.detach().cpu().numpy() for k, v in model.predict(batch)[0].items()}
        # KITTI results cover the camera's view: boxes whose centre projects into the image
        keep = kitti_fov_mask(pred["boxes"][:, :3].astype(np.float64), calib) if len(pred["boxes"]) else \
            np.zeros(0, bool)
        pred = {k: v[keep] for k, v in pred.items()}
        det_names = [names[int(k) - 1] for k in pred["labels"]]
        rows = boxes_to_kitti_labels(pred["boxes"], det_names, calib, score=pred["scores"])
        write_label(out / "data" / f"{frame_id}.txt", rows)
        dt_annos.append(kitti_eval.annos_from_labels(rows))
        if args.scenario:  # the labels write_kitti_frame would write for it
            gt_annos.append(kitti_eval.frame_annos(frame, calib))
        elif label is not None:  # every object of the label file, DontCare and Vans included
            gt_annos.append(kitti_eval.annos_from_labels(read_label(label)))
        else:
            labelled = False
        if shown < args.print_frames:
            print(f"{frame_id}: {len(pred['boxes'])} detection(s), {frame.num_boxes} labelled box(es)")
            for name, score, box in list(zip(det_names, pred["scores"], pred["boxes"]))[:args.print_boxes]:
                heading = (box[6] + np.pi) % (2 * np.pi) - np.pi  # the model's range is OpenPCDet's; print [-pi, pi)
                print(f"  {name:<11} {score:5.2f}  x {box[0]:6.2f} y {box[1]:6.2f} z {box[2]:5.2f}  "
                      f"dx {box[3]:4.2f} dy {box[4]:4.2f} dz {box[5]:4.2f}  heading {heading:5.2f}")
        if shown < args.png:
            gt_mask = np.isin(frame.labels, [i for i, n in enumerate(frame.class_names) if n in names])
            png = save_detections_png(out / f"{frame_id}.png", frame.points, pred, names, frame.boxes[gt_mask],
                                      [frame.class_names[i] for i in frame.labels[gt_mask]],
                                      title=f"{frame_id}: {len(pred['boxes'])} detections (solid), "
                                            f"{int(gt_mask.sum())} labelled {'/'.join(names)} (dashed)")
            print(f"  wrote {png}")
        shown += 1
    if not shown:
        raise CliError("no frames to run on")
    print(f"wrote {shown} KITTI result file(s) to {out / 'data'} (checkpoint {ckpt})")
    if labelled and gt_annos:
        text, results = kitti_eval.evaluate(gt_annos, dt_annos, names)
        print(text)
        (out / "eval.json").write_text(json.dumps(results, indent=1))
        print(_match_summary(gt_annos, dt_annos, names))
    return 0


def _match_summary(gt_annos: list, dt_annos: list, names) -> str:
    """Found / labelled objects per class at KITTI's 3D overlap (0.7 Car, 0.5 others), every labelled
    object counted whatever its difficulty; the line a few frames are better read by than an AP (below 41
    objects of a class, R40 cannot reach 100)."""
    import lidarops
    from lidarops.eval.kitti import iou_boxes

    def lidar_boxes(anno, keep):
        return iou_boxes(anno["location"][keep], anno["dimensions"][keep], anno["rotation_y"][keep])

    parts = []
    for name in names:
        need = 0.7 if name in ("Car", "Van", "Truck", "Bus") else 0.5
        found = labelled = spare = 0
        for gt, dt in zip(gt_annos, dt_annos):
            g, d = gt["name"] == name, dt["name"] == name
            labelled += int(g.sum())
            if not (g.any() and d.any()):
                spare += int(d.sum())
                continue
            iou = lidarops.box_iou_3d(lidar_boxes(gt, g), lidar_boxes(dt, d)).numpy()  # (gts, detections)
            taken = np.zeros(iou.shape[0], bool)
            for j in np.argsort(-dt["score"][d], kind="stable"):  # the best detections take their gts first
                cand = np.where(taken, -1.0, iou[:, j])
                i = int(np.argmax(cand))
                if cand[i] >= need:
                    taken[i] = True
                    found += 1
                else:
                    spare += 1
        parts.append(f"{name}: {found} of {labelled} labelled found (3D IoU >= {need}), {spare} other detections")
    return "matches: " + "; ".join(parts)


def evaluate_results(args: argparse.Namespace) -> int:
    """Scores a folder of KITTI result files against label files."""
    from lidarops.eval import kitti as kitti_eval

    results_dir, labels_dir = Path(args.results), Path(args.labels)
    for p, what in ((results_dir, "--results"), (labels_dir, "--labels")):
        if not p.is_dir():
            raise CliError(f"{what} {p} is not a folder")
    if args.split:
        split = Path(args.split)
        if not split.is_file():
            raise CliError(f"--split {split} not found")
        ids = [line.strip() for line in split.read_text().splitlines() if line.strip()]
    else:
        ids = sorted(p.stem for p in results_dir.glob("*.txt"))
    missing = [i for i in ids if not (results_dir / f"{i}.txt").is_file()]
    if missing:
        raise CliError(f"{len(missing)} frame(s) have no result file in {results_dir} (e.g. {missing[0]}.txt); "
                       "a frame without detections needs an empty file")
    gt = kitti_eval.read_annos(labels_dir, ids)
    dt = kitti_eval.read_annos(results_dir, ids)
    text, results = kitti_eval.evaluate(gt, dt, args.classes)
    print(text)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
        print(f"wrote {args.json}")
    return 0


def register(subparsers) -> None:
    """Adds ``train``, ``detect`` and ``eval`` to the ``lidarops`` parser."""
    t = subparsers.add_parser("train", help="train a detector (PointPillars) on a KITTI-format folder",
                              description="Train a detector from an OpenPCDet-schema config (e.g. configs/"
                                          "pointpillars_synth.yaml) on a KITTI-format folder. Under torchrun it "
                                          "runs DistributedDataParallel, one process per GPU.")
    t.add_argument("--config", required=True, help="YAML config (OpenPCDet schema)")
    t.add_argument("--data", default=None, help="KITTI-format folder (default: the config's DATA_PATH)")
    t.add_argument("--out", required=True, help="run folder: checkpoints, log.csv, evaluations")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from latest.pth")
    t.add_argument("--epochs", type=int, default=None)
    t.add_argument("--batch-size", type=int, default=None, help="frames per step and per process")
    t.add_argument("--lr", type=float, default=None)
    t.add_argument("--amp", choices=("none", "bf16", "fp16"), default=None, help="mixed precision")
    t.add_argument("--workers", type=int, default=None, help="DataLoader workers per process")
    t.add_argument("--eval-every", type=int, default=None, help="epochs between evaluations (0: only at the end)")
    t.add_argument("--max-minutes", type=float, default=None, help="stop with a checkpoint after this long")
    t.add_argument("--max-steps", type=int, default=None, help="stop with a checkpoint after this many steps")
    t.add_argument("--max-train-frames", type=int, default=None, help="use only the first N training frames")
    t.add_argument("--max-val-frames", type=int, default=None, help="evaluate on the first N validation frames")
    t.add_argument("--gt-database-frames", type=int, default=None,
                   help="build the gt-sampling database from the first N training frames (default: all)")
    t.add_argument("--seed", type=int, default=None)
    t.add_argument("--device", default=None, help="auto (default), cpu, cuda")
    t.add_argument("--sync-bn", action="store_true", help="SyncBatchNorm under multi-GPU DDP")
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(func=_guarded("train", train))

    d = subparsers.add_parser("detect", help="detect 3D boxes in frames (a .bin, a KITTI folder or a scenario)",
                              description="Run a detector (default: the shipped PointPillars) on frames: prints "
                                          "the boxes, writes KITTI result files and bird's-eye-view PNGs, and "
                                          "prints KITTI AP when the frames have labels.")
    d.add_argument("input", nargs="?", help="a KITTI velodyne .bin or a KITTI folder")
    d.add_argument("--scenario", default=None, help="simulate frames of this scenario instead (e.g. driving_city)")
    d.add_argument("--frames", type=int, default=None, help="number of frames (scenario: default 1; folder: all)")
    d.add_argument("--seed", type=int, default=1000, help="scenario seed (default 1000)")
    d.add_argument("--split", default=None, help="KITTI folder: an ImageSets name (train, val)")
    d.add_argument("--checkpoint", default=None, help="checkpoint (default: the shipped pointpillars_synth)")
    d.add_argument("--config", default=None, help="config for an OpenPCDet checkpoint (lidarops ones carry theirs)")
    d.add_argument("--out", default="detections", help="output folder (default ./detections)")
    d.add_argument("--score-thresh", type=float, default=None)
    d.add_argument("--device", default="auto")
    d.add_argument("--no-fov", action="store_true", help="keep points outside the camera's field of view")
    d.add_argument("--png", type=int, default=1, help="frames to draw (default 1)")
    d.add_argument("--print-frames", type=int, default=3)
    d.add_argument("--print-boxes", type=int, default=10)
    d.set_defaults(func=_guarded("detect", lambda a: detect(_scenario_defaults(a))))

    e = subparsers.add_parser("eval", help="score KITTI result files against labels (KITTI AP)",
                              description="KITTI's object evaluation (AP R11/R40 of bbox, BEV, 3D, AOS) of a "
                                          "folder of result files against a folder of label files.")
    e.add_argument("--results", required=True, help="folder of <id>.txt result files (16 fields)")
    e.add_argument("--labels", required=True, help="folder of <id>.txt label files (label_2)")
    e.add_argument("--split", default=None, help="file listing the frame ids (default: every result file)")
    e.add_argument("--classes", nargs="+", default=["Car", "Pedestrian", "Cyclist"])
    e.add_argument("--json", default=None, help="also write the results dict here")
    e.set_defaults(func=_guarded("eval", evaluate_results))


def _scenario_defaults(args: argparse.Namespace) -> Any:
    if args.scenario and args.frames is None:
        args.frames = 1
    return args
