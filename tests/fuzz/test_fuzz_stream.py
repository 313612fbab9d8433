"""Fuzz: PillarStream against pillarize's NumPy reference of the points left in its window.

Documented: the stream's pillars are pillarize's of the points in the window (t > t_newest - window)
ordered by time, ties in arrival order; a push that would overflow a capacity raises
PillarOverflowError and has no effect; points outside the grid (NaN or infinite coordinates included)
never enter; points with a non-finite or huge intensity or timestamp are dropped and counted.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.stream import PillarGrid, PillarOverflowError, PillarStream
from lidarops.ops.pillars import _pillarize_reference
from .fuzzing import assert_clear_error, assert_close, assert_no_error, assert_same, fuzz, outcome

GRID = PillarGrid((0.0, 0.0, -2.0, 4.0, 4.0, 2.0), (1.0, 1.0))
WINDOW = 0.1
MAX_ABS_INTENSITY, MAX_ABS_TIME = 1e6, 1e10  # the documented input policy


def _valid(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (np.abs(points[:, 3].astype(np.float64)) <= MAX_ABS_INTENSITY) & (np.abs(t) <= MAX_ABS_TIME)


@st.composite
def slices(draw, t0: float, invalid: bool):
    """One push: (n, 4) float32 points around the grid (some outside, some NaN / inf coordinates) and
    float64 times in [t0, t0 + 0.08] in any order; with ``invalid``, non-finite or huge intensities and
    timestamps too."""
    n = draw(st.integers(0, 8))
    coord = st.floats(-0.5, 4.5, width=32) | st.integers(0, 4).map(float) | st.sampled_from([math.nan, math.inf])
    inten = st.floats(0, 255, width=32)
    tt = st.floats(t0, t0 + 0.08)
    if invalid:
        inten = inten | st.sampled_from([math.nan, math.inf, -math.inf, 1e7, -3e38])
        tt = tt | st.sampled_from([math.nan, math.inf, -math.inf, 1e30, -1e11])
    rows = draw(st.lists(st.tuples(coord, coord, st.floats(-1, 1, width=32), inten), min_size=n, max_size=n))
    t = draw(st.lists(tt, min_size=n, max_size=n))
    return np.array(rows, dtype=np.float32).reshape(n, 4), np.array(t, dtype=np.float64).reshape(n)


def check_stream(pushes, N: int, M: int, device: str, what: str, cuda_graph: bool = True) -> None:
    stream = PillarStream(GRID, window=WINDOW, max_points_per_pillar=N, max_pillars=M, device=device,
                          cuda_graph=cuda_graph)
    kept_p, kept_t = np.zeros((0, 4), np.float32), np.zeros(0)  # valid points pushed so far, in arrival order
    newest = -math.inf
    for i, (points, t) in enumerate(pushes):
        label = f"{what}, push {i} of {len(points)} points"
        res, err = outcome(stream.push, torch.from_numpy(points).to(device), torch.from_numpy(t).to(device))
        valid = _valid(points, t)
        cand_p, cand_t = np.concatenate([kept_p, points[valid]]), np.concatenate([kept_t, t[valid]])
        cand_newest = max([newest] + t[valid].tolist())
        live = cand_t > cand_newest - WINDOW
        order = np.argsort(cand_t[live], kind="stable")  # time order, ties in arrival order
        ref = _pillarize_reference(cand_p[live][order], GRID, 10**6)
        if (ref["num_points"].size and ref["num_points"].max() > N) or ref["coords"].shape[0] > M:
            assert_clear_error(err, PillarOverflowError, ["max_points_per_pillar", "max_pillars"], label)
            continue  # the push had no effect
        assert_no_error(err, label)
        kept_p, kept_t, newest = cand_p, cand_t, cand_newest
        if hasattr(res, "points_invalid"):
            assert res.points_invalid == int((~valid).sum()), f"{label}: points_invalid {res.points_invalid}"
        pil = stream.pillars()
        assert_same(pil.coords, torch.from_numpy(ref["coords"]), label + " coords")
        assert_same(pil.num_points, torch.from_numpy(ref["num_points"]), label + " num_points")
        expected = torch.zeros(ref["coords"].shape[0], N, 9, dtype=torch.float64)
        if ref["features"].shape[0]:
            expected[:, :min(N, ref["features"].shape[1])] = torch.from_numpy(ref["features"])[:, :N]
        scale = max(1.0, float(expected.abs().max())) if expected.numel() else 1.0
        assert_close(pil.features, expected, rtol=4e-7, atol=4e-7 * scale, what=label + " features")


@fuzz
@given(data=st.data())
def test_stream_window(device, data):
    pushes = []
    t0 = data.draw(st.sampled_from([0.0, 1557540000.0]), "t0")
    for i in range(data.draw(st.integers(1, 3), "pushes")):
        pushes.append(data.draw(slices(t0 + 0.06 * i, invalid=False), f"push {i}"))
    check_stream(pushes, data.draw(st.integers(1, 6), "N"), data.draw(st.integers(1, 16), "M"), device,
                 "PillarStream", cuda_graph=data.draw(st.booleans(), "cuda_graph"))


@fuzz
@given(data=st.data())
def test_stream_invalid_values(device, data):
    pushes = [data.draw(slices(0.06 * i, invalid=True), f"push {i}") for i in range(data.draw(st.integers(1, 3)))]
    assume(any(not _valid(p, t).all() for p, t in pushes))
    check_stream(pushes, 8, 16, device, "PillarStream with invalid values",
                 cuda_graph=data.draw(st.booleans(), "cuda_graph"))


@fuzz
@given(data=st.data())
def test_stream_graph_arguments(device, data):
    """cuda_graph must be a bool; warm_up(points) an int >= 0, returning how many graphs it recorded (none on
    the CPU), after which pushes of up to that many points record none."""
    flag = data.draw(st.booleans() | st.sampled_from([None, 0, 1, "yes", 1.0]), "cuda_graph")
    res, err = outcome(PillarStream, GRID, window=WINDOW, device=device, overflow="drop", cuda_graph=flag)
    if not isinstance(flag, bool):
        assert_clear_error(err, ValueError, ["cuda_graph"], f"cuda_graph={flag!r}")
        return
    assert_no_error(err, f"cuda_graph={flag!r}")
    again = data.draw(st.booleans() | st.sampled_from([None, 0, "no"]), "cuda_graph set")
    _, err = outcome(setattr, res, "cuda_graph", again)
    if isinstance(again, bool):
        assert_no_error(err, f"stream.cuda_graph = {again!r}")
        assert res.cuda_graph == (again and device != "cpu")
        flag = again
    else:
        assert_clear_error(err, ValueError, ["cuda_graph"], f"stream.cuda_graph = {again!r}")
    points = data.draw(st.integers(-2, 3000) | st.sampled_from([None, True, 2.0, "10"]), "points")
    got, err = outcome(res.warm_up, points)
    if isinstance(points, bool) or not isinstance(points, int) or points < 0:
        assert_clear_error(err, ValueError, ["points"], f"warm_up({points!r})")
        return
    assert_no_error(err, f"warm_up({points!r})")
    assert got == (0 if device == "cpu" or not flag else max(1024, 1 << max(points - 1, 0).bit_length()).bit_length() - 10), \
        f"warm_up({points!r}) recorded {got}"
    graphs = len(res._push_graphs)
    n = data.draw(st.integers(0, points), "n")
    res.push(torch.rand(n, 4, device=device) * 4, torch.zeros(n, dtype=torch.float64, device=device))
    assert len(res._push_graphs) == graphs, f"a push of {n} points after warm_up({points}) recorded a graph"
