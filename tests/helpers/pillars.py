"""Grids, points and checks shared by the pillarize tests (tests/ops/test_pillars.py) and the stream tests
(tests/stream/test_pillar_stream.py)."""
from __future__ import annotations

import numpy as np
import torch

from helpers.compare import assert_close_report, assert_equal_report
from lidarops.ops.pillars import PillarGrid, Pillars, _pillarize_reference

SMALL = PillarGrid((-8.0, -8.0, -2.0, 8.0, 8.0, 2.0), (1.0, 1.0))  # 16 x 16 pillars: many points per pillar
# driving_city ahead of the car from 10 m: at most ~150 points per pillar in 100 ms
DRIVING_AHEAD = PillarGrid.driving_ahead()

# float32 features are float64 values rounded once: relative error <= 2^-24 (we allow 2^-20)
F32_RTOL, F32_ATOL = 2.0**-20, 1e-7


def random_points(n: int, seed: int, grid: PillarGrid = SMALL, margin: float = 1.0, dtype=torch.float32):
    """Uniform in the grid's range grown by ``margin`` on every side (so some points are outside)."""
    rng = np.random.default_rng(seed)
    lo = np.array(grid.point_cloud_range[:3]) - margin
    hi = np.array(grid.point_cloud_range[3:]) + margin
    xyz = rng.uniform(lo, hi, size=(n, 3))
    inten = rng.uniform(0.0, 1.0, size=(n, 1))
    return torch.from_numpy(np.concatenate([xyz, inten], 1)).to(dtype)


def key_order(coords: torch.Tensor, grid: PillarGrid) -> torch.Tensor:
    c = coords.cpu().to(torch.int64)
    return c[:, 1] * grid.shape[1] + c[:, 2]


def check_against_reference(res: Pillars, points: torch.Tensor, grid: PillarGrid, N: int, where: str):
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
    keys = key_order(coords, grid)
    assert bool((keys[1:] > keys[:-1]).all()), f"{where}: pillars not sorted by key"


def assert_same_pillars(a: Pillars, b: Pillars, where: str, exact: bool = True):
    """Same pillars, same points per pillar (as sets when not exact), features equal or to tolerance."""
    assert_equal_report(a.coords, b.coords, f"{where}: coords")
    assert_equal_report(a.num_points, b.num_points, f"{where}: num_points")
    assert a.features.shape == b.features.shape, where
    if exact:
        assert_equal_report(a.features, b.features, f"{where}: features")
        return
    fa, fb = sorted_rows(a), sorted_rows(b)
    assert_equal_report(fa[:, :5], fb[:, :5], f"{where}: point sets")
    assert_close_report(fa, fb, F32_RTOL, F32_ATOL, f"{where}: features")


def sorted_rows(p: Pillars) -> torch.Tensor:
    """(points, 10) float64: pillar index, then the 9 features, rows sorted by (pillar, x, y, z, i)."""
    f = p.features.detach().cpu().double()
    P, N, _ = f.shape
    valid = torch.arange(N)[None, :] < p.num_points.cpu()[:, None]
    pil = torch.arange(P)[:, None].expand(P, N)[valid].double()
    rows = torch.cat([pil[:, None], f[valid]], 1).numpy()
    order = np.lexsort(rows[:, [4, 3, 2, 1, 0]].T)
    return torch.from_numpy(rows[order])
