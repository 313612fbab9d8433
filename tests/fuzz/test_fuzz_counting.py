"""Fuzz: lidarops.eval.counting and lidarops.query.evaluate. Any arrays of valid counts (every integer and
float dtype, one or several classes, absent classes, ties, counts up to 2**31 - 1) give finite metrics in
their ranges: accuracies in [0, 1], Q-errors >= 1, and the orderings the definitions imply; bad shapes,
dtypes and values raise a ValueError naming the argument, never another exception."""
from __future__ import annotations

import math
import tempfile
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lidarops.eval import counting
from .fuzzing import assert_clear_error, assert_no_error, fuzz, outcome

DTYPES = [np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64, np.float32,
          np.float64]


def _top(dtype) -> int:
    """The largest count ``dtype`` holds exactly, within the accepted 2**31 - 1."""
    if np.dtype(dtype).kind == "f":
        return min(counting.MAX_COUNT, 2 ** (np.finfo(dtype).nmant + 1))
    return min(counting.MAX_COUNT, int(np.iinfo(dtype).max))


@st.composite
def count_pairs(draw, min_frames: int = 1):
    """``(pred, true)`` of one shape and dtype: small counts (ties, zeros, absent classes) and now and
    then the dtype's largest."""
    dtype = draw(st.sampled_from(DTYPES))
    frames = draw(st.integers(min_frames, 12))
    classes = draw(st.integers(1, 3))
    one_d = classes == 1 and draw(st.booleans())
    top = _top(dtype)
    value = st.integers(0, 6) | st.sampled_from([0, 1, top, top - 1])
    shape = (frames,) if one_d else (frames, classes)
    n = frames * (1 if one_d else classes)
    pred = np.array(draw(st.lists(value, min_size=n, max_size=n)), dtype=np.float64).astype(dtype).reshape(shape)
    true = np.array(draw(st.lists(value, min_size=n, max_size=n)), dtype=np.float64).astype(dtype).reshape(shape)
    if draw(st.integers(0, 3)) == 0:
        true = pred.copy()  # a perfect source
    return pred, true


def _in_unit(x, what):
    x = np.atleast_1d(np.asarray(x, np.float64))
    assert np.isfinite(x).all() and (x >= 0).all() and (x <= 1).all(), f"{what} outside [0, 1]: {x}"


@fuzz
@given(pair=count_pairs(), tol=st.sampled_from([0.0, 0.05, 0.1, 0.29, 0.5, 1.0]),
       seed=st.integers(0, 2 ** 32), queries=st.integers(1, 30), groups=st.integers(1, 6),
       fewest=st.integers(1, 8), extra=st.integers(0, 8))
def test_valid_counts_give_metrics_in_range(pair, tol, seed, queries, groups, fewest, extra):
    pred, true = pair
    single, err = outcome(counting.retrieval_single_accuracy, pred, true, tol)
    assert_no_error(err, "retrieval_single_accuracy")
    multiple = counting.retrieval_multiple_accuracy(pred, true, tol)
    exact = counting.counting_accuracy(pred, true)
    mae = counting.mean_absolute_error(pred, true)
    for x, what in ((single, "RETRIEVAL-SINGLE"), (multiple, "RETRIEVAL-MULTIPLE"), (exact, "counting accuracy")):
        _in_unit(x, what)
    # every class within at once is rarer than each class within; an exact count is within any tolerance
    assert multiple <= np.min(single) + 1e-12
    assert (np.atleast_1d(exact) <= np.atleast_1d(single) + 1e-12).all()
    assert (np.atleast_1d(counting.retrieval_single_accuracy(pred, true, 1.0)) >= np.atleast_1d(single) - 1e-12).all()
    assert np.isfinite(mae).all() and (np.atleast_1d(mae) >= 0).all()
    # allowed error: floor(tol * largest true count), exactly
    t2 = true.reshape(len(true), -1).astype(np.int64)
    want = [math.floor(Fraction(str(tol)) * int(m)) for m in t2.max(0)]
    assert np.atleast_1d(counting.allowed_error(true, tol)).tolist() == want

    res, err = outcome(counting.count_query_accuracy, pred, true, queries, groups, (fewest, fewest + extra), seed)
    assert_no_error(err, "count_query_accuracy")
    for k in ("accuracy", "exact"):
        _in_unit(res[k], f"COUNT {k}")
    # an exactly answered query scores 1: the mean score is at least the share answered exactly
    assert (np.atleast_1d(res["accuracy"]) >= np.atleast_1d(res["exact"]) - 1e-12).all()
    assert (np.atleast_1d(res["mean_abs_error"]) >= 0).all()
    if np.array_equal(pred, true):
        assert np.all(np.atleast_1d(res["accuracy"]) == 1.0) and np.all(np.atleast_1d(single) == 1.0)

    agg = counting.aggregation_errors(pred, true, (res["queries"].starts, res["queries"].lengths))
    q = np.asarray(agg["q_error"])
    assert np.isfinite(q).all() and (q >= 1).all(), q
    assert (agg["abs_diff"] >= 0).all()
    # Q-error 1 exactly when the sums agree or both are at most 1
    same = (agg["true"] == agg["pred"]) | ((agg["true"] <= 1) & (agg["pred"] <= 1))
    np.testing.assert_array_equal(q == 1.0, same)


@fuzz
@given(pair=count_pairs())
def test_q_error_in_range(pair):
    pred, true = pair
    q, err = outcome(counting.q_error, pred, true)
    assert_no_error(err, "q_error")
    assert q.shape == np.shape(pred) and np.isfinite(q).all() and (q >= 1).all()
    np.testing.assert_array_equal(q, counting.q_error(true, pred))  # symmetric


BAD = ["shape", "ndim", "negative", "nan", "inf", "fraction", "bool", "str", "complex", "object", "huge",
       "ragged", "empty"]


@st.composite
def bad_pairs(draw):
    """``(pred, true, kind, names)``: one defect, and the names its error must carry."""
    kind = draw(st.sampled_from(BAD))
    frames, classes = draw(st.integers(1, 5)), draw(st.integers(1, 3))
    good = np.array(draw(st.lists(st.integers(0, 4), min_size=frames * classes, max_size=frames * classes)),
                    np.int64).reshape(frames, classes)
    which = draw(st.sampled_from(["pred", "true"]))
    bad = good.copy()
    if kind == "shape":
        bad = np.zeros((frames + 1, classes), np.int64)
        names = ["pred", "true"]
    elif kind == "ndim":
        bad = np.zeros((frames, classes, 2), np.int64)
        names = [which]
    elif kind == "negative":
        bad[draw(st.integers(0, frames - 1)), 0] = -draw(st.integers(1, 5))
        names = [which]
    elif kind in ("nan", "inf", "fraction"):
        bad = bad.astype(np.float64)
        bad[draw(st.integers(0, frames - 1)), 0] = {"nan": math.nan, "inf": -math.inf, "fraction": 0.5}[kind]
        names = [which]
    elif kind == "bool":
        bad = bad > 2
        names = [which, "bool"]
    elif kind == "str":
        bad = bad.astype(str)
        names = [which]
    elif kind == "complex":
        bad = bad.astype(np.complex128)
        names = [which, "complex"]
    elif kind == "object":
        bad = bad.astype(object)
        names = [which, "object"]
    elif kind == "huge":  # beyond a count (2**31 - 1); the last two beyond a sum too (2**62, q_error's limit)
        bad = bad.astype(np.float64 if draw(st.booleans()) else np.int64)
        bad[0, 0] = draw(st.sampled_from([2 ** 31, 2 ** 40, 2 ** 62 + 2 ** 10, 2 ** 63 - 1]))
        names = [which]
    elif kind == "ragged":
        bad = [[1, 2], [3]]
        names = [which]
    else:  # no frames: an accuracy over none is undefined
        bad = np.zeros((0, classes), np.int64)
        good = bad
        names = ["no frames"]
    return (bad, good, kind, names) if which == "pred" else (good, bad, kind, names)


@fuzz
@given(case=bad_pairs(), tol=st.sampled_from([0.1, 0.05]))
def test_bad_counts_raise_value_error_naming_them(case, tol):
    pred, true, kind, names = case
    calls = {
        "retrieval_single_accuracy": lambda: counting.retrieval_single_accuracy(pred, true, tol),
        "retrieval_multiple_accuracy": lambda: counting.retrieval_multiple_accuracy(pred, true, tol),
        "counting_accuracy": lambda: counting.counting_accuracy(pred, true),
        "mean_absolute_error": lambda: counting.mean_absolute_error(pred, true),
        "count_query_accuracy": lambda: counting.count_query_accuracy(pred, true, 5, 2, (1, 3), 0),
        "within_tolerance": lambda: counting.within_tolerance(pred, true, tol),
    }
    if kind != "empty":  # defined over no frames: a sum of 0, an empty Q-error
        calls["aggregation_errors"] = lambda: counting.aggregation_errors(pred, true)
        # q_error takes any shape up to 2-D and sums up to 2**62
        if kind != "ndim" and not (kind == "huge" and max(np.max(pred), np.max(true)) <= 2 ** 62):
            calls["q_error"] = lambda: counting.q_error(pred, true)
    for what, call in calls.items():
        _, err = outcome(call)
        assert_clear_error(err, ValueError, names, f"{what} ({kind})")


@fuzz
@given(tol=st.sampled_from([-0.01, 1.01, math.nan, math.inf, True, "0.1", None, [0.1], 1 + 0j]),
       n=st.integers(0, 3), groups=st.sampled_from([0, -1, 1.5, True, "2"]), seed=st.sampled_from([-1, 0.5, "s"]))
def test_bad_arguments_raise_value_error_naming_them(tol, n, groups, seed):
    pred = true = np.ones((4, 2), np.int64)
    _, err = outcome(counting.retrieval_single_accuracy, pred, true, tol)
    assert_clear_error(err, ValueError, ["tolerance"], "retrieval_single_accuracy tolerance")
    _, err = outcome(counting.random_groups, 10, groups)
    assert_clear_error(err, ValueError, ["groups"], "random_groups groups")
    _, err = outcome(counting.random_groups, 10, 2, (1, 3), seed)
    assert_clear_error(err, ValueError, ["seed"], "random_groups seed")
    _, err = outcome(counting.random_groups, n - 3, 2)
    assert_clear_error(err, ValueError, ["n_frames"], "random_groups n_frames")


@fuzz
@given(data=st.data())
def test_evaluate_on_random_indexes(data):
    pytest.importorskip("duckdb")
    pytest.importorskip("pyarrow")
    from lidarops.query import FrameIndex, QueryError
    from lidarops.query.evaluate import evaluate

    classes = ["Car", "Pedestrian"]
    n_l, n_d = data.draw(st.integers(1, 10), "labels"), data.draw(st.integers(1, 10), "detector")
    ids_l = data.draw(st.lists(st.integers(0, 15), min_size=n_l, max_size=n_l, unique=True), "labels' ids")
    ids_d = data.draw(st.lists(st.integers(0, 15), min_size=n_d, max_size=n_d, unique=True), "detector's ids")
    counts = st.integers(0, 5) | st.just(counting.MAX_COUNT)
    labels = {"frame_id": ids_l, **{c: data.draw(st.lists(counts, min_size=n_l, max_size=n_l), c) for c in classes}}
    det = {"frame_id": ids_d, **{c: data.draw(st.lists(counts, min_size=n_d, max_size=n_d), c) for c in classes}}
    with tempfile.TemporaryDirectory() as root:
        idx = FrameIndex.create(root + "/idx", labels)
        idx.append(det, source="detector")
        common = sorted(set(ids_l) & set(ids_d))
        r, err = outcome(evaluate, idx, groups=3, queries=10, seed=data.draw(st.integers(0, 99), "seed"))
        if not common:
            return assert_clear_error(err, QueryError, ["share no frame"], "evaluate")
        assert_no_error(err, "evaluate")
        assert r.frames == len(common)
        assert r.only_source.tolist() == sorted(set(ids_d) - set(ids_l))
        assert r.only_truth.tolist() == sorted(set(ids_l) - set(ids_d))
        for t in r.tolerances:
            _in_unit(r.retrieval_single[t], "RETRIEVAL-SINGLE")
            _in_unit(r.retrieval_multiple[t], "RETRIEVAL-MULTIPLE")
        for x in (r.counting_accuracy, r.count["accuracy"], r.count["exact"]):
            _in_unit(x, "accuracy")
        for k in ("mean_q_error", "median_q_error", "max_q_error"):
            assert np.isfinite(r.aggregation_groups[k]).all() and (r.aggregation_groups[k] >= 1).all()
        assert (r.aggregation["q_error"] >= 1).all()
        assert isinstance(r.format(), str)
