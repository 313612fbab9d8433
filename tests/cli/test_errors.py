"""One error convention for every command (lidarops/cli/errors.py): a missing file, a bad value or a device the
machine cannot serve is one line on stderr, ``lidarops <command>: error: <message>``, exit code 2, nothing run
and no traceback; Ctrl-C is ``lidarops <command>: interrupted``, exit code 130; a bug keeps its traceback."""
from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import torch

from lidarops.cli import build_parser
from lidarops.cli.errors import CliError, guarded
from .helpers import REPO, one_error_line, repo_config

NEVER = Path("out")  # where the commands below would write, had they not failed first


@pytest.fixture(autouse=True)
def _nothing_written(tmp_path, monkeypatch):
    """Each test runs in an empty folder (relative and default outputs land there) that must stay empty."""
    monkeypatch.chdir(tmp_path)
    yield
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def _commands() -> dict[str, argparse.ArgumentParser]:
    """Every command as typed after ``lidarops`` ("detect", "data synth"), with its parser."""
    found = {}

    def walk(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{prefix} {name}".strip())
        if prefix and not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions):
            found[prefix] = parser

    walk(build_parser(), "")
    return found


def test_every_command_reports_errors_through_guarded():
    commands = _commands()
    assert {"tour", "data synth", "data show", "stream", "train", "detect", "eval"} <= set(commands)
    for name, parser in commands.items():
        func = parser.get_default("func")
        assert func is not None and func.__name__ == f"lidarops {name}", (name, func)


# ---- the wrapper itself: each class of error --------------------------------------------------------------

def _user_errors():
    from lidarops.checkpoint import CheckpointError
    from lidarops.config import ConfigError
    from lidarops.extension import LidaropsBuildError

    return [CliError("give a folder"), FileNotFoundError("config file not found: x.yaml"),
            FileExistsError("runs/pp already holds a run"), NotADirectoryError("x is not a folder"),
            PermissionError(13, "Permission denied", "x.png"), ValueError("--lr must be positive"),
            ConfigError("x.yaml: not valid YAML"), CheckpointError("x.pth: not a readable checkpoint"),
            ImportError("No module named 'matplotlib'"), LidaropsBuildError("not built.\nBuild them with make")]


@pytest.mark.parametrize("error", _user_errors(), ids=lambda e: type(e).__name__)
def test_user_errors_are_one_line(error, capsys):
    def fail(args):
        raise error

    assert guarded("demo", fail)(argparse.Namespace()) == 2
    cap = capsys.readouterr()
    line = one_error_line(cap.err, "demo")
    assert line == "lidarops demo: error: " + " ".join(str(error).split()) and cap.out == ""


def test_interrupt_is_130(capsys):
    def interrupted(args):
        raise KeyboardInterrupt

    assert guarded("demo", interrupted)(argparse.Namespace()) == 130
    assert capsys.readouterr().err == "lidarops demo: interrupted\n"


def test_bugs_keep_their_traceback():
    def buggy(args):
        raise RuntimeError("a bug")

    with pytest.raises(RuntimeError, match="a bug"):
        guarded("demo", buggy)(argparse.Namespace())


def test_exit_codes_pass_through():
    assert guarded("demo", lambda args: None)(argparse.Namespace()) == 0
    assert guarded("demo", lambda args: 1)(argparse.Namespace()) == 1  # e.g. stream's failed identity check


# ---- each command, each class of error ----------------------------------------------------------------------

def _expect_one_line(run_cli, argv: list, pattern: str) -> None:
    import re

    code, out, err = run_cli(argv)
    command = " ".join(argv[:2]) if argv[0] == "data" else argv[0]
    line = one_error_line(err, command)
    assert code == 2 and re.search(pattern, line), line
    assert out == "", f"the command ran before the error:\n{out}"


@pytest.mark.parametrize("argv, pattern", [
    (["train", "--config", "/no/such.yaml", "--out", NEVER], "config file not found: /no/such.yaml"),
    (["train", "--config", repo_config("pointpillars_demo.yaml"), "--data", "/no/such/dir", "--out", NEVER],
     "data folder /no/such/dir not found"),
    (["detect", "/no/such.bin", "--device", "cpu"], "/no/such.bin not found"),
    (["detect", "--checkpoint", "/no/ckpt.pth", "--scenario", "driving_city", "--device", "cpu"],
     "checkpoint /no/ckpt.pth not found"),
    (["eval", "--results", "/no/such/dir", "--labels", "/no/such/dir"], "--results /no/such/dir is not a folder"),
    (["eval", "--results", REPO, "--labels", REPO, "--split", "/no/split.txt"], "--split /no/split.txt not found"),
    (["data", "show", "/no/such/frame.bin", "--out", NEVER / "x.png"], "frame.bin not found: neither a file"),
    (["stream", "--seconds", "0.02", "--device", "cpu", "--out", REPO / "README.md" / "x.png"], "cannot be written"),
])
def test_missing_files(argv, pattern, run_cli):
    _expect_one_line(run_cli, argv, pattern)


@pytest.mark.parametrize("argv, pattern", [
    (["train", "--config", repo_config("pointpillars_demo.yaml"), "--out", NEVER, "--lr", "-1"],
     "lr must be a finite number > 0, got -1.0"),
    (["train", "--config", REPO / "README.md", "--out", NEVER], "not valid YAML"),
    (["detect", "--scenario", "driving_city", "--score-thresh", "2", "--device", "cpu", "--out", NEVER],
     r"--score-thresh must be in \[0, 1\)"),
    (["detect", "--scenario", "no_such_scenario", "--device", "cpu", "--out", NEVER], "no_such_scenario"),
    (["eval", "--results", REPO / "configs", "--labels", REPO / "configs"], "no frames to score"),
    (["data", "synth", "--val-fraction", "2", "--out", NEVER], r"--val-fraction must be in \[0, 1\]"),
    (["data", "show", "driving_city", "--index", "-1"], "--index must be >= 0"),
    (["stream", "--seconds", "0", "--device", "cpu", "--out", NEVER / "x.png"], "--seconds must be a positive number"),
    (["tour", "--n", "10", "--device", "cpu"], "--n must be an integer >= 64, got 10"),
])
def test_bad_values(argv, pattern, run_cli):
    _expect_one_line(run_cli, argv, pattern)


@pytest.mark.parametrize("argv", [
    ["train", "--config", repo_config("pointpillars_demo.yaml"), "--out", NEVER, "--device", "cuda"],
    ["detect", "--scenario", "driving_city", "--device", "cuda:1", "--out", NEVER],
    ["stream", "--seconds", "0.02", "--device", "cuda", "--out", NEVER / "x.png"],
    ["tour", "--device", "cuda"],
])
def test_cuda_without_cuda(argv, monkeypatch, run_cli):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.version, "cuda", None)
    _expect_one_line(run_cli, argv, r"--device cuda(:1)?: this torch \(.*\) is built without CUDA; use --device cpu")


@pytest.mark.parametrize("argv", [
    ["train", "--config", repo_config("pointpillars_demo.yaml"), "--out", NEVER, "--device", "tpu"],
    ["detect", "--scenario", "driving_city", "--device", "tpu", "--out", NEVER],
])
def test_unknown_devices(argv, run_cli):
    _expect_one_line(run_cli, argv, "--device must be cpu or cuda, got 'tpu'")


@pytest.mark.parametrize("command", ["stream", "tour"])
def test_unknown_devices_are_usage_errors(command, capsys):
    """stream and tour list their devices: argparse refuses others (its usage, then one error line, exit 2)."""
    from lidarops.cli import main

    with pytest.raises(SystemExit) as e:
        main([command, "--device", "tpu"])
    assert e.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1].startswith(f"lidarops {command}: error: argument --device")
