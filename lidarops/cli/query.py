"""``lidarops index build`` (count frames into a frame index) and ``lidarops query retrieve|count|sum|avg``
(docs/query.md)."""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from lidarops.cli.data import _realism_arg
from lidarops.cli.errors import CliError, guarded
from lidarops.conventions import HELD_OUT_SEED

_WHERE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|<|>|=)\s*(-?\d+)\s*$")
DEFAULT_CLASSES = ("Car", "Pedestrian", "Cyclist")
SHIPPED_RANGE = "0,-39.68,69.12,39.68"  # the shipped PointPillars' BEV point cloud range (configs/pointpillars)
SHIPPED_COUNTER = "counternet_road7"  # lidarops/weights/: CounterNet, partitions 4, overlap 0.2


def _frames_of(args: argparse.Namespace, needs_labels: bool):
    """(frame ids, ``load(frame_id) -> Frame``) of a scenario or a KITTI folder."""
    if args.scenario:
        from lidarops.data.synthetic import SyntheticFrames

        if args.frames is None or args.frames < 1:
            raise CliError(f"--frames must be >= 1 with --scenario, got {args.frames}")
        if args.frames_per_scene < 1:
            raise CliError(f"--frames-per-scene must be >= 1, got {args.frames_per_scene}")
        realism = getattr(args, "realism", None)
        data = SyntheticFrames(args.scenario, num_frames=args.frames, seed=args.seed,
                               frames_per_scene=args.frames_per_scene,
                               object_counts=None if args.object_counts == "default" else args.object_counts,
                               realism=realism)
        sequence = f"{args.scenario}:{args.seed}" + (f":{realism}" if realism else "")
        return list(range(len(data))), _ScenarioLoader(data, sequence)
    if not args.input:
        raise CliError("give a KITTI folder, or --scenario NAME --frames N")
    path = Path(args.input)
    if not path.is_dir():
        raise CliError(f"{path} is not a folder (a KITTI folder with velodyne/ and label_2/)")
    from lidarops.data.formats.kitti import KittiDataset

    data = KittiDataset(path)
    names = data.ids if args.frames is None else data.ids[:args.frames]
    if not names:
        raise CliError(f"{data.split_dir / 'velodyne'} holds no .bin scans")
    bad = [n for n in names if not n.isdigit()]
    if bad:
        raise CliError(f"{path}: frame id {bad[0]!r} is not a number (the index keys frames by integer ids)")
    if needs_labels and not (data.split_dir / "label_2").is_dir():
        raise CliError(f"{data.split_dir} has no label_2/ folder: --source labels counts the labels "
                       "(use --source detector to count with a detector)")
    if not needs_labels and args.fov == "camera" and not (data.split_dir / "calib").is_dir():
        raise CliError(f"{data.split_dir} has no calib/ folder: --fov camera (the default) keeps the points the "
                       "camera sees, as KITTI detectors are trained and evaluated; pass --fov all to count whole scans")
    return [int(n) for n in names], _KittiLoader(data, names, needs_labels, fov=args.fov == "camera")


class _ScenarioLoader:
    """``frame_id -> Frame`` of a simulated drive, its sequence named ``scenario:seed``."""

    def __init__(self, data, sequence: str):
        self.data, self.sequence = data, sequence

    def __call__(self, fid: int):
        frame = self.data[fid]
        frame.meta["sequence"] = self.sequence
        return frame


class _KittiLoader:
    """``frame_id -> Frame`` over a KITTI folder (a class, not a closure, so DataLoader workers can take it)."""

    def __init__(self, data, names: list[str], needs_labels: bool, fov: bool = False):
        self.data, self.needs_labels, self.fov = data, needs_labels, fov
        where = {n: i for i, n in enumerate(data.ids)}
        self.position = {int(n): where[n] for n in names}

    def __call__(self, fid: int):
        from lidarops.query.build import FrameError

        i = self.position[fid]
        name = self.data.ids[i]
        label = self.data.split_dir / "label_2" / f"{name}.txt"
        if not self.needs_labels:  # a counter needs the scan only: no labels, calibration or box counts read
            import torch

            from lidarops.data.formats.kitti import read_velodyne
            from lidarops.query.build import Scan

            scan = (self.data.split_dir / "velodyne" / f"{name}.bin").resolve()
            points = read_velodyne(scan)
            if self.fov:  # what a KITTI detector (FOV_POINTS_ONLY) was trained on, and what the labels cover
                points = points[self._fov_mask(points, name)]
            return Scan(points=torch.from_numpy(points), source=str(scan), frame_index=i)
        if not label.is_file():
            raise FrameError(f"frame {name}: no labels ({label} is missing)")
        return self.data[i]

    def _fov_mask(self, points, name: str):
        from lidarops.data.formats.kitti import KITTI_IMAGE_SIZE, kitti_fov_mask, png_size, read_calib
        from lidarops.query.build import FrameError

        calib = self.data.split_dir / "calib" / f"{name}.txt"
        if not calib.is_file():
            raise FrameError(f"frame {name}: no calibration ({calib} is missing; --fov camera needs it, --fov all "
                             "counts the whole scan)")
        size = png_size(self.data.split_dir / "image_2" / f"{name}.png") or KITTI_IMAGE_SIZE
        return kitti_fov_mask(points, read_calib(calib), size)


def build(args: argparse.Namespace) -> int:
    """Counts frames into an index (under torchrun: each rank its share, the index their union)."""
    from lidarops.query.build import CounterSource, DetectorSource, LabelsSource, build_index

    for flag, value, least in (("--batch", args.batch, 1), ("--part-frames", args.part_frames, 1),
                               ("--workers", args.workers, 0)):
        if value < least:
            raise CliError(f"{flag} must be >= {least}, got {value}")
    if not 0 <= args.score_thresh <= 1:  # NaN too
        raise CliError(f"--score-thresh must be a score in [0, 1], got {args.score_thresh}")
    for name in args.classes or []:
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
            raise CliError(f"--classes: {name!r} is not a class name (letters, digits, underscores)")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise CliError(f"--out {args.out} is a file; give a folder for the index")
    if args.min_points < 0:
        raise CliError(f"--min-points must be >= 0, got {args.min_points}")
    labels_range = None if args.labels_range == "all" else _region_arg(args.labels_range, "--labels-range")
    from lidarops.cli._device import resolve_device

    device = resolve_device(args.device)  # a bad --device is named even where the labels need none
    if args.precision == "fp16" and args.source != "labels" and device.type != "cuda":
        raise CliError(f"--precision fp16 needs a CUDA device, got --device {args.device} ({device.type}): "
                       "float16 on the CPU is far slower than float32")
    ids, load = _frames_of(args, needs_labels=args.source == "labels")
    from lidarops.train.distributed import DistContext

    # a plain "cuda" becomes cuda:LOCAL_RANK under torchrun
    ctx = DistContext.from_env((device.type if device.index is None else device) if args.source != "labels" else "cpu")
    try:
        if args.source == "labels":
            source = LabelsSource(args.classes or DEFAULT_CLASSES, region=labels_range, min_points=args.min_points)
        else:
            from lidarops.models import load_model, weights

            checkpoint = args.checkpoint or weights.path(SHIPPED_COUNTER if args.source == "counter" else weights.DEFAULT)
            model = load_model(checkpoint).to(ctx.device).eval()
            counts = type(model).__name__ in ("CounterNet", "SelectedCounter")
            if counts != (args.source == "counter"):
                raise CliError(f"--checkpoint {checkpoint} holds a {type(model).__name__}: "
                               f"--source {args.source} needs " + ("a CounterNet" if args.source == "counter" else
                                                                   "a detector (use --source counter for a CounterNet)"))
            graph = False if args.no_graph else None
            source = CounterSource(model, args.precision, graph=graph) if counts else \
                DetectorSource(model, args.score_thresh, args.precision, graph=graph)
        from lidarops._progress import progress_bar

        bar = progress_bar(len(ids), f"index {args.source}",
                           enabled=ctx.is_main and not args.no_progress and sys.stderr.isatty())
        try:
            report = build_index(args.out, ids, load, source, source_name=args.source, batch=args.batch,
                                 part_frames=args.part_frames, workers=args.workers,
                                 on_error="skip" if args.skip_bad else "raise", progress=bar.update)
        finally:
            bar.close()
        reports = ctx.gather_to_main(report)
    finally:
        ctx.close()
    if not ctx.is_main:
        return 0
    indexed = sum(r.indexed for r in reports)
    failed = sorted(f for r in reports for f in r.failed)
    wall = max(r.seconds for r in reports)
    ranks = f" on {len(reports)} ranks" if len(reports) > 1 else ""
    print(f"indexed {indexed} frame(s) with source {args.source} into {args.out} ({reports[0].skipped} already "
          f"there) in {wall:.1f} s{ranks} ({indexed / max(wall, 1e-9):.1f} frames/s; {reports[0].shares()})")
    if args.source == "labels":
        where = "everywhere" if labels_range is None else "centred in x [{:g}, {:g}), y [{:g}, {:g})".format(
            labels_range[0], labels_range[2], labels_range[1], labels_range[3])
        print(f"  labels counted: boxes {where} holding >= {args.min_points} point(s) (--labels-range, --min-points)")
    stages = getattr(source, "stage_seconds", None)
    if stages and report.stage_seconds.get("count"):
        print("  counting: " + ", ".join(f"{k} {100 * v / report.stage_seconds['count']:.0f} %"
                                         for k, v in stages.items()))
    if failed:
        listed = "; ".join(f"{fid}: {why}" for fid, why in failed[:5]) + (" ..." if len(failed) > 5 else "")
        print(f"left out {len(failed)} frame(s) that could not be read (a build run again retries them): {listed}")
        return 1
    return 0


def _parse_where(items: list[str]) -> dict:
    where = {}
    for item in items or []:
        m = _WHERE.match(item)
        if not m:
            raise CliError(f"--where {item!r}: expected CLASS OP NUMBER, e.g. Car>=5 (operators <, <=, =, >=, >)")
        if m.group(1) in where:
            raise CliError(f"--where names {m.group(1)} twice")
        where[m.group(1)] = (m.group(2), int(m.group(3)))
    return where


def _frames_arg(text: str | None):
    if text is None:
        return None
    m = re.match(r"^(\d+):(\d+)$", text)
    if not m or int(m.group(1)) > int(m.group(2)):
        raise CliError(f"--frames {text!r}: expected FIRST:STOP frame ids (STOP excluded), e.g. 0:500")
    return range(int(m.group(1)), int(m.group(2)))


def _region_arg(text: str | None, flag: str = "--region"):
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4:
        raise CliError(f"{flag} {text!r}: expected X0,Y0,X1,Y1 in metres, e.g. 0,-7.5,15,7.5")
    if not (values[0] < values[2] and values[1] < values[3]):  # NaN too
        raise CliError(f"{flag} {text!r}: expected X0 < X1 and Y0 < Y1")
    return tuple(values)


def query(args: argparse.Namespace) -> int:
    """Answers one query over an index (beside every other source's answer with --compare; as a page with
    --html)."""
    from lidarops.query import FrameIndex

    if getattr(args, "html_frames", 0) < 0:
        raise CliError(f"--html-frames must be >= 0, got {args.html_frames}")
    _output_file(args.html, "--html")
    idx = FrameIndex.open(args.index)
    frames, region = _frames_arg(args.frames), _region_arg(args.region)
    if args.source not in idx.sources:
        raise CliError(f"--source {args.source!r}: the index's sources are {', '.join(idx.sources)}")
    where = _parse_where(getattr(args, "where", None))
    for name in list(where) + ([args.cls] if getattr(args, "cls", None) else []):
        if name not in idx.classes:
            flag = "--class" if name == getattr(args, "cls", None) else "--where"
            raise CliError(f"{flag}: unknown class {name!r}; the index's classes: {', '.join(idx.classes)}")
    if args.kind == "count" and len(where) != 1:
        raise CliError("count takes one --where, e.g. --where 'Pedestrian>10'")
    if args.kind in ("sum", "avg") and not args.cls:
        raise CliError(f"{args.kind} needs --class, one of: {', '.join(idx.classes)}")

    def ask(source: str):
        """The query's answer from ``source``'s counts."""
        if args.kind == "retrieve":
            return idx.retrieve(where, frames=frames, source=source, region=region)
        if args.kind == "count":
            (cls, (op, value)), = where.items()
            return idx.count(cls, op, value, frames=frames, source=source, region=region)
        return getattr(idx, args.kind)(args.cls, frames=frames, source=source, region=region)

    answer = ask(args.source)
    if args.compare:
        _compare(idx, args, ask)
    elif args.kind == "retrieve":
        shown = ", ".join(str(i) for i in answer[:args.show]) + (" ..." if len(answer) > args.show else "")
        print(f"{len(answer)} frame(s): {shown}" if answer else "0 frames")
    else:
        print(answer if answer is not None else "no frames")
    if getattr(args, "counts", False) and answer:
        _counts_table(idx, answer[:args.show])
    if args.html:
        _answer_page(idx, args, answer, ask, where, frames, region)
    return 0


def _counts_table(idx, frame_ids: list) -> None:
    """--counts: each frame's count per class, every source's side by side (the labels first)."""
    sources = ["labels"] * ("labels" in idx.sources) + [s for s in idx.sources if s != "labels"]
    got = idx.sql("SELECT * FROM counts WHERE frame_id IN (SELECT UNNEST(?)) AND source IN (SELECT UNNEST(?))",
                  [list(map(int, frame_ids)), sources])
    cells = {(int(r["frame_id"]), r["source"]): r for _, r in got.iterrows()}
    header = ["frame"] + list(idx.classes)
    rows = [[str(f)] + [" / ".join("-" if (f, s) not in cells else str(int(cells[f, s][c])) for s in sources)
                        for c in idx.classes] for f in frame_ids]
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    print(f"counts per frame ({' / '.join(sources)}):")
    for r in [header] + rows:
        print("  ".join(v.rjust(w) for v, w in zip(r, widths)))


def _output_file(path: "str | None", flag: str) -> None:
    """A file the command will write: refused before any work when it is a folder or its folder is missing."""
    if path is None:
        return
    p = Path(path)
    if p.is_dir():
        raise CliError(f"{flag} {path} is a folder; give a file name")
    if not p.parent.is_dir():
        raise CliError(f"{flag} {path}: the folder {p.parent} does not exist")


def _compare(idx, args: argparse.Namespace, ask) -> None:
    """--compare: the answer of every source, beside the labels' (for retrieve: how many of the labels'
    frames each finds, and how many it adds)."""
    from lidarops.query import QueryError

    truth = ask("labels") if "labels" in idx.sources else None
    rows = []
    for source in ["labels"] * (truth is not None) + [s for s in idx.sources if s != "labels"]:
        try:
            got = truth if source == "labels" else ask(source)
        except QueryError as e:  # e.g. a region over a source without centres
            rows.append((source, f"cannot answer: {e}", ""))
            continue
        if args.kind == "retrieve":
            text = f"{len(got)} frame(s)"
            if truth is not None and source != "labels":
                hit = len(set(got) & set(truth))
                rows.append((source, text, f"{hit} of the labels' {len(truth)} found, {len(got) - hit} not in them"))
                continue
        else:
            text = "no frames" if got is None else (f"{got:.3f}" if isinstance(got, float) else str(got))
            if source != "labels" and got is not None and truth is not None:
                rows.append((source, text, f"{got - truth:+.3f}" if isinstance(got, float) else f"{got - truth:+d}"))
                continue
        rows.append((source, text, ""))
    width = max(len(r[0]) for r in rows)
    answer_width = max(len(r[1]) for r in rows)
    print(f"{'source':<{width}}  {'answer':<{answer_width}}  beside the labels")
    for source, text, note in rows:
        print(f"{source:<{width}}  {text:<{answer_width}}  {note}".rstrip())


def _answer_page(idx, args: argparse.Namespace, answer, ask, where: dict, frames, region) -> None:
    """--html: the answer page, its frames pictured (the retrieved ones; those meeting a count's condition;
    an aggregation's frames), beside the labels' answer when the source is another."""
    from lidarops.query import QueryError
    from lidarops.query.page import answer_page, points_from_index

    if args.kind == "retrieve":
        shown = answer
    else:  # count: the frames meeting its condition; sum, avg: every frame aggregated over
        shown = idx.retrieve(where if args.kind == "count" else {}, frames=frames, source=args.source, region=region)
    truth, truth_answer = ("labels" if args.source != "labels" and "labels" in idx.sources else None), None
    if truth:
        try:
            truth_answer = ask(truth)
        except QueryError:  # e.g. labels without centres under --region: the page says so, no truth answer
            pass
    text = " AND ".join(f"{c}{op}{v}" for c, (op, v) in where.items()) or getattr(args, "cls", None) or "all frames"
    text = f"{args.kind} {text}" + (f" frames {args.frames}" if args.frames else "") + (
        f" region {args.region}" if args.region else "")
    path = answer_page(idx, args.html, kind=args.kind, query_text=text, answer=answer, frame_ids=shown,
                       source=args.source, truth=truth, max_frames=args.html_frames, region=region,
                       points_of=points_from_index(idx, shown[:args.html_frames], source=args.source),
                       truth_answer=truth_answer)
    print(f"answer page: {path} ({min(len(shown), args.html_frames)} of {len(shown)} frame(s) pictured)")


def evaluate(args: argparse.Namespace) -> int:
    """Scores a source's counts against the labels' with CounterNet's query metrics."""
    import json

    from lidarops.query import FrameIndex
    from lidarops.query.evaluate import evaluate as run

    _output_file(args.json, "--json")
    m = re.match(r"^(\d+):(\d+)$", args.group_frames)
    if not m:
        raise CliError(f"--group-frames {args.group_frames!r}: expected FEWEST:MOST frames, e.g. 100:500")
    result = run(FrameIndex.open(args.index), source=args.source, truth=args.truth, classes=args.classes,
                 seed=args.seed, tolerances=tuple(args.tolerances), groups=args.groups, queries=args.queries,
                 group_frames=(int(m.group(1)), int(m.group(2))))
    print(result.format())
    if args.json:
        Path(args.json).write_text(json.dumps(result.as_dict(), indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0


def register(subparsers) -> None:
    """Adds ``index`` and ``query`` to the ``lidarops`` parser."""
    p = subparsers.add_parser("index", help="count frames into a frame index (docs/query.md)")
    sub = p.add_subparsers(dest="index_command", metavar="SUBCOMMAND")
    b = sub.add_parser("build", help="count the frames of a KITTI folder or a scenario into an index",
                       description="Count each frame's objects per class (the labels, or the shipped detector used as "
                                   "a counter) into a frame index of Parquet files. Run again on the same --out it "
                                   "skips the frames already counted.")
    b.add_argument("input", nargs="?", help="a KITTI folder (velodyne/, label_2/)")
    b.add_argument("--scenario", help="simulate frames of this scenario instead")
    b.add_argument("--frames", type=int, default=None, help="number of frames (scenario: required; folder: all)")
    b.add_argument("--seed", type=int, default=HELD_OUT_SEED, help=f"scenario seed (default {HELD_OUT_SEED})")
    b.add_argument("--object-counts", choices=["default", "dense", "empty"], default="default",
                   help="scenario traffic (default: the scenario's own)")
    b.add_argument("--frames-per-scene", type=int, default=1, help="scenario: consecutive sweeps of one drive per "
                                                                   "scene (default 1: a new scene each frame)")
    b.add_argument("--realism", default=None, type=_realism_arg, metavar="PROFILE",
                   help="scenario: the simulator's realism profile (kitti, kitti_dr, avia; as `data synth "
                        "--realism`): the frames the shipped CounterNets were trained on; default: as ray-cast")
    b.add_argument("--source", choices=["labels", "detector", "counter"], default="labels",
                   help="what counts (default labels); detector: a detector's boxes; counter: a CounterNet")
    b.add_argument("--checkpoint", help="detector checkpoint (default: the shipped PointPillars), or a CounterNet's "
                                        f"for --source counter (default: the shipped {SHIPPED_COUNTER}, seven road "
                                        "classes)")
    b.add_argument("--score-thresh", type=float, default=0.5, help="detector: count boxes scoring at least this "
                                                                    "(default 0.5)")
    b.add_argument("--classes", nargs="+", help=f"labels: classes to count (default {' '.join(DEFAULT_CLASSES)})")
    b.add_argument("--labels-range", default=SHIPPED_RANGE, help="labels: count boxes centred in X0,Y0,X1,Y1 metres, "
                                                                 "or 'all' (default: the shipped PointPillars' range, "
                                                                 f"{SHIPPED_RANGE}, what it can count)")
    b.add_argument("--min-points", type=int, default=1, help="labels: count boxes holding at least this many points "
                                                             "(default 1: what a LiDAR can see)")
    b.add_argument("--fov", choices=["camera", "all"], default="camera",
                   help="detector/counter on a KITTI folder: the points the camera sees (default: what KITTI "
                        "detectors are trained on and the labels cover; needs calib/), or the whole scan")
    b.add_argument("--device", default="auto", help="detector: auto (default), cpu, cuda")
    b.add_argument("--precision", choices=["fp32", "tf32", "fp16"], default=None,
                   help="detector, counter: the network's arithmetic on CUDA: fp32 (no TF32), tf32, fp16 (float16 "
                        "autocast); default: torch's settings (cuDNN convolutions in TF32)")
    b.add_argument("--batch", type=int, default=8, help="frames per detector call (default 8)")
    b.add_argument("--no-graph", action="store_true", help="detector, counter: run each batch eagerly, not as one "
                                                           "replayed CUDA graph (the default for PointPillars and "
                                                           "CounterNet on CUDA)")
    b.add_argument("--workers", type=int, default=2, help="DataLoader processes reading frames (default 2; 0: "
                                                          "read in this process)")
    b.add_argument("--part-frames", type=int, default=1024, help="frames per Parquet part, the most a killed build "
                                                                 "redoes (default 1024)")
    b.add_argument("--skip-bad", action="store_true", help="leave out frames that cannot be read (an unreadable "
                                                           "scan, missing labels), list them, exit 1; default: stop "
                                                           "at the first")
    b.add_argument("--out", required=True, help="index folder")
    b.add_argument("--no-progress", action="store_true", help="no progress bar")
    b.set_defaults(func=guarded("index build", build))
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])

    q = subparsers.add_parser("query", help="answer RETRIEVAL / COUNT / AGGREGATION queries over a frame index",
                              description="Query a frame index (docs/query.md).")
    qs = q.add_subparsers(dest="query_command", metavar="KIND")
    for kind, text in (("retrieve", "frames meeting every --where"), ("count", "how many frames meet one --where"),
                       ("sum", "total objects of --class"), ("avg", "mean objects of --class per frame")):
        k = qs.add_parser(kind, help=text, description=f"{kind}: {text}.")
        k.add_argument("index", help="index folder")
        if kind in ("retrieve", "count"):
            k.add_argument("--where", action="append", help="CLASS OP NUMBER, e.g. 'Car>=5' (repeatable)")
        else:
            k.add_argument("--class", dest="cls", help="class to aggregate")
        k.add_argument("--source", default="labels", help="whose counts (default labels)")
        k.add_argument("--frames", help="FIRST:STOP frame ids (default: all)")
        k.add_argument("--region", help="X0,Y0,X1,Y1 metres: count only objects inside")
        if kind == "retrieve":
            k.add_argument("--show", type=int, default=20, help="frame ids printed (default 20)")
            k.add_argument("--counts", action="store_true", help="also print the shown frames' counts per class, "
                                                                 "every source's side by side")
        k.add_argument("--compare", action="store_true", help="the answer of every source of the index, beside the "
                                                              "labels'")
        k.add_argument("--html", metavar="PATH", help="also write the answer page: one self-contained HTML file "
                                                      "(counts table, bird's-eye view of each frame; docs/query.md)")
        k.add_argument("--html-frames", type=int, default=24, metavar="N", help="frames pictured on the page "
                                                                                "(default 24)")
        k.set_defaults(func=guarded(f"query {kind}", query), kind=kind)
    e = qs.add_parser("evaluate", help="score a source's counts against the labels (CounterNet's query metrics)",
                      description="RETRIEVAL-SINGLE / -MULTIPLE accuracy, COUNT accuracy over random groups of "
                                  "consecutive frames, AGGREGATION difference and Q-error, per-class counting "
                                  "accuracy (docs/query.md).")
    e.add_argument("index", help="index folder")
    e.add_argument("--source", default="detector", help="the source scored (default detector)")
    e.add_argument("--truth", default="labels", help="the source taken as the truth (default labels)")
    e.add_argument("--classes", nargs="+", help="classes scored (default: all the index's)")
    e.add_argument("--tolerances", nargs="+", type=float, default=[0.10, 0.05], help="RETRIEVAL tolerances "
                                                                                     "(default 0.10 0.05)")
    e.add_argument("--groups", type=int, default=500, help="random groups of consecutive frames (default 500)")
    e.add_argument("--queries", type=int, default=1000, help="COUNT queries per class (default 1000)")
    e.add_argument("--group-frames", default="100:500", help="FEWEST:MOST frames of a group (default 100:500)")
    e.add_argument("--seed", type=int, default=0, help="seed of the random groups and queries (default 0)")
    e.add_argument("--json", metavar="PATH", help="also write the results as JSON")
    e.set_defaults(func=guarded("query evaluate", evaluate))
    q.set_defaults(func=lambda a: (q.print_help(), 2)[1])
