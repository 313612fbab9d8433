"""The index is plain Parquet: DuckDB's answers (through index.duckdb, or reading the parts) equal a plain
pyarrow + NumPy evaluation over the same files, on random count tables of several sources and parts, with
range and list frame filters and regions whose bounds fall between float32 values."""
from __future__ import annotations

import operator
import os

import numpy as np
import pytest

pytest.importorskip("duckdb")
pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")

from lidarops.query import FrameIndex  # noqa: E402
from lidarops.query.index import STORE_FILE, FrameIds  # noqa: E402

CLASSES = ["Car", "Pedestrian", "Cyclist", "Truck"]
OPS = {"<": operator.lt, "<=": operator.le, "=": operator.eq, ">=": operator.ge, ">": operator.gt}


def _tables(rng, ids, classes=CLASSES):
    counts = {"frame_id": ids, "sequence": [f"drive{i // 7}" for i in ids], "timestamp": ids * 0.1,
              **{c: rng.integers(0, 6, len(ids)) for c in classes}}
    n = sum(int(counts[c].sum()) for c in classes)
    centres = {"frame_id": np.concatenate([np.repeat(ids, counts[c]) for c in classes]),
               "class": [c for c in classes for k in counts[c] for _ in range(int(k))],
               "x": rng.uniform(-10, 10, n), "y": rng.uniform(-10, 10, n), "score": rng.uniform(0.3, 1, n)}
    # a third on the float32 neighbours of the regions' bounds (0.1 and -3.3 round up in float32, 7.3 and
    # 9.9 down): the comparison with the bound is exact, not that of the bound rounded to float32
    edges = np.float32([0.1, 7.3, 2.5, -0.2, -3.3, 9.9])
    edges = np.concatenate([edges, np.nextafter(edges, np.float32(np.inf)), np.nextafter(edges, np.float32(-np.inf))])
    centres["x"][: n // 3] = rng.choice(edges.astype(np.float64), n // 3)
    centres["y"][: n // 6] = rng.choice(edges.astype(np.float64), n // 6)
    return counts, centres


@pytest.fixture(params=["parquet", "index.duckdb"])
def engine(request, monkeypatch):
    """Queries read the Parquet parts directly, or index.duckdb made from them (any size)."""
    if request.param == "index.duckdb":
        monkeypatch.setattr(FrameIndex, "STORE_MIN_BYTES", 0)
    return request.param


def _build(root, rng):
    """An index of 3 sources (one without Truck, one without centres), several parts each, frame ids not
    in part order."""
    ids = rng.permutation(np.arange(0, 400, 2))  # every other id: lists may name ids the index lacks
    parts = np.array_split(ids, 3)
    counts, centres = _tables(rng, parts[0])
    idx = FrameIndex.create(root, counts, centres=centres, classes=CLASSES)
    for p in parts[1:]:
        counts, centres = _tables(rng, p)
        idx.append(counts, centres=centres)
    for p in np.array_split(rng.permutation(ids), 2):
        counts, centres = _tables(rng, p, classes=["Car", "Pedestrian", "Cyclist"])
        idx.append(counts, centres=centres, source="detector")
    idx.append(_tables(rng, ids[:50])[0], source="counter")
    return idx


def _plain(root, source):
    """The source's counts and centres, read with pyarrow from the Parquet files alone (no DuckDB)."""
    def read(kind):
        files = sorted((root / kind / source).glob("*.parquet"))
        return [pq.read_table(f).to_pydict() for f in files]
    counts = {"frame_id": [], **{c: [] for c in CLASSES}}
    for t in read("counts"):
        for k in counts:
            counts[k] += t[k] if k in t else [0] * len(t["frame_id"])
    counts = {k: np.asarray(v, np.int64) for k, v in counts.items()}
    centres = {"frame_id": [], "class": [], "x": [], "y": []}
    for t in read("centres"):
        for k in centres:
            centres[k] += t[k]
    centres = {k: np.asarray(v) for k, v in centres.items()}
    centres["x"], centres["y"] = centres["x"].astype(np.float32), centres["y"].astype(np.float32)
    return counts, centres


def _evaluate(counts, centres, frames, region):
    """Per-frame counts (frame ids, {class: counts}) after the frame filter, counted within the region."""
    ids = counts["frame_id"]
    keep = np.ones(len(ids), bool) if frames is None else (
        (ids >= frames.start) & (ids < frames.stop) if isinstance(frames, range) else np.isin(ids, frames))
    if region is None:
        per = {c: counts[c] for c in CLASSES}
    else:
        x0, y0, x1, y1 = region
        x, y = centres["x"].astype(np.float64), centres["y"].astype(np.float64)  # the exact comparison
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        order = np.argsort(ids)
        per = {}
        for c in CLASSES:
            f = centres["frame_id"][inside & (centres["class"] == c)]
            n = np.zeros(len(ids), np.int64)
            np.add.at(n, order[np.searchsorted(ids[order], f)], 1)
            per[c] = n
    return ids[keep], {c: v[keep] for c, v in per.items()}


def test_duckdb_equals_pyarrow_and_numpy(tmp_path, engine):
    rng = np.random.default_rng(7)
    root = tmp_path / "idx"
    _build(root, rng)
    idx = FrameIndex.open(root)
    assert (root / STORE_FILE).is_file() == (engine == "index.duckdb")
    regions = [None, (0.1, -5.0, 7.3, 5.0), (-0.2, -3.3, 2.5, 9.9), (-1e39, -1e39, 1e39, 1e39)]
    filters = [None, range(50, 300), range(301, 302), range(10, 10), [4, 6, 7, 398, 1000, 4], []]
    for source in ("labels", "detector", "counter"):
        counts, centres = _plain(root, source)
        for region in regions if source != "counter" else [None]:
            for frames in filters:
                ids, per = _evaluate(counts, centres, frames, region)
                kw = {"frames": frames, "source": source, "region": region}
                for _ in range(3):
                    where = {str(c): (str(rng.choice(list(OPS))), int(rng.integers(0, 5)))
                             for c in rng.choice(CLASSES, rng.integers(0, 3), replace=False)}
                    keep = np.ones(len(ids), bool)
                    for c, (op, v) in where.items():
                        keep &= OPS[op](per[c], v)
                    got = idx.retrieve(where, **kw)
                    assert got == sorted(ids[keep].tolist()), (source, region, frames, where)
                c = str(rng.choice(CLASSES))
                op, v = str(rng.choice(list(OPS))), int(rng.integers(0, 4))
                assert idx.count(c, op, v, **kw) == int(OPS[op](per[c], v).sum()), (source, region, frames, c, op, v)
                assert idx.sum(c, **kw) == int(per[c].sum()), (source, region, frames, c)
                mean = idx.avg(c, **kw)
                assert (mean is None and len(ids) == 0) or mean == pytest.approx(per[c].mean()), (source, frames)


def test_index_duckdb_follows_the_parts(tmp_path, monkeypatch):
    """index.duckdb answers for the parts it was made from; parts appended since are read from Parquet until
    the next open rebuilds it; a part rewritten in place is noticed; an unwritable folder falls back."""
    monkeypatch.setattr(FrameIndex, "STORE_MIN_BYTES", 0)
    rng = np.random.default_rng(3)
    root = tmp_path / "idx"
    idx = _build(root, rng)
    made = (root / STORE_FILE).stat().st_mtime_ns
    extra = {"frame_id": np.arange(1001, 1011), "Car": np.full(10, 9)}
    idx.append(extra, source="counter")  # a tail part: read from Parquet beside index.duckdb
    assert idx.retrieve({"Car": ("=", 9)}, source="counter")[-10:] == list(range(1001, 1011))
    assert (root / STORE_FILE).stat().st_mtime_ns == made
    again = FrameIndex.open(root)  # rebuilds with the new part
    assert (root / STORE_FILE).stat().st_mtime_ns != made
    assert again.sum("Car", source="counter") == idx.sum("Car", source="counter")
    # a part rewritten in place (same name): the next open notices and rebuilds
    part = sorted((root / "counts" / "counter").glob("*.parquet"))[-1]
    table = pq.read_table(part)
    pq.write_table(table.set_column(table.column_names.index("Car"), "Car", pa.array(np.ones(10, np.int32))), part)
    later = part.stat().st_mtime_ns + 10**9  # as a rewrite a second later would (the clock's tick may be coarse)
    os.utime(part, ns=(later, later))
    assert FrameIndex.open(root).sum("Car", frames=range(1001, 1011), source="counter") == 10
    # a folder where index.duckdb cannot be written: the parts are read
    (root / STORE_FILE).unlink()

    def refuse(*args):
        raise OSError("read-only file system")
    monkeypatch.setattr(FrameIndex, "_build_store", refuse)
    fallback = FrameIndex.open(root)
    assert not (root / STORE_FILE).exists() and not list(root.glob(".*.tmp"))
    assert fallback.sum("Car", frames=range(1001, 1011), source="counter") == 10
    assert fallback.retrieve({}, source="labels") == sorted(again.retrieve({}, source="labels"))


def test_frame_ids_behave_as_a_list():
    ids = FrameIds(np.array([2, 5, 9, 11]))
    assert ids == [2, 5, 9, 11] and [2, 5, 9, 11] == ids and ids != [2, 5, 9] and ids != (2, 5, 9, 11)
    assert ids[1:3] == [5, 9] and ids[-1] == 11 and isinstance(ids[0], int)
    assert list(ids) == [2, 5, 9, 11] and ids.tolist() == [2, 5, 9, 11] and set(ids) == {2, 5, 9, 11}
    assert 9 in ids and 9.0 in ids and 3 not in ids and "9" not in ids
    assert np.asarray(ids).dtype == np.int64 and np.array_equal(np.asarray(ids, np.float64), [2, 5, 9, 11])
    assert bool(ids) and not FrameIds([]) and FrameIds([]) == []
    assert "2, 5, 9, 11" in repr(ids) and "4 frames" in repr(ids)
    with pytest.raises(ValueError):
        np.asarray(ids)[0] = 1  # read-only: an answer is not changed behind the index's back
    with pytest.raises(TypeError):
        hash(ids)
