"""``lidarops data synth`` and ``lidarops data show``: simulated LiDAR data written as dataset files, and a
look at any frame.

``synth`` simulates frames of one or more scenarios (:mod:`lidarops.data.synthetic`) and writes them as a
KITTI object split (velodyne, label_2, calib, ImageSets with whole scenes in val, ``recipe.json``: the same
files for any number of ``--workers``) or as a PandaSet sequence. ``show`` draws a bird's-eye view of one
frame of a KITTI, PandaSet or nuScenes file or folder, or of a scenario, or a ModelNet40 object.

Examples::

    lidarops data synth --scenario driving_city --frames 100 --format kitti --out /tmp/kitti_synth
    lidarops data synth --scenario driving_city driving_highway --frames 2000 1000 --frames-per-scene 5 \\
        --val-fraction 0.2 --workers 8 --out /tmp/kitti_train      # a training set: ImageSets, recipe.json
    lidarops data synth --scenario drone_bridge --frames 50 --format pandaset --out /tmp/pandaset_synth
    lidarops data show /tmp/kitti_synth --index 3 --out bev.png
    lidarops data show driving_highway --out highway.png
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from lidarops._checks import real
from lidarops.conventions import HELD_OUT_SEED
from lidarops._progress import progress, progress_bar
from lidarops.cli.errors import CliError, guarded

__all__ = ["register", "synth", "show"]


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


def _realism_arg(text: str) -> str:
    """``--realism``: a preset or a preset with fields changed, checked here (argparse names the option on error)
    and passed on as written, so the recipe records it."""
    from lidarops.data.realism import make_realism

    try:
        make_realism(text)
    except (ValueError, TypeError) as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _realism_or_none_arg(text: str) -> str:
    """A profile as :func:`_realism_arg` takes, or ``none`` (ray-cast), kept as written."""
    return text if text == "none" else _realism_arg(text)


def _realism_per_scenario(args: argparse.Namespace) -> list[str | None]:
    """``--realism``: one profile for every ``--scenario`` or one per scenario (``none``: ray-cast)."""
    given = getattr(args, "realism", None)
    if given is None:
        return [None] * len(args.scenario)
    if isinstance(given, str):
        given = [given]
    given = [None if g in (None, "none") else g for g in given]
    if len(given) == 1:
        return given * len(args.scenario)
    if len(given) != len(args.scenario):
        raise ValueError(f"--realism takes one profile or one per --scenario ({len(args.scenario)}), got "
                         f"{len(given)}: {' '.join(g or 'none' for g in given)}")
    return given


def _recipe_realism(args: argparse.Namespace):
    """What ``recipe.json`` records as ``realism``: None (ray-cast), the one profile, or one per scenario."""
    per = _realism_per_scenario(args)
    if all(r is None for r in per):
        return None
    return per[0] if len(set(per)) == 1 else per


def _scenario_plan(args: argparse.Namespace) -> list[dict]:
    """Frames, seed and first frame id of each ``--scenario``: ``--frames`` is one total split evenly (the
    first scenarios take the remainder) or one count per scenario; scenario ``k`` is simulated with seed
    ``--seed + 1000 k`` and its ids follow those of the scenario before it."""
    scenarios, frames = list(args.scenario), list(args.frames)
    if len(frames) == 1 and len(scenarios) > 1:
        total = frames[0]
        frames = [total // len(scenarios) + (k < total % len(scenarios)) for k in range(len(scenarios))]
    if len(frames) != len(scenarios):
        raise ValueError(f"--frames takes one total or one count per scenario ({len(scenarios)}), got {len(frames)} values")
    if any(n < 0 for n in frames) or sum(frames) == 0:
        raise ValueError(f"--frames must be >= 0 per scenario and at least 1 in all, got {frames}")
    realism = _realism_per_scenario(args)
    plan, first = [], 0
    for k, (name, n) in enumerate(zip(scenarios, frames)):
        labels = getattr(args, "labels", None) or ("all" if name in _WHOLE_VIEW_SCENARIOS else "camera")
        plan.append({"scenario": name, "frames": n, "seed": args.seed + _SCENARIO_SEED_STRIDE * k, "first_id": first,
                     "labels": labels, "realism": realism[k]})
        first += n
    return plan


_SCENARIO_SEED_STRIDE = 1000
#: Scenarios whose sensor sees far beyond a KITTI camera (the Avia's 70 x 77 degrees: drones above the
#: image): their labels cover the whole view unless --labels camera.
_WHOLE_VIEW_SCENARIOS = frozenset({"drone_bridge", "drone_lock"})
_CHUNK_FRAMES = 10  # frames of one scene per task: consecutive sweeps reuse the worker's simulator
_SOURCES: dict = {}  # the SyntheticFrames a process generated from last (worker or in-process)


def _synth_chunk(task: dict) -> tuple[list[str], int, str]:
    """Writes frames ``start..stop-1`` of one scenario as KITTI files (a pure function of the task: the
    frames are functions of scenario, seed and index, whatever this process generated before)."""
    from lidarops.data.formats.kitti import write_kitti_frame
    from lidarops.data.synthetic import SyntheticFrames

    key = tuple((k, repr(v)) for k, v in sorted(task["source"].items()))
    if key not in _SOURCES:
        _SOURCES.clear()
        _SOURCES[key] = SyntheticFrames(**task["source"])
    frames = _SOURCES[key]
    ids, n_boxes, sensor = [], 0, ""
    for i in range(task["start"], task["stop"]):
        frame = frames[i]
        ids.append(write_kitti_frame(task["out"], frame, frame_id=task["first_id"] + i, split=task["split"],
                                     camera_fov_only=task.get("labels", "camera") == "camera"))
        n_boxes += int((frame.num_points_in_box > 0).sum())
        sensor = frame.meta.get("sensor", "")
    return ids, n_boxes, sensor


def _run_tasks(tasks: list[dict], workers: int, bar) -> list[tuple[list[str], int, str]]:
    """Runs the tasks in this process (``workers == 1``) or in a pool of fresh (spawned) processes, each
    with its share of the cores for its native ray casting and BLAS threads."""
    if workers == 1 or len(tasks) <= 1:
        results = []
        for task in tasks:
            results.append(_synth_chunk(task))
            bar.update(task["stop"] - task["start"])
        _SOURCES.clear()  # its simulator's block cache
        return results
    import multiprocessing
    import os

    workers = min(workers, len(tasks))
    threads = str(max(1, (os.cpu_count() or 1) // workers))
    names = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    saved = {name: os.environ.get(name) for name in names}
    os.environ.update({name: threads for name in names})  # read by the spawned interpreters at start
    try:
        # spawn, not fork: a forked child of a process whose OpenMP pool has run can hang in its first parallel region
        pool = multiprocessing.get_context("spawn").Pool(workers)
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    with pool:
        results = []
        for result in pool.imap_unordered(_synth_chunk, tasks):
            results.append(result)
            bar.update(len(result[0]))
    return results


def _val_scene_counts(scenes: list[int], val_fraction: float) -> list[int]:
    """Validation scenes per scenario: ``round(total * val_fraction)`` shared in proportion to each scenario's
    scenes (largest remainders first)."""
    quotas = [n * val_fraction for n in scenes]
    counts = [int(q) for q in quotas]
    extra = int(round(sum(scenes) * val_fraction)) - sum(counts)
    for k in sorted(range(len(scenes)), key=lambda k: (-(quotas[k] - counts[k]), k))[:max(extra, 0)]:
        counts[k] += 1
    return [min(c, n) for c, n in zip(counts, scenes)]


def _write_scene_image_sets(out: Path, plan: list[dict], frames_per_scene: int, val_fraction: float,
                            seed: int) -> dict[str, list[str]]:
    """``ImageSets/{trainval,train,val}.txt`` with whole scenes in ``val``: scene ``j`` of a scenario holds its
    frames ``j K .. (j + 1) K - 1``; each scenario gives its share of validation scenes, drawn with
    ``default_rng(seed)`` (for one scenario and one frame per scene: the ids ``write_image_sets`` picks)."""
    import numpy as np

    scenes = [-(-entry["frames"] // frames_per_scene) for entry in plan]
    rng = np.random.default_rng(seed)
    val: set[int] = set()
    for entry, n_scenes, n_val in zip(plan, scenes, _val_scene_counts(scenes, val_fraction)):
        for scene in rng.choice(n_scenes, size=n_val, replace=False) if n_val else []:
            lo = entry["first_id"] + int(scene) * frames_per_scene
            val.update(range(lo, min(lo + frames_per_scene, entry["first_id"] + entry["frames"])))
    total = sum(entry["frames"] for entry in plan)
    sets = {"trainval": [f"{i:06d}" for i in range(total)],
            "train": [f"{i:06d}" for i in range(total) if i not in val],
            "val": [f"{i:06d}" for i in sorted(val)]}
    (out / "ImageSets").mkdir(parents=True, exist_ok=True)
    for name, ids in sets.items():
        (out / "ImageSets" / f"{name}.txt").write_text("".join(f"{i}\n" for i in ids))
    return sets


def _command_line(args: argparse.Namespace) -> str:
    """The canonical ``lidarops data synth`` command of the parsed arguments."""
    import shlex

    words = ["lidarops", "data", "synth", "--format", args.format, "--scenario", *args.scenario,
             "--frames", *map(str, args.frames), "--out", str(args.out), "--seed", str(args.seed)]
    if args.sensor:
        words += ["--sensor", args.sensor]
    if args.object_counts is not None:
        words += ["--object-counts", args.object_counts]
    realism = _recipe_realism(args)
    if realism is not None:
        words += ["--realism", *([realism] if isinstance(realism, str) else [r or "none" for r in realism])]
    if getattr(args, "labels", None):
        words += ["--labels", args.labels]
    if args.format == "kitti":
        words += ["--frames-per-scene", str(args.frames_per_scene), "--split", args.split,
                  "--val-fraction", repr(args.val_fraction), "--workers", str(args.workers)]
    else:
        words += ["--sequence", args.sequence]
    return shlex.join(words)


def _write_recipe(out: Path, args: argparse.Namespace, **fields) -> None:
    """``<out>/recipe.json``: how the set was made (enough to make it again)."""
    import lidarops

    recipe = {"format": args.format, "lidarops_version": lidarops.__version__, "command": _command_line(args),
              "seed": args.seed, "sensor": args.sensor, "object_counts": args.object_counts,
              "realism": _recipe_realism(args), **fields}
    (out / "recipe.json").write_text(json.dumps(recipe, indent=2) + "\n")


def _synth_kitti(args: argparse.Namespace, out: Path, counts) -> None:
    plan = _scenario_plan(args)
    k = args.frames_per_scene
    tasks = []
    for entry in plan:
        source = {"scenario": entry["scenario"], "num_frames": entry["frames"], "seed": entry["seed"],
                  "frames_per_scene": k, "sensor": args.sensor, "object_counts": counts, "realism": entry["realism"]}
        for lo in range(0, entry["frames"], k):  # a scene at a time, in chunks
            for start in range(lo, min(lo + k, entry["frames"]), _CHUNK_FRAMES):
                tasks.append({"source": source, "out": str(out), "split": args.split, "first_id": entry["first_id"],
                              "labels": entry["labels"], "start": start,
                              "stop": min(start + _CHUNK_FRAMES, lo + k, entry["frames"])})
    total = sum(entry["frames"] for entry in plan)
    bar = progress_bar(total, f"{'+'.join(args.scenario)} -> KITTI", not args.no_progress)
    try:
        results = _run_tasks(tasks, args.workers, bar)
    finally:
        bar.close()
    n_boxes = sum(r[1] for r in results)
    sensors = {ids[0]: sensor for ids, _, sensor in results if ids}
    for entry in plan:
        entry["scenes"] = -(-entry["frames"] // k)
        entry["sensor"] = sensors.get(f"{entry['first_id']:06d}", args.sensor)
    sets = _write_scene_image_sets(out, plan, k, args.val_fraction, args.seed)
    _write_recipe(out, args, scenarios=plan, frames=total, frames_per_scene=k, val_fraction=args.val_fraction,
                  split=args.split, image_sets={name: len(ids) for name, ids in sets.items()})
    print(f"wrote {total} KITTI frames ({n_boxes} boxes with points) to {out / args.split} "
          f"(train {len(sets['train'])}, val {len(sets['val'])} frames)")


def synth(args: argparse.Namespace) -> int:
    """Writes a synthetic dataset in KITTI or PandaSet format."""
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is an existing file; give a directory")
    if args.workers < 1 or args.frames_per_scene < 1:
        raise ValueError(f"--workers and --frames-per-scene must be >= 1, got {args.workers} and {args.frames_per_scene}")
    if not 0.0 <= args.val_fraction <= 1.0:
        raise ValueError(f"--val-fraction must be in [0, 1], got {args.val_fraction}")
    counts = _object_counts(args.object_counts)
    if getattr(args, "labels", None) and args.format != "kitti":
        raise ValueError(f"--labels chooses KITTI label rows; --format {args.format} writes every object")
    if args.format == "kitti":
        _synth_kitti(args, out, counts)
        return 0
    # one (write_pandaset_sequence needs every frame in memory; this loop writes them as they are simulated)
    from lidarops.data.formats.pandaset import write_pandaset_frame, write_pose_files
    from lidarops.data.synthetic import Simulator

    if len(args.scenario) != 1 or len(args.frames) != 1:
        raise ValueError("--format pandaset writes one sequence: give one --scenario and one --frames")
    scenario, n_frames = args.scenario[0], args.frames[0]
    sim = Simulator(scenario, seed=args.seed, sensor=args.sensor, object_counts=counts,
                    realism=_realism_per_scenario(args)[0])
    seq_dir = out / args.sequence
    poses, stamps = [], []
    for i in progress(range(n_frames), n_frames, f"{scenario} -> PandaSet", not args.no_progress):
        frame = sim.sweep(i)
        write_pandaset_frame(seq_dir, frame, i, world_xyz=sim.points_to_world(frame.points, frame.t))
        poses.append(frame.sensor_pose)
        stamps.append(frame.timestamp)
    write_pose_files(seq_dir, poses, stamps)
    _write_recipe(out, args, scenarios=[{"scenario": scenario, "frames": n_frames, "seed": args.seed,
                                         "sensor": sim.sensor.name}], frames=n_frames, sequence=args.sequence)
    print(f"wrote a {n_frames}-frame PandaSet sequence ({sim.sensor.name}, per-point timestamps) to {seq_dir}")
    return 0


def show(args: argparse.Namespace) -> int:
    """Writes a bird's-eye view of one frame (or a three-view picture of one ModelNet40 object)."""
    from lidarops.data.formats import detect_format, read_frame
    from lidarops.data.scenarios import SCENARIOS
    from lidarops.data.viz import save_bev, save_object

    spec = args.path
    out = Path(args.out)
    if args.index < 0:
        raise ValueError(f"--index must be >= 0, got {args.index}")
    if args.fov is not None:
        real(args.fov, "--fov", 0, 360, lo_open=True, unit=" degrees")
    real(args.max_extent, "--max-extent", 0, None, lo_open=True, unit=" m")
    for i, v in enumerate(args.extent or ()):
        real(v, f"--extent's value {i + 1}", unit=" m")
    is_scenario = spec.startswith("synthetic:") or (spec in SCENARIOS and not Path(spec).exists())
    if not is_scenario and not Path(spec).exists():
        import difflib

        close = difflib.get_close_matches(spec, SCENARIOS, n=1)
        hint = f"did you mean the scenario {close[0]}? " if close else ""
        raise CliError(f"{spec} not found: neither a file, a dataset folder nor a scenario ({hint}scenarios: "
                       f"{', '.join(sorted(SCENARIOS))})")
    if not is_scenario and detect_format(spec) == "modelnet":
        from lidarops.data.formats.modelnet import ModelNet40

        shapes = ModelNet40(spec, split=args.split_name)
        if not 0 <= args.index < len(shapes):
            raise CliError(f"object {args.index} out of range: {spec} has {len(shapes)} shapes")
        points, label = shapes[args.index]
        name = shapes.class_names[label] if 0 <= label < len(shapes.class_names) else str(label)
        save_object(points, out, title=f"{Path(spec).name} #{args.index}: {name} ({points.shape[0]} points)")
        print(f"wrote {out} ({name}, {points.shape[0]} points)")
        return 0
    options = {"num_frames": args.index + 1, "seed": args.seed} if is_scenario else {}
    try:
        frame = read_frame(spec, args.index, **options)
    except IndexError as e:  # read_frame's error for an index out of range
        raise CliError(str(e)) from None
    if args.fov is not None:
        frame = frame.crop_forward(args.fov)
    extent = tuple(args.extent) if args.extent else None
    save_bev(frame, out, extent=extent, color_by=args.color_by, max_extent=args.max_extent)
    names = frame.names
    summary = ", ".join(f"{n}: {names.count(n)}" for n in sorted(set(names))) or "no boxes"
    print(f"wrote {out}: {frame.num_points} points, {summary}")
    return 0


def register(subparsers) -> None:
    """Adds ``data`` with its ``synth`` and ``show`` subcommands to the ``lidarops`` parser."""
    from lidarops.data.scenarios import SCENARIOS

    data = subparsers.add_parser("data", help="simulate LiDAR data, write and view dataset files",
                                 description="Synthetic LiDAR data and dataset files (KITTI, PandaSet, nuScenes, ModelNet40).")
    data_sub = data.add_subparsers(dest="data_command", metavar="DATA_COMMAND")

    def data_help(args: argparse.Namespace) -> int:
        data.print_help()
        return 2

    data.set_defaults(func=data_help)

    s = data_sub.add_parser("synth", help="write a synthetic dataset (KITTI or PandaSet format)",
                            description="Simulate LiDAR frames and write them as a KITTI object split or a PandaSet sequence.")
    s.add_argument("--scenario", choices=sorted(SCENARIOS), nargs="+", default=["driving_city"], metavar="SCENARIO",
                   help=f"one or more of {', '.join(sorted(SCENARIOS))} (default driving_city); scenario k is "
                        "simulated with seed --seed + 1000 k, its frame ids follow the previous scenario's")
    s.add_argument("--frames", type=int, nargs="+", default=[10],
                   help="number of frames (default 10): one total, split evenly over the scenarios, or one per scenario")
    s.add_argument("--format", choices=("kitti", "pandaset"), default="kitti", help="output layout (default kitti)")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--seed", type=int, default=HELD_OUT_SEED,
                   help=f"first scenario's seed (default {HELD_OUT_SEED}: frames no shipped model was trained on)")
    s.add_argument("--sensor", choices=("hdl64", "pandar64", "avia"), default=None,
                   help="sensor preset (default: the scenario's)")
    s.add_argument("--realism", default=None, type=_realism_or_none_arg, nargs="+", metavar="PROFILE",
                   help="a real sensor's intensity response and real vehicles' surfaces (glass, dark paint) on the "
                        "returns: kitti (calibrated against KITTI's HDL-64E scans), kitti_dr (the same with mixed "
                        "pixels at depth edges and each scene's sensor height and intensity scale randomised), avia "
                        "(a Livox Avia's reflectivity and quadcopter drones, from its datasheet), or "
                        "any with fields of lidarops.data.realism.Realism changed "
                        "(kitti:crossing_groups=0.6,crossing_cyclists=0.2); one for every --scenario or one per "
                        "scenario, none for ray-cast (--scenario drone_lock drone_lock --realism avia none: a mix); "
                        "default: as ray-cast")
    s.add_argument("--object-counts", default=None,
                   help="'dense', 'empty' or JSON such as '{\"Car\": 35, \"Pedestrian\": [0, 5]}' (default: the "
                        "scenario's)")
    s.add_argument("--labels", choices=("camera", "all"), default=None,
                   help="KITTI: which objects get label rows: camera (as KITTI: centres that project into the "
                        "camera image) or all (the sensor's whole view); default all for the drone scenes (the "
                        "Avia sees above the image), camera for the others")
    s.add_argument("--frames-per-scene", type=int, default=1,
                   help="KITTI: consecutive sweeps per simulated scene (default 1: independent frames); "
                        "scenes are never split between train and val")
    s.add_argument("--split", default="training", help="KITTI split directory (default training)")
    s.add_argument("--val-fraction", type=float, default=0.2,
                   help="KITTI: share of scenes in ImageSets/val.txt (default 0.2; whole scenes: no scene in both "
                        "splits)")
    s.add_argument("--workers", type=int, default=1,
                   help="KITTI: processes generating frames (default 1); the files are identical for any number")
    s.add_argument("--sequence", default="001", help="PandaSet: sequence directory name (default 001)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=guarded("data synth", synth))

    v = data_sub.add_parser("show", help="bird's-eye view of a frame as PNG",
                            description="Bird's-eye view of a frame, boxes coloured by class. PATH may be a KITTI "
                                        "directory or .bin, a PandaSet sequence or .pkl.gz, a nuScenes .pcd.bin, a "
                                        "ModelNet40 .h5 (shows one object) or a scenario name.")
    v.add_argument("path", help="dataset path or scenario name (e.g. driving_city)")
    v.add_argument("--out", default="bev.png", help="output PNG (default bev.png)")
    v.add_argument("--index", type=int, default=0, help="frame (or ModelNet object) index")
    v.add_argument("--seed", type=int, default=HELD_OUT_SEED,
                   help=f"seed for a scenario name (default {HELD_OUT_SEED})")
    v.add_argument("--split-name", default="train", help="ModelNet40 split when PATH is a directory")
    v.add_argument("--fov", type=float, default=None, help="forward crop opening in degrees (e.g. 90)")
    v.add_argument("--extent", type=float, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"), default=None,
                   help="the area drawn, in metres (default: fitted to the points within --max-extent)")
    v.add_argument("--max-extent", type=float, default=80.0, help="bound of the automatic extent (m)")
    v.add_argument("--color-by", choices=("z", "intensity", "range"), default="z", help="point colours (default z)")
    v.set_defaults(func=guarded("data show", show))
