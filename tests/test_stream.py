"""lidarops.stream: PillarGrid, pillarize (against the float64 NumPy reference ``_pillarize_reference``)
and PillarStream (every step against ``pillarize`` of the window, and the changed pillars against a
diff of the point sets of consecutive windows)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lidarops.stream import (
    MAX_ABS_INTENSITY,
    MAX_ABS_TIME,
    PillarGrid,
    PillarOverflowError,
    Pillars,
    PillarStream,
    StreamCounts,
    StreamUpdate,
    pillarize,
)
from lidarops.stream.pillars import _pillar_keys_reference, _pillarize_reference

from conftest import assert_close_report, assert_equal_report, requires_cuda

SMALL = PillarGrid((-8.0, -8.0, -2.0, 8.0, 8.0, 2.0), (1.0, 1.0))  # 16 x 16 pillars: many points per pillar
# driving_city ahead of the car from 10 m: at most ~150 points per pillar in 100 ms
DRIVING_AHEAD = PillarGrid.driving_ahead()

# float32 features are float64 values rounded once: relative error <= 2^-24 (we allow 2^-20)
F32_RTOL, F32_ATOL = 2.0**-20, 1e-7


# ---- helpers ----

def _random_points(n: int, seed: int, grid: PillarGrid = SMALL, margin: float = 1.0, dtype=torch.float32):
    """Uniform in the grid's range grown by ``margin`` on every side (so some points are outside)."""
    rng = np.random.default_rng(seed)
    lo = np.array(grid.point_cloud_range[:3]) - margin
    hi = np.array(grid.point_cloud_range[3:]) + margin
    xyz = rng.uniform(lo, hi, size=(n, 3))
    inten = rng.uniform(0.0, 1.0, size=(n, 1))
    return torch.from_numpy(np.concatenate([xyz, inten], 1)).to(dtype)


def _key_order(coords: torch.Tensor, grid: PillarGrid) -> torch.Tensor:
    c = coords.cpu().to(torch.int64)
    return c[:, 1] * grid.shape[1] + c[:, 2]


def _check_against_reference(res: Pillars, points: torch.Tensor, grid: PillarGrid, N: int, where: str):
    ref = _pillarize_reference(points, grid, N)
    feats, coords, num_points = res
    assert feats.dtype == points.dtype and coords.dtype == torch.int32 and num_points.dtype == torch.int32, where
    assert feats.device == points.device and coords.device == points.device, where
    assert_equal_report(coords, torch.from_numpy(ref["coords"]), f"{where}: coords")
    assert_equal_report(num_points, torch.from_numpy(ref["num_points"]), f"{where}: num_points")
    got = feats.detach().cpu().double()
    exp = torch.from_numpy(ref["features"])
    # x, y, z, intensity are copies (input order inside a pillar): exact
    assert_equal_report(got[..., :4], exp[..., :4].to(points.dtype).double(), f"{where}: raw features")
    rtol, atol = (1e-12, 1e-12) if points.dtype == torch.float64 else (F32_RTOL, F32_ATOL)
    assert_close_report(got, exp, rtol, atol, f"{where}: decorated features")
    assert res.num_outside == ref["num_outside"] and res.num_invalid == ref["num_invalid"], where
    keys = _key_order(coords, grid)
    assert bool((keys[1:] > keys[:-1]).all()), f"{where}: pillars not sorted by key"


def _assert_same_pillars(a: Pillars, b: Pillars, where: str, exact: bool = True):
    """Same pillars, same points per pillar (as sets when not exact), features equal or to tolerance."""
    assert_equal_report(a.coords, b.coords, f"{where}: coords")
    assert_equal_report(a.num_points, b.num_points, f"{where}: num_points")
    assert a.features.shape == b.features.shape, where
    if exact:
        assert_equal_report(a.features, b.features, f"{where}: features")
        return
    fa, fb = _sorted_rows(a), _sorted_rows(b)
    assert_equal_report(fa[:, :5], fb[:, :5], f"{where}: point sets")
    assert_close_report(fa, fb, F32_RTOL, F32_ATOL, f"{where}: features")


def _sorted_rows(p: Pillars) -> torch.Tensor:
    """(points, 10) float64: pillar index, then the 9 features, rows sorted by (pillar, x, y, z, i)."""
    f = p.features.detach().cpu().double()
    P, N, _ = f.shape
    valid = torch.arange(N)[None, :] < p.num_points.cpu()[:, None]
    pil = torch.arange(P)[:, None].expand(P, N)[valid].double()
    rows = torch.cat([pil[:, None], f[valid]], 1).numpy()
    order = np.lexsort(rows[:, [4, 3, 2, 1, 0]].T)
    return torch.from_numpy(rows[order])


# ---- PillarGrid ----

def test_grid_presets():
    assert PillarGrid.drone().shape == (512, 512)
    k = PillarGrid.kitti()
    assert k.shape == (496, 432) and (k.H, k.W) == (496, 432)
    assert PillarGrid.driving().shape == (640, 640)
    g = PillarGrid((0, 0, 0, 4, 2, 1), (0.5, 0.25))
    assert g.shape == (8, 8) and g.voxel_size == (0.5, 0.25, 1.0) and g.grid_size == [8, 8, 1]
    assert g == PillarGrid((0, 0, 0, 4, 2, 1), (0.5, 0.25)) and "shape=(8, 8)" in repr(g)


@pytest.mark.parametrize("kwargs, match", [
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), pillar_size=(0.3, 0.25)), "whole number of pillars along x"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), pillar_size=(0.25, -1)), "pillar_size"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), pillar_size=(0.25,)), "pillar_size"),
    (dict(point_cloud_range=(0, 1, 0, 1, 0, 1), pillar_size=(0.25, 0.25)), "y0 < y1"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1), pillar_size=(0.25, 0.25)), "point_cloud_range"),
])
def test_grid_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PillarGrid(**kwargs)


# ---- pillarize ----

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("seed", [0, 1])
def test_pillarize_random_matches_reference(device, dtype, seed):
    pts = _random_points(5000, seed, dtype=dtype).to(device)
    res = pillarize(pts, SMALL, max_points_per_pillar=60, max_pillars=256)
    assert isinstance(res, Pillars) and isinstance(res, tuple) and res._fields == ("features", "coords", "num_points")
    _check_against_reference(res, pts, SMALL, 60, f"{device} {dtype} seed={seed}")
    assert 0 < res.num_outside < 5000 and res.coords.shape[0] == 256  # every pillar occupied
    feats = res.features.cpu()
    pad = torch.arange(60)[None, :] >= res.num_points.cpu()[:, None]
    assert not feats[pad].any(), "padding slots must be zero in all 9 features"


def test_pillarize_lidar_like(device):
    from lidarops.data.synthetic import Simulator
    for scenario, grid in [("drone_bridge", PillarGrid.drone()), ("driving_city", DRIVING_AHEAD)]:
        p, _ = Simulator(scenario, seed=1).stream(0.0, 0.1)
        pts = torch.from_numpy(p).to(device)
        res = pillarize(pts, grid, max_points_per_pillar=200, max_pillars=12000)
        _check_against_reference(res, pts, grid, 200, f"{device} {scenario}")
        assert res.coords.shape[0] > 1000 and res.num_outside > 0


def test_pillarize_kitti_grid_and_non_contiguous(device):
    grid = PillarGrid.kitti()
    pts = _random_points(3000, 5, grid=grid, margin=2.0)
    buf = torch.zeros(3000, 6, device=device)
    buf[:, 1:5] = pts.to(device)
    nc = buf[:, 1:5]  # a view made on the device (.to() of a CPU view would make it contiguous)
    assert not nc.is_contiguous()
    res = pillarize(nc, grid, 8, 3000)
    _check_against_reference(res, pts.to(device), grid, 8, f"{device} kitti non-contiguous")


def test_pillarize_edge_cases(device):
    # empty input
    res = pillarize(torch.zeros(0, 4, device=device), SMALL)
    assert res.features.shape == (0, 100, 9) and res.coords.shape == (0, 3) and res.num_points.shape == (0,)
    assert res.num_outside == 0
    # everything outside, NaN and inf included; x == x1 and z == z1 are outside
    out = torch.tensor([[100.0, 0, 0, 1], [0, 0, 5, 1], [float("nan"), 0, 0, 1], [0, float("inf"), 0, 1],
                        [8.0, 0, 0, 1], [0, 0, 2.0, 1]], device=device)
    res = pillarize(out, SMALL)
    assert res.coords.shape[0] == 0 and res.num_outside == 6 and res.num_invalid == 0
    # duplicates: identical points share a pillar; their offsets to the mean are 0
    dup = torch.tensor([[0.5, 0.5, 0.0, 0.2]] * 7 + [[-7.5, 7.5, 1.0, 0.3]], device=device)
    res = pillarize(dup, SMALL, max_points_per_pillar=7, max_pillars=2)
    _check_against_reference(res, dup, SMALL, 7, f"{device} duplicates")
    assert res.num_points.tolist() == [7, 1]  # key 8 * 16 + 8 = 136 before 15 * 16 + 0 = 240
    assert res.coords.tolist() == [[0, 8, 8], [0, 15, 0]]
    assert not res.features[0, :7, 4:7].any()
    # a point on a pillar boundary goes to the upper pillar; the centre offsets are exact
    res = pillarize(torch.tensor([[1.0, -1.0, 0.0, 0.0]], device=device), SMALL)
    assert res.coords.tolist() == [[0, 7, 9]]
    assert res.features[0, 0, 7:].tolist() == [-0.5, -0.5]


def test_pillarize_overflow(device):
    pts = _random_points(4000, 3).to(device)
    n_max = int(pillarize(pts, SMALL, 1000, 1000).num_points.max())
    with pytest.raises(PillarOverflowError, match=rf"max_points_per_pillar=10\b.*at least {n_max}") as e:
        pillarize(pts, SMALL, max_points_per_pillar=10, max_pillars=1000)
    assert isinstance(e.value, ValueError) and "missed" in str(e.value)
    with pytest.raises(PillarOverflowError, match=r"256 pillars would be occupied but max_pillars=100.*at least 256"):
        pillarize(pts, SMALL, max_points_per_pillar=1000, max_pillars=100)
    # exactly enough is fine
    assert pillarize(pts, SMALL, n_max, 256).coords.shape[0] == 256


@pytest.mark.parametrize("points, match", [
    (np.zeros((3, 4), np.float32), "torch.Tensor"),
    (torch.zeros(3, 3), r"\(n, 4\)"),
    (torch.zeros(3, 4, 1), r"\(n, 4\)"),
    (torch.zeros(3, 4, dtype=torch.int32), "float32 or float64"),
    (torch.zeros(3, 4, dtype=torch.float16), "float32 or float64"),
])
def test_pillarize_bad_points(points, match):
    with pytest.raises(ValueError, match=match):
        pillarize(points, SMALL)


def test_pillarize_bad_arguments():
    pts = torch.zeros(3, 4)
    with pytest.raises(ValueError, match="grid must be a lidarops.stream.PillarGrid"):
        pillarize(pts, (0, 0, 0, 1, 1, 1))
    with pytest.raises(ValueError, match="max_points_per_pillar must be a positive int"):
        pillarize(pts, SMALL, max_points_per_pillar=0)
    with pytest.raises(ValueError, match="max_pillars must be a positive int"):
        pillarize(pts, SMALL, max_pillars=2.5)


def test_opcheck_non_mutating_ops(device):
    pts = _random_points(600, 7).to(device)
    res = pillarize(pts, SMALL, 30, 256)
    raw = res.features[..., :4].contiguous()
    for dt in (torch.float32, torch.float64):
        torch.library.opcheck(torch.ops.lidarops.pillar_decorate.default,
                              (raw.to(dt), res.num_points, res.coords, [1.0, 1.0], [-8.0, -8.0]))
    s = PillarStream(SMALL, window=1.0, max_points_per_pillar=30, max_pillars=256, device=device)
    s.push(pts, torch.linspace(0, 0.5, 600, dtype=torch.float64, device=device))
    keys = _key_order(res.coords, SMALL).to(device)
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
    _assert_same_pillars(got, expected, where)
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
        p = _random_points(n, seed * 1000 + s).numpy()
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
        p = _random_points(200, 40 + i).numpy()
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
        p = _random_points(150, 60 + i).numpy()
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
        p = _random_points(150, 80 + i).numpy()
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
    _assert_same_pillars(stream.pillars(), before, "after points overflow")
    assert stream.t == 0.0 and stream.num_points == 15
    # too many pillars: 50 distinct pillars
    xy = np.stack(np.meshgrid(np.arange(10) - 7.5, np.arange(5) - 2.5), -1).reshape(-1, 2)
    p1 = np.concatenate([xy, np.zeros((50, 2))], 1).astype(np.float32)
    with pytest.raises(PillarOverflowError, match=r"50 pillars would be occupied but max_pillars=40.*at least 50"):
        stream.push(p1, np.full(50, 0.02))
    _assert_same_pillars(stream.pillars(), before, "after pillars overflow")
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
        p = _random_points(n, 900 + i, margin=0.0).numpy()
        t = i * 0.01 + rng.uniform(0, 0.02, n)
        ids = _check_step(stream, ref, (stream.push(p, t), ref.push(p, t))[0], ids, f"{device} step {i}", N, M)
    assert stream._log_cell.numel() > 1024


def test_stream_pillars_subset_and_errors(device):
    stream = PillarStream(SMALL, window=0.1, max_points_per_pillar=100, max_pillars=256, device=device)
    pts = _random_points(2000, 11, margin=0.0)
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
    for kwargs, match in [(dict(window=0), "window must be a positive"), (dict(window="1"), "window"),
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
        _assert_same_pillars(streams["cuda"].pillars(), streams["cpu"].pillars(), f"step {i}")


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
    _assert_same_pillars(stream.pillars(), expected, "policy")
    assert torch.isfinite(stream.pillars().features).all()
    # pillarize applies the same rule to the intensity (it has no timestamps): given the points whose t
    # is in the window, invalid intensities and outside points included, it gives the stream's pillars
    in_time = np.nonzero(np.abs(t) <= 0.05)[0]
    in_time = in_time[np.argsort(t[in_time], kind="stable")]
    res = pillarize(torch.from_numpy(p[in_time]).to(device), SMALL, 20, 256)
    _assert_same_pillars(res, stream.pillars(), "pillarize vs stream")
    assert (res.num_invalid, res.num_outside) == (int((fate[in_time] == "invalid").sum()), 4)
    _check_against_reference(res, torch.from_numpy(p[in_time]).to(device), SMALL, 20, f"{device} policy reference")
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


def test_pillarize_policy_is_lazy_and_replace_drops_counts(device):
    pts = torch.tensor([[0.5, 0.5, 0.0, float("nan")], [0.5, 0.5, 0.0, 1.0], [100.0, 0.0, 0.0, 1.0]], device=device)
    res = pillarize(pts, SMALL)
    assert isinstance(res._num_invalid, torch.Tensor)  # not read until asked for
    assert (res.num_invalid, res.num_outside) == (1, 1) and res.num_points.tolist() == [1]
    assert res._replace(coords=res.coords).num_invalid is None
