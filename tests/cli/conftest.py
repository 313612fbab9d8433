"""Fixtures of the command-line tests: ``lidarops`` run in-process, and one small synthetic KITTI folder shared
by the train, detect and eval tests."""
from __future__ import annotations

from pathlib import Path

import pytest

from lidarops.cli import main


@pytest.fixture
def run_cli(capsys):
    """``run_cli(argv) -> (exit code, stdout, stderr)`` of ``lidarops argv``, run in-process."""

    def run(argv: list) -> tuple[int, str, str]:
        code = main([str(a) for a in argv])
        out = capsys.readouterr()
        return code, out.out, out.err

    return run


@pytest.fixture(scope="session")
def synth_kitti(tmp_path_factory) -> Path:
    """6 simulated driving_city frames as a KITTI folder: 4 in ImageSets/train.txt, 2 in val.txt."""
    out = tmp_path_factory.mktemp("synth")
    assert main(["data", "synth", "--scenario", "driving_city", "--frames", "6", "--val-fraction", "0.34",
                 "--out", str(out), "--no-progress", "--seed", "3"]) == 0
    return out
