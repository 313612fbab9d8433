"""lidarops.query.FrameIndex against brute-force Python evaluations over random count tables: empty sets,
ties at the threshold, classes absent from a source, regions, several parts and sources; bad input named."""
from __future__ import annotations

import json
import operator

import numpy as np
import pytest

duckdb = pytest.importorskip("duckdb")
pa = pytest.importorskip("pyarrow")

from helpers.query import centres_of as _centres_of  # noqa: E402
from lidarops.query import FrameIndex, QueryError  # noqa: E402

CLASSES = ["Car", "Pedestrian", "Cyclist"]
OPS = {"<": operator.lt, "<=": operator.le, "=": operator.eq, ">=": operator.ge, ">": operator.gt}


def table(rng, n, first=0, classes=CLASSES, high=8):
    ids = np.arange(first, first + n) * 3 + 1  # not 0..n-1: ids are not positions
    return {"frame_id": ids, **{c: rng.integers(0, high, n) for c in classes}}


def centres_of(rng, counts):
    return _centres_of(rng, counts, CLASSES, ties=0.3)


def brute(counts, where=None, frames=None, region=None, centres=None):
    """Per-frame counts as Python dicts, after the frame filter and the region."""
    out = []
    for i, fid in enumerate(counts["frame_id"]):
        fid = int(fid)
        if frames is not None and fid not in set(frames):
            continue
        if region is None:
            row = {c: int(counts[c][i]) if c in counts else 0 for c in CLASSES}
        else:
            x0, y0, x1, y1 = region
            row = {c: 0 for c in CLASSES}
            for f, c, x, y in zip(centres["frame_id"], centres["class"], centres["x"], centres["y"]):
                x, y = np.float32(x), np.float32(y)
                if f == fid and x0 <= x < x1 and y0 <= y < y1:
                    row[c] += 1
        out.append((fid, row))
    if where:
        out = [(f, r) for f, r in out if all(OPS[op](r[c], v) for c, (op, v) in where.items())]
    return out


@pytest.fixture
def index(tmp_path):
    rng = np.random.default_rng(0)
    a = table(rng, 60)
    b = table(rng, 40, first=60)
    idx = FrameIndex.create(tmp_path / "idx", a, centres=centres_of(rng, a))
    idx.append(b, centres=centres_of(rng, b))  # a second part
    return idx, {k: np.concatenate([a[k], b[k]]) for k in a}


def test_queries_match_brute_force(index):
    idx, counts = index
    rng = np.random.default_rng(1)
    for _ in range(60):
        where = {c: (str(rng.choice(list(OPS))), int(rng.integers(-1, 9))) for c in rng.choice(CLASSES, rng.integers(0, 4), replace=False)}
        frames = None if rng.random() < 0.5 else sorted(rng.choice(counts["frame_id"], 20, replace=False).tolist())
        want = [f for f, _ in brute(counts, where, frames)]
        assert idx.retrieve(where, frames=frames) == want, (where, frames)
        c = str(rng.choice(CLASSES))
        op, v = str(rng.choice(list(OPS))), int(rng.integers(0, 8))
        rows = brute(counts, None, frames)
        assert idx.count(c, op, v, frames=frames) == sum(OPS[op](r[c], v) for _, r in rows)
        assert idx.sum(c, frames=frames) == sum(r[c] for _, r in rows)
        mean = idx.avg(c, frames=frames)
        assert (mean is None and not rows) or mean == pytest.approx(np.mean([r[c] for _, r in rows]))


def test_ties_empty_sets_and_ranges(index):
    idx, counts = index
    v = int(counts["Car"][7])
    at = [int(f) for f, c in zip(counts["frame_id"], counts["Car"]) if c == v]
    assert idx.retrieve({"Car": ("=", v)}) == at and len(at) >= 1  # the tie is in for =, <=, >=
    assert set(at) <= set(idx.retrieve({"Car": (">=", v)})) and set(at) <= set(idx.retrieve({"Car": ("<=", v)}))
    assert not set(at) & set(idx.retrieve({"Car": (">", v)}))
    assert idx.retrieve({"Car": (">", 100)}) == [] and idx.count("Car", ">", 100) == 0
    assert idx.sum("Car", frames=[]) == 0 and idx.avg("Car", frames=[]) is None
    r = range(10, 100)
    assert idx.retrieve({}, frames=r) == [int(f) for f in counts["frame_id"] if 10 <= f < 100]
    assert idx.retrieve({}) == sorted(int(f) for f in counts["frame_id"])


def test_regions(tmp_path):
    rng = np.random.default_rng(2)
    counts = table(rng, 50)
    centres = centres_of(rng, counts)
    idx = FrameIndex.create(tmp_path / "idx", counts, centres=centres)
    for region in [(0.0, -10.0, 20.0, 10.0), (10.0, -20.0, 10.5, 20.0), (-100.0, -100.0, 100.0, 100.0)]:
        rows = brute(counts, None, None, region, centres)
        assert idx.sum("Pedestrian", region=region) == sum(r["Pedestrian"] for _, r in rows)
        where = {"Car": (">=", 2)}
        assert idx.retrieve(where, region=region) == [f for f, _ in brute(counts, where, None, region, centres)]
        assert idx.count("Cyclist", "=", 0, region=region) == sum(r["Cyclist"] == 0 for _, r in rows)
    # the whole plane gives the counts themselves
    assert idx.sum("Car", region=(-1e3, -1e3, 1e3, 1e3)) == idx.sum("Car")


def test_sources_side_by_side_and_absent_classes(tmp_path):
    rng = np.random.default_rng(3)
    labels = table(rng, 30)
    detector = {"frame_id": labels["frame_id"], "Car": np.maximum(labels["Car"] - 1, 0)}  # no Pedestrian, Cyclist
    idx = FrameIndex.create(tmp_path / "idx", labels)
    idx.append(detector, source="detector")
    assert idx.sources == ["detector", "labels"]
    assert idx.sum("Pedestrian", source="detector") == 0
    assert idx.sum("Car", source="detector") == int(detector["Car"].sum())
    assert idx.sum("Car") == int(labels["Car"].sum())
    again = FrameIndex.open(tmp_path / "idx")
    assert again.retrieve({"Car": (">=", 3)}, source="detector") == \
        [int(f) for f, c in zip(detector["frame_id"], detector["Car"]) if c >= 3]
    # the same answer from the Parquet files read without DuckDB
    import pyarrow.parquet as pq
    t = pa.concat_tables([pq.read_table(p) for p in sorted((tmp_path / "idx" / "counts").glob("*/*.parquet"))])
    d = t.to_pydict()
    plain = sorted(f for f, s, c in zip(d["frame_id"], d["source"], d["Car"]) if s == "detector" and c >= 3)
    assert plain == again.retrieve({"Car": (">=", 3)}, source="detector")


def test_pandas_input_and_sql(tmp_path):
    pd = pytest.importorskip("pandas")
    df = pd.DataFrame({"frame_id": [5, 6, 7], "sequence": ["a", "a", "b"], "timestamp": [0.0, 0.1, 0.2],
                       "Car": [1, 0, 3], "Pedestrian": [0, 2, 2]})
    idx = FrameIndex.create(tmp_path / "idx", df)
    assert idx.classes == ["Car", "Pedestrian"]
    out = idx.sql("SELECT sequence, sum(\"Car\") AS cars FROM counts GROUP BY sequence ORDER BY sequence")
    assert out["cars"].tolist() == [1, 3]


@pytest.mark.parametrize("call,pattern", [
    (lambda i: i.retrieve({"Truck": (">=", 1)}), "unknown class 'Truck'; the index's classes: Car, Pedestrian, Cyclist"),
    (lambda i: i.retrieve({"Car": ("=>", 1)}), "unknown operator '=>'; valid: <, <=, =, >=, >"),
    (lambda i: i.count("Car", ">=", float("nan")), "must be a finite number"),
    (lambda i: i.sum("Car", source="lidar"), "unknown source 'lidar'; the index's sources: labels"),
    (lambda i: i.sum("Car", region=(1, 0, 0, 1)), "x0 < x1 and y0 < y1"),
    (lambda i: i.retrieve({"Car": (">=", 1)}, frames="1-5"), "frames must be a range or a list"),
    (lambda i: i.retrieve({"Car": ">= 1"}), "must be \\(operator, value\\)"),
])
def test_bad_queries_are_named(index, call, pattern):
    with pytest.raises(QueryError, match=pattern):
        call(index[0])


def test_bad_tables_are_named(tmp_path):
    with pytest.raises(QueryError, match="duplicates, e.g. \\[3\\]"):
        FrameIndex.create(tmp_path / "a", {"frame_id": [1, 3, 3], "Car": [0, 1, 2]})
    with pytest.raises(QueryError, match="must be >= 0"):
        FrameIndex.create(tmp_path / "b", {"frame_id": [1, 2], "Car": [0, -1]})
    with pytest.raises(QueryError, match="needs a frame_id column"):
        FrameIndex.create(tmp_path / "c", {"Car": [0, 1]})
    with pytest.raises(QueryError, match="whole numbers"):
        FrameIndex.create(tmp_path / "d", {"frame_id": [1, 2], "Car": [0.5, 1]})
    idx = FrameIndex.create(tmp_path / "e", {"frame_id": [1, 2], "Car": [0, 1]})
    with pytest.raises(QueryError, match="already holds frames \\[2\\]"):
        idx.append({"frame_id": [2, 3], "Car": [1, 1]})
    with pytest.raises(QueryError, match="already holds an index"):
        FrameIndex.create(tmp_path / "e", {"frame_id": [1], "Car": [0]})
    with pytest.raises(QueryError, match="no frame index at"):
        FrameIndex.open(tmp_path / "nowhere")
    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "index.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(QueryError, match="not a lidarops frame index"):
        FrameIndex.open(tmp_path / "f")
    with pytest.raises(QueryError, match="has no object centres"):
        idx.sum("Car", region=(0, 0, 1, 1))


def test_import_is_light():
    import subprocess
    import sys
    code = "import sys, lidarops.query; assert 'duckdb' not in sys.modules and 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_compare_asks_every_source(tmp_path):
    rng = np.random.default_rng(11)
    a, b = table(rng, 30), table(rng, 30)
    idx = FrameIndex.create(tmp_path / "idx", b, source="zeta")
    idx.append(a, source="labels")
    got = idx.compare("count", "Car", ">=", 4, frames=range(4, 70))
    assert list(got) == ["labels", "zeta"]
    for name, t in (("labels", a), ("zeta", b)):
        inside = (t["frame_id"] >= 4) & (t["frame_id"] < 70)
        assert got[name] == int(((t["Car"] >= 4) & inside).sum())
    sums = idx.compare("sum", "Pedestrian")
    assert sums == {"labels": int(a["Pedestrian"].sum()), "zeta": int(b["Pedestrian"].sum())}
    with pytest.raises(QueryError, match="kind must be one of"):
        idx.compare("max", "Car")
    with pytest.raises(QueryError, match="leave source out"):
        idx.compare("sum", "Car", source="labels")
