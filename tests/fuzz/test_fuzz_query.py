"""Fuzz: lidarops.query.FrameIndex against a brute-force evaluation: random count tables (empty ones, ties,
duplicated ids, negative counts) and random queries (unknown classes and operators, non-finite values,
frame lists with ids the index lacks). A clear QueryError naming the argument, or the brute-force answer."""
from __future__ import annotations

import math
import operator
import tempfile

import pytest
from hypothesis import given
from hypothesis import strategies as st

pytest.importorskip("duckdb")
pytest.importorskip("pyarrow")

from lidarops.query import FrameIndex, QueryError  # noqa: E402
from .fuzzing import assert_clear_error, fuzz, outcome  # noqa: E402

CLASSES = ["Car", "Pedestrian"]
OPS = {"<": operator.lt, "<=": operator.le, "=": operator.eq, ">=": operator.ge, ">": operator.gt}


@fuzz
@given(data=st.data())
def test_index_queries(data):
    n = data.draw(st.integers(0, 12), "frames")
    ids = data.draw(st.lists(st.integers(0, 20), min_size=n, max_size=n), "frame_id")
    counts = {c: data.draw(st.lists(st.integers(-1, 4), min_size=n, max_size=n), c) for c in CLASSES}
    table = {"frame_id": ids, **counts}
    with tempfile.TemporaryDirectory() as root:
        idx, err = outcome(FrameIndex.create, root + "/idx", table, classes=CLASSES)
        bad = (["frame_id"] if len(set(ids)) != len(ids) else []) + (["Car", "Pedestrian"] if any(
            v < 0 for c in CLASSES for v in counts[c]) else [])
        if bad:
            return assert_clear_error(err, QueryError, bad, "FrameIndex.create")
        assert err is None, err
        cls = data.draw(st.sampled_from(CLASSES + ["Truck"]), "class")
        op = data.draw(st.sampled_from(list(OPS) + ["=>"]), "operator")
        value = data.draw(st.integers(-1, 5) | st.sampled_from([math.nan, math.inf, 2.5]), "value")
        frames = data.draw(st.none() | st.lists(st.integers(0, 25), max_size=6), "frames")
        res, err = outcome(idx.retrieve, {cls: (op, value)}, frames=frames)
        if cls == "Truck":
            return assert_clear_error(err, QueryError, ["Truck"], "retrieve")
        if op == "=>":
            return assert_clear_error(err, QueryError, ["=>"], "retrieve")
        if not math.isfinite(value):
            return assert_clear_error(err, QueryError, ["value"], "retrieve")
        assert err is None, err
        rows = [(f, {c: counts[c][i] for c in CLASSES}) for i, f in enumerate(ids) if frames is None or f in frames]
        assert res == sorted(f for f, r in rows if OPS[op](r[cls], value))
        assert idx.count(cls, op, value, frames=frames) == len(res)
        assert idx.sum(cls, frames=frames) == sum(r[cls] for _, r in rows)


@fuzz
@given(data=st.data())
def test_compare(data):
    """compare: each source's brute-force answer, labels first, or a QueryError naming the kind, the source
    argument, the class or the operator."""
    n = data.draw(st.integers(0, 8), "frames")
    with tempfile.TemporaryDirectory() as root:
        tables = {}
        for source in data.draw(st.lists(st.sampled_from(["labels", "detector", "net"]), min_size=1, max_size=3,
                                         unique=True), "sources"):
            tables[source] = {"frame_id": list(range(n)),
                              **{c: data.draw(st.lists(st.integers(0, 4), min_size=n, max_size=n), c) for c in CLASSES}}
            if len(tables) == 1:
                idx = FrameIndex.create(root + "/idx", tables[source], source=source, classes=CLASSES)
            else:
                idx.append(tables[source], source=source)
        kind = data.draw(st.sampled_from(["count", "sum", "retrieve", "max", ""]), "kind")
        cls = data.draw(st.sampled_from(CLASSES + ["Truck"]), "class")
        op = data.draw(st.sampled_from(list(OPS) + ["=>"]), "operator")
        extra = data.draw(st.sampled_from([{}, {"source": "labels"}]), "extra")
        args = {"count": (cls, op, 2), "sum": (cls,), "retrieve": ({cls: (op, 2)},)}.get(kind, (cls,))
        res, err = outcome(idx.compare, kind, *args, **extra)
        if kind not in ("count", "sum", "retrieve"):
            return assert_clear_error(err, QueryError, ["kind"], "compare")
        if extra:
            return assert_clear_error(err, QueryError, ["source"], "compare")
        if cls == "Truck":
            return assert_clear_error(err, QueryError, ["Truck"], "compare")
        if op == "=>" and kind != "sum":
            return assert_clear_error(err, QueryError, ["=>"], "compare")
        assert err is None, err
        assert list(res) == sorted(tables, key=lambda s: (s != "labels", s))
        for source, t in tables.items():
            hits = [f for f in t["frame_id"] if OPS.get(op, operator.ge)(t[cls][f], 2)]
            want = {"count": len(hits), "sum": sum(t[cls]), "retrieve": hits}[kind]
            assert res[source] == want, (source, kind)
