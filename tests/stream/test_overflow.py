"""PillarStream(overflow="drop") and SSCATeRPointPillars(overflow="drop"): every step against an
independent NumPy implementation of the documented drop rule (docs/stream.md, "Overflow policy"):

- the window is decided from every valid pushed point (a dropped point still moves t_newest), and
  the points that leave it expire;
- points already in the window are never evicted;
- the entering points of a pillar are admitted in (t, arrival) order while its queue has room
  (max_points_per_pillar minus the points it keeps);
- when more pillars would become occupied than there are free slots (max_pillars minus the pillars
  that keep points), new pillars are admitted in key order (y * W + x) and the entering points of
  the others are dropped.

The reference below is written from that text (a plain loop over pillars), not from the code under
test; the stream's pillars are compared with ``_pillarize_reference`` of the reference's window, and
SSCATeR's output with ``recompute`` of the same window.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers.compare import assert_close_report, assert_equal_report
from helpers.devices import requires_cuda
from lidarops.ops.pillars import _pillar_keys_reference, _pillarize_reference
from lidarops.stream import PillarGrid, PillarOverflowError, PillarStream, StreamCounts

GRID = PillarGrid((0.0, 0.0, -2.0, 16.0, 16.0, 2.0), (1.0, 1.0))  # 16 x 16 pillars (divisible by 8: SSCATeR)
F32_RTOL, F32_ATOL = 2.0**-20, 1e-6


def _invalid(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The input policy: intensity or t NaN, infinite or beyond 1e6 / 1e10."""
    with np.errstate(invalid="ignore"):
        return ~(np.abs(points[:, 3].astype(np.float64)) <= 1e6) | ~(np.abs(t) <= 1e10)


class DropReference:
    """The window as the overflow rule defines it: kept points with their arrival ids."""

    def __init__(self, grid: PillarGrid, window: float, N: int, M: int):
        self.grid, self.window, self.N, self.M = grid, window, N, M
        self.p = np.zeros((0, 4), np.float32)
        self.t = np.zeros(0)
        self.key = np.zeros(0, np.int64)
        self.id = np.zeros(0, np.int64)
        self.newest = -math.inf
        self.arrived = 0

    def push(self, points: np.ndarray, t: np.ndarray, now=None) -> dict:
        n = len(points)
        invalid = _invalid(points, t)
        if (~invalid).any():
            self.newest = max(self.newest, float(t[~invalid].max()))
        if now is not None:
            self.newest = max(self.newest, float(now))
        cutoff = self.newest - self.window
        live = self.t > cutoff
        out = int((~live).sum())
        self.p, self.t, self.key, self.id = self.p[live], self.t[live], self.key[live], self.id[live]
        keys = np.where(invalid, -1, _pillar_keys_reference(points, self.grid))
        outside = ~invalid & (keys < 0)
        late = ~invalid & (keys >= 0) & ~(t > cutoff)
        entering = ~invalid & (keys >= 0) & (t > cutoff)
        has = {int(k): int(c) for k, c in zip(*np.unique(self.key, return_counts=True))}
        free = self.M - len(has)
        admit = np.zeros(n, bool)
        drop_points = drop_pillars = 0
        for k in sorted(set(keys[entering].tolist())):  # pillars in key order
            mine = np.nonzero(entering & (keys == k))[0]
            mine = mine[np.lexsort((mine, t[mine]))]  # (t, arrival) order
            if has.get(k, 0) == 0:  # a new pillar needs a free slot
                if free == 0:
                    drop_pillars += len(mine)
                    continue
                free -= 1
            room = self.N - has.get(k, 0)
            admit[mine[:room]] = True
            drop_points += max(0, len(mine) - room)
        ids = self.arrived + np.arange(n)
        self.arrived += n
        self.p = np.concatenate([self.p, points[admit]])
        self.t = np.concatenate([self.t, t[admit]])
        self.key = np.concatenate([self.key, keys[admit]])
        self.id = np.concatenate([self.id, ids[admit]])
        return dict(points_in=int(admit.sum()), points_out=out, points_outside=int(outside.sum()),
                    points_late=int(late.sum()), points_invalid=int(invalid.sum()),
                    points_dropped=drop_points + drop_pillars, dropped_max_points=drop_points,
                    dropped_max_pillars=drop_pillars)

    def window_points(self) -> np.ndarray:
        """The kept window in (t, arrival) order: the order of the stream's queues."""
        order = np.lexsort((self.id, self.t))
        return self.p[order]


def _dense_slices(seed: int, steps: int, dt: float = 0.01, crowd=((2, 3), (2, 4), (9, 9), (12, 1), (5, 14))):
    """Slices that overflow repeatedly: most points in a few pillars (so queues fill up), the rest
    spread over the grid (so new pillars compete for slots); timestamps out of order, some late,
    duplicates, a few points outside the grid and a few invalid ones, some empty slices."""
    rng = np.random.default_rng(seed)
    crowd = np.array(crowd, np.float64)
    for s in range(steps):
        n = 0 if s % 17 == 5 else int(rng.integers(1, 25))
        hot = rng.random(n) < 0.7
        cell = np.where(hot[:, None], crowd[rng.integers(0, len(crowd), n)], rng.integers(0, 16, (n, 2)))
        xy = cell + rng.uniform(0.05, 0.95, (n, 2))
        p = np.concatenate([xy, rng.uniform(-1.5, 1.5, (n, 1)), rng.uniform(0, 1, (n, 1))], 1).astype(np.float32)
        if n > 3:
            p[1] = p[0]  # an exact duplicate
        t = np.round((s + 1) * dt - rng.uniform(0, 0.03, n), 3)  # out of order, repeats, some late
        odd = rng.random(n)
        p[odd < 0.04, 0] = 40.0  # outside
        p[(odd >= 0.04) & (odd < 0.07), 3] = np.nan  # invalid intensity
        t[(odd >= 0.07) & (odd < 0.09)] = np.inf  # invalid timestamp
        yield p, t


def _check_pillars(stream: PillarStream, ref: DropReference, where: str):
    exp = _pillarize_reference(ref.window_points(), ref.grid, ref.N)
    got = stream.pillars()
    assert_equal_report(got.coords, torch.from_numpy(exp["coords"]), f"{where}: coords")
    assert_equal_report(got.num_points, torch.from_numpy(exp["num_points"]), f"{where}: num_points")
    feats = got.features.detach().cpu().double()
    ef = torch.from_numpy(exp["features"])
    assert_equal_report(feats[..., :4], ef[..., :4].float().double(), f"{where}: x, y, z, intensity")
    assert_close_report(feats, ef, F32_RTOL, F32_ATOL, f"{where}: decorated features")


def _check_counts(u, expected: dict, n: int, where: str):
    got = {k: getattr(u, k) for k in ("points_in", "points_out", "points_outside", "points_late", "points_invalid",
                                      "points_dropped")}
    exp = {k: expected[k] for k in got}
    assert got == exp, f"{where}: {got} != {exp}"
    assert u.points_in + u.points_outside + u.points_late + u.points_invalid + u.points_dropped == n, where


@pytest.mark.parametrize("N, M, seed", [(4, 6, 0), (3, 4, 1), (6, 12, 2)])
def test_drop_matches_reference_rule(device, N, M, seed):
    window = 0.05
    stream = PillarStream(GRID, window=window, max_points_per_pillar=N, max_pillars=M, device=device,
                          overflow="drop")
    ref = DropReference(GRID, window, N, M)
    totals = dict.fromkeys(("points_pushed", "points_in", "points_out", "points_outside", "points_late",
                            "points_invalid", "points_dropped", "dropped_max_points", "dropped_max_pillars"), 0)
    overflowing_pushes = 0
    for i, (p, t) in enumerate(_dense_slices(seed, 90)):
        now = 0.01 * (i + 1) if i % 11 == 3 else None
        where = f"{device} N={N} M={M} step {i}"
        u = stream.push(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device), now=now)
        exp = ref.push(p, t, now)
        assert u.t == ref.newest, where
        _check_counts(u, exp, len(p), where)
        _check_pillars(stream, ref, where)
        assert stream.num_points == len(ref.t) and stream.num_active == len(set(ref.key.tolist())), where
        overflowing_pushes += exp["points_dropped"] > 0
        totals["points_pushed"] += len(p)
        for k in totals:
            if k != "points_pushed":
                totals[k] += exp[k]
    assert stream.counts == StreamCounts(**{k: totals[k] for k in StreamCounts._fields if k in totals},
                                         invalid_intensity=stream.counts.invalid_intensity,
                                         invalid_t=stream.counts.invalid_t)
    c = stream.counts
    assert c.points_pushed == c.points_in + c.points_outside + c.points_late + c.points_invalid + c.points_dropped
    # the stream did overflow, often, on both capacities
    assert overflowing_pushes > 20 and c.dropped_max_points > 0 and c.dropped_max_pillars > 0


def test_drop_rule_by_hand(device):
    """A case small enough to count on paper. N = 2 points per pillar, M = 2 pillars, window 1 s."""
    s = PillarStream(GRID, window=1.0, max_points_per_pillar=2, max_pillars=2, device=device, overflow="drop")
    A, B, C, D = (0.5, 0.5), (1.5, 0.5), (0.5, 1.5), (1.5, 1.5)  # keys 0, 1, 16, 17

    def pts(*xy):
        return np.array([[x, y, 0.0, 0.1 * i] for i, (x, y) in enumerate(xy)], np.float32)

    # 3 points in A arriving out of order (t = 0.2, 0.0, 0.1): the two earliest (t = 0.0, 0.1) stay
    u = s.push(pts(A, A, A), np.array([0.2, 0.0, 0.1]))
    assert (u.points_in, u.points_dropped) == (2, 1)
    f = s.pillars().features
    assert f[0, :2, 3].tolist() == pytest.approx([0.1, 0.2])  # the intensities of the 2nd and 3rd point
    # A is full (kept points are never evicted, even by newer ones); D, C and B are new but one slot
    # is free: B (key 1) wins over C (16) and D (17), whatever the arrival order
    u = s.push(pts(D, C, A, B, B, B), np.full(6, 0.3))
    assert (u.points_in, u.points_dropped) == (2, 4)
    assert s.pillars().coords.tolist() == [[0, 0, 0], [0, 0, 1]] and s.pillars().num_points.tolist() == [2, 2]
    c = s.counts
    # full queues: A's 3rd and 4th point, B's 3rd point; no slot: C's and D's point
    assert (c.dropped_max_points, c.dropped_max_pillars) == (3, 2)
    # at t = 1.05 A's points of t = 0.0 expire (t <= 1.05 - 1): room for exactly one more in A,
    # the (t, arrival)-first one of this push
    u = s.push(pts(A, A), np.array([1.05, 1.0]))
    assert (u.points_out, u.points_in, u.points_dropped) == (1, 1, 1)
    # the t = 0.1 point of the first push (intensity 0.2), then this push's t = 1.0 point (intensity 0.1)
    assert s.pillars().features[0, :2, 3].tolist() == pytest.approx([0.2, 0.1])
    assert s.t == 1.05  # the dropped point (t = 1.05) moved t_newest all the same


def test_raise_is_the_default_and_names_drop(device):
    s = PillarStream(GRID, window=1.0, max_points_per_pillar=2, max_pillars=8, device=device)
    assert s.overflow == "raise"
    p = np.array([[0.5, 0.5, 0.0, 1.0]] * 3, np.float32)
    with pytest.raises(PillarOverflowError, match=r"max_points_per_pillar=2.*overflow='drop'.*no effect"):
        s.push(p, np.zeros(3))
    assert s.num_points == 0 and s.counts == StreamCounts()
    for bad in ("clip", None, 1, "Drop"):
        with pytest.raises(ValueError, match="overflow must be 'raise' or 'drop'"):
            PillarStream(GRID, overflow=bad)


@requires_cuda
def test_drop_cpu_cuda_parity():
    streams = {d: PillarStream(GRID, window=0.05, max_points_per_pillar=4, max_pillars=6, device=d, overflow="drop")
               for d in ("cpu", "cuda")}
    for i, (p, t) in enumerate(_dense_slices(7, 60)):
        ups = {d: s.push(p, t) for d, s in streams.items()}
        for k in ("active", "changed", "removed", "change_map"):
            assert_equal_report(getattr(ups["cuda"], k), getattr(ups["cpu"], k), f"step {i} {k}")
        assert ups["cuda"][5:] == ups["cpu"][5:], f"step {i} counts"
        for a, b in zip(streams["cuda"].pillars(), streams["cpu"].pillars()):
            assert_equal_report(a, b, f"step {i} pillars")


# ---- SSCATeR: identical to the full recomputation of the points kept ----

def _model(device, dtype=torch.float64):
    from lidarops.models.bev_backbone import BaseBEVBackbone
    from lidarops.models.sscater_pointpillars import PillarFeatureNet
    torch.manual_seed(0)
    pfn = PillarFeatureNet(9, 8)
    bb = BaseBEVBackbone(8, (1, 1, 1), (2, 2, 2), (8, 16, 16), (1, 2, 4), (8, 8, 8))
    with torch.no_grad():  # BatchNorm statistics that are not the identity, and a bias that makes ReLU sparse
        for m in list(pfn.modules()) + list(bb.modules()):
            if isinstance(m, torch.nn.BatchNorm1d | torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.2, 0.2)
                m.running_var.uniform_(0.5, 2.0)
                m.weight.uniform_(0.5, 1.5)
                m.bias.uniform_(-0.3, 0.1)
    return pfn.eval().to(device, dtype), bb.eval().to(device, dtype)


@pytest.mark.parametrize("refresh_every, steps", [(0, 30), pytest.param(7, 100, marks=pytest.mark.slow)])
def test_sscater_drop_equals_recompute_of_kept_points(device, refresh_every, steps):
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    N, M, window = 4, 6, 0.05
    pfn, bb = _model(device)
    model = SSCATeRPointPillars(pfn, bb, GRID, window=window, max_points_per_pillar=N, max_pillars=M,
                                refresh_every=refresh_every, dtype=torch.float64, device=device, overflow="drop")
    assert model.stream.overflow == "drop"
    ref = DropReference(GRID, window, N, M)
    dropped = 0
    for i, (p, t) in enumerate(_dense_slices(3, steps)):
        out = model.step(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device))
        exp = ref.push(p, t)
        where = f"{device} refresh_every={refresh_every} step {i}"
        st = model.stats
        assert (st.points_in, st.points_out, st.points_invalid, st.points_dropped) == (
            exp["points_in"], exp["points_out"], exp["points_invalid"], exp["points_dropped"]), where
        _check_pillars(model.stream, ref, where)
        full = model.recompute(torch.from_numpy(ref.window_points()).to(device))
        scale = full.abs().max().item()
        diff = (out - full).abs().max().item()
        assert diff <= 1e-12 * max(scale, 1e-300) or diff == 0, f"{where}: |step - recompute| = {diff:.3e} of {scale:.3e}"
        dropped += st.points_dropped
    assert dropped > steps


def test_sscater_raise_by_default():
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    pfn, bb = _model("cpu")
    model = SSCATeRPointPillars(pfn, bb, GRID, window=1.0, max_points_per_pillar=2, max_pillars=8,
                                dtype=torch.float64, device="cpu")
    with pytest.raises(PillarOverflowError, match="overflow='drop'"):
        model.step(np.array([[0.5, 0.5, 0.0, 1.0]] * 3, np.float32), np.zeros(3))
    with pytest.raises(ValueError, match="overflow must be 'raise' or 'drop'"):
        SSCATeRPointPillars(pfn, bb, GRID, overflow="skip")
