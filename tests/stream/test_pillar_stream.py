"""lidarops.stream: PillarStream, every step against ``pillarize`` of the window, and the changed pillars
against a diff of the point sets of consecutive windows (pillarize and PillarGrid themselves:
tests/ops/test_pillars.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from helpers.compare import assert_equal_report
from helpers.devices import requires_cuda
from helpers.pillars import DRIVING_AHEAD, SMALL, assert_same_pillars, check_against_reference, key_order, random_points
from lidarops.ops.pillars import _pillar_keys_reference
from lidarops.stream import (
    MAX_ABS_INTENSITY,
    MAX_ABS_TIME,
    PillarGrid,
    PillarOverflowError,
    PillarStream,
    StreamCounts,
    StreamUpdate,
    pillarize,
)


def test_opcheck_non_mutating_ops(device):
    pts = random_points(600, 7).to(device)
    res = pillarize(pts, SMALL, 30, 256)
    raw = res.features[..., :4].contiguous()
    for dt in (torch.float32, torch.float64):
        torch.library.opcheck(torch.ops.lidarops.pillar_decorate.default,
                              (raw.to(dt), res.num_points, res.coords, [1.0, 1.0], [-8.0, -8.0]))
    s = PillarStream(SMALL, window=1.0, max_points_per_pillar=30, max_pillars=256, device=device)
    s.push(pts, torch.linspace(0, 0.5, 600, dtype=torch.float64, device=device))
    keys = key_order(res.coords, SMALL).to(device)
    torch.library.opcheck(torch.ops.lidarops.pillar_stream_gather.default,
                          (s._pool_xyzi, s._head, s._count, s._cell_slot, keys[::3].contiguous()))


# ---- PillarStream: against pillarize of the window ----

def _invalid_reference(points: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The input policy, written out for the tests: intensity or t NaN, infinite or beyond 1e6 / 1e10."""
    with np.errstate(invalid="ignore"):
        return ~(np.abs(points[:, 3].astype(np.float64)) <= 1e6) | ~(np.abs(t) <= 1e10)


class _Reference:
    """Every pushed point (arrival order) with its id; the window and its pillar keys on request.
    Points that the input policy drops never count (not in the window, not in ``newest``)."""

    def __init__(self, grid: PillarGrid, window: float):
        self.grid, self.window = grid, window
        self.points = np.zeros((0, 4), np.float32)
        self.t = np.zeros(0, np.float64)
        self.newest = -math.inf

    def push(self, points: np.ndarray, t: np.ndarray, now=None):
        self.points = np.concatenate([self.points, points])
        self.t = np.concatenate([self.t, t])
        valid = ~_invalid_reference(points, t)
        if valid.any():
            self.newest = max(self.newest, float(t[valid].max()))
        if now is not None:
            self.newest = max(self.newest, float(now))

    def window_ids(self) -> np.ndarray:
        """Ids of the points in the window and in the grid, in (t, arrival) order."""
        keys = _pillar_keys_reference(self.points, self.grid)
        valid = ~_invalid_reference(self.points, self.t)
        ids = np.nonzero((self.t > self.newest - self.window) & (keys >= 0) & valid)[0]
        return ids[np.argsort(self.t[ids], kind="stable")]


def _check_step(stream: PillarStream, ref: _Reference, update: StreamUpdate, prev_ids: np.ndarray, where: str,
                N: int, M: int) -> np.ndarray:
    g = ref.grid
    dev = stream.device
    ids = ref.window_ids()
    assert update.t == ref.newest, where
    # the window's pillars: pillarize of the window in time order gives the very same queues
    expected = pillarize(torch.from_numpy(ref.points[ids]).to(dev), g, N, M)
    got = stream.pillars()
    assert_same_pillars(got, expected, where)
    assert_equal_report(update.active, expected.coords, f"{where}: active")
    assert stream.num_active == expected.coords.shape[0] and stream.num_points == ids.size, where
    # changed = pillars of the points that entered or left
    keys = _pillar_keys_reference(ref.points, g)
    entered, left = np.setdiff1d(ids, prev_ids), np.setdiff1d(prev_ids, ids)
    ch = np.unique(keys[np.concatenate([entered, left])])
    exp_changed = np.stack([np.zeros_like(ch), ch // g.shape[1], ch % g.shape[1]], 1).astype(np.int32)
    assert_equal_report(update.changed, torch.from_numpy(exp_changed).reshape(-1, 3), f"{where}: changed")
    exp_removed = ~np.isin(ch, keys[ids])
    assert_equal_report(update.removed, torch.from_numpy(exp_removed), f"{where}: removed")
    cmap = torch.zeros(g.shape, dtype=torch.bool)
    cmap[torch.from_numpy(ch // g.shape[1]), torch.from_numpy(ch % g.shape[1])] = True
    assert_equal_report(update.change_map, cmap, f"{where}: change_map")
    assert (update.points_in, update.points_out) == (entered.size, left.size), where
    for tensor in (update.active, update.changed, update.removed, update.change_map):
        assert tensor.device.type == torch.device(dev).type, where
    return ids


@pytest.mark.slow
@pytest.mark.parametrize("scenario, grid, N, M", [
    ("drone_bridge", PillarGrid.drone(), 100, 12000),
    ("driving_city", DRIVING_AHEAD, 200, 8000),
])
def test_stream_simulator_matches_pillarize(device, scenario, grid, N, M):
    from lidarops.data.synthetic import Simulator
    sim = Simulator(scenario, seed=2)
    stream = PillarStream(grid, window=0.100, max_points_per_pillar=N, max_pillars=M, device=device)
    ref = _Reference(grid, 0.100)
    ids = np.zeros(0, np.int64)
    steps = 0
    for i, (p, t) in enumerate(sim.slices(0.0, 2.0, 0.01)):
        outside = int((_pillar_keys_reference(p, grid) < 0).sum())
        update = stream.push(p, t)
        ref.push(p, t)
        assert update.points_outside == outside and update.points_late == 0
        ids = _check_step(stream, ref, update, ids, f"{device} {scenario} step {i}", N, M)
        steps += 1
    assert steps == 200 and stream.num_active > 100


def _jittered_slices(seed: int, steps: int = 40, per_slice: int = 300, jitter: float = 0.07, dt: float = 0.01):
    """Slices of random points whose timestamps are out of order (jitter within and across slices),
    with equal timestamps (rounded to 1 ms) and exact duplicates."""
    rng = np.random.default_rng(seed)
    for s in range(steps):
        n = int(rng.integers(0, per_slice))
        p = random_points(n, seed * 1000 + s).numpy()
        if n > 4:
            p[: n // 4] = p[n // 4: 2 * (n // 4)]  # duplicated points
        t = np.round((s + 1) * dt - rng.uniform(0, jitter, size=n), 3)
        yield p, t


@pytest.mark.parametrize("seed", [0, 1])
def test_stream_out_of_order_and_duplicates(device, seed):
    N, M = 200, 256
    stream = PillarStream(SMALL, window=0.05, max_points_per_pillar=N, max_pillars=M, device=device)
    ref = _Reference(SMALL, 0.05)
    ids = np.zeros(0, np.int64)
    late = 0
    for i, (p, t) in enumerate(_jittered_slices(seed)):
        exp_late = int(((_pillar_keys_reference(p, SMALL) >= 0)
                        & (t <= max(ref.newest, t.max(initial=-math.inf)) - 0.05)).sum())
        update = stream.push(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device))
        ref.push(p, t)
        assert update.points_late == exp_late
        late += exp_late
        ids = _check_step(stream, ref, update, ids, f"{device} seed={seed} step {i}", N, M)
    assert late > 0  # some points arrived already expired


def test_stream_equal_timestamps_and_scalar_t(device):
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=500, max_pillars=256, device=device)
    ref = _Reference(SMALL, 0.1)
    ids = np.zeros(0, np.int64)
    for i, t in enumerate([0.0, 0.0, 0.05, 0.1, 0.1, 0.1001, 0.2]):
        p = random_points(200, 40 + i).numpy()
        update = stream.push(torch.from_numpy(p).to(device), t)  # one float for the whole slice
        ref.push(p, np.full(200, t))
        ids = _check_step(stream, ref, update, ids, f"{device} t={t}", 500, 256)
    # at t = 0.2 the points of t = 0.1 are exactly at the window's edge: out
    assert ref.t[ids].min() > 0.1


def test_stream_gaps_empty_slices_and_now(device):
    N, M = 200, 256
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=N, max_pillars=M, device=device)
    ref = _Reference(SMALL, 0.1)
    ids = np.zeros(0, np.int64)
    empty_p, empty_t = np.zeros((0, 4), np.float32), np.zeros(0)
    # empty push before anything: nothing happens, t stays -inf
    u = stream.push(empty_p, empty_t)
    assert u.t == -math.inf and u.changed.shape == (0, 3) and u.active.shape == (0, 3)
    for i in range(10):
        p = random_points(150, 60 + i).numpy()
        t = np.linspace(i * 0.01, (i + 1) * 0.01, 150, endpoint=False)
        ids = _check_step(stream, ref, (stream.push(p, t), ref.push(p, t))[0], ids, f"{device} fill {i}", N, M)
    # empty slices without `now`: no change at all
    u = stream.push(empty_p, empty_t)
    ref.push(empty_p, empty_t)
    assert u.changed.shape == (0, 3) and u.points_out == 0
    ids = _check_step(stream, ref, u, ids, f"{device} empty", N, M)
    # a 200 ms gap, advanced by `now` on empty slices: everything expires
    before, in_window = stream.num_active, ids.size
    u = stream.push(empty_p, empty_t, now=0.3)
    ref.push(empty_p, empty_t, now=0.3)
    assert u.points_out == in_window and stream.num_active == 0 and bool(u.removed.all())
    assert u.changed.shape[0] == before
    ids = _check_step(stream, ref, u, ids, f"{device} now", N, M)
    # refill, then a gap with no `now`: the first point after it expires everything
    for i in range(5):
        p = random_points(150, 80 + i).numpy()
        t = np.full(150, 0.31 + 0.01 * i)
        ids = _check_step(stream, ref, (stream.push(p, t), ref.push(p, t))[0], ids, f"{device} refill {i}", N, M)
    p = np.array([[0.5, 0.5, 0.0, 1.0]], np.float32)
    in_window = ids.size
    u = stream.push(p, np.array([0.6]))
    ref.push(p, np.array([0.6]))
    assert stream.num_active == 1 and u.points_out == in_window and u.points_in == 1
    ids = _check_step(stream, ref, u, ids, f"{device} gap", N, M)
    # a point older than the window never enters
    u = stream.push(p, np.array([0.45]))
    assert u.points_late == 1 and u.points_in == 0 and u.changed.shape == (0, 3)


def test_stream_points_outside(device):
    stream = PillarStream(SMALL, device=device)
    p = torch.tensor([[100.0, 0, 0, 1], [float("nan"), 0, 0, 1], [0, 0, -2.5, 1], [0.5, 0.5, 0.5, 1]], device=device)
    u = stream.push(p, torch.tensor([0.0, 0.0, 0.0, 0.0], dtype=torch.float64, device=device))
    assert (u.points_outside, u.points_in, u.points_late) == (3, 1, 0)
    assert u.active.tolist() == [[0, 8, 8]] and stream.num_points == 1


def test_stream_overflow_leaves_state_unchanged(device):
    N, M = 20, 40
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=N, max_pillars=M, device=device)
    p0 = np.array([[0.5, 0.5, 0.0, 1.0]] * 15, np.float32)
    stream.push(p0, np.full(15, 0.0))
    before = stream.pillars()
    with pytest.raises(PillarOverflowError, match=r"hold 25 points but max_points_per_pillar=20.*at least 25.*no "
                                                  r"effect") as e:
        stream.push(np.array([[0.6, 0.6, 0.0, 1.0]] * 10, np.float32), np.full(10, 0.05))
    assert isinstance(e.value, ValueError)
    assert_same_pillars(stream.pillars(), before, "after points overflow")
    assert stream.t == 0.0 and stream.num_points == 15
    # too many pillars: 50 distinct pillars
    xy = np.stack(np.meshgrid(np.arange(10) - 7.5, np.arange(5) - 2.5), -1).reshape(-1, 2)
    p1 = np.concatenate([xy, np.zeros((50, 2))], 1).astype(np.float32)
    with pytest.raises(PillarOverflowError, match=r"50 pillars would be occupied but max_pillars=40.*at least 50"):
        stream.push(p1, np.full(50, 0.02))
    assert_same_pillars(stream.pillars(), before, "after pillars overflow")
    # the same points after the first ones expired fit (15 + 0 points, 50 pillars > 40 still do not)
    u = stream.push(p1[:40], np.full(40, 0.2))
    assert u.points_out == 15 and stream.num_active == 40


def test_stream_log_growth_and_wrap(device):
    """A small log (N * M = 1024 entries) that has to wrap, compact and grow."""
    N, M = 64, 256
    stream = PillarStream(SMALL, window=0.05, max_points_per_pillar=N, max_pillars=M, device=device)
    ref = _Reference(SMALL, 0.05)
    ids = np.zeros(0, np.int64)
    rng = np.random.default_rng(9)
    for i in range(30):
        n = int(rng.integers(100, 900))
        p = random_points(n, 900 + i, margin=0.0).numpy()
        t = i * 0.01 + rng.uniform(0, 0.02, n)
        ids = _check_step(stream, ref, (stream.push(p, t), ref.push(p, t))[0], ids, f"{device} step {i}", N, M)
    assert stream._log_cell.numel() > 1024


def test_stream_pillars_subset_and_errors(device):
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=100, max_pillars=256, device=device)
    pts = random_points(2000, 11, margin=0.0)
    u = stream.push(pts.to(device), torch.zeros(2000, dtype=torch.float64, device=device))
    full = stream.pillars()
    pick = torch.tensor([5, 0, 200, 17])
    sub = stream.pillars(u.active[pick.to(device)])
    for field in range(3):
        assert_equal_report(sub[field], full[field][pick.to(device)], f"subset field {field}")
    assert stream.pillars(u.active[:0]).features.shape == (0, 100, 9)
    # int64 coords are accepted
    assert_equal_report(stream.pillars(u.active.long()[:3]).features, full.features[:3], "int64 coords")
    with pytest.raises(ValueError, match=r"coords\[1\] = \[0, 16, 0\] is not an active pillar"):
        stream.pillars(torch.tensor([[0, 0, 0], [0, 16, 0]], device=device))
    with pytest.raises(ValueError, match="not an active pillar"):
        stream.pillars(torch.tensor([[1, 0, 0]], device=device))
    with pytest.raises(ValueError, match=r"integer \(P, 3\)"):
        stream.pillars(torch.zeros(2, 3, device=device))
    with pytest.raises(ValueError, match=r"integer \(P, 3\)"):
        stream.pillars(torch.zeros(2, 2, dtype=torch.int32, device=device))
    # a pillar that became empty is no longer active
    u = stream.push(np.zeros((0, 4), np.float32), np.zeros(0), now=1.0)
    assert bool(u.removed.all()) and stream.num_active == 0
    with pytest.raises(ValueError, match="not an active pillar"):
        stream.pillars(u.changed[:1])
    # the unchecked gather (the SSCATeR step runs its PFN on every changed pillar) gives an emptied
    # pillar zero points and zero features
    empty = stream.pillars(u.changed, check=False)
    assert empty.features.shape == (u.changed.shape[0], 100, 9) and empty.features.abs().sum().item() == 0
    assert (empty.num_points == 0).all() and torch.equal(empty.coords, u.changed)


def test_stream_bad_input(device):
    stream = PillarStream(SMALL, device=device)
    p = torch.zeros(3, 4, device=device)
    t = torch.zeros(3, dtype=torch.float64, device=device)
    with pytest.raises(ValueError, match="points must be float32"):
        stream.push(p.double(), t)
    with pytest.raises(ValueError, match=r"points must be float32 \(n, 4\)"):
        stream.push(p[:, :3], t)
    with pytest.raises(ValueError, match="points must be a torch.Tensor or a NumPy array"):
        stream.push([[0, 0, 0, 0]], t)
    with pytest.raises(ValueError, match="t must be float64"):
        stream.push(p, t.float())
    with pytest.raises(ValueError, match=r"t must be float64 \(n,\) with n = 3"):
        stream.push(p, t[:2])
    with pytest.raises(ValueError, match="now must be a finite"):
        stream.push(p, t, now=float("inf"))
    with pytest.raises(ValueError, match=r"now must be a finite number of seconds with \|now\| <= 1e\+10"):
        stream.push(p, t, now=2e10)  # e.g. a millisecond clock
    if device == "cuda":
        with pytest.raises(ValueError, match="points is on cpu but the stream is on cuda"):
            stream.push(p.cpu(), t)
    assert stream.num_points == 0 and stream.t == -math.inf  # nothing was applied
    for kwargs, match in [(dict(window=0), "window must be a finite number of seconds >= 1e-05"), (dict(window="1"), "window"),
                          (dict(max_points_per_pillar=0), "max_points_per_pillar"),
                          (dict(max_pillars=-1), "max_pillars"), (dict(device="mps"), "device must be")]:
        with pytest.raises(ValueError, match=match):
            PillarStream(SMALL, **kwargs)
    with pytest.raises(ValueError, match="grid must be"):
        PillarStream("drone")


def test_stream_reset_and_properties(device):
    stream = PillarStream(PillarGrid.drone(), window=0.2, max_points_per_pillar=10, max_pillars=100, device=device)
    assert stream.grid == PillarGrid.drone() and stream.window == 0.2 and stream.device.type == device
    stream.push(np.array([[1.0, 1.0, 0.0, 0.5]], np.float32), np.array([3.0]))
    assert stream.num_active == 1 and stream.t == 3.0 and "1 active pillars" in repr(stream)
    stream.reset()
    assert stream.num_active == 0 and stream.t == -math.inf and stream.pillars().coords.shape == (0, 3)
    u = stream.push(np.array([[1.0, 1.0, 0.0, 0.5]], np.float32), np.array([0.0]))  # time may restart
    assert u.points_in == 1 and u.active.tolist() == [[0, 262, 6]]  # (1 + 40.96) / 0.16 = 262.25


@requires_cuda
def test_stream_cpu_cuda_parity():
    streams = {d: PillarStream(SMALL, window=0.05, max_points_per_pillar=200, max_pillars=256, device=d)
               for d in ("cpu", "cuda")}
    for i, (p, t) in enumerate(_jittered_slices(3, steps=25)):
        ups = {d: s.push(p, t) for d, s in streams.items()}
        for k in ("active", "changed", "removed", "change_map"):
            assert_equal_report(getattr(ups["cuda"], k), getattr(ups["cpu"], k), f"step {i} {k}")
        assert_same_pillars(streams["cuda"].pillars(), streams["cpu"].pillars(), f"step {i}")


def test_import_is_light():
    import subprocess
    import sys
    code = ("import sys, lidarops.stream; bad = [m for m in ('scipy', 'matplotlib') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


# ---- the input policy (docs/stream.md, "Input policy") ----

def _policy_rows():
    """(x, y, z, intensity, t, fate) for every column's NaN / inf / huge value and the bounds."""
    nan, inf = float("nan"), float("inf")
    above = float(np.nextafter(np.float32(MAX_ABS_INTENSITY), np.float32(inf)))  # the next float32 above 1e6
    return [
        (0.5, 0.5, 0.0, 0.3, 0.0, "in"),
        (0.5, 0.5, 0.0, nan, 0.0, "invalid"),
        (0.5, 0.5, 0.0, inf, 0.0, "invalid"),
        (0.5, 0.5, 0.0, -inf, 0.0, "invalid"),
        (1.5, 0.5, 0.0, 1e30, 0.0, "invalid"),
        (1.5, 0.5, 0.0, above, 0.0, "invalid"),
        (1.5, 0.5, 0.0, MAX_ABS_INTENSITY, 0.0, "in"),  # the bounds themselves are valid
        (2.5, 0.5, 0.0, -MAX_ABS_INTENSITY, 0.0, "in"),
        (0.5, 1.5, 0.0, 0.2, nan, "invalid"),
        (0.5, 1.5, 0.0, 0.2, inf, "invalid"),
        (0.5, 1.5, 0.0, 0.2, -inf, "invalid"),
        (0.5, 1.5, 0.0, 0.2, 1e30, "invalid"),  # would become t_newest and expire every later point
        (0.5, 1.5, 0.0, 0.2, -1.5e10, "invalid"),
        (nan, 0.5, 0.0, 0.2, 0.0, "outside"),
        (0.5, inf, 0.0, 0.2, 0.0, "outside"),
        (0.5, 0.5, 1e30, 0.2, 0.0, "outside"),
        (-1e30, 0.5, 0.0, 0.2, 0.0, "outside"),
        (nan, 0.5, 0.0, nan, 0.0, "invalid"),  # counted once, as invalid (the first rule)
        (2.5, 2.5, 0.0, nan, nan, "invalid"),  # both columns bad: one point
        (2.5, 2.5, 0.0, 0.7, -0.5, "late"),
        (3.5, 2.5, 0.0, 0.1, -0.02, "in"),
    ]


def test_stream_and_pillarize_input_policy(device):
    rows = _policy_rows()
    p = np.array([r[:4] for r in rows], np.float32)
    t = np.array([r[4] for r in rows], np.float64)
    fate = np.array([r[5] for r in rows])
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=20, max_pillars=256, device=device)
    u = stream.push(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device))
    assert u.t == 0.0  # not 1e30: an invalid t never moves t_newest
    assert (u.points_in, u.points_outside, u.points_late, u.points_invalid) == tuple(
        int((fate == f).sum()) for f in ("in", "outside", "late", "invalid"))
    assert stream.counts == StreamCounts(points_pushed=21, points_in=4, points_out=0, points_outside=4,
                                         points_late=1, points_invalid=12, invalid_intensity=7, invalid_t=6)
    c = stream.counts
    assert c.points_pushed == c.points_in + c.points_outside + c.points_late + c.points_invalid
    # the stream holds exactly the valid points of the window: pillarize of them, in time order
    keep = np.nonzero(fate == "in")[0]
    keep = keep[np.argsort(t[keep], kind="stable")]
    expected = pillarize(torch.from_numpy(p[keep]).to(device), SMALL, 20, 256)
    assert_same_pillars(stream.pillars(), expected, "policy")
    assert torch.isfinite(stream.pillars().features).all()
    # pillarize applies the same rule to the intensity (it has no timestamps): given the points whose t
    # is in the window, invalid intensities and outside points included, it gives the stream's pillars
    in_time = np.nonzero(np.abs(t) <= 0.05)[0]
    in_time = in_time[np.argsort(t[in_time], kind="stable")]
    res = pillarize(torch.from_numpy(p[in_time]).to(device), SMALL, 20, 256)
    assert_same_pillars(res, stream.pillars(), "pillarize vs stream")
    assert (res.num_invalid, res.num_outside) == (int((fate[in_time] == "invalid").sum()), 4)
    check_against_reference(res, torch.from_numpy(p[in_time]).to(device), SMALL, 20, f"{device} policy reference")
    # invalid points never expire either (they were never in): a later push only expires the valid ones
    u = stream.push(np.zeros((0, 4), np.float32), np.zeros(0), now=1.0)
    assert u.points_out == 4 and stream.num_points == 0 and stream.counts.points_out == 4
    # the time bounds are valid; a slice of invalid points only changes nothing
    u = stream.push(np.array([[0.5, 0.5, 0.0, 1.0]], np.float32), np.array([MAX_ABS_TIME]))
    assert u.points_in == 1 and u.t == MAX_ABS_TIME
    u = stream.push(p[fate == "invalid"], t[fate == "invalid"])
    assert u.points_invalid == 12 and u.points_in == 0 and u.changed.shape == (0, 3) and u.t == MAX_ABS_TIME
    stream.reset()
    assert stream.counts == StreamCounts()


# ---- the push's scalars read on the device, and the push as a CUDA graph ----

def _bits(x: float) -> int:
    return int(np.array([x], np.float64).view(np.int64)[0])


def test_push_op_reads_its_scalars(device):
    """With ``scalars`` (log_head and the bits of cutoff, on the state's device) the op ignores its log_head and
    cutoff arguments: the same outputs and state as the call given them as arguments."""
    streams = [PillarStream(SMALL, window=0.05, max_points_per_pillar=200, max_pillars=256, device=device,
                            cuda_graph=False) for _ in range(2)]
    slices = list(_jittered_slices(5, steps=8))
    for p, t in slices[:6]:
        for s in streams:
            s.push(p, t)
    p, t = (torch.from_numpy(x).to(device) for x in slices[6])
    a, b = streams
    runs = torch.tensor(list(a._runs), dtype=torch.int64, device=device).reshape(-1, 2)
    cutoff = max(a.t, float(t.max())) - 0.05
    g = SMALL

    def call(s, log_head, cut, scalars=None):
        return torch.ops.lidarops.pillar_stream_push(
            s._pool_xyzi, s._pool_t, s._head, s._count, s._slot_cell, s._cell_slot, s._free_slots, s._num_free,
            s._log_cell, s._log_t, p, t, runs, log_head, cut, list(g.point_cloud_range), list(g.pillar_size),
            list(g.shape), False, scalars=scalars)

    want = call(a, a._log_head, cutoff)
    got = call(b, 0, 0.0, torch.tensor([b._log_head, _bits(cutoff)], dtype=torch.int64, device=device))
    assert int(want[1][0]) > 0 and int(want[1][1]) > 0, "the push should bring points in and expire some"
    for x, y, k in zip(got, want, ("change_map", "stats", "run_pops")):
        assert_equal_report(x, y, k)
    for k in ("_num_free", "_log_cell", "_log_t"):  # CUDA's slots are taken in any order: pillars compared by key
        assert_equal_report(getattr(b, k), getattr(a, k), k)

    def window(s):
        yx = torch.nonzero(s._cell_slot.view(SMALL.shape) >= 0)
        return s.pillars(torch.cat([torch.zeros_like(yx[:, :1]), yx], 1).int(), check=False)

    assert_same_pillars(window(b), window(a), "the pillars after the push")
    wrong = call(streams[0], 0, 0.0, torch.tensor([a._log_head, _bits(cutoff - 0.02)], dtype=torch.int64,
                                                  device=device))
    assert int(wrong[1][1]) != int(want[1][1]) or not torch.equal(wrong[0], want[0]), \
        "another cutoff in the scalars should change what expires"


def _update_fields(u):
    return {k: (v.clone() if isinstance(v, torch.Tensor) else v) for k, v in u._asdict().items()}


def _assert_same_update(got, want, what):
    for k, v in want.items():
        if isinstance(v, torch.Tensor):
            assert_equal_report(got[k], v, f"{what} {k}")
        else:
            assert got[k] == v, f"{what} {k}: {got[k]} != {v}"


@requires_cuda
@pytest.mark.parametrize("overflow", ["raise", "drop"])
def test_graphed_push_equals_the_eager_push(overflow):
    """Every field of every update, the counts, t_newest, the pillars and the raised errors: a push replayed as a
    CUDA graph against the eager push, on out-of-order, duplicated, invalid and late points, empty slices, gaps
    closed by ``now``, capacities that overflow, and slices large enough to need bigger graphs and a longer log."""
    N, M = (200, 256) if overflow == "raise" else (6, 40)
    make = lambda graph: PillarStream(SMALL, window=0.05, max_points_per_pillar=N, max_pillars=M,  # noqa: E731
                                      device="cuda", overflow=overflow, cuda_graph=graph)
    streams = {True: make(True), False: make(False)}
    assert streams[True].cuda_graph and not streams[False].cuda_graph
    rng = np.random.default_rng(3)
    raised = 0
    for i, (p, t) in enumerate(_jittered_slices(11, steps=60, per_slice=2500 if overflow == "drop" else 300)):
        if i % 7 == 3 and len(p) > 2:  # invalid intensities and timestamps
            p[0, 3], t[1] = np.nan, np.inf
        now = None if i % 5 else 0.01 * (i + 1) + 0.02 * rng.random()
        if i == 40:  # a gap: nothing pushed, the window moves on
            p, t, now = p[:0], t[:0], 0.01 * (i + 1) + 0.2
        res = {}
        for graph, s in streams.items():
            try:
                res[graph] = ("ok", _update_fields(s.push(torch.from_numpy(p).cuda(), torch.from_numpy(t).cuda(),
                                                          now=now)))
            except PillarOverflowError as e:
                res[graph] = ("raised", str(e))
        assert res[True][0] == res[False][0], f"step {i}: {res[True][0]} against {res[False][0]}"
        if res[True][0] == "raised":
            raised += 1
            assert res[True][1] == res[False][1], f"step {i}: the messages differ"
        else:
            _assert_same_update(res[True][1], res[False][1], f"step {i}")
        a, b = streams[True], streams[False]
        assert a.counts == b.counts and a.t == b.t and a.num_points == b.num_points, f"step {i}"
        assert_same_pillars(a.pillars(), b.pillars(), f"step {i}")
    if overflow == "drop":
        assert streams[True].counts.points_dropped > 0, "the drop stream should have dropped points"
        assert max(k[0] for k in streams[True]._push_graphs) >= 2048, "slices above 1024 points need a larger graph"
    assert len(streams[True]._push_graphs) >= 1


@requires_cuda
def test_graphed_push_raises_as_the_eager_push():
    """An overflow with overflow="raise": the same error, and the push has no effect, in a graph as eagerly."""
    for graph in (True, False):
        s = PillarStream(SMALL, window=1.0, max_points_per_pillar=2, max_pillars=8, device="cuda", cuda_graph=graph)
        p = torch.tensor([[0.5, 0.5, 0.0, 1.0]] * 3, device="cuda")
        with pytest.raises(PillarOverflowError, match="max_points_per_pillar=2"):
            s.push(p, torch.zeros(3, dtype=torch.float64, device="cuda"))
        assert s.num_points == 0 and s.counts == StreamCounts() and s.t == -math.inf
        u = s.push(p[:2], torch.zeros(2, dtype=torch.float64, device="cuda"))
        assert u.points_in == 2 and s.num_points == 2


@requires_cuda
def test_graphed_push_updates_are_not_overwritten():
    """An update's tensors are its own: the next push, which replays the same graph, leaves them as they were."""
    s = PillarStream(SMALL, window=0.05, max_points_per_pillar=200, max_pillars=256, device="cuda")
    slices = list(_jittered_slices(2, steps=6))
    kept = []
    for p, t in slices:
        u = s.push(torch.from_numpy(p).cuda(), torch.from_numpy(t).cuda())
        kept.append((u, _update_fields(u)))
    for i, (u, copy) in enumerate(kept):
        _assert_same_update(_update_fields(u), copy, f"update {i} after later pushes")
    assert len({k for k in s._push_graphs}) == 1, "every slice here fits the first graph"


@requires_cuda
def test_warm_up_records_the_push_graphs_before_the_first_push():
    s = PillarStream(SMALL, window=0.05, max_points_per_pillar=200, max_pillars=256, device="cuda")
    assert s.warm_up(3000) == 3  # 1024, 2048, 4096 points
    assert s.warm_up(3000) == 0
    for p, t in _jittered_slices(4, steps=5, per_slice=3000):
        s.push(torch.from_numpy(p).cuda(), torch.from_numpy(t).cuda())
    assert len(s._push_graphs) == 3
    s.reset()
    assert not s._push_graphs and s.warm_up(10) == 1
    assert PillarStream(SMALL, device="cuda", cuda_graph=False).warm_up(3000) == 0
