"""Fault injection into a streamed SSCATeR front: long streams with NaN / infinite / huge
intensities and timestamps, non-finite coordinates, duplicate and out-of-order timestamps, late
points, empty slices and gaps. After every step SSCATeR's output must equal the full recomputation of
the window as the stream's policy defines it, computed here independently from the points pushed:
points that are valid (intensity and t finite and within MAX_ABS_INTENSITY / MAX_ABS_TIME), inside the
grid, with ``t`` in ``(t_newest - window, t_newest]`` where ``t_newest`` is the largest valid
timestamp (or ``now``) seen so far. The stream's counts must equal this test's own classification.
Runs use ``refresh_every=0``, so nothing but the guard may refresh the recycled state.

Tolerances. float64: the recycled and the fresh sums differ only in the order of additions, a few
hundred rounding errors of 2^-53 relative to the accumulators' magnitudes (which are within a small
factor of max|output| here): 1e-12 of max|output| leaves a margin of more than 10x. float32: the same
argument with 2^-24 gives about 1e-7 per step, adding up like a random walk (measured: about 1e-6 after
300 steps); we allow the 1e-5 of max|output| that docs/sscater.md states for the recycled sums.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lidarops.models.sscater_pointpillars import PillarFeatureNet
from lidarops.stream import MAX_ABS_INTENSITY, MAX_ABS_TIME, PillarGrid
from helpers.models import randomize_bn, small_backbone

GRID = PillarGrid((-8.0, -8.0, -2.0, 8.0, 8.0, 2.0), (1.0, 1.0))  # 16 x 16 pillars of 1 m, z in [-2, 2)
WINDOW = 0.1
N, M = 64, 256
TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


# tiny tensors: on a shared 2-core machine OpenMP wake-ups cost more than the work
pytestmark = pytest.mark.usefixtures("one_thread")


def _model(dtype, guard=True, seed=0, refresh_every=0):
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    torch.manual_seed(seed)
    pfn = PillarFeatureNet(9, 8)
    randomize_bn(pfn, seed)
    bb = small_backbone(cin=8, seed=seed + 1, negative_bias=0.3, dtype=dtype)
    return SSCATeRPointPillars(pfn.eval().to(dtype), bb, GRID, window=WINDOW, max_points_per_pillar=N, max_pillars=M,
                               refresh_every=refresh_every, dtype=dtype, guard=guard)


class _Window:
    """Every pushed point and the test's own reading of the policy (written out, not imported)."""

    def __init__(self):
        self.p = np.zeros((0, 4), np.float32)
        self.t = np.zeros(0, np.float64)
        self.newest = -math.inf
        self.ids = np.zeros(0, np.int64)  # the window's points (indices into p), (t, arrival) order
        self.totals = dict(outside=0, late=0, invalid=0, invalid_intensity=0, invalid_t=0)

    def push(self, p: np.ndarray, t: np.ndarray, now):
        """Classify a slice; returns this step's (invalid, entered, left) counts."""
        with np.errstate(invalid="ignore"):
            bad_i = ~(np.abs(p[:, 3].astype(np.float64)) <= 1e6)  # NaN fails every comparison
            bad_t = ~(np.abs(t) <= 1e10)
            x, y, z = (p[:, a].astype(np.float64) for a in range(3))
            inside = (x >= -8) & (x < 8) & (y >= -8) & (y < 8) & (z >= -2) & (z < 2)
        invalid = bad_i | bad_t
        if (~invalid).any():
            self.newest = max(self.newest, float(t[~invalid].max()))
        if now is not None:
            self.newest = max(self.newest, now)
        cutoff = self.newest - WINDOW
        late = ~invalid & inside & (t <= cutoff)
        entered = ~invalid & inside & ~late
        for k, v in (("outside", ~invalid & ~inside), ("late", late), ("invalid", invalid),
                     ("invalid_intensity", bad_i), ("invalid_t", bad_t)):
            self.totals[k] += int(v.sum())
        base = self.p.shape[0]
        self.p = np.concatenate([self.p, p])
        self.t = np.concatenate([self.t, t])
        kept = np.concatenate([self.ids, base + np.nonzero(entered)[0]])
        kept = kept[self.t[kept] > cutoff]
        kept = kept[np.lexsort((kept, self.t[kept]))]  # time order, ties in arrival order (the stream's)
        left = np.setdiff1d(self.ids, kept).size
        self.ids = kept
        return int(invalid.sum()), int(entered.sum()), left

    def points(self) -> torch.Tensor:
        return torch.from_numpy(self.p[self.ids])


def _clean_slice(rng, i, n, grid_margin=True):
    """n points in the middle of pillars (0.05 m from their edges, so that no float rounding decides
    the pillar), a ring of pillars outside the grid included, t inside the slice [0.01 i, 0.01 (i + 1))."""
    lo = -1 if grid_margin else 0
    cells = rng.integers(lo, 16 - lo, size=(n, 2))
    p = np.empty((n, 4), np.float32)
    p[:, 0] = -8 + cells[:, 0] + rng.uniform(0.05, 0.95, n)
    p[:, 1] = -8 + cells[:, 1] + rng.uniform(0.05, 0.95, n)
    p[:, 2] = rng.uniform(-1.9, 1.9, n)
    p[:, 3] = rng.uniform(0.0, 1.0, n)
    t = 0.01 * i + rng.uniform(0.0, 0.0099, n)
    return p, t


_F32_ABOVE_MAX_I = float(np.nextafter(np.float32(MAX_ABS_INTENSITY), np.float32(np.inf)))  # 1e6 + 1/16: invalid
_T_ABOVE_MAX = float(np.nextafter(MAX_ABS_TIME, np.inf))
BAD_INTENSITY = [math.nan, math.inf, -math.inf, 1e30, -1e30, 3.4e38, 1.5e6, -_F32_ABOVE_MAX_I, _F32_ABOVE_MAX_I]
BAD_T = [math.nan, math.inf, -math.inf, 1e30, -1e30, 2e10, -2e10, _T_ABOVE_MAX, -_T_ABOVE_MAX]
BAD_COORD = [math.nan, math.inf, -math.inf, 1e30, -1e30]


def _faulty_slice(rng, i, now):
    """A slice with faults: bad intensities, timestamps and coordinates (some points several), exact
    duplicates, equal timestamps, out-of-order and late points, a point exactly at the window's edge."""
    n = int(rng.integers(15, 60))
    p, t = _clean_slice(rng, i, n)
    if rng.random() < 0.3:
        t = np.round(t, 3)  # equal timestamps (1 ms clock)
    if rng.random() < 0.15:
        t[:] = t[0]  # one timestamp for the whole slice
    old = rng.random(n) < 0.15
    t[old] -= rng.uniform(0.0, 0.15, int(old.sum()))  # out of order; older than the window: late
    if n > 6:
        k = int(rng.integers(1, 4))
        p[-k:], t[-k:] = p[:k], t[:k]  # exact duplicates of points and timestamps
    for rows, values, cols in ((rng.random(n) < 0.08, BAD_INTENSITY, [3]), (rng.random(n) < 0.08, BAD_T, None),
                               (rng.random(n) < 0.06, BAD_COORD, [0, 1, 2])):
        for r in np.nonzero(rows)[0]:
            v = values[int(rng.integers(len(values)))]
            if cols is None:
                t[r] = v
            else:
                p[r, cols[int(rng.integers(len(cols)))]] = v
    if now is not None and rng.random() < 0.3:
        # exactly at the window's edge after this push (t_newest = now): t <= t_newest - window, late
        p = np.concatenate([p, p[:1]])
        p[-1, 3] = 0.5
        t = np.concatenate([t, [now - WINDOW]])
    return p, t


def _check_step(model, ref: _Window, out, counts, dtype, where):
    invalid, entered, left = counts
    st = model.stats
    assert (st.points_invalid, st.points_in, st.points_out) == (invalid, entered, left), where
    assert st.t == ref.newest, where
    c = model.stream.counts
    assert (c.points_outside, c.points_late, c.points_invalid, c.invalid_intensity, c.invalid_t) == (
        ref.totals["outside"], ref.totals["late"], ref.totals["invalid"], ref.totals["invalid_intensity"],
        ref.totals["invalid_t"]), where
    assert model.stream.num_points == ref.ids.size, where
    window = ref.points()
    if window.shape[0] == 0:  # no pillar: no active site, an all-zero map (exactly)
        assert st.pillars_active == 0 and not out.any(), where
        return 0.0
    expected = model.recompute(window)
    scale = expected.abs().max().item()
    diff = (out - expected).abs().max().item()
    assert scale > 0 and diff <= TOL[dtype] * scale, f"{where}: max |diff| {diff:.3g} = {diff / scale:.3g} of max|out|"
    return diff / scale


@pytest.mark.parametrize("dtype,refresh_every", [(torch.float32, 0), (torch.float64, 0), (torch.float32, 7)])
def test_faults_never_enter_the_recycled_state(dtype, refresh_every):
    """300 steps (3 s) of faulty slices and empty slices, with and without ``now``: every step equals
    the recomputation of the policy's window, the counts equal the test's classification, and the
    guard never fires: no fault reaches the state (a NaN or 1e30 that entered would trip it). With
    ``refresh_every=0`` nothing else refreshes either; with 7, the periodic refreshes interleave."""
    model = _model(dtype, refresh_every=refresh_every)
    ref = _Window()
    rng = np.random.default_rng(1)
    steps = 300 if dtype == torch.float32 else 150
    worst, empty = 0.0, 0
    for i in range(steps):
        now = 0.01 * (i + 1) if rng.random() < 0.7 else None
        if rng.random() < 0.07:
            p, t = np.zeros((0, 4), np.float32), np.zeros(0)
            empty += 1
        else:
            p, t = _faulty_slice(rng, i, now)
        counts = ref.push(p, t, now)
        out = model.step(torch.from_numpy(p), torch.from_numpy(t), now=now)
        worst = max(worst, _check_step(model, ref, out, counts, dtype, f"step {i}"))
        assert model.stats.guard == "" and math.isfinite(model.stats.state_max), f"step {i}: {model.stats.guard}"
        assert model.stats.refreshed == (i == 0 or (refresh_every > 0 and i % refresh_every == 0)), f"step {i}"
    st = model.stats
    assert st.guard_refreshes == 0 and st.step == steps - 1
    t = ref.totals
    # the stream really carried every kind of fault
    assert empty > 5 and t["invalid_intensity"] > 50 and t["invalid_t"] > 50 and t["outside"] > 50 and t["late"] > 50


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gaps_all_invalid_slices_and_extreme_valid_values(dtype):
    """Gaps that empty the grid (``now`` far ahead; and a jump of the timestamps without ``now``), slices
    whose every point is invalid, and valid points at the policy's bounds (intensity exactly
    +-MAX_ABS_INTENSITY: they enter, and the guard must clean up when they leave, since a 1e6 that
    entered and left leaves about 1e6 x 2^-24 of rounding behind in float32)."""
    model = _model(dtype)
    ref = _Window()
    rng = np.random.default_rng(2)
    clock = 0.0  # the slices' start times: gaps move it on
    emptied = 0
    for i in range(200):
        now = None
        if i in (40, 130):  # a 300 ms gap reported by `now` on an empty slice: everything expires
            clock += 0.3
            p, t, now = np.zeros((0, 4), np.float32), np.zeros(0), clock
        elif i in (41, 131):  # a quiet empty step on the empty grid
            p, t, now = np.zeros((0, 4), np.float32), np.zeros(0), clock
        elif i == 90:  # a gap without `now`: the first slice after it expires the window at once
            clock += 0.5
            p, t = _clean_slice(rng, 0, 40)
            t += clock
        elif i in (60, 61, 150):  # every point invalid: nothing changes, t_newest stays
            p, t = _clean_slice(rng, 0, 30)
            t += clock
            p[::2, 3] = np.float32(np.nan)
            t[1::2] = np.inf
        else:
            p, t = _clean_slice(rng, 0, int(rng.integers(20, 50)))
            t += clock
            now = clock + 0.01 if rng.random() < 0.5 else None
            if i in (100, 170):  # valid at the bound: it enters, stays 100 ms, then leaves
                p[0, 3] = MAX_ABS_INTENSITY if i == 100 else -MAX_ABS_INTENSITY
                p[0, :3] = (0.5, 0.5, 0.0)
        clock += 0.01
        counts = ref.push(p, t, now)
        out = model.step(torch.from_numpy(p), torch.from_numpy(t), now=now)
        _check_step(model, ref, out, counts, dtype, f"step {i}")
        emptied += ref.ids.size == 0
        assert math.isfinite(model.stats.state_max), f"step {i}"
    assert emptied >= 4  # both gaps emptied the grid (two steps each)
    # the extreme valid values swung the state: the guard refreshed (entering, and leaving)
    assert model.stats.guard_refreshes >= 2


def _clean_run(model, ref, rng, start, steps, dtype):
    out = None
    for i in range(start, start + steps):
        p, t = _clean_slice(rng, i, int(rng.integers(25, 45)))
        now = 0.01 * (i + 1)
        counts = ref.push(p, t, now)
        out = model.step(torch.from_numpy(p), torch.from_numpy(t), now=now)
        _check_step(model, ref, out, counts, dtype, f"step {i}")
    return out


def test_guard_never_fires_on_a_clean_stream():
    model = _model(torch.float32)
    ref = _Window()
    rng = np.random.default_rng(3)
    for i in range(250):
        p, t = _clean_slice(rng, i, int(rng.integers(20, 50)))
        counts = ref.push(p, t, 0.01 * (i + 1))
        out = model.step(torch.from_numpy(p), torch.from_numpy(t), now=0.01 * (i + 1))
        _check_step(model, ref, out, counts, torch.float32, f"step {i}")
        assert model.stats.guard == "" and not (i and model.stats.refreshed), f"step {i}"
    assert model.stats.guard_refreshes == 0


def _corrupt(model, poison: float):
    """Write ``poison`` into a block-1 layer's accumulator where its output is largest (a site and
    channel whose value is not a ReLU zero, so that the corruption cannot hide behind the ReLU)."""
    layer = next(lay for lay in model.delta.layers if lay.name.startswith("block1.subm"))
    assert layer.feats.max() > 0
    y, x, c = np.unravel_index(int(layer.feats.argmax()), tuple(layer.feats.shape))
    layer.acc[y, x, c] = poison


@pytest.mark.parametrize("poison,why", [(math.nan, "NaN or inf"), (-math.inf, "NaN or inf"), (1e20, "jumped")])
def test_guard_refreshes_a_corrupted_state(poison, why):
    dtype = torch.float32
    model = _model(dtype)
    ref = _Window()
    rng = np.random.default_rng(4)
    _clean_run(model, ref, rng, 0, 20, dtype)
    assert model.stats.guard_refreshes == 0
    _corrupt(model, poison)
    _clean_run(model, ref, rng, 20, 1, dtype)  # checked against the recomputation
    st = model.stats
    assert why in st.guard and st.guard_refreshes == 1 and st.refreshed, st.guard
    assert math.isfinite(st.state_max) and "not finite either" not in st.guard
    for i in range(21, 40):  # recycling resumes, and stays right
        _clean_run(model, ref, rng, i, 1, dtype)
        assert model.stats.guard == "" and not model.stats.refreshed, f"step {i}"
    assert model.stats.guard_refreshes == 1


@pytest.mark.parametrize("poison", [math.nan, 1e20])
def test_without_the_guard_the_corruption_shows(poison):
    """The control of the test above: with ``guard=False`` the same corruption reaches the output
    (so that test would fail if the guard did nothing)."""
    model = _model(torch.float32, guard=False)
    ref = _Window()
    rng = np.random.default_rng(4)
    _clean_run(model, ref, rng, 0, 20, torch.float32)
    _corrupt(model, poison)
    with pytest.raises(AssertionError, match="max"):
        _clean_run(model, ref, rng, 20, 20, torch.float32)
