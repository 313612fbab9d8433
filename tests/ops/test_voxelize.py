"""lidarops.voxelize, its registered ops and the spconv PointToVoxel face, against the dict-based
NumPy reference ``_voxelize_reference`` (first-seen loop over the points in input order)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lidarops
from helpers.devices import CUDA_OK, DEVICES
from helpers.voxelize import KITTI_PILLARS, KITTI_SECOND, lidar_sweep
from lidarops import extension
from lidarops.compat.spconv_utils import PointToVoxel
from lidarops.ops.voxelize import VoxelizeResult, VoxelOverflowError, _voxelize_reference, voxel_grid_shape

CPU_METHODS = ["dense", "hash"]


def _methods(device):
    return CPU_METHODS if device == "cpu" else ["auto"]


def _check(res, ref, points, where=""):
    """Exact comparison of a voxelize result with the reference, with a message saying where."""
    V = ref["coords"].shape[0]
    assert isinstance(res, VoxelizeResult)
    voxels, coords, num_points = res
    assert voxels.dtype == points.dtype and coords.dtype == torch.int32 and num_points.dtype == torch.int32
    assert voxels.device == points.device and coords.device == points.device
    assert voxels.shape == (V,) + ref["voxels"].shape[1:], f"{where}: voxels {tuple(voxels.shape)}"
    got_c = coords.cpu().numpy()
    bad = np.nonzero((got_c != ref["coords"]).any(1))[0]
    assert bad.size == 0, f"{where}: coords differ at row {bad[0]}: {got_c[bad[0]]} vs {ref['coords'][bad[0]]}"
    np.testing.assert_array_equal(num_points.cpu().numpy(), ref["num_points"], err_msg=f"{where}: num_points")
    got_v = voxels.cpu().to(torch.float64).numpy()
    diff = np.abs(got_v - ref["voxels"])
    assert diff.max(initial=0.0) == 0.0, f"{where}: voxels differ by {diff.max()} at {np.unravel_index(diff.argmax(), diff.shape)}"
    info = res.info
    np.testing.assert_array_equal(info.point_voxel.cpu().numpy(), ref["point_voxel"], err_msg=f"{where}: point_voxel")
    np.testing.assert_array_equal(info.point_slot.cpu().numpy(), ref["point_slot"], err_msg=f"{where}: point_slot")
    assert info.num_voxels == V
    for key in ("num_voxels_needed", "num_in_range", "num_dropped_max_voxels", "num_dropped_max_points",
                "max_points_in_voxel", "num_overfull_voxels"):
        assert getattr(info, key) == ref[key], f"{where}: {key} = {getattr(info, key)}, reference {ref[key]}"
    assert info.num_out_of_range == points.shape[0] - ref["num_in_range"]
    assert res.num_dropped == ref["num_dropped_max_voxels"] + ref["num_dropped_max_points"]


def _random_cloud(n, seed, dtype=torch.float32, device="cpu", lo=(-4.0, -4.0, -2.0), hi=(4.0, 4.0, 2.0),
                  margin=1.0, channels=4):
    g = torch.Generator().manual_seed(seed)
    lo_t = torch.tensor(lo, dtype=torch.float64) - margin
    hi_t = torch.tensor(hi, dtype=torch.float64) + margin
    xyz = lo_t + (hi_t - lo_t) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    extra = torch.rand(n, channels - 3, generator=g, dtype=torch.float64)
    return torch.cat([xyz, extra], 1).to(dtype=dtype, device=device)


# ---- against the reference ----

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_cloud_matches_reference(device, dtype, seed):
    # clustered points (many per voxel) plus points outside the range, small capacities: both kinds
    # of drop happen
    pts = _random_cloud(3000, seed, dtype, device)
    vs, pr = (0.5, 0.5, 0.5), (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0)
    for method in _methods(device):
        for P, M in [(100, 10_000), (3, 10_000), (5, 200), (1, 1)]:
            ref = _voxelize_reference(pts, vs, pr, P, M)
            res = lidarops.voxelize(pts, vs, pr, P, M, overflow="drop", method=method)
            _check(res, ref, pts, f"{device} {dtype} seed={seed} method={method} P={P} M={M}")
    assert ref["num_dropped_max_voxels"] > 0 and 0 < ref["num_in_range"] < pts.shape[0]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("config", ["pillars", "second"])
def test_lidar_sweep_matches_reference(device, config):
    cfg = KITTI_PILLARS if config == "pillars" else KITTI_SECOND
    pts = torch.from_numpy(lidar_sweep(30_000, seed=3)).to(device)
    for method in _methods(device):
        for P, M in [(32, 16_000), (5, 4_000)]:
            ref = _voxelize_reference(pts, cfg["voxel_size"], cfg["point_cloud_range"], P, M)
            res = lidarops.voxelize(pts, cfg["voxel_size"], cfg["point_cloud_range"], P, M, overflow="drop", method=method)
            _check(res, ref, pts, f"{device} {config} method={method} P={P} M={M}")
    if config == "pillars":
        assert res.info.grid_shape == (1, 496, 432)
        assert (res.coords[:, 0] == 0).all()


@pytest.mark.parametrize("device", DEVICES)
def test_large_grid_uses_hash_table(device):
    # 2^20-cell-per-axis grid: the CPU picks the hash table; result equal to the reference
    pts = _random_cloud(2000, 7, torch.float64, device, lo=(0, 0, 0), hi=(100, 100, 100), margin=0)
    vs, pr = (0.01, 0.01, 0.01), (0.0, 0.0, 0.0, 100.0, 100.0, 100.0)
    ref = _voxelize_reference(pts, vs, pr, 2, 5000)
    _check(lidarops.voxelize(pts, vs, pr, 2, 5000, overflow="drop"), ref, pts, "large grid")
    assert voxel_grid_shape(vs, pr) == (10_000, 10_000, 10_000)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("side", [46_340, 46_341])
def test_grids_at_the_32_bit_key_boundary(device, side):
    # side^2 cells: 2^31 - 87,847 (CUDA sorts 31-bit keys) and 2^31 + 4,634 (64-bit keys); points in the far
    # corner, where the keys' top bits differ, and outside the grid (the key one past the cells)
    g = torch.Generator().manual_seed(side)
    far = side - 50 + 60 * torch.rand(3000, 2, generator=g, dtype=torch.float64)  # some beyond the grid
    near = 50 * torch.rand(500, 2, generator=g, dtype=torch.float64)
    xy = torch.cat([far, near]).floor() + 0.5
    xy = torch.cat([xy, xy[::7]])  # duplicates: several points per cell
    pts = torch.cat([xy, torch.rand(xy.shape[0], 2, generator=g, dtype=torch.float64)], 1).to(device)
    vs, pr = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, float(side), float(side), 1.0)
    assert math.prod(voxel_grid_shape(vs, pr)) == side * side
    ref = _voxelize_reference(pts, vs, pr, 3, 1500)
    _check(lidarops.voxelize(pts, vs, pr, 3, 1500, overflow="drop"), ref, pts, f"side {side}")
    assert ref["num_dropped_max_voxels"] > 0 and ref["num_in_range"] < pts.shape[0]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_computed_in_float32(device, dtype):
    pts = _random_cloud(2000, 4, dtype, device)
    vs, pr = (0.5, 0.5, 0.5), (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0)
    ref = _voxelize_reference(pts, vs, pr, 4, 1000)  # reference computes in float32 for these
    _check(lidarops.voxelize(pts, vs, pr, 4, 1000, overflow="drop"), ref, pts, str(dtype))


# ---- conventions ----

@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_points_on_voxel_boundaries(device, dtype):
    # exactly representable boundaries x0 + i * v: floor semantics, lower bound in, upper bound out
    vs, pr = (0.25, 0.5, 0.125), (-8.0, -4.0, -1.0, 8.0, 4.0, 1.0)
    D = (64, 16, 16)  # x, y, z cells
    i = torch.arange(0, 65, dtype=torch.float64)
    xs = -8.0 + 0.25 * i
    pts = torch.stack([xs, torch.full_like(xs, -4.0), torch.full_like(xs, 1.0 - 0.125)], 1)
    pts = torch.cat([pts, torch.tensor([[-8.0, 4.0, 0.0], [-8.0, 0.0, 1.0], [8.0, 0.0, 0.0]], dtype=torch.float64)])
    below = torch.nextafter(torch.tensor(-8.0, dtype=dtype), torch.tensor(-9.0, dtype=dtype)).item()
    pts = torch.cat([pts, torch.tensor([[below, 0.0, 0.0]], dtype=torch.float64)]).to(dtype=dtype, device=device)
    res = lidarops.voxelize(pts, vs, pr, 1, 1000)
    assert res.info.grid_shape == (D[2], D[1], D[0])
    # x = x0 + i * 0.25 for i < 64 is voxel i; x = x1 (i = 64) and the 4 extra points are outside
    assert res.coords.shape == (64, 3)
    expected = torch.stack([torch.full((64,), 15), torch.zeros(64, dtype=torch.int64), torch.arange(64)], 1)
    assert torch.equal(res.coords.cpu().long(), expected)
    assert res.num_out_of_range == 5 and res.num_dropped == 0
    assert torch.equal(res.info.point_voxel.cpu()[:64], torch.arange(64))


@pytest.mark.parametrize("device", DEVICES)
def test_non_dyadic_boundaries_follow_float32_floor(device):
    # x0 + i * v with v = 0.16, x0 = -39.68 (float32 values); the cell is floor((x - x0) / v) in float32
    # (spconv and mmcv), which sometimes gives i - 1 at a boundary: the reference says which
    vs, pr = KITTI_PILLARS["voxel_size"], KITTI_PILLARS["point_cloud_range"]
    i = torch.arange(0, 496, dtype=torch.float32)
    y = torch.tensor(-39.68, dtype=torch.float32) + i * torch.tensor(0.16, dtype=torch.float32)
    pts = torch.stack([torch.full_like(y, 10.0), y, torch.zeros_like(y), torch.zeros_like(y)], 1).to(device)
    ref = _voxelize_reference(pts, vs, pr, 4, 1000)
    res = lidarops.voxelize(pts, vs, pr, 4, 1000)
    _check(res, ref, pts, "non-dyadic boundaries")
    cy = np.floor((y.numpy() - np.float32(-39.68)) / np.float32(0.16)).astype(np.int64)
    assert (res.info.point_voxel >= 0).all()
    got = res.coords[res.info.point_voxel][:, 1].cpu().numpy()
    np.testing.assert_array_equal(got, cy)  # per point: the float32 formula
    assert (cy != np.arange(496)).any()  # the case is real: some boundary points land one voxel lower


@pytest.mark.parametrize("device", DEVICES)
def test_out_of_range_points_are_counted_not_dropped(device):
    vs, pr = (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 4.0, 4.0, 4.0)
    inside = [[0.5, 0.5, 0.5], [3.5, 3.5, 3.5], [0.0, 0.0, 0.0]]
    outside = [[-0.1, 1, 1], [4.0, 1, 1], [1, -1e-7, 1], [1, 4.0, 1], [1, 1, -5], [1, 1, 4.0],
               [math.nan, 1, 1], [1, math.inf, 1], [1, 1, -math.inf], [1e30, 1, 1]]
    pts = torch.tensor(inside + outside, dtype=torch.float32, device=device)
    res = lidarops.voxelize(pts, vs, pr, 2, 10)  # overflow="raise": out of range is not an overflow
    assert res.num_out_of_range == len(outside) and res.num_dropped == 0 and res.info.num_in_range == 3
    assert res.coords.tolist() == [[0, 0, 0], [3, 3, 3]]
    assert res.num_points.tolist() == [2, 1]
    assert res.info.point_voxel.tolist() == [0, 1, 0] + [-1] * len(outside)
    assert res.info.point_slot.tolist() == [0, 0, 1] + [-1] * len(outside)


@pytest.mark.parametrize("device", DEVICES)
def test_first_seen_order_and_input_order_within_voxel(device):
    # voxel B appears first, then A; A's points in input order; 3rd point of B dropped (P = 2)
    pts = torch.tensor([[2.5, 0.5, 0.5, 1], [0.5, 0.5, 0.5, 2], [2.6, 0.5, 0.5, 3], [0.6, 0.5, 0.5, 4],
                        [2.7, 0.5, 0.5, 5]], dtype=torch.float32, device=device)
    res = lidarops.voxelize(pts, (1, 1, 1), (0, 0, 0, 4, 1, 1), 2, 10, overflow="drop")
    assert res.coords.tolist() == [[0, 0, 2], [0, 0, 0]]
    assert res.voxels[:, :, 3].tolist() == [[1.0, 3.0], [2.0, 4.0]]
    assert res.num_points.tolist() == [2, 2]
    assert res.num_dropped == 1 and res.info.num_dropped_max_points == 1 and res.info.max_points_in_voxel == 3
    assert res.info.point_voxel.tolist() == [0, 1, 0, 1, 0]  # the dropped point's voxel is still known
    assert res.info.point_slot.tolist() == [0, 0, 1, 1, -1]


@pytest.mark.parametrize("device", DEVICES)
def test_pillars(device):
    # z extent of one voxel: PointPillars; equals the 3-D result with the z cell forced to 0
    pts = torch.from_numpy(lidar_sweep(20_000, seed=5)).to(device)
    vs, pr = (0.2, 0.2, 6.0), (-40.0, -40.0, -3.0, 40.0, 40.0, 3.0)
    res = lidarops.voxelize(pts, vs, pr, 64, 40_000, overflow="drop")
    assert res.info.grid_shape == (1, 400, 400)
    assert (res.coords[:, 0] == 0).all()
    ref = _voxelize_reference(pts, vs, pr, 64, 40_000)
    _check(res, ref, pts, "pillars")
    # same (y, x) coords as a 2-D hash of the same floor formula
    xy = pts[:, :2].cpu().numpy()
    c = np.floor((xy - np.float32(-40.0)) / np.float32(0.2)).astype(np.int64)
    ok = (xy >= -40).all(1) & (xy < 40).all(1) & (pts[:, 2].cpu().numpy() >= -3) & (pts[:, 2].cpu().numpy() < 3)
    first = {}
    for k in map(tuple, c[ok][:, ::-1]):
        first.setdefault(k, len(first))
    assert [tuple(r) for r in res.coords[:, 1:].tolist()] == list(first)


@pytest.mark.parametrize("device", DEVICES)
def test_empty_inputs(device):
    vs, pr = (0.5, 0.5, 0.5), (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0)
    for pts in (torch.zeros(0, 4, device=device), torch.full((5, 4), 100.0, device=device)):
        res = lidarops.voxelize(pts, vs, pr, 8, 100)
        voxels, coords, num_points = res
        assert voxels.shape == (0, 8, 4) and coords.shape == (0, 3) and num_points.shape == (0,)
        assert res.num_dropped == 0 and res.num_out_of_range == pts.shape[0]
        assert res.info.point_voxel.shape == (pts.shape[0],)
        assert (res.info.point_voxel == -1).all()


@pytest.mark.parametrize("device", DEVICES)
def test_non_contiguous_points(device):
    base = _random_cloud(1500, 9, torch.float32, device, channels=6)
    pts = base[::2, ::2]  # (750, 3), strided rows and columns
    assert not pts.is_contiguous()
    vs, pr = (0.5, 0.5, 0.5), (-4.0, -4.0, -2.0, 4.0, 4.0, 2.0)
    ref = _voxelize_reference(pts.contiguous(), vs, pr, 3, 500)
    _check(lidarops.voxelize(pts, vs, pr, 3, 500, overflow="drop"), ref, pts, "non-contiguous")


@pytest.mark.parametrize("device", DEVICES)
def test_deterministic(device):
    pts = torch.from_numpy(lidar_sweep(20_000, seed=6)).to(device)
    a = lidarops.voxelize(pts, **KITTI_SECOND, max_points_per_voxel=5, max_voxels=3000, overflow="drop")
    for _ in range(3):
        b = lidarops.voxelize(pts, **KITTI_SECOND, max_points_per_voxel=5, max_voxels=3000, overflow="drop")
        assert all(torch.equal(x, y) for x, y in zip(a, b))


@pytest.mark.skipif(not CUDA_OK, reason="needs CUDA kernels and a GPU")
@pytest.mark.parametrize("config", ["pillars", "second"])
def test_cpu_cuda_parity(config):
    cfg = KITTI_PILLARS if config == "pillars" else KITTI_SECOND
    pts = torch.from_numpy(lidar_sweep(120_000, seed=8))
    a = lidarops.voxelize(pts, **cfg, max_points_per_voxel=16, max_voxels=12_000, overflow="drop")
    b = lidarops.voxelize(pts.cuda(), **cfg, max_points_per_voxel=16, max_voxels=12_000, overflow="drop")
    for name, x, y in zip(("voxels", "coords", "num_points"), a, b):
        assert torch.equal(x, y.cpu()), name
    assert torch.equal(a.info.point_slot, b.info.point_slot.cpu())
    assert a.info[:9] == b.info[:9]


# ---- overflow ----

def _crowded(device):
    # voxel (0,0,0): 10 points; voxels x = 1..4: 1 point each, first seen in that order
    pts = [[0.5, 0.5, 0.5]] * 10 + [[1.5 + k, 0.5, 0.5] for k in range(4)]
    return torch.tensor(pts, dtype=torch.float32, device=device)


@pytest.mark.parametrize("device", DEVICES)
def test_overflow_raise_and_drop_counts(device):
    pts = _crowded(device)
    vs, pr = (1, 1, 1), (0, 0, 0, 8, 1, 1)
    ok = lidarops.voxelize(pts, vs, pr, 10, 5)  # exactly fits: no error
    assert ok.num_dropped == 0 and ok.num_points.tolist() == [10, 1, 1, 1, 1]
    with pytest.raises(VoxelOverflowError, match=r"1 voxel holds more than max_points_per_voxel=4 points "
                                                 r"\(the fullest holds 10; 6 points over\)\. .*raise "
                                                 r"max_points_per_voxel to at least 10, or"):
        lidarops.voxelize(pts, vs, pr, 4, 5)
    with pytest.raises(VoxelOverflowError, match=r"occupy 5 voxels but max_voxels=3 \(2 points.*raise max_voxels to "
                                                 r"at least 5, or"):
        lidarops.voxelize(pts, vs, pr, 10, 3)
    with pytest.raises(ValueError, match="would drop 8 of the 14 points"):  # both; a ValueError subclass
        lidarops.voxelize(pts, vs, pr, 4, 3)
    res = lidarops.voxelize(pts, vs, pr, 4, 3, overflow="drop")
    assert res.num_dropped == 8
    assert res.info.num_dropped_max_points == 6 and res.info.num_dropped_max_voxels == 2
    assert res.info.num_voxels_needed == 5 and res.info.max_points_in_voxel == 10
    assert res.num_points.tolist() == [4, 1, 1]
    assert res.coords[:, 2].tolist() == [0, 1, 2]
    assert res.info.point_voxel.tolist() == [0] * 10 + [1, 2, -1, -1]
    assert res.info.point_slot.tolist() == [0, 1, 2, 3] + [-1] * 6 + [0, 0, -1, -1]


@pytest.mark.parametrize("device", DEVICES)
def test_overflow_raise_on_lidar_sweep(device):
    # near the sensor, 0.16 m pillars hold more than 32 points: raising is the default
    pts = torch.from_numpy(lidar_sweep(120_000, seed=0)).to(device)
    with pytest.raises(VoxelOverflowError, match="max_points_per_voxel=32"):
        lidarops.voxelize(pts, **KITTI_PILLARS, max_points_per_voxel=32, max_voxels=16_000)
    res = lidarops.voxelize(pts, **KITTI_PILLARS, max_points_per_voxel=32, max_voxels=16_000, overflow="drop")
    ref = _voxelize_reference(pts, KITTI_PILLARS["voxel_size"], KITTI_PILLARS["point_cloud_range"], 32, 16_000)
    _check(res, ref, pts, "sweep, drop")
    assert res.num_dropped > 0 and res.info.max_points_in_voxel > 32
    assert res.num_dropped == res.info.num_in_range - int(res.num_points.sum())


def test_generous_max_voxels_costs_nothing():
    # the padded assignment is capped at N rows unless padded=True: 2^31 - 1 does not allocate 24 GB
    pts = _random_cloud(500, 5)
    res = lidarops.voxelize(pts, (0.5, 0.5, 0.5), (-4, -4, -2, 4, 4, 2), 500, 2**31 - 1)
    ref = _voxelize_reference(pts, (0.5, 0.5, 0.5), (-4, -4, -2, 4, 4, 2), 500, 2**31 - 1)
    _check(res, ref, pts, "max_voxels = 2^31 - 1")


# ---- padded (static shapes) ----

@pytest.mark.parametrize("device", DEVICES)
def test_padded_matches_exact(device):
    pts = torch.from_numpy(lidar_sweep(20_000, seed=2)).to(device)
    exact = lidarops.voxelize(pts, **KITTI_PILLARS, max_points_per_voxel=8, max_voxels=6000, overflow="drop")
    pad = lidarops.voxelize(pts, **KITTI_PILLARS, max_points_per_voxel=8, max_voxels=6000, overflow="drop",
                            padded=True)
    V = exact.info.num_voxels
    assert pad.voxels.shape == (6000, 8, 4) and isinstance(pad.info.num_voxels, torch.Tensor)
    assert int(pad.info.num_voxels) == V and int(pad.num_dropped) == exact.num_dropped
    assert torch.equal(pad.voxels[:V], exact.voxels) and not pad.voxels[V:].any()
    assert torch.equal(pad.coords[:V], exact.coords) and (pad.coords[V:] == -1).all()
    assert torch.equal(pad.num_points[:V], exact.num_points) and not pad.num_points[V:].any()
    with pytest.raises(ValueError, match="padded=True"):
        lidarops.voxelize(pts, **KITTI_PILLARS, max_points_per_voxel=8, max_voxels=6000, padded=True)


def test_torch_compile_fullgraph_padded():
    pts = torch.from_numpy(lidar_sweep(5000, seed=1))

    def f(p):
        v, c, n = lidarops.voxelize(p, (0.5, 0.5, 8.0), (-40, -40, -4, 40, 40, 4), 16, 3000, "drop", padded=True)
        return v, c, n

    compiled = torch.compile(f, fullgraph=True, backend="eager")
    for a, b in zip(compiled(pts), f(pts)):
        assert torch.equal(a, b)


# ---- autograd through the scatter ----

def test_voxels_differentiable_wrt_points():
    pts = _random_cloud(400, 3, torch.float64).requires_grad_()
    res = lidarops.voxelize(pts, (1, 1, 1), (-4, -4, -2, 4, 4, 2), 2, 1000, overflow="drop")
    w = torch.randn_like(res.voxels)
    (res.voxels * w).sum().backward()
    stored = res.info.point_slot >= 0
    expected = torch.zeros_like(pts)
    expected[stored] = w[res.info.point_voxel[stored], res.info.point_slot[stored]]
    assert torch.equal(pts.grad, expected)


def test_scatter_gradcheck():
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        n = 20
        feats = torch.randn(n, 5, generator=g, dtype=torch.float64, requires_grad=True)
        cell = torch.randperm(6 * 4, generator=g)[:n]  # unique (voxel, slot) pairs; voxel 5 is beyond num_voxels
        pv, ps = cell // 4, cell % 4
        pv = torch.where(torch.rand(n, generator=g) < 0.15, torch.full_like(pv, -1), pv)
        ps = torch.where(torch.rand(n, generator=g) < 0.15, torch.full_like(ps, -1), ps)

        def f(x):
            return torch.ops.lidarops.voxelize_scatter(x, pv, ps, 5, 4)

        assert torch.autograd.gradcheck(f, (feats,))
        assert torch.autograd.gradgradcheck(f, (feats,))


# ---- opcheck ----

@pytest.mark.parametrize("device", DEVICES)
def test_opcheck(device):
    pts = _random_cloud(300, 11, torch.float32, device)
    args = (pts, [0.5, 0.5, 0.5], [-4.0, -4.0, -2.0, 4.0, 4.0, 2.0], [16, 16, 8], 3, 100, 0)
    torch.library.opcheck(torch.ops.lidarops.voxelize_assign, args)
    _, _, pv, ps, stats = torch.ops.lidarops.voxelize_assign(*args)
    feats = torch.randn(300, 5, device=device, dtype=torch.float64, requires_grad=True)
    torch.library.opcheck(torch.ops.lidarops.voxelize_scatter, (feats, pv, ps, int(stats[0]), 3))
    torch.library.opcheck(torch.ops.lidarops.voxelize_assign, (pts[:0],) + args[1:])


# ---- bad inputs ----

@pytest.mark.parametrize("kwargs, match", [
    (dict(points=torch.zeros(10, 2)), r"points must be \(N, C\) with C >= 3"),
    (dict(points=torch.zeros(2, 10, 3)), r"points must be \(N, C\)"),
    (dict(points=torch.zeros(10, 4, dtype=torch.int32)), "points must be floating point"),
    (dict(points=[[0.0, 0.0, 0.0]]), "points must be a torch.Tensor"),
    (dict(points=torch.zeros(10, 4, device="meta")), "meta tensors need padded=True"),
    (dict(voxel_size=(0.5, 0.0, 0.5)), "voxel_size must be 3 finite positive"),
    (dict(voxel_size=(0.5, -0.5, 0.5)), "voxel_size must be 3 finite positive"),
    (dict(voxel_size=(0.5, math.nan, 0.5)), "voxel_size must be 3 finite positive"),
    (dict(voxel_size=(0.5, 0.5)), "voxel_size must be a sequence of 3 numbers"),
    (dict(point_cloud_range=(4, -4, -2, -4, 4, 2)), "x0 < x1"),
    (dict(point_cloud_range=(-4, -4, 2, 4, 4, 2)), "z0 < z1"),
    (dict(point_cloud_range=(-4, -4, -2, 4, 4, math.inf)), "6 finite numbers"),
    (dict(point_cloud_range=(-4, -4, -2, 4, 4)), "point_cloud_range must be a sequence of 6 numbers"),
    (dict(point_cloud_range=(-4, -4, -2, 4.3, 4, 2)), "whole number of voxels"),
    (dict(max_points_per_voxel=0), "max_points_per_voxel must be a positive int"),
    (dict(max_voxels=-3), "max_voxels must be a positive int"),
    (dict(max_voxels=2.5), "max_voxels must be a positive int"),
    (dict(overflow="ignore"), "overflow must be 'raise' or 'drop'"),
    (dict(method="sort"), "method must be one of"),
])
def test_bad_inputs(kwargs, match):
    args = dict(points=torch.zeros(10, 4), voxel_size=(0.5, 0.5, 0.5), point_cloud_range=(-4, -4, -2, 4, 4, 2),
                max_points_per_voxel=4, max_voxels=100)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        lidarops.voxelize(**args)


def test_cuda_points_on_cpu_only_build():
    if extension.cuda_available() or not torch.cuda.is_available():
        pytest.skip("needs a GPU and a build without CUDA kernels")
    with pytest.raises(extension.LidaropsBuildError):
        lidarops.voxelize(torch.zeros(3, 4, device="cuda"), (1, 1, 1), (0, 0, 0, 1, 1, 1), 1, 1)


def test_op_rejects_bad_arguments():
    pts = torch.zeros(4, 4)
    with pytest.raises(ValueError, match="grid_size must lie in"):
        torch.ops.lidarops.voxelize_assign(pts, [1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0, 1.0, 1.0], [1, 0, 1], 1, 1, 0)
    with pytest.raises(ValueError, match="voxel_size must be finite and positive"):
        torch.ops.lidarops.voxelize_assign(pts, [1.0, -1.0, 1.0], [0.0, 0.0, 0.0, 1.0, 1.0, 1.0], [1, 1, 1], 1, 1, 0)
    with pytest.raises(ValueError, match="point_slot must be int64"):
        torch.ops.lidarops.voxelize_scatter(pts, torch.zeros(4, dtype=torch.long), torch.zeros(3, dtype=torch.long), 1, 1)


# ---- spconv PointToVoxel face ----

def _spconv_reference(pc, vsize, crange, P, M):
    """spconv 2.x CPU semantics: float32 grid rounding, cell test only (no upper coordinate bound)."""
    vs32 = np.float32(vsize)
    lo32, hi32 = np.float32(crange[:3]), np.float32(crange[3:])
    grid = [int(math.floor(float(np.float32(hi32[a] - lo32[a]) / vs32[a]) + 0.5)) for a in range(3)]
    pr = [float(v) for v in lo32] + [math.inf] * 3
    return _voxelize_reference(pc, [float(v) for v in vs32], pr, P, M, grid_size=grid), grid


@pytest.mark.parametrize("device", DEVICES)
def test_point_to_voxel_face(device):
    pc = torch.from_numpy(lidar_sweep(30_000, seed=4)).to(device)
    vsize, crange = [0.16, 0.16, 4.0], [0, -39.68, -3, 69.12, 39.68, 1]
    gen = PointToVoxel(vsize_xyz=vsize, coors_range_xyz=crange, num_point_features=4, max_num_voxels=8000,
                       max_num_points_per_voxel=16, device=torch.device(device), overflow="drop")
    ref, grid = _spconv_reference(pc, vsize, crange, 16, 8000)
    assert gen.grid_size == grid[::-1] == [1, 496, 432]
    assert gen.vsize == [float(np.float32(v)) for v in vsize[::-1]]
    assert gen.grid_stride == [432 * 496, 432, 1]
    res = gen(pc)
    _check(res, ref, pc, "PointToVoxel")
    voxels, indices, num_per_voxel, pc_voxel_id = gen.generate_voxel_with_id(pc)
    assert torch.equal(voxels, res.voxels) and torch.equal(pc_voxel_id.cpu(), torch.from_numpy(ref["point_voxel"]))
    # default: raise instead of spconv's silent drop
    strict = PointToVoxel(vsize, crange, 4, 8000, 16, device=torch.device(device))
    with pytest.raises(VoxelOverflowError, match="max_num_points_per_voxel=16"):
        strict(pc)


@pytest.mark.parametrize("device", DEVICES)
def test_point_to_voxel_empty_mean_and_non_multiple_range(device):
    # range 0..10.1 with 0.5 voxels: spconv rounds to 20 cells and tests only the cell, so x in
    # [10.0, 10.1) is outside and nothing above the range bound is checked
    pc = torch.tensor([[0.1, 0.1, 0.1, 1.0], [0.2, 0.2, 0.2, 3.0], [9.9, 0.1, 0.1, 5.0], [10.05, 0.1, 0.1, 7.0]],
                      device=device)
    gen = PointToVoxel([0.5, 0.5, 0.5], [0, 0, 0, 10.1, 1, 1], 4, 10, 3, device=torch.device(device))
    assert gen.grid_size == [2, 2, 20]
    voxels, indices, num = gen(pc, empty_mean=True)
    assert indices.tolist() == [[0, 0, 0], [0, 0, 19]] and num.tolist() == [2, 1]
    assert voxels.dtype == torch.float32
    assert torch.allclose(voxels[0, 2], pc[:2].mean(0)) and torch.equal(voxels[1, 1], pc[2]) and torch.equal(voxels[1, 2], pc[2])
    with pytest.raises(ValueError, match="num_point_features=4"):
        gen(pc[:, :3])
    with pytest.raises(ValueError, match="device"):
        gen(pc.to("meta"))
    with pytest.raises(ValueError, match="3-D grids"):
        PointToVoxel([0.5, 0.5], [0, 0, 1, 1], 4, 10, 3)
