"""The ``lidarops`` command line: every command, one module each.

    lidarops tour                      a short tour of the neighbourhood ops on a synthetic sweep
    lidarops data synth|show           simulate LiDAR data; write and view dataset files
    lidarops stream                    the simulator streamed through SSCATeR PointPillars
    lidarops train                     train a model (detector, classifier, CAS-Net) from a config
    lidarops detect                    run a detector on frames; boxes, result files, pictures
    lidarops eval                      KITTI AP of result files against labels
    lidarops index build, query ...    count frames into a frame index; RETRIEVAL / COUNT / AGGREGATION queries
    lidarops sample                    keep 1/D of a scan's points; sampled files and before/after pictures

Each module in ``_SUBCOMMAND_MODULES`` adds its command through ``register(subparsers)``; they are imported
when the parser is built, not by ``import lidarops``. Every command reports errors the same way
(:mod:`lidarops.cli.errors`). This package is the one place that joins the models, data, training and
evaluation; nothing below it imports it.
"""
from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["build_parser", "main"]

_SUBCOMMAND_MODULES = (
    "lidarops.cli.tour",
    "lidarops.cli.data",
    "lidarops.cli.stream",
    "lidarops.cli.train",
    "lidarops.cli.detect",
    "lidarops.cli.eval",
    "lidarops.cli.query",
    "lidarops.cli.sample",
)


def build_parser() -> argparse.ArgumentParser:
    """The ``lidarops`` parser with every command's subparser."""
    parser = argparse.ArgumentParser(prog="lidarops", description="Fast LiDAR point-cloud ops for PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Runs ``lidarops`` with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
