"""lidarops.compat.mmcv against NumPy re-implementations of mmcv's kernels.

The references follow open-mmlab/mmcv ``mmcv/ops/csrc/common/cuda/``:
``furthest_point_sample_cuda_kernel.cuh`` (start 0, ``temp`` initialised to 1e10, arg-max of
``min(temp, d)``; index 0 once every distance is 0), ``ball_query_cuda_kernel.cuh`` (index order,
``d2 == 0 || (min_r2 <= d2 < max_r2)`` with float32 squares, the first hit fills every slot, zeros when
none), ``knn_cuda_kernel.cuh`` (heap of k, initial index 0; output transposed to (B, k, npoint)),
``three_nn_cuda_kernel.cuh`` (strict ``<``, 1e40 sentinel; the Python side returns ``sqrt(dist2)``),
``gather_points`` / ``group_points`` (plain gathers with atomicAdd backward). Ties: lowest index.

Tests taking ``device`` run on cpu and, where lidarops has its CUDA kernels, cuda (the ``device``
fixture of ``tests/conftest.py``).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lidarops.compat import mmcv
from helpers.compat import assert_equal, lidar_like, np_of, sqdist, to_t


def cloud(kind, B, N, rng):
    if kind == "uniform":
        return rng.uniform(-1.0, 1.0, (B, N, 3)).astype(np.float32)
    return np.stack([lidar_like(N, rng) for _ in range(B)])


def f32_square(r):
    return np.float32(r) * np.float32(r)


# ---------------------------------------------------------------------------------------------
# references (mmcv kernels, one cloud at a time)
# ---------------------------------------------------------------------------------------------

def ref_fps(pts, m):
    B, N = pts.shape[:2]
    out = np.zeros((B, m), dtype=np.int32)
    for b in range(B):
        temp = np.full(N, 1e10, dtype=pts.dtype)
        old = 0
        for j in range(1, m):
            if N == 0:
                break
            temp = np.minimum(temp, sqdist(pts[b, old:old + 1], pts[b])[0])
            old = int(np.argmax(temp))
            out[b, j] = old
    return out


def ref_ball(xyz, centers, min_r, max_r, nsample):
    B, M = centers.shape[:2]
    lo, hi = f32_square(min_r), f32_square(max_r)
    out = np.zeros((B, M, nsample), dtype=np.int32)
    for b in range(B):
        d = sqdist(centers[b], xyz[b])
        for i in range(M):
            hits = np.nonzero((d[i] == 0) | ((d[i] >= lo) & (d[i] < hi)))[0][:nsample]
            if len(hits):
                out[b, i, :] = hits[0]
                out[b, i, :len(hits)] = hits
    return out


def ref_knn(xyz, centers, k):
    """(B, k, M) int32, ascending (ties lower index), index 0 padding."""
    B, M = centers.shape[:2]
    out = np.zeros((B, M, k), dtype=np.int32)
    dist = np.full((B, M, k), np.inf)
    for b in range(B):
        if xyz.shape[1] == 0:
            continue
        d = sqdist(centers[b], xyz[b])
        order = np.argsort(d, axis=1, kind="stable")[:, :k]
        out[b, :, :order.shape[1]] = order
        dist[b, :, :order.shape[1]] = np.take_along_axis(d, order, 1)
    return out.transpose(0, 2, 1), dist


# ---------------------------------------------------------------------------------------------
# furthest_point_sample
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_fps_matches_reference(device, kind):
    rng = np.random.default_rng(0)
    pts = cloud(kind, 3, 400, rng)
    got = mmcv.furthest_point_sample(to_t(pts, device), 64)
    assert got.dtype == torch.int32 and got.shape == (3, 64)
    assert_equal(got, ref_fps(pts, 64))


def test_fps_more_samples_than_points_and_duplicates(device):
    rng = np.random.default_rng(1)
    base = rng.uniform(-3, 3, (4, 3)).astype(np.float32)
    pts = np.stack([rng.uniform(-1, 1, (10, 3)).astype(np.float32),     # num_points > N
                    base[rng.integers(0, 4, 10)],                      # 4 distinct locations
                    np.full((10, 3), 7.0, np.float32)])                # all identical
    got = mmcv.furthest_point_sample(to_t(pts, device), 16)
    want = ref_fps(pts, 16)
    assert_equal(got, want)
    assert (want[0, 10:] == 0).all() and (want[2] == 0).all()
    empty = mmcv.furthest_point_sample(torch.zeros(2, 0, 3, device=device), 5)
    assert empty.dtype == torch.int32 and (empty == 0).all() and empty.shape == (2, 5)
    assert mmcv.furthest_point_sample(to_t(pts, device), 0).shape == (3, 0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16])
def test_fps_dtypes_and_non_contiguous(device, dtype):
    rng = np.random.default_rng(2)
    base = to_t(rng.uniform(-5, 5, (2, 3, 200)), device, dtype)
    pts = base.transpose(1, 2)
    assert not pts.is_contiguous()
    assert_equal(mmcv.furthest_point_sample(pts, 20), ref_fps(np_of(pts), 20))


# ---------------------------------------------------------------------------------------------
# ball_query
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind,min_r,max_r", [("uniform", 0.0, 0.3), ("uniform", 0.1, 0.35),
                                              ("lidar", 0.0, 2.0), ("lidar", 0.5, 3.0)])
def test_ball_query_matches_reference(device, kind, min_r, max_r):
    rng = np.random.default_rng(3)
    xyz = cloud(kind, 2, 500, rng)
    centers = xyz[:, rng.choice(500, 64, replace=False)]  # centres on points: d2 == 0 hits
    got = mmcv.ball_query(min_r, max_r, 16, to_t(xyz, device), to_t(centers, device))
    assert got.dtype == torch.int32 and got.shape == (2, 64, 16)
    assert_equal(got, ref_ball(xyz, centers, min_r, max_r, 16))


def test_ball_query_inner_ball_needs_more_candidates(device):
    # 100 points inside the inner ball come first in index order; the 5 valid ring points come after
    # them, so the first core query (k = sample_num) finds none and must be widened.
    rng = np.random.default_rng(4)
    inner = rng.uniform(-0.05, 0.05, (100, 3))
    ring = np.array([[0.3, 0, 0], [0, 0.3, 0], [0, 0, 0.3], [0.2, 0.2, 0], [0.9, 0, 0]])
    centre_dup = np.zeros((1, 3))
    xyz = np.concatenate([inner, ring, centre_dup])[None].astype(np.float32)
    centers = np.array([[[0.0, 0.0, 0.0], [5.0, 5.0, 5.0]]], np.float32)
    got = mmcv.ball_query(0.2, 0.5, 8, to_t(xyz, device), to_t(centers, device))
    want = ref_ball(xyz, centers, 0.2, 0.5, 8)
    assert_equal(got, want)
    assert want[0, 0].tolist() == [100, 101, 102, 103, 105, 100, 100, 100]  # first hit fills
    assert (want[0, 1] == 0).all()  # no hit: zeros


def test_ball_query_float64_uses_float32_radii(device):
    # mmcv squares the radii in float32 even for float64 points; a point between the float64 and the
    # float32 square of max_radius is inside for mmcv
    r = 0.1
    lo64, hi32 = r * r, float(f32_square(r))
    assert lo64 < hi32
    x = math.sqrt((lo64 + hi32) / 2)
    xyz = np.array([[[x, 0, 0], [0.05, 0, 0]]], np.float64)
    centers = np.zeros((1, 1, 3))
    got = mmcv.ball_query(0.0, r, 4, to_t(xyz, device, torch.float64), to_t(centers, device, torch.float64))
    want = ref_ball(xyz, centers, 0.0, r, 4)
    assert want[0, 0].tolist() == [0, 1, 0, 0]
    assert_equal(got, want)


def test_ball_query_bad_input():
    xyz, c = torch.rand(2, 10, 3), torch.rand(2, 4, 3)
    with pytest.raises(ValueError, match="min_radius"):
        mmcv.ball_query(0.3, 0.2, 4, xyz, c)
    with pytest.raises(ValueError, match="min_radius"):
        mmcv.ball_query(-0.1, 0.2, 4, xyz, c)
    with pytest.raises(ValueError, match="sample_num"):
        mmcv.ball_query(0.0, 0.2, 0, xyz, c)
    with pytest.raises(ValueError, match="center_xyz"):
        mmcv.ball_query(0.0, 0.2, 4, xyz, torch.rand(3, 4, 3))
    with pytest.raises(ValueError, match="center_xyz"):
        mmcv.ball_query(0.0, 0.2, 4, xyz, torch.rand(2, 4, 2))
    bad = xyz.clone()
    bad[1, 2, 1] = math.nan
    with pytest.raises(ValueError, match="xyz contains NaN"):
        mmcv.ball_query(0.0, 0.2, 4, bad, c)
    bad[1, 2, 1] = -math.inf
    with pytest.raises(ValueError, match="points_xyz contains NaN or infinite"):
        mmcv.furthest_point_sample(bad, 4)


# ---------------------------------------------------------------------------------------------
# knn / three_nn
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_knn_matches_reference(device, kind):
    rng = np.random.default_rng(5)
    xyz = cloud(kind, 2, 300, rng)
    centers = cloud(kind, 2, 50, rng)
    got = mmcv.knn(12, to_t(xyz, device), to_t(centers, device))
    assert got.dtype == torch.int32 and got.shape == (2, 12, 50)
    assert_equal(got, ref_knn(xyz, centers, 12)[0])
    # transposed inputs, and center_xyz=None (queries are the points themselves)
    got_t = mmcv.knn(12, to_t(xyz, device).transpose(1, 2).contiguous(),
                     to_t(centers, device).transpose(1, 2).contiguous(), True)
    assert_equal(got_t, ref_knn(xyz, centers, 12)[0])
    assert_equal(mmcv.knn(5, to_t(xyz, device)), ref_knn(xyz, xyz, 5)[0])


def test_knn_pads_with_zero_and_ties(device):
    rng = np.random.default_rng(6)
    lattice = rng.integers(-2, 3, (1, 40, 3)).astype(np.float32)  # many equal distances
    assert_equal(mmcv.knn(9, to_t(lattice, device), to_t(lattice[:, :10], device)),
                 ref_knn(lattice, lattice[:, :10], 9)[0])
    few = lattice[:, :3]
    got = mmcv.knn(5, to_t(few, device), to_t(lattice[:, :4], device))
    want = ref_knn(few, lattice[:, :4], 5)[0]
    assert_equal(got, want)
    assert (want[:, 3:] == 0).all()


@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_three_nn_matches_reference(device, kind):
    rng = np.random.default_rng(7)
    target = cloud(kind, 2, 80, rng)
    source = cloud(kind, 2, 30, rng)
    t = to_t(target, device).requires_grad_(True)
    dist, idx = mmcv.three_nn(t, to_t(source, device))
    want_idx, want_d2 = ref_knn(source, target, 3)
    assert idx.dtype == torch.int32 and idx.shape == (2, 80, 3)
    assert_equal(idx, want_idx.transpose(0, 2, 1))
    assert dist.dtype == torch.float32 and not dist.requires_grad  # mmcv: no gradient
    # torch.sqrt on CPU is not always correctly rounded in float32: allow 1 ulp
    np.testing.assert_allclose(dist.cpu().numpy(), np.sqrt(want_d2.astype(np.float32)), rtol=2.4e-7, atol=0)


def test_three_nn_fewer_than_three_sources(device):
    target = torch.rand(1, 4, 3, device=device)
    source = torch.rand(1, 2, 3, device=device)
    dist, idx = mmcv.three_nn(target, source)
    assert (idx[..., 2] == 0).all() and torch.isinf(dist[..., 2]).all()
    assert torch.isfinite(dist[..., :2]).all()
    dist64, _ = mmcv.three_nn(target.double(), source.double())
    assert dist64.dtype == torch.float64


def test_knn_bad_input():
    xyz = torch.rand(2, 10, 3)
    for call, name in ((lambda: mmcv.knn(2, xyz * 1e20), "xyz"), (lambda: mmcv.three_nn(xyz, xyz * 1e20), "source"),
                       (lambda: mmcv.furthest_point_sample(xyz * 1e20, 2), "points_xyz"),
                       (lambda: mmcv.ball_query(0.0, 0.5, 2, xyz, xyz * 1e20), "center_xyz")):
        with pytest.raises(ValueError, match=f"{name} has a coordinate of magnitude"):  # squares overflow float32
            call()
    with pytest.raises(ValueError, match="k"):
        mmcv.knn(0, xyz)
    with pytest.raises(ValueError, match="transposed"):
        mmcv.knn(3, xyz, transposed=True)
    with pytest.raises(ValueError, match="xyz"):
        mmcv.knn(3, xyz[0])
    with pytest.raises(ValueError, match="dtype"):
        mmcv.three_nn(xyz, xyz.double())
    with pytest.raises(ValueError, match="target"):
        mmcv.three_nn(torch.rand(3, 4, 3), xyz)


# ---------------------------------------------------------------------------------------------
# gather_points / grouping_operation
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_gather_points(device, dtype):
    rng = np.random.default_rng(8)
    feats = rng.normal(size=(2, 6, 50))
    idx = rng.integers(0, 50, (2, 17)).astype(np.int32)
    got = mmcv.gather_points(to_t(feats, device, dtype), to_t(idx, device, torch.int32))
    want = np.stack([feats[b][:, idx[b]] for b in range(2)])
    assert got.shape == (2, 6, 17) and got.dtype == dtype and got.is_contiguous()
    np.testing.assert_array_equal(got.cpu().to(torch.float64).numpy(),
                                  to_t(want, "cpu", dtype).to(torch.float64).numpy())


def test_gather_points_gradient(device):
    gen = torch.Generator().manual_seed(9)
    feats = torch.randn(2, 3, 8, generator=gen, dtype=torch.float64).to(device).requires_grad_(True)
    idx = torch.tensor([[0, 7, 7, 2], [1, 1, 5, 0]], dtype=torch.int32, device=device)
    assert torch.autograd.gradcheck(lambda f: mmcv.gather_points(f, idx), (feats,), fast_mode=True)
    # backward = scatter-add: repeated indices accumulate
    mmcv.gather_points(feats, idx).sum().backward()
    counts = torch.zeros(2, 8, dtype=torch.float64)
    for b in range(2):
        for i in idx[b].tolist():
            counts[b, i] += 1
    torch.testing.assert_close(feats.grad.cpu(), counts[:, None, :].expand(2, 3, 8))


def test_grouping_operation(device):
    rng = np.random.default_rng(10)
    feats = rng.normal(size=(2, 4, 30))
    idx = rng.integers(0, 30, (2, 6, 5)).astype(np.int32)
    got = mmcv.grouping_operation(to_t(feats, device, torch.float64), to_t(idx, device, torch.int32))
    want = np.stack([feats[b][:, idx[b]] for b in range(2)])  # (B, C, npoint, nsample)
    assert got.shape == (2, 4, 6, 5) and got.is_contiguous()
    np.testing.assert_array_equal(got.cpu().numpy(), want)
    f = to_t(feats[:, :, :9], device, torch.float64).requires_grad_(True)
    small = to_t(idx[:, :3] % 9, device, torch.int32)
    assert torch.autograd.gradcheck(lambda v: mmcv.grouping_operation(v, small), (f,), fast_mode=True)


def test_grouping_operation_stacked(device):
    rng = np.random.default_rng(11)
    n_cnt, m_cnt = [5, 0, 7], [3, 2, 4]
    feats = rng.normal(size=(sum(n_cnt), 3))
    idx = np.concatenate([rng.integers(0, max(n, 1), (m, 4)) for n, m in zip(n_cnt, m_cnt)]).astype(np.int32)
    idx[3:5] = -1  # the example without points: -1 gives zeros
    offsets = np.cumsum([0] + n_cnt[:-1])
    example = np.repeat(np.arange(3), m_cnt)
    want = np.where((idx >= 0)[..., None], feats[np.maximum(idx + offsets[example][:, None], 0)], 0.0)
    want = want.transpose(0, 2, 1)  # (M, C, nsample)
    args = (to_t(idx, device, torch.int32), to_t(n_cnt, device, torch.int32), to_t(m_cnt, device, torch.int32))
    got = mmcv.grouping_operation(to_t(feats, device, torch.float64), *args)
    assert got.shape == (9, 3, 4)
    np.testing.assert_array_equal(got.cpu().numpy(), want)
    f = to_t(feats, device, torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: mmcv.grouping_operation(v, *args), (f,), fast_mode=True)


def test_gather_bad_input():
    f = torch.rand(2, 3, 10)
    with pytest.raises(ValueError, match="indices"):
        mmcv.gather_points(f, torch.zeros(2, 4))
    with pytest.raises(ValueError, match="indices"):
        mmcv.gather_points(f, torch.zeros(3, 4, dtype=torch.int32))
    with pytest.raises(ValueError, match="idx must lie"):
        mmcv.gather_points(f, torch.full((2, 4), 10, dtype=torch.int32))
    with pytest.raises(ValueError, match="indices"):
        mmcv.grouping_operation(f, torch.zeros(2, 4, dtype=torch.int32))
    with pytest.raises(ValueError, match="batch_cnt"):
        mmcv.grouping_operation(torch.rand(5, 3), torch.zeros(2, 4, dtype=torch.int32),
                                torch.tensor([5], dtype=torch.int32))
    with pytest.raises(ValueError, match="sum to"):
        mmcv.grouping_operation(torch.rand(5, 3), torch.zeros(2, 4, dtype=torch.int32),
                                torch.tensor([4], dtype=torch.int32), torch.tensor([2], dtype=torch.int32))
    with pytest.raises(ValueError, match="stacked"):
        mmcv.grouping_operation(torch.rand(5, 3), torch.full((2, 4), -2, dtype=torch.int32),
                                torch.tensor([5], dtype=torch.int32), torch.tensor([2], dtype=torch.int32))
    with pytest.raises(ValueError, match="num_points"):
        mmcv.furthest_point_sample(torch.rand(2, 5, 3), -1)


def _fps_on_matrix_reference(d: np.ndarray, k: int) -> list:
    """Plain-Python F-FPS: start at 0, then the point farthest (min over the chosen) from the chosen set."""
    out = []
    for b in range(d.shape[0]):
        chosen, near = [0], [1e10] * d.shape[1]
        for _ in range(1, k):
            near = [min(a, float(d[b, chosen[-1], j])) for j, a in enumerate(near)]
            best = max(near)
            chosen.append(near.index(best))
        out.append(chosen[:k])
    return out


@pytest.mark.parametrize("k", [1, 3, 6, 9])
def test_furthest_point_sample_with_dist(device, k):
    g = torch.Generator().manual_seed(k)
    xyz = torch.rand(2, 6, 3, generator=g)
    xyz[1, 4] = xyz[1, 2]  # a duplicate: distance 0 to a chosen point
    d = ((xyz[:, :, None] - xyz[:, None]) ** 2).sum(-1)
    idx = mmcv.furthest_point_sample_with_dist(d.to(device), k)
    assert idx.dtype == torch.int32 and idx.shape == (2, k)
    assert idx.cpu().tolist() == _fps_on_matrix_reference(d.double().numpy(), k)
    # on Euclidean squared distances it picks what furthest_point_sample picks while points remain
    same = mmcv.furthest_point_sample(xyz.to(device), min(k, 5))
    assert torch.equal(idx[0, :min(k, 5)].cpu(), same[0].cpu())


def test_furthest_point_sample_with_dist_bad_input():
    with pytest.raises(ValueError, match=r"points_dist must be a floating \(B, N, N\)"):
        mmcv.furthest_point_sample_with_dist(torch.rand(2, 3, 4), 2)
    with pytest.raises(ValueError, match="num_points must be an int >= 0"):
        mmcv.furthest_point_sample_with_dist(torch.rand(2, 3, 3), -1)
    with pytest.raises(ValueError, match="points_dist contains NaN"):
        mmcv.furthest_point_sample_with_dist(torch.full((1, 3, 3), float("nan")), 2)
