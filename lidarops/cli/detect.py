"""``lidarops detect``: runs a detector on frames (a KITTI velodyne ``.bin``, a KITTI folder, or frames the
simulator makes on the spot); prints the boxes, writes KITTI result files (``OUT/data/<id>.txt``) and
bird's-eye-view pictures, and prints KITTI AP and the matches per class when the frames have labels.

The model is a shipped PointPillars (:mod:`lidarops.models.weights`) unless ``--checkpoint`` names another
file or shipped name: ``pointpillars_synth_real`` (trained on the simulator with its realism profile) for
scans, ``pointpillars_synth`` for the simulator's ray-cast frames (``--scenario``, or a folder ``data synth``
wrote without ``--realism``). A lidarops checkpoint says which model it holds; an OpenPCDet one needs
``--config``.

Behind a sampler (issue 37): ``--sampler random|fps|chunked-fps|casnet --ratio D`` keeps ``N // D`` of the
``N`` points of each frame the detector would see (after the field-of-view filter), every channel, with the
samplers of ``lidarops sample``, and runs the detector on them; each frame's line, the summary and
``detect.json`` give the points in and kept and the sampling time. ``--ratio 1`` keeps every point (the
reference). ``casnet`` reads ``--sampler-checkpoint`` (a file or a shipped name), by default the shipped
``casnet_pointpillars_d8`` when there is one (``casnet_pointpillars_real_d8`` in front of
``pointpillars_synth_real``).

Examples::

    lidarops detect --scenario driving_city --frames 20 --out det/          # the shipped model, simulated frames
    lidarops detect data/synth/training/velodyne/000123.bin --out det/
    lidarops detect data/synth --split val --checkpoint runs/pp/final.pth --out det/
    lidarops detect kitti/ --split val --checkpoint pointpillar_7728.pth --config pointpillar.yaml --out det/
    lidarops detect --scenario driving_city --frames 20 --sampler fps --ratio 8 --out det_fps8/
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from lidarops._progress import progress_bar
from lidarops.cli.data import _realism_arg
from lidarops.cli.errors import CliError, guarded
from lidarops.cli.sample import SHIPPED_CASNET  # --sampler casnet without --sampler-checkpoint
from lidarops.conventions import HELD_OUT_SEED

__all__ = ["register", "detect", "save_detections_png"]

#: --sampler casnet without --sampler-checkpoint in front of pointpillars_synth_real (docs/casnet.md)
SHIPPED_CASNET_REAL = "casnet_pointpillars_real_d8"

_CASNET_FILES = ("a CAS-Net file of CASNet.save, a lidarops train checkpoint of CASNetPointNet / CASNetPointPillars, "
                 "or a shipped name")


@dataclass
class _Sampling:
    """What ``--sampler`` asks for: the method (``lidarops sample``'s names), ``D``, the random sampler's
    seed, and the CAS-Net checkpoint (a file, a shipped one resolved to its file)."""

    method: str
    ratio: int
    seed: int
    checkpoint: "str | None"

    def record(self) -> dict:
        """What ``detect.json`` says about the sampler."""
        return {"method": self.method, "ratio": self.ratio, **({"seed": self.seed} if self.method == "random" else {}),
                **({"checkpoint": self.checkpoint} if self.checkpoint else {})}


def _sampling(args: argparse.Namespace) -> "_Sampling | None":
    """The checked ``--sampler``, ``--ratio``, ``--sampler-seed`` and ``--sampler-checkpoint``; None without
    ``--sampler`` (then the other three must be left out too)."""
    from lidarops.cli.sample import METHODS, _positive

    if args.sampler is None:
        for flag, value in (("--ratio", args.ratio), ("--sampler-seed", args.sampler_seed),
                            ("--sampler-checkpoint", args.sampler_checkpoint)):
            if value is not None:
                raise CliError(f"{flag} {value} needs --sampler ({flag} is the sampler's: --sampler "
                               f"{'|'.join(METHODS)} {flag} ...)")
        return None
    if args.sampler not in METHODS:
        raise CliError(f"--sampler must be one of {', '.join(METHODS)}, got {args.sampler!r}")
    ratio = _positive(args.ratio, "--ratio") if args.ratio is not None else 8
    seed = 0
    if args.sampler_seed is not None:
        try:
            seed = int(args.sampler_seed, 10)
        except (TypeError, ValueError):
            seed = -1
        if not 0 <= seed < 2**63:
            raise CliError(f"--sampler-seed must be an int in [0, 2^63), got {args.sampler_seed!r}")
    checkpoint = args.sampler_checkpoint
    if checkpoint is not None and args.sampler != "casnet":
        raise CliError(f"--sampler-checkpoint {checkpoint} is a CAS-Net's, for --sampler casnet only (got --sampler "
                       f"{args.sampler})")
    if args.sampler == "casnet":
        from lidarops.models import weights

        shipped = weights.available()
        if checkpoint is None:
            # the shipped sampler trained in front of the shipped detector that runs, when there is one
            real = (args.checkpoint or _default_checkpoint(args)) == SHIPPED_REAL and SHIPPED_CASNET_REAL in shipped
            checkpoint = SHIPPED_CASNET_REAL if real else SHIPPED_CASNET
            if checkpoint not in shipped:
                raise CliError(f"--sampler casnet: the shipped detection CAS-Net ({SHIPPED_CASNET}) is missing; give "
                               f"--sampler-checkpoint: {_CASNET_FILES}")
        if not Path(checkpoint).is_file():
            if checkpoint not in shipped:
                why = "is a directory" if Path(checkpoint).is_dir() else "not found"
                raise CliError(f"--sampler-checkpoint {checkpoint} {why}: give {_CASNET_FILES} (shipped: "
                               f"{', '.join(shipped) or 'none'})")
            checkpoint = str(weights.path(checkpoint))
    return _Sampling(args.sampler, ratio, seed, checkpoint)


def _build_sampler(sampling: _Sampling, device):
    """``lidarops sample``'s sampler for ``sampling`` on ``device``; a CAS-Net checkpoint that cannot be read
    is a one-line error naming ``--sampler-checkpoint``."""
    from lidarops.cli.sample import _sampler

    try:
        return _sampler(sampling.method, sampling.seed, sampling.checkpoint, device)
    except (ValueError, OSError) as e:
        if sampling.method != "casnet":
            raise
        text = str(e)  # sample's messages name its own flag, --checkpoint
        text = "--sampler-" + text[2:] if text.startswith("--checkpoint ") else \
            f"--sampler-checkpoint {sampling.checkpoint}: {text}"
        raise CliError(text) from None


#: the shipped detector for real scans, and the one for the simulator's ray-cast frames (docs/detector.md)
SHIPPED_REAL, SHIPPED_CAST = "pointpillars_synth_real", "pointpillars_synth"


def _default_checkpoint(args: argparse.Namespace) -> str:
    """The shipped detector for the input: the simulator's ray-cast frames (``--scenario`` without ``--realism``,
    or a ``data synth`` folder made without it) get the model trained on them; everything else, a user's own scans
    above all, the model trained for real scans."""
    if args.scenario:
        return SHIPPED_REAL if getattr(args, "realism", None) else SHIPPED_CAST
    recipe = Path(args.input) / "recipe.json" if args.input else None
    if recipe is not None and recipe.is_file():
        try:
            if json.loads(recipe.read_text()).get("realism") is None:
                return SHIPPED_CAST
        except (OSError, ValueError, AttributeError):
            pass
    return SHIPPED_REAL


def _load_model(args: argparse.Namespace):
    """(the model in eval mode on its device, the device, the checkpoint's path)."""
    from lidarops.cli._device import resolve_device
    from lidarops.models import load_model, weights

    device = resolve_device(args.device)
    name = args.checkpoint or _default_checkpoint(args)
    path = Path(name)
    if not path.is_file() and name in weights.available():  # a shipped name
        path = weights.path(name)
    if not args.checkpoint:
        print(f"model: the shipped {name} ({'for real scans' if name == SHIPPED_REAL else 'for ray-cast simulated frames'}"
              f"; --checkpoint {SHIPPED_CAST if name == SHIPPED_REAL else SHIPPED_REAL} for "
              f"{'the simulator without --realism' if name == SHIPPED_REAL else 'real scans'})")
    if not path.is_file():
        raise CliError(f"checkpoint {path} not found (shipped: {', '.join(weights.available())})")
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


def _recipe_sources(recipe) -> list[dict]:
    """The simulated sources of a ``data synth`` recipe: scenario, seed, first frame id, frames, and what
    else decides a frame (sensor, object counts, frames per scene)."""
    if not isinstance(recipe, dict):
        return []
    same = {k: recipe.get(k) for k in ("sensor", "object_counts")}
    same["frames_per_scene"] = recipe.get("frames_per_scene", 1)
    return [{**same, "scenario": e.get("scenario"), "seed": e.get("seed"), "first_id": e.get("first_id", 0),
             "frames": e.get("frames", 0)} for e in recipe.get("scenarios") or [] if isinstance(e, dict)]


def _in_recipe(recipe, scenario: str, seed: int, index: int, sensor=None, object_counts=None,
               frames_per_scene: int = 1) -> bool:
    """Whether frame ``index`` of (scenario, seed) with these settings is one of ``recipe``'s frames (the
    simulator's frames are functions of exactly these)."""
    return any(src["scenario"] == scenario and src["seed"] == seed and 0 <= index < src["frames"]
               and src["sensor"] == sensor and src["object_counts"] == object_counts
               and src["frames_per_scene"] == frames_per_scene for src in _recipe_sources(recipe))


def _trained_ids(args: argparse.Namespace, model_recipe, ids: Sequence[str]) -> list[str]:
    """The frame ids among ``ids`` that are frames of the model's data recipe (it was trained or validated
    on them): a simulated ``--scenario`` run, or a folder ``data synth`` wrote (its ``recipe.json``)."""
    if not model_recipe:
        return []
    if args.scenario:
        return [i for k, i in enumerate(ids) if _in_recipe(model_recipe, args.scenario, args.seed, k)]
    if not args.input or not (Path(args.input) / "recipe.json").is_file():
        return []
    try:
        folder = json.loads((Path(args.input) / "recipe.json").read_text())
    except (OSError, ValueError):
        return []
    hits = []
    for frame_id in ids:
        if not frame_id.isdigit():
            continue
        for src in _recipe_sources(folder):
            index = int(frame_id) - int(src["first_id"] or 0)
            if 0 <= index < src["frames"] and _in_recipe(model_recipe, src["scenario"], src["seed"], index,
                                                         src["sensor"], src["object_counts"], src["frames_per_scene"]):
                hits.append(frame_id)
                break
    return hits


def _frame_count(args: argparse.Namespace) -> int | None:
    if args.scenario:
        return 1 if args.frames is None else args.frames
    return args.frames


def _frames(args: argparse.Namespace) -> Iterator[tuple]:
    """(frame id, Frame, calib, label file or None) of a scenario, a .bin or a KITTI folder; the input is
    checked on the call, before the first frame is asked for."""
    from lidarops.data.formats.kitti import KittiCalib, KittiDataset, read_kitti_frame

    if args.frames is not None and args.frames < 1:  # 0 would mean "every frame" of a folder
        raise CliError(f"--frames must be >= 1 (leave it out for every frame of a folder), got {args.frames}")
    for flag in ("png", "print_frames", "print_boxes"):
        if getattr(args, flag) < 0:
            raise CliError(f"--{flag.replace('_', '-')} must be >= 0, got {getattr(args, flag)}")
    if not 0 <= args.draw_score <= 1:  # NaN too
        raise CliError(f"--draw-score must be a score in [0, 1], got {args.draw_score}")
    if args.scenario:
        from lidarops.data.synthetic import SyntheticFrames

        source = SyntheticFrames(args.scenario, num_frames=1 if args.frames is None else args.frames, seed=args.seed,
                                 realism=getattr(args, "realism", None))
        return ((f"{args.scenario}_{i:06d}", source[i], KittiCalib.default(), None) for i in range(len(source)))
    if getattr(args, "realism", None):
        raise CliError("--realism makes --scenario frames; the frames of a file or folder are already made")
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
                        gt_names=None, title: str = "", other_boxes=None, score_floor: float = 0.0) -> Path:
    """A bird's-eye view: points shaded by height (with its key), ground-truth boxes (dashed), other labelled
    boxes that are not counted (dotted grey: out of the model's range or in no KITTI difficulty) and
    detections (solid) scoring at least ``score_floor``, each score written where it does not cover another.

    Args:
        path: the PNG to write (its folder is created).
        points (ndarray[N, >=3]): the frame's points.
        pred: ``boxes (K, 7)``, ``labels (K,)`` (1-based into ``class_names``), ``scores (K,)``.
        gt_boxes (ndarray[M, 7] | None), gt_names (list[str] | None): the counted labelled boxes.
        other_boxes (ndarray[L, 7] | None): labelled boxes drawn but not counted.
        score_floor: detections below it are not drawn (the title says how many).
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    from lidarops.data.frame import CLASS_COLORS
    from lidarops.data.geometry import box_corners
    from lidarops.data.viz import new_figure

    fig = new_figure(9.0, 8.2)
    ax = fig.add_subplot(1, 1, 1)
    p = points[(points[:, 0] > -5) & (points[:, 0] < 75) & (np.abs(points[:, 1]) < 42)]
    # grey by height: the ground light, objects and structures darker
    shade = ax.scatter(p[:, 0], p[:, 1], s=0.4, c=p[:, 2], cmap="Greys", vmin=-3.5, vmax=0.0, linewidths=0,
                       rasterized=True)
    placed: list[tuple[float, float]] = []

    def draw(box, color, style, text=None):
        bottom = box_corners(box)[0, :4, :2]  # counter-clockwise from front-left: 0 and 3 span the front face
        ax.add_patch(Polygon(bottom, closed=True, fill=False, edgecolor=color, lw=1.4 if style == "-" else 1.0,
                             linestyle=style))
        if style == "-":  # the heading: centre to the middle of the front face
            front = bottom[[0, 3]].mean(0)
            ax.plot([box[0], front[0]], [box[1], front[1]], color=color, lw=1.0)
        if text:
            x, y = box[0] + box[3] / 2 + 0.3, box[1]
            if all(abs(x - px) > 3.0 or abs(y - py) > 1.2 for px, py in placed):  # skip a label that would overlap
                placed.append((x, y))
                ax.text(x, y, text, color=color, fontsize=6)

    for box in other_boxes if other_boxes is not None else []:
        draw(box, "0.6", ":")
    for box, name in zip(gt_boxes if gt_boxes is not None else [], gt_names if gt_names is not None else []):
        draw(box, CLASS_COLORS.get(name, "black"), "--")
    seen = {}
    shown = np.asarray(pred["scores"]) >= score_floor
    order = np.argsort(-np.asarray(pred["scores"]), kind="stable")  # the best boxes get their labels first
    for i in order[shown[order]]:
        name = class_names[int(pred["labels"][i]) - 1]
        seen[name] = CLASS_COLORS.get(name, "black")
        draw(pred["boxes"][i], seen[name], "-", f"{pred['scores'][i]:.2f}")
    ax.plot([0], [0], marker="^", color="black", markersize=6)
    ax.set_xlim(-2, 72)
    ax.set_ylim(-40, 40)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, forward)")
    ax.set_ylabel("y (m, left)")
    handles = [Line2D([0], [0], color=c, lw=2, label=n) for n, c in sorted(seen.items())]
    handles += [Line2D([0], [0], color="gray", lw=1, ls="--", label="labelled (counted)"),
                Line2D([0], [0], color="0.6", lw=1, ls=":", label="labelled, not counted"),
                Line2D([0], [0], color="gray", lw=1.4, label=f"detection (score >= {score_floor:g})")]
    ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.85)
    fig.colorbar(shade, ax=ax, fraction=0.025, pad=0.01, label="point height z (m)")
    hidden = int((~shown).sum())
    ax.set_title(title + (f"; {hidden} below {score_floor:g} not drawn" if hidden else ""), fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def _model_record(path: Path) -> dict:
    """What a checkpoint records beside the weights (its data recipe, its evaluation); {} when unreadable."""
    from lidarops.checkpoint import read_checkpoint

    try:
        ckpt = read_checkpoint(path)
    except (OSError, ValueError):
        return {}
    return {k: ckpt.get(k) for k in ("data_recipe", "evaluation")}


def _sees_whole_view(record: dict) -> bool:
    """Whether a model was trained on labels of its sensor's whole view (``data synth --labels all``: the
    drone scenes), not a camera's: it is then run on every point and scored on the whole view."""
    scenarios = (record.get("data_recipe") or {}).get("scenarios") or []
    return bool(scenarios) and all(isinstance(s, dict) and s.get("labels") == "all" for s in scenarios)


def detect(args: argparse.Namespace) -> int:
    """Runs a detector on frames; prints boxes, writes KITTI result files and BEV pictures, and scores
    them when the frames have labels."""
    import torch

    from lidarops.cli.eval import ap_headline, counted, match_summary
    from lidarops.data.formats.kitti import (boxes_to_kitti_labels, camera_to_lidar_boxes, kitti_fov_mask, read_label,
                                             write_label)
    from lidarops.eval import kitti as kitti_eval

    if args.score_thresh is not None and not 0 <= args.score_thresh < 1:  # NaN too
        raise CliError(f"--score-thresh must be in [0, 1) (a sigmoid score), got {args.score_thresh}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise CliError(f"--out {out} is a file; give a folder")
    sampling = _sampling(args)
    frames = _frames(args)
    model, device, ckpt = _load_model(args)
    if sampling is not None:
        from lidarops.cli.sample import _timed_sample, sample_count

        sampler = _build_sampler(sampling, device)
    names = model.config.class_names
    pc_range = list(model.config.point_cloud_range)
    record = _model_record(ckpt)  # read once: the file is the whole checkpoint
    whole = args.no_fov or _sees_whole_view(record)
    gt_annos, dt_annos, ids, shown = [], [], [], 0
    labelled = True
    model_seconds, sample_ms, per_frame = [], [], []
    start = time.perf_counter()
    total = _frame_count(args)
    # a bar only on a terminal, where it redraws in place (a log would keep every redraw)
    bar = progress_bar(total or 0, "detect", enabled=not args.no_progress and (total is None or total > 3)
                       and sys.stderr.isatty(), leave=False)
    for frame_id, frame, calib, label in frames:
        points = frame.points if whole else frame.points[kitti_fov_mask(frame.points, calib)]
        points_in = len(points)
        if sampling is not None:
            m = sample_count(points_in, sampling.ratio)
            idx, ms = _timed_sample(sampler, points, m, device) if m else (np.zeros(0, np.int64), 0.0)
            # in the scan's order, as without a sampler: the pillars' point cap then keeps the same points,
            # and --ratio 1 is the run without a sampler
            points = points[np.sort(idx)]
            sample_ms.append(ms)
        per_frame.append({"frame": frame_id, "points_in": points_in, "points_kept": len(points),
                          "sample_ms": round(sample_ms[-1], 3) if sampling is not None else None})
        batch = {"points": torch.from_numpy(np.concatenate([np.zeros((len(points), 1), np.float32), points], 1))
                 .to(device), "batch_size": 1}
        t0 = time.perf_counter()
        pred = {k: v.detach().cpu().numpy() for k, v in model.predict(batch)[0].items()}  # .cpu() waits for the GPU
        model_seconds.append(time.perf_counter() - t0)
        ids.append(frame_id)
        bar.update(1)
        # KITTI results cover the camera's view: boxes whose centre projects into the image (all of them for a
        # whole-view model)
        if not whole and len(pred["boxes"]):
            pred = {k: v[kitti_fov_mask(pred["boxes"][:, :3].astype(np.float64), calib)] for k, v in pred.items()}
        det_names = [names[int(k) - 1] for k in pred["labels"]]
        rows = boxes_to_kitti_labels(pred["boxes"], det_names, calib, score=pred["scores"])
        write_label(out / "data" / f"{frame_id}.txt", rows)
        dt_annos.append(kitti_eval.whole_view_annos(kitti_eval.annos_from_labels(rows)) if whole
                        else kitti_eval.annos_from_labels(rows))
        gt = None
        if args.scenario:  # the labels write_kitti_frame would write for it
            gt = kitti_eval.frame_annos(frame, calib, camera_fov_only=not whole)
        elif label is not None:  # every object of the label file, DontCare and Vans included
            gt = kitti_eval.annos_from_labels(read_label(label))
        else:
            labelled = False
        if gt is not None:
            gt = kitti_eval.whole_view_annos(gt, calib, pc_range) if whole else gt
            gt_annos.append(gt)
        # one count everywhere: objects of the model's classes, in a KITTI difficulty and in its range
        ours = np.isin(gt["name"], list(names)) if gt is not None else np.zeros(0, bool)
        count = ours & counted(gt, pc_range) if gt is not None else ours
        if shown < args.print_frames:
            seen = f", {int(count.sum())} labelled in range" if gt is not None else ""
            if sampling is not None:
                seen += (f"; {sampling.method} 1/{sampling.ratio}: {points_in:,} -> {len(points):,} points in "
                         f"{sample_ms[-1]:.1f} ms")
            print(f"{frame_id}: {len(pred['boxes'])} detection(s){seen}")
            for name, score, box in list(zip(det_names, pred["scores"], pred["boxes"]))[:args.print_boxes]:
                heading = (box[6] + np.pi) % (2 * np.pi) - np.pi  # the model's range is OpenPCDet's; print [-pi, pi)
                print(f"  {name:<11} {score:5.2f}  x {box[0]:6.2f} y {box[1]:6.2f} z {box[2]:5.2f}  "
                      f"dx {box[3]:4.2f} dy {box[4]:4.2f} dz {box[5]:4.2f}  heading {heading:5.2f}")
        if shown < args.png:
            gt_boxes = camera_to_lidar_boxes(gt["location"], gt["dimensions"][:, [1, 2, 0]], gt["rotation_y"],
                                             calib) if gt is not None and len(gt["name"]) else np.zeros((0, 7))
            kept = "" if sampling is None else \
                f"; the detector's {len(points):,} of {points_in:,} points ({sampling.method}, 1/{sampling.ratio})"
            # behind a sampler the picture shows what the detector saw
            png = save_detections_png(out / f"{frame_id}.png", frame.points if sampling is None else points, pred,
                                      names, gt_boxes[count], list(gt["name"][count]) if gt is not None else [],
                                      title=f"{frame_id}: {len(pred['boxes'])} detections (solid), "
                                            f"{int(count.sum())} labelled in range (dashed){kept}",
                                      other_boxes=gt_boxes[ours & ~count], score_floor=args.draw_score)
            print(f"  wrote {png}")
        shown += 1
    bar.close()
    if not shown:
        raise CliError("no frames to run on")
    wall = time.perf_counter() - start
    # the first call pays for lazy initialisation (kernels, allocator): the steady rate leaves it out
    steady = model_seconds[1:] or model_seconds
    print(f"wrote {shown} KITTI result file(s) to {out / 'data'} (checkpoint {ckpt})")
    print(f"{shown} frame(s) in {wall:.1f} s ({shown / wall:.2f} frames/s with reading and writing); the model: "
          f"{1e3 * sum(steady) / len(steady):.1f} ms per frame on {device}"
          + (f" (first frame {1e3 * model_seconds[0]:.0f} ms)" if len(model_seconds) > 1 else ""))
    if sampling is not None:
        steady_ms = sample_ms[1:] or sample_ms
        print(f"the sampler ({sampling.method}, 1/{sampling.ratio}): {sum(steady_ms) / len(steady_ms):.1f} ms per "
              f"frame on {device}" + (f" (first frame {sample_ms[0]:.0f} ms)" if len(sample_ms) > 1 else "")
              + f"; {sum(f['points_in'] for f in per_frame) / shown:,.0f} -> "
                f"{sum(f['points_kept'] for f in per_frame) / shown:,.0f} points per frame")
    trained = _trained_ids(args, record.get("data_recipe"), ids)
    if trained:
        print(f"lidarops detect: warning: {len(trained)} of the {shown} frame(s) are frames of the model's own "
              f"data recipe (it was trained or validated on them, e.g. {trained[0]}): scores on them measure "
              f"memory, not detection. Unseen frames: --seed {HELD_OUT_SEED} (data synth and detect's default)",
              file=sys.stderr)
    (out / "detect.json").write_text(json.dumps({"checkpoint": str(ckpt), "frames": ids,
                                                 "frames_of_the_model_recipe": trained,
                                                 "sampler": sampling.record() if sampling is not None else None,
                                                 "per_frame": per_frame}, indent=1))
    if labelled and gt_annos:
        text, results = kitti_eval.evaluate(gt_annos, dt_annos, names)
        (out / "eval.txt").write_text(text + "\n")
        (out / "eval.json").write_text(json.dumps(results, indent=1))
        recorded = ((record.get("evaluation") or {}).get("metrics")) or None
        print(ap_headline(results, names, len(gt_annos), recorded, kitti_eval.count_difficulties(gt_annos, names)))
        print(f"  (KITTI's full table: {out / 'eval.txt'}; below 41 objects of a class R40 cannot reach 100)")
        print(match_summary(gt_annos, dt_annos, names, pc_range))
    return 0


def register(subparsers) -> None:
    """Adds ``detect`` to the ``lidarops`` parser."""
    d = subparsers.add_parser("detect", help="detect 3D boxes in frames (a .bin, a KITTI folder or a scenario)",
                              description="Run a detector (default: the shipped PointPillars) on frames: prints "
                                          "the boxes, writes KITTI result files and bird's-eye-view PNGs, and "
                                          "prints KITTI AP when the frames have labels.")
    d.add_argument("input", nargs="?", help="a KITTI velodyne .bin or a KITTI folder")
    d.add_argument("--scenario", default=None, help="simulate frames of this scenario instead (e.g. driving_city)")
    d.add_argument("--realism", default=None, type=_realism_arg, metavar="PROFILE",
                   help="--scenario: the simulator's realism profile of the frames (kitti, kitti_dr, avia; as data "
                        "synth --realism); default: ray-cast")
    d.add_argument("--frames", type=int, default=None, help="number of frames (scenario: default 1; folder: all)")
    d.add_argument("--format", choices=("auto", "kitti", "nuscenes"), default="auto",
                   help="layout of a scan file: KITTI (4 floats per point) or nuScenes (5); default from the name "
                        "(*.pcd.bin: nuScenes, velodyne/*.bin: KITTI)")
    d.add_argument("--seed", type=int, default=HELD_OUT_SEED,
                   help=f"scenario seed (default {HELD_OUT_SEED}: frames no shipped model was trained on)")
    d.add_argument("--split", default=None, help="KITTI folder: an ImageSets name (train, val)")
    d.add_argument("--checkpoint", default=None, help="checkpoint file or shipped name (default: the shipped "
                   "pointpillars_synth_real for scans and --realism, pointpillars_synth for --scenario and folders "
                   "data synth made without --realism)")
    d.add_argument("--config", default=None, help="config for an OpenPCDet checkpoint (lidarops ones carry theirs)")
    d.add_argument("--out", default="detections", help="output folder (default ./detections)")
    d.add_argument("--score-thresh", type=float, default=None,
                   help="keep detections scoring at least this (default: the model's SCORE_THRESH, 0.1 for the "
                        "shipped one)")
    d.add_argument("--device", default="auto", help="auto (default: cuda when available and built), cpu, cuda")
    d.add_argument("--no-fov", action="store_true",
                   help="run on the sensor's whole view: every point, every detection, scored without the camera's "
                        "image (BEV and 3D AP); the default for models trained on whole-view labels (the drone "
                        "scenes' aerial_pointpillars)")
    d.add_argument("--png", type=int, default=1, help="frames to draw (default 1)")
    d.add_argument("--print-frames", type=int, default=3, help="frames whose boxes are printed (default 3)")
    d.add_argument("--print-boxes", type=int, default=10, help="boxes printed per frame (default 10)")
    d.add_argument("--draw-score", type=float, default=0.3,
                   help="detections scoring below this are left out of the pictures (default 0.3)")
    d.add_argument("--no-progress", action="store_true", help="no progress bar")
    s = d.add_argument_group("behind a sampler", "keep N // D of each frame's N points (after the field-of-view "
                             "filter), every channel, before the detector (lidarops sample's samplers)")
    s.add_argument("--sampler", default=None, metavar="METHOD",
                   help="random, fps, chunked-fps or casnet (default: none, every point)")
    s.add_argument("--ratio", default=None, metavar="D", help="keep N // D points of a frame of N (default 8; "
                   "1 keeps every point, the reference)")
    s.add_argument("--sampler-checkpoint", default=None, metavar="PATH_OR_NAME",
                   help=f"--sampler casnet: {_CASNET_FILES} (default: the shipped {SHIPPED_CASNET_REAL} in front "
                        f"of {SHIPPED_REAL}, else {SHIPPED_CASNET})")
    s.add_argument("--sampler-seed", default=None, metavar="S",
                   help="--sampler random: the generator's seed (default 0); each frame draws new points")
    d.set_defaults(func=guarded("detect", detect))
