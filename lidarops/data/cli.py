"""``lidarops data synth`` and ``lidarops data show``.

Examples::

    lidarops data synth --scenario driving_city --frames 100 --format kitti --out /tmp/kitti_synth
    lidarops data synth --scenario drone_bridge --frames 50 --format pandaset --out /tmp/pandaset_synth
    lidarops data show /tmp/kitti_synth --index 3 --out bev.png
    lidarops data show driving_highway --out highway.png
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["register", "synth", "show"]


def _progress(iterable, total: int, desc: str, enabled: bool):
    if not enabled:
        return iterable
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm is optional
        return iterable
    return tqdm(iterable, total=total, desc=desc, unit="frame")


def _object_counts(text: str | None):
    if text is None:
        return None
    if text in ("dense", "empty"):
        return text
    try:
        counts = json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"--object-counts must be 'dense', 'empty' or a JSON object like '{{\"Car\": 35}}' ({e})") from None
    if not isinstance(counts, dict):
        raise ValueError("--object-counts JSON must be an object mapping class names to counts or [low, high]")
    return {k: tuple(v) if isinstance(v, list) else v for k, v in counts.items()}


def synth(args: argparse.Namespace) -> int:
    """Writes a synthetic dataset in KITTI or PandaSet format."""
    from lidarops.data.synthetic import Simulator, SyntheticFrames

    out = Path(args.out)
    counts = _object_counts(args.object_counts)
    show_progress = not args.no_progress
    if args.format == "kitti":
        from lidarops.data.formats.kitti import write_image_sets, write_kitti_frame

        frames = SyntheticFrames(args.scenario, num_frames=args.frames, seed=args.seed,
                                 frames_per_scene=args.frames_per_scene, sensor=args.sensor, object_counts=counts)
        ids, n_boxes = [], 0
        for i in _progress(range(args.frames), args.frames, f"{args.scenario} -> KITTI", show_progress):
            frame = frames[i]
            ids.append(write_kitti_frame(out, frame, frame_id=i, split=args.split))
            n_boxes += int((frame.num_points_in_box > 0).sum())
        write_image_sets(out, ids, val_fraction=args.val_fraction, seed=args.seed)
        print(f"wrote {len(ids)} KITTI frames ({n_boxes} boxes with points) to {out / args.split}")
    else:
        from lidarops.data.formats.pandaset import _write_pose_files, write_pandaset_frame

        sim = Simulator(args.scenario, seed=args.seed, sensor=args.sensor, object_counts=counts)
        seq_dir = out / args.sequence
        poses, stamps = [], []
        for i in _progress(range(args.frames), args.frames, f"{args.scenario} -> PandaSet", show_progress):
            frame = sim.sweep(i)
            write_pandaset_frame(seq_dir, frame, i, world_xyz=sim.points_to_world(frame.points, frame.t))
            poses.append(frame.sensor_pose)
            stamps.append(frame.timestamp)
        _write_pose_files(seq_dir, poses, stamps)
        print(f"wrote a {args.frames}-frame PandaSet sequence ({sim.sensor.name}, per-point timestamps) to {seq_dir}")
    return 0


def show(args: argparse.Namespace) -> int:
    """Writes a bird's-eye view of one frame (or a three-view picture of one ModelNet40 object)."""
    from lidarops.data.formats import detect_format, read_frame
    from lidarops.data.scene import SCENARIOS
    from lidarops.data.viz import save_bev, save_object

    spec = args.path
    out = Path(args.out)
    is_scenario = spec.startswith("synthetic:") or (spec in SCENARIOS and not Path(spec).exists())
    if not is_scenario and detect_format(spec) == "modelnet":
        from lidarops.data.formats.modelnet import ModelNet40

        shapes = ModelNet40(spec, split=args.split_name)
        if not 0 <= args.index < len(shapes):
            raise IndexError(f"object {args.index} out of range: {spec} has {len(shapes)} shapes")
        points, label = shapes[args.index]
        name = shapes.class_names[label] if 0 <= label < len(shapes.class_names) else str(label)
        save_object(points, out, title=f"{Path(spec).name} #{args.index}: {name} ({points.shape[0]} points)")
        print(f"wrote {out} ({name}, {points.shape[0]} points)")
        return 0
    options = {"num_frames": args.index + 1, "seed": args.seed} if is_scenario else {}
    frame = read_frame(spec, args.index, **options)
    if args.fov is not None:
        frame = frame.crop_forward(args.fov)
    extent = tuple(args.extent) if args.extent else None
    save_bev(frame, out, extent=extent, color_by=args.color_by, max_extent=args.max_extent)
    names = frame.names
    summary = ", ".join(f"{n}: {names.count(n)}" for n in sorted(set(names))) or "no boxes"
    print(f"wrote {out}: {frame.num_points} points, {summary}")
    return 0


def _guarded(fn):
    def run(args: argparse.Namespace) -> int:
        try:
            return fn(args)
        except (FileNotFoundError, ValueError, IndexError, ImportError) as e:
            print(f"lidarops data {args.data_command}: error: {e}", file=sys.stderr)
            return 2

    return run


def register(subparsers) -> None:
    """Adds ``data`` with its ``synth`` and ``show`` subcommands to the ``lidarops`` parser."""
    from lidarops.data.scene import SCENARIOS

    data = subparsers.add_parser("data", help="simulate LiDAR data, write and view dataset files",
                                 description="Synthetic LiDAR data and dataset files (KITTI, PandaSet, nuScenes, ModelNet40).")
    data_sub = data.add_subparsers(dest="data_command", metavar="DATA_COMMAND")

    def data_help(args: argparse.Namespace) -> int:
        data.print_help()
        return 2

    data.set_defaults(func=data_help)

    s = data_sub.add_parser("synth", help="write a synthetic dataset (KITTI or PandaSet format)",
                            description="Simulate LiDAR frames and write them as a KITTI object split or a PandaSet sequence.")
    s.add_argument("--scenario", choices=sorted(SCENARIOS), default="driving_city")
    s.add_argument("--frames", type=int, default=10, help="number of frames (default 10)")
    s.add_argument("--format", choices=("kitti", "pandaset"), default="kitti")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--sensor", choices=("hdl64", "pandar64", "avia"), default=None,
                   help="sensor preset (default: the scenario's)")
    s.add_argument("--object-counts", default=None,
                   help="'dense', 'empty' or JSON such as '{\"Car\": 35, \"Pedestrian\": [0, 5]}'")
    s.add_argument("--frames-per-scene", type=int, default=1,
                   help="KITTI: consecutive sweeps per simulated scene (default 1: independent frames)")
    s.add_argument("--split", default="training", help="KITTI split directory (default training)")
    s.add_argument("--val-fraction", type=float, default=0.2, help="KITTI: share of ids in ImageSets/val.txt")
    s.add_argument("--sequence", default="001", help="PandaSet: sequence directory name (default 001)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=_guarded(synth))

    v = data_sub.add_parser("show", help="bird's-eye view of a frame as PNG",
                            description="Bird's-eye view of a frame, boxes coloured by class. PATH may be a KITTI "
                                        "directory or .bin, a PandaSet sequence or .pkl.gz, a nuScenes .pcd.bin, a "
                                        "ModelNet40 .h5 (shows one object) or a scenario name.")
    v.add_argument("path", help="dataset path or scenario name (e.g. driving_city)")
    v.add_argument("--out", default="bev.png", help="output PNG (default bev.png)")
    v.add_argument("--index", type=int, default=0, help="frame (or ModelNet object) index")
    v.add_argument("--seed", type=int, default=0, help="seed for a scenario name")
    v.add_argument("--split-name", default="train", help="ModelNet40 split when PATH is a directory")
    v.add_argument("--fov", type=float, default=None, help="forward crop opening in degrees (e.g. 90)")
    v.add_argument("--extent", type=float, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"), default=None)
    v.add_argument("--max-extent", type=float, default=80.0, help="bound of the automatic extent (m)")
    v.add_argument("--color-by", choices=("z", "intensity", "range"), default="z")
    v.set_defaults(func=_guarded(show))
