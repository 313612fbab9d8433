"""lidarops.ops.pillars: PillarGrid and pillarize, against the float64 NumPy reference ``_pillarize_reference``
(the stream that keeps pillars over a time window: tests/stream/test_pillar_stream.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers.pillars import DRIVING_AHEAD, SMALL, check_against_reference, random_points
from lidarops.ops.pillars import PillarGrid, PillarOverflowError, Pillars, pillarize


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
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), voxel_size=(0.3, 0.25)), "whole number of pillars along x"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), voxel_size=(0.25, -1)), "voxel_size"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1, 1), voxel_size=(0.25,)), "voxel_size"),
    (dict(point_cloud_range=(0, 1, 0, 1, 0, 1), voxel_size=(0.25, 0.25)), "y0 < y1"),
    (dict(point_cloud_range=(0, 0, 0, 1, 1), voxel_size=(0.25, 0.25)), "point_cloud_range"),
])
def test_grid_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PillarGrid(**kwargs)


# ---- pillarize ----

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("seed", [0, 1])
def test_pillarize_random_matches_reference(device, dtype, seed):
    pts = random_points(5000, seed, dtype=dtype).to(device)
    res = pillarize(pts, SMALL, max_points_per_pillar=60, max_pillars=256)
    assert isinstance(res, Pillars) and isinstance(res, tuple) and res._fields == ("features", "coords", "num_points")
    check_against_reference(res, pts, SMALL, 60, f"{device} {dtype} seed={seed}")
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
        check_against_reference(res, pts, grid, 200, f"{device} {scenario}")
        assert res.coords.shape[0] > 1000 and res.num_outside > 0


def test_pillarize_kitti_grid_and_non_contiguous(device):
    grid = PillarGrid.kitti()
    pts = random_points(3000, 5, grid=grid, margin=2.0)
    buf = torch.zeros(3000, 6, device=device)
    buf[:, 1:5] = pts.to(device)
    nc = buf[:, 1:5]  # a view made on the device (.to() of a CPU view would make it contiguous)
    assert not nc.is_contiguous()
    res = pillarize(nc, grid, 8, 3000)
    check_against_reference(res, pts.to(device), grid, 8, f"{device} kitti non-contiguous")


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
    check_against_reference(res, dup, SMALL, 7, f"{device} duplicates")
    assert res.num_points.tolist() == [7, 1]  # key 8 * 16 + 8 = 136 before 15 * 16 + 0 = 240
    assert res.coords.tolist() == [[0, 8, 8], [0, 15, 0]]
    assert not res.features[0, :7, 4:7].any()
    # a point on a pillar boundary goes to the upper pillar; the centre offsets are exact
    res = pillarize(torch.tensor([[1.0, -1.0, 0.0, 0.0]], device=device), SMALL)
    assert res.coords.tolist() == [[0, 7, 9]]
    assert res.features[0, 0, 7:].tolist() == [-0.5, -0.5]


def test_pillarize_overflow(device):
    pts = random_points(4000, 3).to(device)
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


def test_pillarize_policy_is_lazy_and_replace_drops_counts(device):
    pts = torch.tensor([[0.5, 0.5, 0.0, float("nan")], [0.5, 0.5, 0.0, 1.0], [100.0, 0.0, 0.0, 1.0]], device=device)
    res = pillarize(pts, SMALL)
    assert isinstance(res._num_invalid, torch.Tensor)  # not read until asked for
    assert (res.num_invalid, res.num_outside) == (1, 1) and res.num_points.tolist() == [1]
    assert res._replace(coords=res.coords).num_invalid is None
