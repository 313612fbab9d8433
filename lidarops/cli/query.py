"""``lidarops index build`` (count frames into a frame index) and ``lidarops query retrieve|count|sum|avg``
(docs/query.md)."""
from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from lidarops.cli.errors import CliError, guarded
from lidarops.conventions import HELD_OUT_SEED

_WHERE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(<=|>=|<|>|=)\s*(-?\d+)\s*$")
DEFAULT_CLASSES = ("Car", "Pedestrian", "Cyclist")


def _frames_of(args: argparse.Namespace):
    """(frame_id, Frame) pairs of a scenario or a KITTI folder."""
    if args.scenario:
        from lidarops.data.synthetic import SyntheticFrames

        if args.frames is None or args.frames < 1:
            raise CliError(f"--frames must be >= 1 with --scenario, got {args.frames}")
        data = SyntheticFrames(args.scenario, num_frames=args.frames, seed=args.seed)
        return len(data), ((i, data[i]) for i in range(len(data)))
    if not args.input:
        raise CliError("give a KITTI folder, or --scenario NAME --frames N")
    path = Path(args.input)
    if not path.is_dir():
        raise CliError(f"{path} is not a folder (a KITTI folder with velodyne/ and label_2/)")
    from lidarops.data.formats.kitti import KittiDataset

    data = KittiDataset(path)
    n = len(data) if args.frames is None else min(len(data), args.frames)
    if n == 0:
        raise CliError(f"{path} holds no frames")
    for i in range(n):
        if not data.ids[i].isdigit():
            raise CliError(f"{path}: frame id {data.ids[i]!r} is not a number (the index keys frames by integer ids)")
    return n, ((int(data.ids[i]), data[i]) for i in range(n))


def build(args: argparse.Namespace) -> int:
    """Counts frames into an index."""
    from lidarops.query.build import DetectorSource, LabelsSource, build_index

    if args.chunk < 1:
        raise CliError(f"--chunk must be >= 1, got {args.chunk}")
    if not 0 <= args.score_thresh <= 1:  # NaN too
        raise CliError(f"--score-thresh must be a score in [0, 1], got {args.score_thresh}")
    for name in args.classes or []:
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
            raise CliError(f"--classes: {name!r} is not a class name (letters, digits, underscores)")
    from lidarops.cli._device import resolve_device

    device = resolve_device(args.device)
    if args.source == "labels":
        source = LabelsSource(args.classes or DEFAULT_CLASSES)
    else:
        from lidarops.models import load_model, weights

        model = load_model(args.checkpoint or weights.path()).to(device).eval()
        source = DetectorSource(model, args.score_thresh)
    total, frames = _frames_of(args)
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise CliError(f"--out {args.out} is a file; give a folder for the index")
    from lidarops._progress import progress_bar

    start = time.perf_counter()
    bar = progress_bar(total, f"index {args.source}", enabled=not args.no_progress and sys.stderr.isatty())
    try:
        result = build_index(args.out, frames, source, source_name=args.source, chunk=args.chunk, progress=bar.update)
    finally:
        bar.close()
    wall = time.perf_counter() - start
    print(f"indexed {result['indexed']} frame(s) with source {args.source} into {args.out} "
          f"({result['skipped']} already there) in {wall:.1f} s ({total / max(wall, 1e-9):.1f} frames/s)")
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


def _region_arg(text: str | None):
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4:
        raise CliError(f"--region {text!r}: expected X0,Y0,X1,Y1 in metres, e.g. 0,-7.5,15,7.5")
    return tuple(values)


def query(args: argparse.Namespace) -> int:
    """Answers one query over an index."""
    from lidarops.query import FrameIndex

    idx = FrameIndex.open(args.index)
    frames, region = _frames_arg(args.frames), _region_arg(args.region)
    if args.source not in idx.sources:
        raise CliError(f"--source {args.source!r}: the index's sources are {', '.join(idx.sources)}")
    where = _parse_where(getattr(args, "where", None))
    for name in list(where) + ([args.cls] if getattr(args, "cls", None) else []):
        if name not in idx.classes:
            flag = "--class" if name == getattr(args, "cls", None) else "--where"
            raise CliError(f"{flag}: unknown class {name!r}; the index's classes: {', '.join(idx.classes)}")
    if args.kind == "retrieve":
        ids = idx.retrieve(where, frames=frames, source=args.source, region=region)
        shown = ", ".join(str(i) for i in ids[:args.show]) + (" ..." if len(ids) > args.show else "")
        print(f"{len(ids)} frame(s): {shown}" if ids else "0 frames")
        return 0
    if args.kind == "count":
        if len(where) != 1:
            raise CliError("count takes one --where, e.g. --where 'Pedestrian>10'")
        (cls, (op, value)), = where.items()
        print(idx.count(cls, op, value, frames=frames, source=args.source, region=region))
        return 0
    if not args.cls:
        raise CliError(f"{args.kind} needs --class, one of: {', '.join(idx.classes)}")
    value = getattr(idx, args.kind)(args.cls, frames=frames, source=args.source, region=region)
    print(value if value is not None else "no frames")
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
    b.add_argument("--source", choices=["labels", "detector"], default="labels", help="what counts (default labels)")
    b.add_argument("--checkpoint", help="detector checkpoint (default: the shipped PointPillars)")
    b.add_argument("--score-thresh", type=float, default=0.5, help="detector: count boxes scoring at least this "
                                                                    "(default 0.5)")
    b.add_argument("--classes", nargs="+", help=f"labels: classes to count (default {' '.join(DEFAULT_CLASSES)})")
    b.add_argument("--device", default="auto", help="detector: auto (default), cpu, cuda")
    b.add_argument("--chunk", type=int, default=64, help="frames per Parquet part (default 64)")
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
        k.set_defaults(func=guarded(f"query {kind}", query), kind=kind)
    q.set_defaults(func=lambda a: (q.print_help(), 2)[1])
