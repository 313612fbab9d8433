"""The ``lidarops`` command line.

Each area adds its subcommands through a ``register(subparsers)`` function in its own module
(listed in ``_SUBCOMMAND_MODULES``), imported lazily so that ``import lidarops`` stays light.
"""
from __future__ import annotations

import argparse
import importlib
import sys

_SUBCOMMAND_MODULES = (
    "lidarops.tour",  # lidarops tour: a short tour of the ops on synthetic clouds
    "lidarops.data.cli",  # lidarops data synth|show
    "lidarops.sscater.cli",  # lidarops stream: the simulator through SSCATeR PointPillars (make demo)
    "lidarops.models.cli",  # lidarops train|detect|eval: the PointPillars detector
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lidarops", description="Fast LiDAR point-cloud ops for PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as e:  # an area not present in this build
            if e.name != name:
                raise
            continue
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
