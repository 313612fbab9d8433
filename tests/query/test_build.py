"""Filling an index from frames (lidarops.query.build) and the ``lidarops index`` / ``lidarops query``
commands: counts equal the frames' labels, a build stopped midway and run again holds every frame once."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

from lidarops.cli import main  # noqa: E402
from lidarops.query import FrameIndex  # noqa: E402
from lidarops.query.build import LabelsSource, build_index  # noqa: E402


class FakeFrame:
    class_names = ("Car", "Pedestrian", "Cyclist", "Truck")

    def __init__(self, rng):
        n = int(rng.integers(0, 9))
        self.labels = rng.integers(-1, 4, n)  # -1: a class outside the list, 3: a class not counted
        self.boxes = np.concatenate([rng.uniform(-30, 60, (n, 2)), np.ones((n, 5))], 1).astype(np.float32)


def frames(n, seed=0):
    rng = np.random.default_rng(seed)
    return [(10 * i + 3, FakeFrame(rng)) for i in range(n)]


def truth(pairs):
    return {fid: {c: int((f.labels == k).sum()) for k, c in enumerate(("Car", "Pedestrian", "Cyclist"))}
            for fid, f in pairs}


def test_labels_counts_and_centres(tmp_path):
    pairs = frames(23)
    out = build_index(tmp_path / "idx", pairs, LabelsSource(["Car", "Pedestrian", "Cyclist"]), chunk=5)
    assert out == {"indexed": 23, "skipped": 0}
    idx = FrameIndex.open(tmp_path / "idx")
    want = truth(pairs)
    got = idx.sql('SELECT frame_id, "Car", "Pedestrian", "Cyclist" FROM counts ORDER BY frame_id')
    assert {int(r.frame_id): {"Car": r.Car, "Pedestrian": r.Pedestrian, "Cyclist": r.Cyclist}
            for r in got.itertuples()} == want
    n_centres = int(idx.sql("SELECT count(*) AS n FROM centres")["n"][0])
    assert n_centres == sum(sum(v.values()) for v in want.values())
    # a region equals counting the labelled boxes inside it
    region = (0.0, -10.0, 30.0, 10.0)
    inside = sum(int(((f.labels == 0) & (f.boxes[:, 0] >= 0) & (f.boxes[:, 0] < 30) & (f.boxes[:, 1] >= -10)
                      & (f.boxes[:, 1] < 10)).sum()) for _, f in pairs)
    assert idx.sum("Car", region=region) == inside


def test_a_stopped_build_resumes_without_duplicates(tmp_path):
    pairs = frames(30, seed=1)
    calls = {"n": 0}
    inner = LabelsSource(["Car", "Pedestrian", "Cyclist"])

    def dying(batch):  # the process is killed while counting the third chunk
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return inner(batch)

    with pytest.raises(KeyboardInterrupt):
        build_index(tmp_path / "idx", pairs, dying, source_name="labels", classes=inner.classes, chunk=7)
    assert FrameIndex.open(tmp_path / "idx").count("Car", ">=", 0) == 14  # two chunks landed
    out = build_index(tmp_path / "idx", pairs, inner, chunk=7)
    assert out == {"indexed": 16, "skipped": 14}
    idx = FrameIndex.open(tmp_path / "idx")
    ids = idx.retrieve({})
    assert ids == sorted(fid for fid, _ in pairs)  # every frame once
    assert idx.sum("Pedestrian") == sum(v["Pedestrian"] for v in truth(pairs).values())
    assert build_index(tmp_path / "idx", pairs, inner) == {"indexed": 0, "skipped": 30}


def test_cli_build_and_query(tmp_path, capsys):
    out = str(tmp_path / "idx")
    assert main(["index", "build", "--scenario", "driving_city", "--frames", "3", "--out", out, "--no-progress"]) == 0
    assert "indexed 3 frame(s) with source labels" in capsys.readouterr().out
    idx = FrameIndex.open(out)
    cars = idx.sum("Car")
    assert main(["query", "sum", out, "--class", "Car"]) == 0
    assert capsys.readouterr().out.strip() == str(cars)
    assert main(["query", "retrieve", out, "--where", "Car>=0", "--frames", "0:2"]) == 0
    assert capsys.readouterr().out.strip() == "2 frame(s): 0, 1"
    assert main(["query", "count", out, "--where", f"Car>{cars}"]) == 0
    assert capsys.readouterr().out.strip() == "0"


@pytest.mark.parametrize("argv,message", [
    (["query", "retrieve", "{idx}", "--where", "Car=>1"], "expected CLASS OP NUMBER"),
    (["query", "retrieve", "{idx}", "--where", "Truck>=1"], "unknown class 'Truck'; the index's classes: Car"),
    (["query", "count", "{idx}", "--where", "Car>1", "--where", "Cyclist>1"], "count takes one --where"),
    (["query", "sum", "{idx}"], "sum needs --class, one of: Car, Pedestrian, Cyclist"),
    (["query", "sum", "{idx}", "--class", "Car", "--frames", "5-9"], "expected FIRST:STOP"),
    (["query", "avg", "{idx}", "--class", "Car", "--region", "1,2,3"], "expected X0,Y0,X1,Y1"),
    (["query", "sum", "{idx}", "--class", "Car", "--source", "radar"], "--source 'radar': the index's sources are labels"),
    (["query", "sum", "{nowhere}", "--class", "Car"], "no frame index at"),
    (["index", "build", "--out", "{new}"], "give a KITTI folder, or --scenario NAME --frames N"),
    (["index", "build", "--scenario", "driving_city", "--out", "{new}"], "--frames must be >= 1"),
])
def test_cli_errors_are_one_line(tmp_path, capsys, argv, message):
    idx = tmp_path / "idx"
    FrameIndex.create(idx, {"frame_id": [0, 1], "Car": [1, 2], "Pedestrian": [0, 0], "Cyclist": [0, 1]})
    argv = [a.format(idx=idx, nowhere=tmp_path / "nowhere", new=tmp_path / "new") for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
