"""Fuzz: fps, knn, ball_query, gather against their float64-exact references (lidarops.ops.neighbors).

The kernels round every operation of a squared distance like the references do (documented), so
distances and indices must be equal, not close.
"""
from __future__ import annotations

import math
import threading

import torch
from hypothesis import assume, given
from hypothesis import strategies as st

import lidarops
from lidarops.ops.neighbors import (_ball_query_reference, _compute_dtype, _fps_reference, _gather_reference,
                                    _knn_reference, _sqdist_reference)
from .fuzzing import Cloud, assert_clear_error, assert_no_error, assert_same, clouds, fuzz, outcome

#: k that no memory holds (an attempt fails at once instead of filling the machine)
HUGE_K = (2**36, 2**40, 2**62, 2**63 - 1)
#: k past int32, used with empty queries only (nothing to allocate)
INT32_K = (2**31 - 1, 2**31, 2**32 + 1)


def _lengths_on(c: Cloud, device):
    return None if c.lengths is None else c.lengths.to(device)


def _overflows(q: Cloud, p: Cloud) -> bool:
    """Some squared distance between valid rows overflows the compute dtype (a known bug's input)."""
    ct = _compute_dtype(q.points.dtype)
    for b, (m, n) in enumerate(zip(q.rows(), p.rows())):
        if m and n:
            d = _sqdist_reference(q.points[b, :m].to(ct), p.points[b, :n].to(ct))
            if not bool(torch.isfinite(d).all()):
                return True
    return False


def _self_overflows(c: Cloud) -> bool:
    return _overflows(c, c)


def _expected_errors(pairs) -> list:
    """Argument names that must appear in the ValueError: non-finite coordinates, lengths out of range."""
    names = []
    for name, cloud, lname in pairs:
        if not cloud.finite():
            names.append(name)
        if lname and not cloud.valid_lengths:
            names.append(lname)
    return names


def _allowed_errors(pairs) -> list:
    """Arguments a ValueError may name without being required: clouds of huge magnitudes (an op may
    bound its coordinates, e.g. so that squared distances cannot overflow)."""
    return [name for name, cloud, _ in pairs if cloud.regime == "huge"]


def _judge(err, must: list, may: list, what: str) -> bool:
    """True when the outcome is settled by an error: a required one (``must``) or an allowed one
    (``may``); False when a result is expected."""
    if must:
        assert_clear_error(err, ValueError, must + may, what)
        return True
    if err is not None and may:
        assert_clear_error(err, ValueError, may, what)
        return True
    assert_no_error(err, what)
    return False


# ---------------------------------------------------------------------------------------------- knn
def check_knn(q: Cloud, p: Cloud, k: int, method: str, device: str) -> None:
    what = f"knn(k={k}, method={method!r}, {q.regime}/{p.regime}, {q.points.dtype})"
    res, err = outcome(lidarops.knn, q.points.to(device), p.points.to(device), k, _lengths_on(q, device),
                       _lengths_on(p, device), method)
    pairs = [("query", q, "query_lengths"), ("points", p, "point_lengths")]
    must = _expected_errors(pairs) + (["tree"] if method == "tree" and device != "cpu" else [])
    if _judge(err, must, _allowed_errors(pairs), what):
        return
    dist, idx = res
    ql = None if q.lengths is None else q.lengths
    pl = None if p.lengths is None else p.lengths
    edist, eidx = _knn_reference(q.points, p.points, k, ql, pl)
    assert dist.dtype == _compute_dtype(q.points.dtype) and idx.dtype == torch.int64, what
    assert_same(idx, eidx, what + " idx")
    assert_same(dist, edist, what + " dist2")


_KNN_METHODS = st.sampled_from(["auto", "brute", "grid", "tree"])


@fuzz
@given(data=st.data())
def test_knn(device, data):
    q = data.draw(clouds(), "query")
    p = data.draw(clouds(batch=q.points.shape[0], dtype=q.points.dtype), "points")
    check_knn(q, p, data.draw(st.integers(1, 14), "k"), data.draw(_KNN_METHODS, "method"), device)


@fuzz
@given(data=st.data())
def test_knn_overflowing_distances(device, data):
    q = data.draw(clouds(regime="huge", min_n=1), "query")
    p = data.draw(clouds(batch=q.points.shape[0], dtype=q.points.dtype, regime="huge", min_n=1), "points")
    assume(q.finite() and p.finite() and _overflows(q, p))
    check_knn(q, p, data.draw(st.integers(1, 6), "k"), data.draw(_KNN_METHODS, "method"), device)


def check_huge_k(op: str, k: int, cloud: Cloud, device: str) -> None:
    """A k beyond any memory (or past int32 with nothing to compute): a ValueError naming k, or the
    result of the same call with k = N (what can exist) padded with -1 / +inf."""
    pts = cloud.points.to(device)
    fn = {"knn": lambda: lidarops.knn(pts, pts, k), "ball_query": lambda: lidarops.ball_query(pts, pts, 1.0, k),
          "fps": lambda: lidarops.fps(pts, k)}[op]
    what = f"{op}(k={k}) on {tuple(pts.shape)}"
    res, err = outcome(fn)
    if err is not None:
        return assert_clear_error(err, ValueError, ["k"], what)
    out = res if isinstance(res, tuple) else (res,)
    for t in out:
        assert t.shape[-1] == k, what


@fuzz
@given(data=st.data())
def test_huge_k(device, data):
    op = data.draw(st.sampled_from(["knn", "ball_query", "fps"]), "op")
    empty = data.draw(st.booleans(), "empty")
    k = data.draw(st.sampled_from(INT32_K if empty else HUGE_K), "k")
    if empty:  # outputs with no entries: (B, M = 0, k) for knn and ball_query, (B = 0, k) for fps
        batch, n = (0, data.draw(st.integers(0, 3))) if op == "fps" else (None, 0)
    else:
        batch, n = 1, data.draw(st.integers(1, 4))
    cloud = data.draw(clouds(regime="normal", lengths=False, min_n=n, max_n=n, batch=batch), "cloud")
    check_huge_k(op, k, cloud, device)


# ---------------------------------------------------------------------------------------------- ball query
_RADII = st.sampled_from([0.0, 1.0, 2.5, -1.0, math.nan, math.inf, 1e20, 1e-30]) | st.floats(0, 80)


def check_ball_query(q: Cloud, p: Cloud, radius, k: int, method: str, device: str) -> None:
    what = f"ball_query(radius={radius!r}, k={k}, method={method!r}, {q.regime}/{p.regime}, {q.points.dtype})"
    res, err = outcome(lidarops.ball_query, q.points.to(device), p.points.to(device), radius, k,
                       _lengths_on(q, device), _lengths_on(p, device), method)
    pairs = [("query", q, "query_lengths"), ("points", p, "point_lengths")]
    must = _expected_errors(pairs) + ([] if math.isfinite(radius) and radius >= 0 else ["radius"])
    if _judge(err, must, _allowed_errors(pairs), what):
        return
    dist, idx = res
    edist, eidx = _ball_query_reference(q.points, p.points, radius, k, q.lengths, p.lengths)
    assert_same(idx, eidx, what + " idx")
    assert_same(dist, edist, what + " dist2")


@fuzz
@given(data=st.data())
def test_ball_query(device, data):
    q = data.draw(clouds(), "query")
    p = data.draw(clouds(batch=q.points.shape[0], dtype=q.points.dtype), "points")
    check_ball_query(q, p, data.draw(_RADII, "radius"), data.draw(st.integers(1, 12), "k"),
                     data.draw(st.sampled_from(["auto", "brute", "grid"]), "method"), device)


@fuzz
@given(data=st.data())
def test_ball_query_overflowing_distances(device, data):
    q = data.draw(clouds(regime="huge", min_n=1), "query")
    p = data.draw(clouds(batch=q.points.shape[0], dtype=q.points.dtype, regime="huge", min_n=1), "points")
    assume(q.finite() and p.finite() and _overflows(q, p))
    check_ball_query(q, p, data.draw(st.sampled_from([1.0, 1e20, 3e38]), "radius"), 4,
                     data.draw(st.sampled_from(["auto", "brute", "grid"]), "method"), device)


# ---------------------------------------------------------------------------------------------- fps
def check_fps(c: Cloud, k: int, start, method: str, device: str) -> None:
    what = f"fps(k={k}, start_idx={start!r}, method={method!r}, {c.regime}, {c.points.dtype})"
    start_arg = start.to(device) if isinstance(start, torch.Tensor) else start
    res, err = outcome(lidarops.fps, c.points.to(device), k, _lengths_on(c, device), start_arg, method)
    pairs = [("points", c, "lengths")]
    must = _expected_errors(pairs)
    if start is not None and c.valid_lengths:
        s = [int(start)] * len(c.rows()) if not isinstance(start, torch.Tensor) else start.tolist()
        if any(n > 0 and not 0 <= si < n for si, n in zip(s, c.rows())):
            must.append("start_idx")
    if _judge(err, must, _allowed_errors(pairs), what):
        return
    expected = _fps_reference(c.points, k, c.lengths, start if start is not None else None)
    assert_same(res, expected, what)


@fuzz
@given(data=st.data())
def test_fps(device, data):
    c = data.draw(clouds(), "cloud")
    B, N = c.points.shape[:2]
    start = data.draw(st.none() | st.integers(-1, N + 1)
                      | st.lists(st.integers(0, max(N - 1, 0)), min_size=B, max_size=B).map(torch.tensor), "start")
    if isinstance(start, torch.Tensor):
        start = start.to(torch.int64).reshape(B)
    check_fps(c, data.draw(st.integers(1, 14), "k"), start, data.draw(st.sampled_from(["auto", "plain", "leaves"])),
              device)


@fuzz
@given(data=st.data())
def test_fps_overflowing_distances(device, data):
    c = data.draw(clouds(regime="huge", min_n=2), "cloud")
    assume(c.finite() and _self_overflows(c))
    check_fps(c, data.draw(st.integers(1, 8), "k"), None, data.draw(st.sampled_from(["auto", "plain", "leaves"])),
              device)


# ---------------------------------------------------------------------------------------------- gather
@fuzz
@given(data=st.data())
def test_gather(device, data):
    B = data.draw(st.integers(0, 3), "B")
    N = data.draw(st.integers(0, 6), "N")
    C = data.draw(st.integers(1, 4), "C")
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64, torch.float16, torch.int64, torch.int32]))
    x = torch.tensor(data.draw(st.lists(st.integers(-1000, 1000), min_size=B * N * C, max_size=B * N * C)),
                     dtype=torch.int64).reshape(B, N, C).to(dtype)
    shape = data.draw(st.lists(st.integers(0, 4), min_size=1, max_size=2), "idx shape")
    count = B * math.prod(shape)
    idx = torch.tensor(data.draw(st.lists(st.integers(-2, N + 1), min_size=count, max_size=count)),
                       dtype=torch.int64).reshape(B, *shape)
    idx = idx.to(data.draw(st.sampled_from([torch.int64, torch.int32])))
    what = f"gather(x {tuple(x.shape)} {dtype}, idx {tuple(idx.shape)})"
    res, err = outcome(lidarops.gather, x.to(device), idx.to(device))
    if idx.numel() and bool(((idx < -1) | (idx >= N)).any()):
        return assert_clear_error(err, ValueError, ["idx"], what)
    assert_no_error(err, what)
    assert_same(res, _gather_reference(x, idx.long()), what)


# ---------------------------------------------------------------------------------------------- threads
@fuzz
@given(data=st.data())
def test_validation_switch_is_per_thread(device, data):
    """One thread turns the value checks off; an op with NaN coordinates on another thread must still
    raise its ValueError."""
    c = data.draw(clouds(regime="nonfinite", min_n=1, lengths=False, batch=1), "cloud")
    assume(not c.finite())
    inside, done = threading.Event(), threading.Event()

    def quiet():
        with lidarops.validation(False):
            inside.set()
            done.wait(10)

    t = threading.Thread(target=quiet)
    t.start()
    try:
        inside.wait(10)
        pts = c.points.to(device)
        _, err = outcome(lidarops.knn, pts, pts, 2)
    finally:
        done.set()
        t.join()
    assert_clear_error(err, ValueError, ["query", "points"], "knn with NaN while another thread validates nothing")
