"""``lidarops detect``: runs a detector on frames (a KITTI velodyne ``.bin``, a KITTI folder, or frames the
simulator makes on the spot); prints the boxes, writes KITTI result files (``OUT/data/<id>.txt``) and
bird's-eye-view pictures, and prints KITTI AP and the matches per class when the frames have labels.

The model is the shipped PointPillars (:mod:`lidarops.models.weights`) unless ``--checkpoint`` names
another file: a lidarops checkpoint says which model it holds; an OpenPCDet one needs ``--config``.

Examples::

    lidarops detect --scenario driving_city --frames 20 --out det/          # the shipped model, simulated frames
    lidarops detect data/synth/training/velodyne/000123.bin --out det/
    lidarops detect data/synth --split val --checkpoint runs/pp/final.pth --out det/
    lidarops detect kitti/ --split val --checkpoint pointpillar_7728.pth --config pointpillar.yaml --out det/
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from lidarops.cli.errors import CliError, guarded

__all__ = ["register", "detect", "save_detections_png"]


def _load_model(args: argparse.Namespace):
    """(the model in eval mode on its device, the device, the checkpoint's path)."""
    from lidarops.cli._device import resolve_device
    from lidarops.models import load_model, weights

    device = resolve_device(args.device)
    path = Path(args.checkpoint) if args.checkpoint else weights.path()
    if not path.is_file():
        raise CliError(f"checkpoint {path} not found")
    model = load_model(path, config=args.config, map_location="cpu").to(device)
    if args.score_thresh is not None:
        model.config.score_thresh = float(args.score_thresh)
    return model, device, path


def _scan_format(path: Path, fmt: str) -> str:
    """The layout of a scan file: ``--format``, else the name (``*.pcd.bin``: nuScenes, 5 floats per point;
    ``velodyne/*.bin``: KITTI, 4 floats); a loose ``.bin`` whose size fits both layouts is refused, since
    reading one as the other gives a grid of nonsense points without an error."""
    if fmt != "auto":
        return fmt
    if path.name.endswith(".pcd.bin"):
        return "nuscenes"
    if path.parent.name == "velodyne":
        return "kitti"
    size = path.stat().st_size
    fits = [name for name, record in (("kitti", 16), ("nuscenes", 20)) if size % record == 0]
    if len(fits) == 2 and size:
        raise CliError(f"{path}: its {size} bytes fit both KITTI's 4 and nuScenes' 5 floats per point and its name "
                       "says neither (velodyne/*.bin, *.pcd.bin): give --format kitti or --format nuscenes")
    return fits[0] if fits else "kitti"  # the reader names a size that fits neither


def _frames(args: argparse.Namespace) -> Iterator[tuple]:
    """(frame id, Frame, calib, label file or None) of a scenario, a .bin or a KITTI folder; the input is
    checked on the call, before the first frame is asked for."""
    from lidarops.data.formats.kitti import KittiCalib, KittiDataset, read_kitti_frame

    if args.frames is not None and args.frames < 1:  # 0 would mean "every frame" of a folder
        raise CliError(f"--frames must be >= 1 (leave it out for every frame of a folder), got {args.frames}")
    for flag in ("png", "print_frames", "print_boxes"):
        if getattr(args, flag) < 0:
            raise CliError(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    if args.scenario:
        from lidarops.data.synthetic import SyntheticFrames

        source = SyntheticFrames(args.scenario, num_frames=1 if args.frames is None else args.frames, seed=args.seed)
        return ((f"{args.scenario}_{i:06d}", source[i], KittiCalib.default(), None) for i in range(len(source)))
    if not args.input:
        raise CliError("give a .bin file, a KITTI folder, or --scenario NAME")
    path = Path(args.input)
    if not path.exists():
        raise CliError(f"{path} not found")
    if path.is_file():
        if path.suffix != ".bin":
            raise CliError(f"{path}: expected a KITTI velodyne .bin, a nuScenes .pcd.bin or a folder")
        fmt = _scan_format(path, args.format)

        def one():
            if fmt == "nuscenes":  # in lidarops' axes (x forward) with intensity in [0, 1], as the model was trained
                from lidarops.data.formats.nuscenes import read_nuscenes_bin

                frame = read_nuscenes_bin(path, x_forward=True, normalize_intensity=True)
                yield path.name[:-len(".pcd.bin")] if path.name.endswith(".pcd.bin") else path.stem, frame, \
                    KittiCalib.default(), None
                return
            frame = read_kitti_frame(path)
            label = path.parent.parent / "label_2" / f"{path.stem}.txt"
            yield path.stem, frame, frame.meta.get("calib") or KittiCalib.default(), label if label.is_file() else None

        return one()
    data = KittiDataset(path, image_set=args.split)

    def folder():
        for i in range(min(len(data), args.frames) if args.frames else len(data)):
            frame = data[i]
            label = data.split_dir / "label_2" / f"{data.ids[i]}.txt"
            yield data.ids[i], frame, frame.meta.get("calib") or KittiCalib.default(), label if label.is_file() else None

    return folder()


def save_detections_png(path: Path, points: np.ndarray, pred: dict, class_names: Sequence[str], gt_boxes=None,
                        gt_names=None, title: str = "") -> Path:
    """A bird's-eye view: points, ground-truth boxes (dashed) and detections (solid, with scores).

    Args:
        path: the PNG to write (its folder is created).
        points (ndarray[N, >=3]): the frame's points.
        pred: ``boxes (K, 7)``, ``labels (K,)`` (1-based into ``class_names``), ``scores (K,)``.
        gt_boxes (ndarray[M, 7] | None), gt_names (list[str] | None): the labelled boxes.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    from lidarops.data.frame import CLASS_COLORS
    from lidarops.data.geometry import box_corners
    from lidarops.data.viz import new_figure

    fig = new_figure(9.0, 9.0)
    ax = fig.add_subplot(1, 1, 1)
    p = points[(points[:, 0] > -5) & (points[:, 0] < 75) & (np.abs(points[:, 1]) < 42)]
    # grey by height: the ground light, objects and structures darker
    ax.scatter(p[:, 0], p[:, 1], s=0.4, c=p[:, 2], cmap="Greys", vmin=-3.5, vmax=0.0, linewidths=0, rasterized=True)

    def draw(box, color, dashed, text=None):
        bottom = box_corners(box)[0, :4, :2]  # counter-clockwise from front-left: 0 and 3 span the front face
        ax.add_patch(Polygon(bottom, closed=True, fill=False, edgecolor=color, lw=1.0 if dashed else 1.4,
                             linestyle="--" if dashed else "-"))
        if not dashed:  # the heading: centre to the middle of the front face
            front = bottom[[0, 3]].mean(0)
            ax.plot([box[0], front[0]], [box[1], front[1]], color=color, lw=1.0)
        if text:
            ax.text(box[0] + box[3] / 2 + 0.3, box[1], text, color=color, fontsize=6)

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

    from lidarops.cli.eval import match_summary
    from lidarops.data.formats.kitti import boxes_to_kitti_labels, kitti_fov_mask, read_label, write_label
    from lidarops.eval import kitti as kitti_eval

    if args.score_thresh is not None and not 0 <= args.score_thresh < 1:  # NaN too
        raise CliError(f"--score-thresh must be in [0, 1) (a sigmoid score), got {args.score_thresh}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; give a folder")
    frames = _frames(args)
    model, device, ckpt = _load_model(args)
    names = model.config.class_names
    gt_annos, dt_annos, shown = [], [], 0
    labelled = True
    for frame_id, frame, calib, label in frames:
        points = frame.points if args.no_fov else frame.points[kitti_fov_mask(frame.points, calib)]
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
        print(match_summary(gt_annos, dt_annos, names))
    return 0


def register(subparsers) -> None:
    """Adds ``detect`` to the ``lidarops`` parser."""
    d = subparsers.add_parser("detect", help="detect 3D boxes in frames (a .bin, a KITTI folder or a scenario)",
                              description="Run a detector (default: the shipped PointPillars) on frames: prints "
                                          "the boxes, writes KITTI result files and bird's-eye-view PNGs, and "
                                          "prints KITTI AP when the frames have labels.")
    d.add_argument("input", nargs="?", help="a KITTI velodyne .bin or a KITTI folder")
    d.add_argument("--scenario", default=None, help="simulate frames of this scenario instead (e.g. driving_city)")
    d.add_argument("--frames", type=int, default=None, help="number of frames (scenario: default 1; folder: all)")
    d.add_argument("--format", choices=("auto", "kitti", "nuscenes"), default="auto",
                   help="layout of a scan file: KITTI (4 floats per point) or nuScenes (5); default from the name "
                        "(*.pcd.bin: nuScenes, velodyne/*.bin: KITTI)")
    d.add_argument("--seed", type=int, default=1000, help="scenario seed (default 1000)")
    d.add_argument("--split", default=None, help="KITTI folder: an ImageSets name (train, val)")
    d.add_argument("--checkpoint", default=None, help="checkpoint (default: the shipped pointpillars_synth)")
    d.add_argument("--config", default=None, help="config for an OpenPCDet checkpoint (lidarops ones carry theirs)")
    d.add_argument("--out", default="detections", help="output folder (default ./detections)")
    d.add_argument("--score-thresh", type=float, default=None)
    d.add_argument("--device", default="auto", help="auto (default: cuda when available and built), cpu, cuda")
    d.add_argument("--no-fov", action="store_true", help="keep points outside the camera's field of view")
    d.add_argument("--png", type=int, default=1, help="frames to draw (default 1)")
    d.add_argument("--print-frames", type=int, default=3)
    d.add_argument("--print-boxes", type=int, default=10)
    d.set_defaults(func=guarded("detect", detect))
