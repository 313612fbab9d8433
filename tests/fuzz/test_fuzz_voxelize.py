"""Fuzz: voxelize and pillarize against their pure-Python / NumPy references.

Cells are computed in the points' dtype with the references' rounding (documented), so coords, slots
and counts must be equal; pillar features are float64 arithmetic rounded once, compared to a few ulps.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

import lidarops
from lidarops.ops.voxelize import VoxelOverflowError, _voxelize_reference
from lidarops.stream import PillarGrid, PillarOverflowError, pillarize
from lidarops.ops.pillars import _pillarize_reference
from .fuzzing import (assert_clear_error, assert_close, assert_no_error, assert_same, fuzz, outcome,
                     scalars)

#: documented input policy of pillarize and PillarStream (lidarops.ops.pillars)
MAX_ABS_INTENSITY = 1e6


@st.composite
def point_rows(draw, C: int, dtype: torch.dtype, lo: float, hi: float, max_n: int = 16,
               regimes=("normal", "lattice", "tiny", "huge", "nonfinite")) -> tuple:
    """(n, C) points mostly inside [lo, hi) on x, y, z (with duplicates, points on cell faces and
    outside the range), other columns any float of the regime; and the regime."""
    regime = draw(st.sampled_from(regimes))
    width = 32 if dtype == torch.float32 else 64
    inside = st.floats(lo, hi, width=width) | st.integers(int(math.ceil(lo)), int(math.floor(hi))).map(float)
    coord = inside | scalars(regime, dtype)
    n = draw(st.integers(0, max_n))
    pool = draw(st.lists(st.lists(coord, min_size=C, max_size=C), min_size=1, max_size=max(1, n)))
    rows = [draw(st.sampled_from(pool)) for _ in range(n)]
    return torch.tensor(rows, dtype=torch.float64).reshape(n, C).to(dtype), regime


_GRIDS = [  # (voxel_size, point_cloud_range): whole numbers of voxels
    ((1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 4.0, 4.0, 2.0)),
    ((0.5, 0.25, 4.0), (-1.0, -1.0, -2.0, 1.0, 1.0, 2.0)),  # one cell along z: pillars
    ((0.1, 0.1, 0.2), (-0.4, 0.0, -0.2, 0.4, 0.3, 0.2)),  # sizes that float32 rounds
    ((2.0, 2.0, 2.0), (-4.0, -4.0, -4.0, 4.0, 4.0, 4.0)),
]
_BAD = [((0.0, 1.0, 1.0), "voxel_size"), ((-1.0, 1.0, 1.0), "voxel_size"), ((math.nan, 1.0, 1.0), "voxel_size"),
        ((0.3, 1.0, 1.0), "point_cloud_range")]  # 0.3 does not divide the x extent 4


@fuzz
@given(data=st.data())
def test_voxelize(device, data):
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    C = data.draw(st.integers(3, 5), "C")
    points, regime = data.draw(point_rows(C, dtype, -4.5, 4.5), "points")
    if data.draw(st.integers(0, 7)) == 0:
        (vs, bad_name), pr = data.draw(st.sampled_from(_BAD)), _GRIDS[0][1]
    else:
        (vs, pr), bad_name = data.draw(st.sampled_from(_GRIDS)), None
    P = data.draw(st.integers(1, 4), "max_points_per_voxel")
    M = data.draw(st.integers(1, 20), "max_voxels")
    overflow = data.draw(st.sampled_from(["raise", "drop"]), "overflow")
    padded = data.draw(st.booleans(), "padded")
    method = data.draw(st.sampled_from(["auto", "dense", "hash"]), "method") if device == "cpu" else "auto"
    what = f"voxelize({regime} {tuple(points.shape)} {dtype}, {vs}, {pr}, P={P}, M={M}, {overflow}, padded={padded})"
    res, err = outcome(lidarops.voxelize, points.to(device), vs, pr, P, M, overflow, padded=padded, method=method)
    if bad_name:
        return assert_clear_error(err, ValueError, [bad_name], what)
    if padded and overflow == "raise":
        return assert_clear_error(err, ValueError, ["padded", "overflow"], what)
    ref = _voxelize_reference(points, vs, pr, P, M)
    dropped = ref["num_dropped_max_voxels"] + ref["num_dropped_max_points"]
    if overflow == "raise" and dropped:
        return assert_clear_error(err, VoxelOverflowError, ["max_points_per_voxel", "max_voxels"], what)
    assert_no_error(err, what)
    V = ref["coords"].shape[0]
    voxels, coords, num_points = res
    info = res.info
    if padded:  # max_voxels rows: coords -1, num_points 0 and zeros beyond V
        assert voxels.shape[0] == M and bool((coords[V:] == -1).all()) and bool((num_points[V:] == 0).all()), what
        assert bool((voxels[V:] == 0).all()), what
        voxels, coords, num_points = voxels[:V], coords[:V], num_points[:V]
    assert_same(coords, torch.from_numpy(ref["coords"]), what + " coords")
    assert_same(num_points, torch.from_numpy(ref["num_points"]), what + " num_points")
    assert voxels.dtype == dtype, what
    assert_same(voxels, torch.from_numpy(ref["voxels"]), what + " voxels")
    assert_same(info.point_voxel, torch.from_numpy(ref["point_voxel"]), what + " point_voxel")
    assert_same(info.point_slot, torch.from_numpy(ref["point_slot"]), what + " point_slot")
    for name in ("num_voxels_needed", "num_in_range", "num_dropped_max_voxels", "num_dropped_max_points",
                 "max_points_in_voxel", "num_overfull_voxels"):
        assert int(getattr(info, name)) == ref[name], f"{what}: info.{name} {int(getattr(info, name))} != {ref[name]}"
    assert int(info.num_out_of_range) == points.shape[0] - ref["num_in_range"], what



@fuzz
@given(data=st.data())
def test_voxel_assignment(device, data):
    """voxel_assignment against the reference: voxelize's coords, counts and per-point rows and slots (the drop
    rule of ``overflow="drop"``), padded to max_voxels rows; bad grids and capacities named."""
    from lidarops.ops.voxelize import voxel_assignment

    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    points, regime = data.draw(point_rows(3, dtype, -4.5, 4.5), "points")
    if data.draw(st.integers(0, 7)) == 0:
        (vs, bad_name), pr = data.draw(st.sampled_from(_BAD)), _GRIDS[0][1]
    else:
        (vs, pr), bad_name = data.draw(st.sampled_from(_GRIDS)), None
    P = data.draw(st.sampled_from([1, 2, 4, 0, -1]), "max_points_per_voxel")
    M = data.draw(st.sampled_from([1, 5, 20, 0, 2.5]), "max_voxels")
    what = f"voxel_assignment({regime} {tuple(points.shape)} {dtype}, {vs}, {pr}, P={P}, M={M})"
    res, err = outcome(voxel_assignment, points.to(device), vs, pr, P, M)
    if bad_name or P < 1 or not isinstance(M, int) or M < 1:
        return assert_clear_error(err, ValueError, [bad_name or "max_points_per_voxel", "max_voxels"], what)
    assert_no_error(err, what)
    ref = _voxelize_reference(points, vs, pr, P, M)
    V = ref["coords"].shape[0]
    assert res.coords.shape == (M, 3) and bool((res.coords[V:] == -1).all()) and bool((res.num_points[V:] == 0).all())
    assert_same(res.coords[:V], torch.from_numpy(ref["coords"]), what + " coords")
    assert_same(res.num_points[:V], torch.from_numpy(ref["num_points"]), what + " num_points")
    assert_same(res.point_voxel, torch.from_numpy(ref["point_voxel"]), what + " point_voxel")
    assert_same(res.point_slot, torch.from_numpy(ref["point_slot"]), what + " point_slot")

_PILLAR_GRIDS = [PillarGrid((0.0, 0.0, -2.0, 4.0, 4.0, 2.0), (1.0, 1.0)),
                 PillarGrid((-0.8, -0.48, -1.0, 0.8, 0.48, 1.0), (0.16, 0.16)),
                 PillarGrid((-3.0, -1.0, -3.0, 3.0, 1.0, 3.0), (1.5, 0.5))]


def _valid_intensity(points: torch.Tensor) -> torch.Tensor:
    return points[:, 3].double().abs() <= MAX_ABS_INTENSITY


def check_pillarize(points: torch.Tensor, grid: PillarGrid, P: int, M: int, device: str, what: str) -> None:
    res, err = outcome(pillarize, points.to(device), grid, P, M)
    keep = _valid_intensity(points)  # the input policy: such points are dropped and counted, not pillarized
    ref = _pillarize_reference(points[keep], grid, 10**6)
    needed_p = int(ref["num_points"].max()) if ref["num_points"].size else 0
    if needed_p > P or ref["coords"].shape[0] > M:
        return assert_clear_error(err, PillarOverflowError, ["max_points_per_pillar", "max_pillars"], what)
    assert_no_error(err, what)
    features, coords, num_points = res
    assert_same(coords, torch.from_numpy(ref["coords"]), what + " coords")
    assert_same(num_points, torch.from_numpy(ref["num_points"]), what + " num_points")
    expected = torch.from_numpy(ref["features"])[:, :P] if ref["features"].shape[0] else torch.zeros(0, P, 9)
    if expected.shape[1] < P:
        expected = torch.cat([expected, expected.new_zeros(expected.shape[0], P - expected.shape[1], 9)], 1)
    f32 = points.dtype == torch.float32
    scale = max(1.0, float(expected.abs().max())) if expected.numel() else 1.0
    assert_close(features, expected, rtol=4e-7 if f32 else 1e-14, atol=scale * (4e-7 if f32 else 1e-14),
                 what=what + " features")
    assert res.num_outside == ref["num_outside"], f"{what}: num_outside {res.num_outside} != {ref['num_outside']}"


@fuzz
@given(data=st.data())
def test_pillarize(device, data):
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    grid = data.draw(st.sampled_from(_PILLAR_GRIDS), "grid")
    x0, y0, z0, x1, y1, z1 = grid.point_cloud_range
    points, regime = data.draw(point_rows(4, dtype, min(x0, y0, z0) - 0.5, max(x1, y1, z1) + 0.5), "points")
    P = data.draw(st.integers(1, 5), "max_points_per_pillar")
    M = data.draw(st.integers(1, 30), "max_pillars")
    check_pillarize(points, grid, P, M, device, f"pillarize({regime} {tuple(points.shape)} {dtype}, {grid}, P={P}, M={M})")


@fuzz
@given(data=st.data())
def test_pillarize_invalid_intensity(device, data):
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    grid = _PILLAR_GRIDS[0]
    points, _ = data.draw(point_rows(4, dtype, -0.5, 4.5, regimes=("nonfinite", "huge")), "points")
    assume(not bool(_valid_intensity(points).all()))
    check_pillarize(points, grid, 16, 16, device, f"pillarize(invalid intensities {points[:, 3].tolist()})")
