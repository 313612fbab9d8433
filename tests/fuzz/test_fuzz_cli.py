"""Fuzz: every ``lidarops`` command with hostile option values.

Each example takes a command's cheapest valid command line and replaces one to three of its options by a
value drawn from what a user could type and the command cannot mean (NaN, infinities, negative or zero
counts, fractions outside [0, 1], junk, a directory or a binary file where a text file goes, a file that
does not exist). The rule: the command exits with 2 without running, and says so in one line that names
the option (its flag, or its value as typed): ``lidarops <command>: error: ...`` from the command, or
argparse's ``error: argument --flag: ...`` after its usage line. Never a traceback, never exit code 0 or 1,
never a file written.
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from lidarops.cli import main

from .fuzzing import fuzz

_INT_JUNK = ["abc", "", "1.5", "nan", "1e3", "0x10"]
_FLOAT_JUNK = ["abc", "", "nan", "inf", "-inf", "NaN", "1e309"]
_NOT_A_FILE = ["{missing}", "{dir}"]
_NOT_TEXT = ["{binary}", "{dir}", "{missing}"]


# command -> (its cheapest valid argv, {option: values it must refuse})
COMMANDS: dict[str, tuple[list[str], dict[str, list[str]]]] = {
    "detect": (["detect", "--scenario", "driving_city", "--frames", "1", "--device", "cpu", "--png", "0",
                "--out", "{out}"], {
        "--frames": _INT_JUNK + ["0", "-1", "-100"],
        "--seed": _INT_JUNK,
        "--score-thresh": _FLOAT_JUNK + ["-0.5", "1.5"],
        "--png": _INT_JUNK + ["-1"],
        "--print-frames": _INT_JUNK + ["-1"],
        "--print-boxes": _INT_JUNK + ["-1"],
        "--draw-score": _FLOAT_JUNK + ["-0.1", "1.5"],
        "--checkpoint": _NOT_A_FILE + ["{binary}", "{empty}"],
        "--config": _NOT_TEXT + ["{empty}"],
        "--device": ["gpu", "cuda:x", "", "tpu", "meta"],
        "--scenario": ["driving", "", "nope"],
        "--format": ["bin", ""],
    }),
    "eval": (["eval", "--results", "{results}", "--labels", "{labels}"], {
        "--results": _NOT_A_FILE + ["{binary}"],
        "--labels": _NOT_A_FILE + ["{binary}"],
        "--split": _NOT_TEXT + ["{empty}"],
        "--classes": ["", " "],
    }),
    "train": (["train", "--config", "{config}", "--data", "{dir}", "--out", "{out}", "--device", "cpu"], {
        "--config": _NOT_TEXT + ["{empty}"],
        "--epochs": _INT_JUNK + ["0", "-1"],
        "--batch-size": _INT_JUNK + ["0", "-3"],
        "--lr": _FLOAT_JUNK + ["0", "-0.1"],
        "--workers": _INT_JUNK + ["-1"],
        "--eval-every": _INT_JUNK + ["-1"],
        "--max-minutes": _FLOAT_JUNK[:-1] + ["0", "-1"],
        "--max-steps": _INT_JUNK + ["0", "-1"],
        "--max-train-frames": _INT_JUNK + ["0", "-1"],
        "--max-val-frames": _INT_JUNK + ["0", "-1"],
        "--gt-database-frames": _INT_JUNK + ["0", "-1"],
        "--pretrained-model": _NOT_A_FILE + ["{binary}", "{empty}", "no_such_model"],
        "--amp": ["fp8", ""],
        "--device": ["gpu", "", "cuda:x", "tpu", "meta"],
    }),
    "data synth": (["data", "synth", "--frames", "1", "--out", "{out}", "--no-progress"], {
        "--frames": _INT_JUNK + ["0", "-1"],
        "--val-fraction": _FLOAT_JUNK + ["-0.1", "1.5"],
        "--frames-per-scene": _INT_JUNK + ["0", "-2"],
        "--workers": _INT_JUNK + ["0", "-1"],
        "--object-counts": ["{", "[1, 2]", '{"Car": -1}', '{"Lorry": 3}', '{"Car": "many"}', "sparse",
                            '{"Car": [5, 2]}', '{"Car": NaN}'],
        "--scenario": ["nope", ""],
        "--sensor": ["vlp16"],
        "--seed": _INT_JUNK,
    }),
    "data show": (["data", "show", "{scan}", "--out", "{out}/bev.png"], {
        "path": _NOT_A_FILE + ["{empty}"],
        "--index": _INT_JUNK + ["-1", "99"],
        "--fov": _FLOAT_JUNK + ["-10", "0", "400"],
        "--max-extent": _FLOAT_JUNK + ["0", "-5"],
        "--color-by": ["height", ""],
    }),
    "stream": (["stream", "--small", "--seconds", "0.2", "--device", "cpu", "--no-progress"], {
        "--seconds": _FLOAT_JUNK + ["0", "-1"],
        "--slice": _FLOAT_JUNK + ["0", "-0.01"],
        "--window": _FLOAT_JUNK + ["0", "-0.1"],
        "--check-every": _INT_JUNK + ["-1"],
        "--refresh-every": _INT_JUNK + ["-1"],
        "--relu-zeros": _FLOAT_JUNK + ["-0.1", "1.5"],
        "--max-points-per-pillar": _INT_JUNK + ["0", "-1"],
        "--max-pillars": _INT_JUNK + ["0", "-1"],
        "--threads": _INT_JUNK + ["0", "-1"],
        "--scenario": ["nope"],
        "--dtype": ["float16"],
    }),
    "index build": (["index", "build", "--scenario", "driving_city", "--frames", "1", "--out", "{out}/idx",
                     "--no-progress"], {
        "--frames": _INT_JUNK + ["0", "-1"],
        "--seed": _INT_JUNK,
        "--batch": _INT_JUNK + ["0", "-4"],
        "--part-frames": _INT_JUNK + ["0", "-4"],
        "--workers": _INT_JUNK + ["-1"],
        "--score-thresh": _FLOAT_JUNK + ["-0.5", "1.5"],
        "--precision": ["fp8", "", "FP16", "half", "bf16"],
        "--fov": ["", "Camera", "none", "360"],
        "--classes": ["", "two words", "1st"],
        "--labels-range": ["1,2,3", "a,b,c,d", "1,1,0,0", "nan,0,1,1", ""],
        "--min-points": _INT_JUNK + ["-1"],
        "--object-counts": ["busy", ""],
        "--frames-per-scene": _INT_JUNK + ["0"],
        "--source": ["radar", ""],
        "--device": ["gpu", "", "cuda:x", "tpu"],
        "--scenario": ["nope", ""],
    }),
    "tour": (["tour", "--device", "cpu", "--n", "2000"], {
        "--n": _INT_JUNK + ["0", "-1"],
        "--seed": _INT_JUNK,
        "--device": ["gpu", ""],
    }),
    # the path third, where _with puts a positional's hostile value
    "sample": (["sample", "--no-picture", "{scan}", "--device", "cpu", "--out", "{out}"], {
        "path": _NOT_A_FILE + ["{empty}", "{binary}"],
        "--ratio": _INT_JUNK + ["0", "-1"],
        "--frames": _INT_JUNK + ["0", "-1"],
        "--method": ["voxel", "", "FPS"],
        "--seed": _INT_JUNK + ["-1"],
        "--checkpoint": _NOT_A_FILE + ["{binary}"],
        "--device": ["gpu", "", "cuda:x", "tpu"],
        "--out": ["{binary}"],
    }),
}


if importlib.util.find_spec("duckdb") and importlib.util.find_spec("pyarrow"):  # the query extra
    COMMANDS["query sum"] = (["query", "sum", "{index}", "--class", "Car"], {
        "--class": ["", "Truck", "car"],
        "--source": ["radar", ""],
        "--frames": ["5-9", "a:b", "9:5", ""],
        "--region": ["1,2,3", "a,b,c,d", "1,1,0,0", "nan,0,1,1", ""],
    })
    COMMANDS["query retrieve"] = (["query", "retrieve", "{index}", "--where", "Car>=1"], {
        "--where": ["Car=>1", "Truck>=1", "Car>=x", "", "Car>=1.5"],
        "--show": _INT_JUNK,
        "--frames": ["5-9", "9:5"],
        "--html-frames": _INT_JUNK + ["-1"],
        "--html": ["{dir}", "/nonexistent/dir/page.html"],
    })
    COMMANDS["query evaluate"] = (["query", "evaluate", "{index}", "--source", "labels", "--groups", "3",
                                   "--queries", "5", "--group-frames", "1:2"], {
        "--source": ["radar", ""],
        "--truth": ["radar", ""],
        "--classes": ["Truck", ""],
        "--tolerances": _FLOAT_JUNK + ["-0.1", "1.5"],
        "--groups": _INT_JUNK + ["0", "-1"],
        "--queries": _INT_JUNK + ["0", "-1"],
        "--group-frames": ["5-9", "9:5", "0:0", ""],
        "--seed": _INT_JUNK + ["-1"],
        "--json": ["{dir}", "/nonexistent/dir/x.json"],
    })


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The paths the command lines refer to: a result and a label folder, a config, a scan, junk."""
    root = tmp_path_factory.mktemp("cli-fuzz")
    (root / "results").mkdir()
    (root / "labels").mkdir()
    line = "Car 0.00 0 -1.58 100.0 150.0 200.0 220.0 1.50 1.60 3.90 1.00 1.60 12.00 -1.55"
    (root / "results" / "000000.txt").write_text(line + " 0.9\n")
    (root / "labels" / "000000.txt").write_text(line + "\n")
    (root / "binary.bin").write_bytes(bytes(range(256)) * 4)
    (root / "empty.txt").write_bytes(b"")
    (root / "dir").mkdir()
    repo = Path(__file__).resolve().parents[2]
    scan = root / "velodyne" / "000000.bin"
    scan.parent.mkdir()
    import numpy as np

    pts = np.random.default_rng(0).uniform(-20, 20, (500, 4)).astype(np.float32)
    pts[:, 3] = 0.5
    scan.write_bytes(pts.tobytes())
    index = root / "index"
    if "query sum" in COMMANDS:
        from lidarops.query import FrameIndex

        FrameIndex.create(index, {"frame_id": [0, 1, 2], "Car": [1, 0, 4], "Pedestrian": [0, 2, 0]},
                          centres={"frame_id": [0, 2, 2], "class": ["Car", "Car", "Car"], "x": [1.0, 5.0, 50.0],
                                   "y": [0.0, 1.0, -3.0]})
    return {"results": root / "results", "labels": root / "labels", "binary": root / "binary.bin",
            "empty": root / "empty.txt", "dir": root / "dir", "missing": root / "no" / "such.file",
            "config": repo / "configs" / "pointpillars" / "pointpillars_demo.yaml", "scan": scan, "index": index}


def _fill(arg: str, paths: dict) -> str:
    """``arg`` with its ``{name}`` placeholders replaced by ``paths[name]`` (JSON text is left as it is)."""
    if arg.startswith("{") and arg.split("}")[0][1:] in paths:
        return arg.format(**{k: str(v) for k, v in paths.items()})
    return arg


def _with(argv: list[str], option: str, value: str) -> list[str]:
    """``argv`` with ``option`` set to ``value`` (a positional option replaces the first path argument)."""
    argv = list(argv)
    if not option.startswith("--"):
        argv[2] = value
        return argv
    if option in argv:
        argv[argv.index(option) + 1] = value
        return argv
    return argv + [option, value]


@fuzz
@given(data=st.data())
def test_hostile_option_values_are_one_clear_error(tmp_path_factory, files, capsys, data):
    name = data.draw(st.sampled_from(sorted(COMMANDS)), "command")
    base, hostile = COMMANDS[name]
    options = data.draw(st.lists(st.sampled_from(sorted(hostile)), min_size=1, max_size=3, unique=True), "options")
    out = tmp_path_factory.mktemp("out")
    paths = {**files, "out": out}
    argv = [_fill(a, paths) for a in base]
    chosen = {}
    for option in options:
        value = _fill(data.draw(st.sampled_from(hostile[option]), option), paths)
        chosen[option] = value
        argv = _with(argv, option, value)
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as e:  # argparse's own usage errors
        code = e.code
        err = capsys.readouterr().err
        assert code == 2, f"{argv}: argparse exited with {code}"
        last = err.strip().splitlines()[-1]
        assert last.startswith(f"lidarops {name}: error: ") or last.startswith("lidarops: error: ") or \
            "error: " in last, err
    else:
        err = capsys.readouterr().err
        assert code == 2, f"lidarops {' '.join(argv)} exited with {code}, expected 2 (an error)\n{err}"
        lines = err.splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"lidarops {name}: error: "), \
            f"lidarops {' '.join(argv)}: expected one error line, got:\n{err}"
        last = lines[0]
    named = [o for o in chosen if o in last or (o.startswith("--") and o[2:].replace("-", "_") in last)
             or (chosen[o] and chosen[o] in last) or (o == "path" and "path" in last)]
    assert named, f"lidarops {' '.join(argv)}: the error names none of {sorted(chosen)} nor their values: {last}"
    assert not any(out.iterdir()), f"lidarops {' '.join(argv)} wrote {sorted(p.name for p in out.iterdir())}"
