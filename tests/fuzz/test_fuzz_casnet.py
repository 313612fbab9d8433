"""Fuzz: CAS-Net and the samplers behind ``sampler(points, m, lengths) -> indices`` (lidarops.models.samplers,
lidarops.models.casnet).

- **bad arguments**: one of ``points``, ``m``, ``lengths`` (or the model's ``mode``) replaced by a drawn bad value
  (wrong rank, too few channels, integer or bool dtype, not a tensor; m that is 0, negative, a float, a bool, a
  string or beyond any memory; lengths of the wrong size or dtype or out of range): a ``ValueError`` naming it.
- **valid clouds** (ragged, duplicated points, lattice ties, empty clouds): every sampler returns (B, m) int64
  indices, per cloud ``min(m, n)`` distinct valid indices then -1, and :func:`sample_features` gives exactly the
  input rows; CAS-Net's forward (hard mode) returns rows equal to the input rows at its indices, each index
  inside its cloud, distinct with ``dedup``; soft mode gives finite convex combinations.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.models.casnet import CASNet, CASNetSampler
from lidarops.models.samplers import ChunkedFPSSampler, FPSSampler, RandomSampler, sample_features
from lidarops.ops.neighbors import _gather_reference

from helpers.models import randomize_bn

from .fuzzing import assert_clear_error, assert_no_error, assert_same, clouds, fuzz, outcome

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny tensors: OpenMP wake-ups cost more than the work


def _net() -> CASNet:
    torch.manual_seed(0)
    net = CASNet(4, k=4, radius=1.5)
    randomize_bn(net, 0)
    return net.eval()


def _anchored() -> CASNet:
    torch.manual_seed(0)
    net = CASNet(4, k=4, radius=1.5, head="anchored", candidates=3)
    randomize_bn(net, 0)
    with torch.no_grad():  # the feature terms away from their zero start
        net.head.key.weight.normal_()
        net.head.score.weight.normal_()
    return net.eval()


_NET = _net()
_ANCHORED = _anchored()
_SAMPLERS = {
    "casnet_anchored_whole": lambda device: CASNetSampler(_ANCHORED.to(device), whole=True),
    "random": lambda device: RandomSampler(7),
    "fps": lambda device: FPSSampler(),
    "chunked_fps": lambda device: ChunkedFPSSampler(5),
    "casnet": lambda device: CASNetSampler(_NET.to(device), max_points=64),
}


def _with_intensity(points: torch.Tensor) -> torch.Tensor:
    g = torch.Generator().manual_seed(points.numel())
    return torch.cat([points, torch.rand(*points.shape[:2], 1, generator=g, dtype=torch.float64).to(points.dtype)], -1)


_BAD_POINTS = st.sampled_from([
    ("a list", lambda B, N: [[[0.0, 0.0, 0.0]] * N] * B),
    ("2-D", lambda B, N: torch.zeros(N, 3)),
    ("4-D", lambda B, N: torch.zeros(B, N, 3, 1)),
    ("2 channels", lambda B, N: torch.zeros(B, N, 2)),
    ("int64", lambda B, N: torch.zeros(B, N, 3, dtype=torch.int64)),
    ("bool", lambda B, N: torch.zeros(B, N, 4, dtype=torch.bool)),
])
_BAD_M = st.sampled_from([0, -1, -(2**63), 1.5, 2.0, True, False, "2", None, 2**40, 2**62, torch.tensor(1.0),
                          torch.tensor([1, 2])])


def _bad_lengths(B: int, N: int) -> st.SearchStrategy:
    return st.sampled_from([
        torch.full((B + 1,), N), torch.full((B, 1), N), torch.full((B,), float(N)), torch.full((B,), N + 1),
        torch.full((B,), -1), torch.full((B,), True), [N] * (B + 1),
    ])


@fuzz
@given(data=st.data())
def test_bad_sampler_arguments_name_the_argument(device, data):
    kind = data.draw(st.sampled_from(sorted(_SAMPLERS)), "sampler")
    B, N = data.draw(st.integers(1, 2), "B"), data.draw(st.integers(1, 6), "N")
    which = data.draw(st.sampled_from(["points", "m", "lengths"]), "argument")
    points, m, lengths = torch.rand(B, N, 4, device=device), data.draw(st.integers(1, 8), "m"), None
    if which == "points":
        label, make = data.draw(_BAD_POINTS, "bad points")
        points = make(B, N)
        points = points.to(device) if isinstance(points, torch.Tensor) else points
    elif which == "m":
        m = data.draw(_BAD_M, "bad m")
    else:
        lengths = data.draw(_bad_lengths(B, N), "bad lengths")
        lengths = lengths.to(device) if isinstance(lengths, torch.Tensor) else lengths
    _, err = outcome(_SAMPLERS[kind](device), points, m, lengths)
    assert_clear_error(err, ValueError, [which], f"{kind}: bad {which}")


@fuzz
@given(data=st.data())
def test_bad_model_arguments_name_the_argument(device, data):
    net = _NET.to(device)
    B, N = data.draw(st.integers(1, 2), "B"), data.draw(st.integers(1, 6), "N")
    which = data.draw(st.sampled_from(["points", "lengths", "mode", "dedup"]), "argument")
    points, lengths, mode, dedup = torch.rand(B, N, 4, device=device), None, None, None
    if which == "points":
        label, make = data.draw(_BAD_POINTS | st.sampled_from([
            ("empty batch", lambda B, N: torch.zeros(0, N, 3)), ("no points", lambda B, N: torch.zeros(B, 0, 3)),
            ("NaN", lambda B, N: torch.full((B, N, 3), math.nan)),
            ("inf", lambda B, N: torch.full((B, N, 3), -math.inf))]), "bad points")
        points = make(B, N)
        points = points.to(device) if isinstance(points, torch.Tensor) else points
    elif which == "lengths":
        lengths = data.draw(_bad_lengths(B, N) | st.just(torch.zeros(B, dtype=torch.int64)), "bad lengths")
        lengths = lengths.to(device) if isinstance(lengths, torch.Tensor) else lengths
    elif which == "mode":
        mode = data.draw(st.sampled_from(["Hard", "", "argmax", 1]), "bad mode")
    else:
        dedup = data.draw(st.sampled_from(["yes", 1, 0.0, torch.tensor(True)]), "bad dedup")
    _, err = outcome(net, points, lengths, mode, dedup)
    assert_clear_error(err, ValueError, [which], f"CASNet: bad {which}")


@fuzz
@given(data=st.data())
def test_samplers_return_distinct_rows_of_the_input(device, data):
    kind = data.draw(st.sampled_from(sorted(_SAMPLERS)), "sampler")
    c = data.draw(clouds(regime=data.draw(st.sampled_from(["normal", "lattice"]), "regime"), max_n=24), "cloud")
    assume(c.valid_lengths)
    m = data.draw(st.integers(1, 30), "m")
    pts = _with_intensity(c.points).to(device)
    lengths = None if c.lengths is None else c.lengths.to(device)
    idx, err = outcome(_SAMPLERS[kind](device), pts, m, lengths)
    what = f"{kind}(m={m}) on {tuple(pts.shape)}, lengths {None if c.lengths is None else c.lengths.tolist()}"
    assert_no_error(err, what)
    assert idx.dtype == torch.int64 and tuple(idx.shape) == (pts.shape[0], m) and idx.device == pts.device, what
    for b, n in enumerate(c.rows()):
        k = min(m, n)
        row = idx[b].cpu()
        assert bool((row[k:] == -1).all()), f"{what}: cloud {b}: not -1 past {k}: {row.tolist()}"
        assert bool(((row[:k] >= 0) & (row[:k] < n)).all()), f"{what}: cloud {b}: out of [0, {n}): {row.tolist()}"
        assert row[:k].unique().numel() == k, f"{what}: cloud {b}: repeats {row.tolist()}"
    rows = sample_features(pts, idx)
    assert_same(rows, _gather_reference(pts.cpu(), idx.cpu()), what + " rows")


@fuzz
@given(data=st.data())
def test_casnet_forward_samples_rows_of_the_input(device, data):
    c = data.draw(clouds(batch=data.draw(st.integers(1, 3), "B"), min_n=1, max_n=20,
                         regime=data.draw(st.sampled_from(["normal", "lattice"]), "regime")), "cloud")
    assume(c.valid_lengths and (c.lengths is None or bool((c.lengths >= 1).all())))
    mode = data.draw(st.sampled_from(["hard", "soft"]), "mode")
    dedup = data.draw(st.booleans(), "dedup")
    pts = _with_intensity(c.points).to(device)
    lengths = None if c.lengths is None else c.lengths.to(device)
    what = f"CASNet(mode={mode}, dedup={dedup}) on {tuple(pts.shape)}, lengths {c.rows()}"
    with torch.no_grad():
        out, err = outcome(_NET.to(device), pts, lengths, mode, dedup)
    assert_no_error(err, what)
    B, m = pts.shape[0], _NET.num_out
    assert tuple(out.sampled.shape) == (B, m, 4) and out.sampled.dtype == pts.dtype, what
    for b, n in enumerate(c.rows()):
        assert bool((out.soft_matrix[b, :, n:] == 0).all()), f"{what}: weight on padding in cloud {b}"
        if mode == "hard":
            idx = out.indices[b]
            assert bool(((idx >= 0) & (idx < n)).all()), f"{what}: cloud {b}: indices {idx.tolist()} not in [0, {n})"
            assert_same(out.sampled[b], pts[b, idx], f"{what}: cloud {b} rows")
            if dedup:
                assert idx.unique().numel() == min(m, n), f"{what}: cloud {b}: repeats {idx.tolist()}"
        else:
            assert bool(torch.isfinite(out.sampled[b]).all()), what
            lo, hi = pts[b, :n].amin(0), pts[b, :n].amax(0)
            slack = 1e-4 * (1 + pts[b, :n].abs().amax(0))
            assert bool(((out.sampled[b] >= lo - slack) & (out.sampled[b] <= hi + slack)).all()), \
                f"{what}: cloud {b}: soft samples outside the cloud's box"


_BAD_NUM_OUT = st.sampled_from([0, -1, 1.5, True, "2", 2.0])


def _near_ties(scores: torch.Tensor, tol: float = 1e-5) -> bool:
    """Whether two of a cloud's finite pair scores lie within ``tol`` of each other (exact ties included)."""
    for row in scores.flatten(1):
        v = row[torch.isfinite(row)].sort().values
        if v.numel() > 1 and bool((v.diff() <= tol).any()):
            return True
    return False


@fuzz
@given(data=st.data())
def test_anchored_pick_equals_forward_and_names_bad_arguments(device, data):
    c = data.draw(clouds(batch=data.draw(st.integers(1, 3), "B"), min_n=1, max_n=20,
                         regime=data.draw(st.sampled_from(["normal", "lattice"]), "regime")), "cloud")
    assume(c.valid_lengths and (c.lengths is None or bool((c.lengths >= 1).all())))
    pts = _with_intensity(c.points).to(device)
    lengths = None if c.lengths is None else c.lengths.to(device)
    net = _ANCHORED.to(device)
    m = data.draw(st.integers(1, 24), "num_out")
    dedup = data.draw(st.booleans(), "dedup")
    what = f"CASNet(head='anchored').pick(num_out={m}, dedup={dedup}) on {tuple(pts.shape)}, lengths {c.rows()}"
    got, err = outcome(net.pick, pts, lengths, m, dedup)
    assert_no_error(err, what)
    with torch.no_grad():
        out = net(pts, lengths, mode="hard", dedup=dedup, num_out=m)
    want = out.indices
    scores = torch.log_softmax(out.logits.detach().double(), -1)
    if dedup and _near_ties(scores):
        # pick's greedy takes forward's pairs in forward's order up to the rounding of the log-softmax (its
        # docstring): pairs whose scores tie to rounding may go either way, and the greedy's later picks with them;
        # what holds: as many distinct points, each pick one of its row's candidates or the row's own best
        with torch.no_grad():
            plain = net(pts, lengths, mode="hard", dedup=False, num_out=m).indices
        for b in range(pts.shape[0]):
            assert got[b].unique().numel() == want[b].unique().numel(), f"{what}: cloud {b}: {got[b]} vs {want[b]}"
            ok = torch.isfinite(scores[b].gather(1, got[b, :, None]))[:, 0] | (got[b] == plain[b])
            assert bool(ok.all()), f"{what}: cloud {b}: {got[b]} picks outside the rows' candidates"
    else:
        assert_same(got, want, what)
    for b, n in enumerate(c.rows()):
        assert bool(((got[b] >= 0) & (got[b] < n)).all()), f"{what}: cloud {b}: {got[b].tolist()} not in [0, {n})"
    bad = data.draw(_BAD_NUM_OUT, "bad num_out")
    _, err = outcome(net.pick, pts, lengths, bad, dedup)
    assert_clear_error(err, ValueError, ["num_out"], f"pick: bad num_out {bad!r}")
