"""Tests of the neighborhood ops: lidarops.fps, knn, ball_query, gather.

Expected values come from independent NumPy references written here (not from the library):
brute force in the kernels' compute dtype (float32 for float32/float16/bfloat16 inputs, float64 for
float64) with the documented rounding ``((dx*dx + dy*dy) + dz*dz)`` and tie rules, so indices and
distances must match exactly; distances are also checked against exact float64 values of the same
inputs. Every ``method`` must give the same answer. The library's own ``_*_reference`` functions are
cross-checked against these, since benchmarks use them.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lidarops
from helpers.clouds import (
    CLOUD_KINDS,
    duplicate_cloud,
    identical_cloud,
    lattice_cloud,
    lidar_cloud,
    make_cloud,
    noncontiguous,
    ragged_lengths,
    uniform_cloud,
)
from helpers.compare import assert_close_report, assert_equal_report
from helpers.devices import requires_cuda
from helpers.dtypes import DTYPE_IDS, FLOAT_DTYPES, TOL, compute_dtype, np_dtype
from lidarops.ops import neighbors as nb

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
KNN_METHODS = ("brute", "grid", "auto")  # ball_query's; knn adds the CPU k-d tree
KNN_ONLY_METHODS = KNN_METHODS + ("tree",)
FPS_METHODS = ("plain", "leaves", "auto")


# ================================================================================================
# Independent NumPy references (compute dtype; same rounding and tie rules as documented)
# ================================================================================================

def knn_methods(device) -> tuple[str, ...]:
    """The knn methods available on ``device``."""
    return KNN_ONLY_METHODS if torch.device(device).type == "cpu" else KNN_METHODS


def skip_tree_off_cpu(device, method):
    if method == "tree" and torch.device(device).type != "cpu":
        pytest.skip("the k-d tree is CPU-only")


def np_sqdist(q: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(M, 3), (N, 3) -> (M, N) as ((dx*dx + dy*dy) + dz*dz), every operation rounded (NumPy never fuses)."""
    d = q[:, None, :] - p[None, :, :]
    s = d * d
    return (s[..., 0] + s[..., 1]) + s[..., 2]


def _as_np(x: torch.Tensor, dtype: torch.dtype) -> np.ndarray:
    """The kernel's view of x: its values upcast to the compute dtype."""
    return x.detach().cpu().to(compute_dtype(dtype)).numpy()


def _lens(lengths, B, n):
    return [n] * B if lengths is None else [int(v) for v in lengths]


def np_knn(query, points, k, qlen=None, plen=None):
    dt = query.dtype
    q, p = _as_np(query, dt), _as_np(points, dt)
    B, M, N = q.shape[0], q.shape[1], p.shape[1]
    dist = np.full((B, M, k), np.inf, dtype=q.dtype)
    idx = np.full((B, M, k), -1, dtype=np.int64)
    for b, (m, n) in enumerate(zip(_lens(qlen, B, M), _lens(plen, B, N))):
        if m == 0 or n == 0:
            continue
        for s in range(0, m, 512):
            d = np_sqdist(q[b, s:min(m, s + 512)], p[b, :n])
            order = np.argsort(d, axis=1, kind="stable")[:, :k]  # stable: ties to the lower index
            kk = order.shape[1]
            idx[b, s:s + len(d), :kk] = order
            dist[b, s:s + len(d), :kk] = np.take_along_axis(d, order, 1)
    return torch.from_numpy(dist), torch.from_numpy(idx)


def np_ball_query(query, points, radius, k, qlen=None, plen=None):
    dt = query.dtype
    q, p = _as_np(query, dt), _as_np(points, dt)
    ct = q.dtype.type
    r2 = ct(radius) * ct(radius)  # the compute-dtype threshold, as documented
    B, M, N = q.shape[0], q.shape[1], p.shape[1]
    dist = np.full((B, M, k), np.inf, dtype=q.dtype)
    idx = np.full((B, M, k), -1, dtype=np.int64)
    for b, (m, n) in enumerate(zip(_lens(qlen, B, M), _lens(plen, B, N))):
        if m == 0 or n == 0:
            continue
        for s in range(0, m, 512):
            d = np_sqdist(q[b, s:min(m, s + 512)], p[b, :n])
            hit = d < r2
            rank = np.cumsum(hit, axis=1)
            rows, cols = np.nonzero(hit & (rank <= k))  # row-major: columns ascending within a row
            slot = rank[rows, cols] - 1
            idx[b, s + rows, slot] = cols
            dist[b, s + rows, slot] = d[rows, cols]
    return torch.from_numpy(dist), torch.from_numpy(idx)


def np_fps(points, k, lengths=None, start=None):
    p = _as_np(points, points.dtype)
    B, N = p.shape[:2]
    out = np.full((B, k), -1, dtype=np.int64)
    for b, n in enumerate(_lens(lengths, B, N)):
        if n == 0:
            continue
        s = 0 if start is None else int(start if isinstance(start, int) else start[b])
        dist = np.full(n, np.inf, dtype=p.dtype)
        taken = np.zeros(n, dtype=bool)
        for i in range(min(k, n)):
            out[b, i] = s
            taken[s] = True
            dist = np.minimum(dist, np_sqdist(p[b, s:s + 1], p[b, :n])[0])
            s = int(np.argmax(np.where(taken, -1.0, dist)))  # first maximum: ties to the lowest index
    return torch.from_numpy(out)


def np_gather(x, idx):
    xn, flat = x.detach().cpu(), idx.detach().cpu().reshape(idx.shape[0], -1).long()
    B, C = xn.shape[0], xn.shape[2]
    out = torch.zeros((B, flat.shape[1], C), dtype=xn.dtype)
    for b in range(B):
        for j in range(flat.shape[1]):
            if flat[b, j] >= 0:
                out[b, j] = xn[b, flat[b, j]]
    return out.reshape(*idx.shape, C)


def exact_sqdist_at(query, points, idx):
    """float64 squared distances of the input values at the given neighbour indices (inf where -1)."""
    q = query.detach().cpu().double()
    p = torch.cat([points.detach().cpu().double(), q.new_zeros(points.shape[0], 1, 3)], 1)  # a row for idx -1
    i = idx.cpu()
    nbr = torch.stack([p[b][i[b]] for b in range(p.shape[0])]) if p.shape[0] else q.new_zeros(0, *i.shape[1:], 3)
    d = ((q.unsqueeze(2) - nbr) ** 2).sum(-1)
    return torch.where(i >= 0, d, torch.full_like(d, math.inf))


def check_knn_like(result, expected, query, points, dtype, what):
    dist, idx = result
    edist, eidx = expected
    assert dist.dtype == compute_dtype(dtype), f"{what}: dist2 dtype {dist.dtype}"
    assert idx.dtype == torch.int64 and dist.device == query.device and idx.device == query.device
    assert_equal_report(idx, eidx, f"{what} idx")
    assert_equal_report(dist, edist.to(dist.dtype), f"{what} dist2")
    assert_close_report(dist, exact_sqdist_at(query, points, idx), TOL[dtype].dist2_rtol, 0.0,
                        f"{what} dist2 vs exact float64")


def _cast(x, device, dtype):
    return x.to(device=device, dtype=dtype)


# ================================================================================================
# The references themselves (cheap sanity checks, so a wrong reference cannot hide a wrong kernel)
# ================================================================================================

def test_numpy_references_against_hand_computed_example():
    pts = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [1, 0, 0], [0, 0, -3]]])
    q = torch.tensor([[[0.9, 0, 0]]])
    d, i = np_knn(q, pts, 3)
    assert i.tolist() == [[[1, 3, 0]]]  # 1 and 3 tie at 0.01: lower index first
    assert np.allclose(d.numpy(), [[[0.01, 0.01, 0.81]]])
    d, i = np_ball_query(q, pts, 1.0, 4)
    assert i.tolist() == [[[0, 1, 3, -1]]]
    assert np_fps(pts, 6).tolist() == [[0, 4, 2, 1, 3, -1]]  # 1 and 3 tie at distance 1: 1 first


@pytest.mark.parametrize("kind", ["uniform", "lattice"])
def test_library_references_agree_with_numpy(kind):
    pts = make_cloud(kind, 2, 120, seed=3).float()
    q = make_cloud(kind, 2, 30, seed=4).float()
    ql, pl = ragged_lengths(2, 30, 1), ragged_lengths(2, 120, 2)
    assert_equal_report(nb._fps_reference(pts, 40, pl), np_fps(pts, 40, pl), "_fps_reference")
    for got, exp in zip(nb._knn_reference(q, pts, 7, ql, pl), np_knn(q, pts, 7, ql, pl)):
        assert_equal_report(got, exp, "_knn_reference")
    for got, exp in zip(nb._ball_query_reference(q, pts, 0.7, 5, ql, pl), np_ball_query(q, pts, 0.7, 5, ql, pl)):
        assert_equal_report(got, exp, "_ball_query_reference")
    idx = torch.randint(-1, 120, (2, 9, 4))
    assert_equal_report(nb._gather_reference(pts, idx), np_gather(pts, idx), "_gather_reference")


# ================================================================================================
# FPS
# ================================================================================================

def check_fps_properties(out, k, lengths, start):
    """Spec properties independent of any reference: start first, distinct, in range, -1 tail."""
    out = out.cpu()
    for b in range(out.shape[0]):
        n = int(lengths[b])
        row = out[b].tolist()
        m = min(k, n)
        assert all(v == -1 for v in row[m:]), f"row {b}: expected -1 after {m} samples, got {row}"
        assert all(0 <= v < n for v in row[:m]), f"row {b}: indices outside [0, {n}): {row}"
        assert len(set(row[:m])) == m, f"row {b}: repeated indices {row}"
        if m:
            assert row[0] == int(start[b])


@pytest.mark.parametrize("kind", CLOUD_KINDS)
def test_fps_matches_reference(device, dtype, kind):
    B, N, K = 4, 500, 48
    pts = _cast(make_cloud(kind, B, N, seed=11), device, dtype)
    lengths = ragged_lengths(B, N, seed=5)
    lengths[3] = 30  # fewer points than samples: -1 tail
    start = torch.tensor([7, 0, 3, 29])
    expected = np_fps(pts, K, lengths, start)
    for method in FPS_METHODS:
        out = lidarops.fps(pts, K, lengths.to(device), start.to(device), method=method)
        assert out.dtype == torch.int64 and out.device == pts.device and out.shape == (B, K)
        assert_equal_report(out, expected, f"fps method={method}")
        check_fps_properties(out, K, lengths, start)


@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_fps_larger_cloud_all_methods(device, kind):
    """Enough points for the leaf pruning (and CUDA's multi-block paths) to matter."""
    B, N, K = 2, 20000, 200
    pts = _cast(make_cloud(kind, B, N, seed=2), device, torch.float32)
    lengths = torch.tensor([N, 13001])
    expected = np_fps(pts, K, lengths)
    for method in FPS_METHODS:
        assert_equal_report(lidarops.fps(pts, K, lengths.to(device), method=method), expected,
                            f"fps {kind} method={method}")


def test_fps_defaults_and_start_forms(device):
    pts = _cast(uniform_cloud(3, 100, seed=1), device, torch.float32)
    assert_equal_report(lidarops.fps(pts, 10), np_fps(pts, 10), "default start")
    assert_equal_report(lidarops.fps(pts, 10, start_idx=42), np_fps(pts, 10, start=42), "int start")
    st = torch.tensor([5, 99, 0], dtype=torch.int32, device=device)  # int32 accepted
    assert_equal_report(lidarops.fps(pts, 10, start_idx=st), np_fps(pts, 10, start=st.cpu()), "int32 tensor start")
    lens = [100, 50, 1]  # a list is accepted as lengths (and placed on the points' device)
    assert_equal_report(lidarops.fps(pts, 10, lengths=lens), np_fps(pts, 10, lengths=lens), "list lengths")


@pytest.mark.parametrize("method", FPS_METHODS)
def test_fps_identical_points_tie_order(device, dtype, method):
    """All distances tie: after the start, the lowest unselected index, never a repeat, then -1."""
    n, K = 70, 80
    pts = _cast(identical_cloud(2, n), device, dtype)
    start = torch.tensor([0, 33], device=device)
    out = lidarops.fps(pts, K, start_idx=start, method=method).cpu()
    for b, s in enumerate([0, 33]):
        expected = [s] + [i for i in range(n) if i != s] + [-1] * (K - n)
        assert out[b].tolist() == expected


@pytest.mark.parametrize("method", FPS_METHODS)
def test_fps_duplicates(device, method):
    """Distinct indices; every distinct location is sampled before any duplicate of a sampled one."""
    B, N, U = 2, 300, 40
    pts = _cast(duplicate_cloud(B, N, seed=4, unique=U), device, torch.float32)
    out = lidarops.fps(pts, N + 5, method=method)
    assert_equal_report(out, np_fps(pts, N + 5), f"fps duplicates method={method}")
    check_fps_properties(out, N + 5, [N] * B, [0] * B)
    for b in range(B):
        locs = [tuple(pts[b, i].tolist()) for i in out[b, :N].tolist()]
        n_unique = len(set(locs))
        assert len(set(locs[:n_unique])) == n_unique


@pytest.mark.parametrize("how", ["transposed", "strided", "channels", "expanded"])
def test_fps_noncontiguous(device, how):
    base = lidar_cloud(3 if how != "expanded" else 1, 400, seed=6).float().to(device)
    pts = base.expand(3, -1, -1) if how == "expanded" else noncontiguous(base, how)
    assert not pts.is_contiguous()
    assert_equal_report(lidarops.fps(pts, 32), np_fps(pts, 32), f"fps {how}")


def test_fps_empty(device):
    pts = torch.zeros(0, 10, 3, device=device)
    assert lidarops.fps(pts, 4).shape == (0, 4)
    empty = torch.zeros(3, 0, 3, device=device)
    out = lidarops.fps(empty, 5)
    assert out.shape == (3, 5) and (out == -1).all()
    pts = _cast(uniform_cloud(2, 8, seed=0), device, torch.float32)
    out = lidarops.fps(pts, 20, lengths=torch.tensor([0, 8], device=device))
    assert (out[0] == -1).all()
    assert_equal_report(out, np_fps(pts, 20, [0, 8]), "fps k > N")
    # the start index of an empty cloud is not used (nor checked)
    out = lidarops.fps(pts, 3, lengths=torch.tensor([0, 8], device=device), start_idx=torch.tensor([5, 2], device=device))
    assert (out[0] == -1).all() and out[1, 0] == 2


@pytest.mark.parametrize("offset", [(1000.0, -1000.0, 0.0), (1.0e5, 2.0e5, -3.0e5)])
@pytest.mark.parametrize("dt", [torch.float32, torch.float64], ids=lambda d: DTYPE_IDS[d])
def test_fps_large_coordinates(device, offset, dt):
    pts = (lidar_cloud(2, 3000, seed=9) + torch.tensor(offset, dtype=torch.float64)).to(device, dt)
    expected = np_fps(pts, 64)
    for method in FPS_METHODS:
        assert_equal_report(lidarops.fps(pts, 64, method=method), expected, f"fps offset {offset} method={method}")


# ================================================================================================
# kNN
# ================================================================================================

@pytest.mark.parametrize("kind", CLOUD_KINDS)
def test_knn_matches_reference(device, dtype, kind):
    B, M, N, k = 3, 300, 1500, 8
    pts = _cast(make_cloud(kind, B, N, seed=21), device, dtype)
    q = _cast(make_cloud(kind, B, M, seed=22), device, dtype)
    ql, pl = ragged_lengths(B, M, seed=1), ragged_lengths(B, N, seed=2)
    ql[1], pl[2] = M - 17, 5  # row 1: no points; row 2: fewer points than k
    expected = np_knn(q, pts, k, ql, pl)
    for method in knn_methods(device):
        out = lidarops.knn(q, pts, k, ql.to(device), pl.to(device), method=method)
        check_knn_like(out, expected, q, pts, dtype, f"knn {kind} method={method}")


@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_knn_auto_grid_size(device, kind):
    """Large enough that method="auto" picks the grid on CPU; queries both on and off the points."""
    B, N, M, k = 2, 6000, 400, 16
    pts = _cast(make_cloud(kind, B, N, seed=31), device, torch.float32)
    q = torch.cat([pts[:, :200], _cast(make_cloud(kind, B, M - 200, seed=32), device, torch.float32)], 1)
    pl = torch.tensor([N, 4500])
    expected = np_knn(q, pts, k, None, pl)
    for method in knn_methods(device):
        check_knn_like(lidarops.knn(q, pts, k, None, pl.to(device), method=method), expected, q, pts,
                       torch.float32, f"knn {kind} method={method}")


@pytest.mark.parametrize("method", KNN_ONLY_METHODS)
def test_knn_k_larger_than_n_and_self(device, dtype, method):
    skip_tree_off_cpu(device, method)
    pts = _cast(uniform_cloud(2, 7, seed=3), device, dtype)
    dist, idx = lidarops.knn(pts, pts, 10, method=method)
    check_knn_like((dist, idx), np_knn(pts, pts, 10), pts, pts, dtype, "knn k > N")
    assert (idx[..., 7:] == -1).all() and torch.isinf(dist[..., 7:]).all() and (dist[..., 7:] > 0).all()
    assert (dist[..., 0] == 0).all()  # each point is its own nearest neighbour


@pytest.mark.parametrize("method", KNN_ONLY_METHODS)
def test_knn_ties(device, method):
    """Identical points: indices 0..k-1 in order; lattice: exact ties broken to the lower index."""
    skip_tree_off_cpu(device, method)
    pts = _cast(identical_cloud(2, 50), device, torch.float32)
    q = pts[:, :5] + torch.tensor([0.5, 0.0, 0.0], device=device)
    dist, idx = lidarops.knn(q, pts, 12, method=method)
    assert idx.cpu().tolist() == [[list(range(12))] * 5] * 2
    assert (dist == 0.25).all()
    pts = _cast(lattice_cloud(2, 3000, seed=8, side=6), device, torch.float64)
    q = _cast(lattice_cloud(2, 100, seed=9, side=6) + 0.5, device, torch.float64)  # cell centres: 8-way ties
    check_knn_like(lidarops.knn(q, pts, 20, method=method), np_knn(q, pts, 20), q, pts, torch.float64, "knn lattice")


@pytest.mark.parametrize("method", KNN_ONLY_METHODS)
def test_knn_empty(device, method):
    skip_tree_off_cpu(device, method)
    def run(B, M, N, k=4, **kw):
        q, p = torch.zeros(B, M, 3, device=device), torch.zeros(B, N, 3, device=device)
        dist, idx = lidarops.knn(q, p, k, method=method, **kw)
        assert dist.shape == idx.shape == (B, M, k)
        assert (idx == -1).all() and torch.isinf(dist).all() and (dist > 0).all()
    run(0, 5, 5)
    run(2, 0, 5)
    run(2, 5, 0)
    run(2, 5, 5, point_lengths=torch.zeros(2, dtype=torch.int64, device=device))
    run(2, 5, 5, query_lengths=torch.zeros(2, dtype=torch.int64, device=device))


@pytest.mark.parametrize("how", ["transposed", "strided", "channels", "expanded"])
def test_knn_noncontiguous(device, how):
    base_p = lidar_cloud(1 if how == "expanded" else 2, 2500, seed=41).float().to(device)
    base_q = lidar_cloud(1 if how == "expanded" else 2, 100, seed=42).float().to(device)
    if how == "expanded":
        p, q = base_p.expand(2, -1, -1), base_q.expand(2, -1, -1)
    else:
        p, q = noncontiguous(base_p, how), noncontiguous(base_q, how)
    expected = np_knn(q, p, 6)
    for method in knn_methods(device):
        check_knn_like(lidarops.knn(q, p, 6, method=method), expected, q, p, torch.float32, f"knn {how} {method}")


@pytest.mark.parametrize("offset", [(1000.0, -1000.0, 0.0), (-2.0e5, 1.0e5, 3.0e4)])
@pytest.mark.parametrize("dt", [torch.float32, torch.float64], ids=lambda d: DTYPE_IDS[d])
def test_knn_large_coordinates(device, offset, dt):
    off = torch.tensor(offset, dtype=torch.float64)
    pts = (lidar_cloud(2, 3000, seed=51) + off).to(device, dt)
    q = (lidar_cloud(2, 150, seed=52) + off).to(device, dt)
    expected = np_knn(q, pts, 8)
    for method in knn_methods(device):
        check_knn_like(lidarops.knn(q, pts, 8, method=method), expected, q, pts, dt, f"knn offset {offset} {method}")


@pytest.mark.parametrize("method", KNN_ONLY_METHODS)
def test_knn_far_neighbours_are_not_sentinels(device, method):
    """Neighbours 1e3 .. 1e6 m away are real results, not 'not found' (a sentinel like 1e10 would fail)."""
    skip_tree_off_cpu(device, method)
    q = torch.zeros(1, 4, 3, dtype=torch.float64)
    q[0, :, 0] = torch.tensor([0.0, 1.0, 2.0, 3.0])
    p = torch.tensor([[[1.0e6, 0, 0], [0, -3.0e5, 0], [0, 0, 1.0e3], [7.0e4, 7.0e4, 7.0e4]]], dtype=torch.float64)
    p = torch.cat([p, 2.0e5 + uniform_cloud(1, 3000, seed=1)], 1)  # a far dense block too
    for dt in (torch.float32, torch.float64):
        qq, pp = q.to(device, dt), p.to(device, dt)
        out = lidarops.knn(qq, pp, 3004, method=method)
        check_knn_like(out, np_knn(qq, pp, 3004), qq, pp, dt, f"knn far {dt}")
        assert (out[1] >= 0).all() and torch.isfinite(out[0]).all()


@pytest.mark.parametrize("dt", [torch.float32, torch.float64, torch.float16], ids=lambda d: DTYPE_IDS[d])
def test_knn_tree_nonfinite_points_and_dense_clusters(dt):
    """CPU k-d tree vs brute force through the raw op (no value checks): NaN/inf points are never
    neighbours; 300 identical points (leaves of zero extent, all ties); k below and above a leaf."""
    pts = lidar_cloud(2, 6000, seed=131)
    pts[0, 100:400] = pts[0, 100]
    pts[1, 7] = math.nan
    pts[1, 8, 2] = math.inf
    pts[1, 9, 0] = -math.inf
    q = torch.cat([pts[:, 1::30], lidar_cloud(2, 100, seed=132)], 1).to(dt)
    pts = pts.to(dt)
    ql, pl = torch.tensor([q.shape[1], q.shape[1] - 9]), torch.tensor([6000, 5000])
    for k in (1, 16, 17, 40, 333):
        brute = torch.ops.lidarops.knn(q, pts, ql, pl, k, 1)
        tree = torch.ops.lidarops.knn(q, pts, ql, pl, k, 3)
        assert_equal_report(tree[1], brute[1], f"tree idx k={k}")
        assert_equal_report(tree[0], brute[0], f"tree dist2 k={k}")
        assert not torch.isin(tree[1][1], torch.tensor([7, 8, 9])).any()


@requires_cuda
def test_knn_tree_is_cpu_only():
    p = torch.rand(1, 50, 3, device="cuda")
    with pytest.raises(ValueError, match="CPU-only"):
        lidarops.knn(p, p, 3, method="tree")


# ================================================================================================
# Ball query
# ================================================================================================

BALL_RADIUS = {"uniform": 0.3, "lidar": 2.0, "lattice": 1.0, "duplicates": 0.25}


@pytest.mark.parametrize("kind", CLOUD_KINDS)
def test_ball_query_matches_reference(device, dtype, kind):
    B, M, N, k = 3, 300, 1500, 12
    radius = BALL_RADIUS[kind]  # lattice: radius 1 exactly, so axis neighbours sit on the boundary
    pts = _cast(make_cloud(kind, B, N, seed=61), device, dtype)
    q = _cast(make_cloud(kind, B, M, seed=62), device, dtype)
    ql, pl = ragged_lengths(B, M, seed=3), ragged_lengths(B, N, seed=4)
    ql[1], pl[2] = M - 17, 5
    expected = np_ball_query(q, pts, radius, k, ql, pl)
    assert (expected[1] >= 0).any() and (expected[1] == -1).any()  # the test is not vacuous
    for method in KNN_METHODS:
        out = lidarops.ball_query(q, pts, radius, k, ql.to(device), pl.to(device), method=method)
        check_knn_like(out, expected, q, pts, dtype, f"ball_query {kind} r={radius} method={method}")


@pytest.mark.parametrize("kind,radius", [("uniform", 0.15), ("lidar", 1.0), ("lidar", 7.5)])
def test_ball_query_auto_grid_size(device, kind, radius):
    B, N, M, k = 2, 6000, 400, 32
    pts = _cast(make_cloud(kind, B, N, seed=71), device, torch.float32)
    q = torch.cat([pts[:, :200], _cast(make_cloud(kind, B, M - 200, seed=72), device, torch.float32)], 1)
    pl = torch.tensor([N, 4100])
    expected = np_ball_query(q, pts, radius, k, None, pl)
    for method in KNN_METHODS:
        check_knn_like(lidarops.ball_query(q, pts, radius, k, None, pl.to(device), method=method), expected,
                       q, pts, torch.float32, f"ball_query {kind} r={radius} {method}")


@pytest.mark.parametrize("method", KNN_METHODS)
def test_ball_query_radius_boundary(device, dtype, method):
    """Points at exactly the radius (in the compute dtype) are outside; one ulp inside are inside."""
    ct = np_dtype(dtype)
    rng = np.random.default_rng(5)
    radii = [0.5, 0.1, 1.0 / 3.0, 2.0]
    for radius in radii:
        r = ct(radius)
        # on the axes (distance exactly r), just inside, and random directions on the sphere
        axes = np.array([[r, 0, 0], [0, -r, 0], [0, 0, r]], dtype=ct)
        inside = np.array([[np.nextafter(r, ct(0)), 0, 0]], dtype=ct)
        v = rng.normal(size=(300, 3))
        sphere = (v / np.linalg.norm(v, axis=1, keepdims=True) * float(r)).astype(ct)
        pts = torch.from_numpy(np.concatenate([axes, inside, sphere, axes * ct(0.5)]))[None]
        pts = pts.to(device, dtype)
        q = torch.zeros(1, 1, 3, device=device, dtype=dtype)
        expected = np_ball_query(q, pts, radius, 400)
        out = lidarops.ball_query(q, pts, radius, 400, method=method)
        check_knn_like(out, expected, q, pts, dtype, f"ball_query boundary r={radius}")
        if dtype in (torch.float32, torch.float64):  # the axis points are representable exactly
            got = set(out[1][0, 0].tolist())
            assert not {0, 1, 2} & got, f"points at distance exactly r={radius} must be outside"
            assert 3 in got


@pytest.mark.parametrize("method", KNN_METHODS)
def test_ball_query_radius_edge_values(device, method):
    pts = _cast(identical_cloud(2, 20), device, torch.float32)
    # radius 0: nothing is strictly closer than 0, not even the point itself
    dist, idx = lidarops.ball_query(pts, pts, 0.0, 4, method=method)
    assert (idx == -1).all() and torch.isinf(dist).all()
    # ties everywhere: the first k indices in order
    dist, idx = lidarops.ball_query(pts[:, :3], pts, 0.1, 6, method=method)
    assert idx.cpu().tolist() == [[list(range(6))] * 3] * 2 and (dist == 0).all()
    # a huge radius covers the cloud: first k in index order, and fewer points than k
    p = _cast(lidar_cloud(1, 900, seed=3), device, torch.float32)
    out = lidarops.ball_query(p[:, :50], p, 1.0e4, 16, method=method)
    assert out[1].cpu().tolist() == [[list(range(16))] * 50]
    out = lidarops.ball_query(p[:, :5], p[:, :10], 1.0e4, 16, method=method)
    check_knn_like(out, np_ball_query(p[:, :5], p[:, :10], 1.0e4, 16), p[:, :5], p[:, :10], torch.float32, "bq k > N")


@pytest.mark.parametrize("method", KNN_METHODS)
def test_ball_query_empty(device, method):
    def run(B, M, N, k=4, **kw):
        q, p = torch.zeros(B, M, 3, device=device), torch.zeros(B, N, 3, device=device)
        dist, idx = lidarops.ball_query(q, p, 1.0, k, method=method, **kw)
        assert dist.shape == idx.shape == (B, M, k)
        assert (idx == -1).all() and torch.isinf(dist).all() and (dist > 0).all()
    run(0, 5, 5)
    run(2, 0, 5)
    run(2, 5, 0)
    run(2, 5, 5, point_lengths=torch.zeros(2, dtype=torch.int64, device=device))


@pytest.mark.parametrize("how", ["transposed", "strided", "channels", "expanded"])
def test_ball_query_noncontiguous(device, how):
    base_p = lidar_cloud(1 if how == "expanded" else 2, 2500, seed=81).float().to(device)
    base_q = lidar_cloud(1 if how == "expanded" else 2, 100, seed=82).float().to(device)
    if how == "expanded":
        p, q = base_p.expand(2, -1, -1), base_q.expand(2, -1, -1)
    else:
        p, q = noncontiguous(base_p, how), noncontiguous(base_q, how)
    expected = np_ball_query(q, p, 3.0, 10)
    for method in KNN_METHODS:
        check_knn_like(lidarops.ball_query(q, p, 3.0, 10, method=method), expected, q, p, torch.float32,
                       f"ball_query {how} {method}")


@pytest.mark.parametrize("offset", [(1000.0, -1000.0, 0.0), (-2.0e5, 1.0e5, 3.0e4)])
@pytest.mark.parametrize("dt", [torch.float32, torch.float64], ids=lambda d: DTYPE_IDS[d])
def test_ball_query_large_coordinates(device, offset, dt):
    off = torch.tensor(offset, dtype=torch.float64)
    pts = (lidar_cloud(2, 3000, seed=91) + off).to(device, dt)
    q = (lidar_cloud(2, 150, seed=92) + off).to(device, dt)
    expected = np_ball_query(q, pts, 4.0, 16)
    assert (expected[1] >= 0).sum() > 100
    for method in KNN_METHODS:
        check_knn_like(lidarops.ball_query(q, pts, 4.0, 16, method=method), expected, q, pts, dt,
                       f"ball_query offset {offset} {method}")


# ================================================================================================
# Random small cases (Hypothesis): every op, every method, ties, ragged, empty, offsets
# ================================================================================================

@settings(max_examples=30, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_random_small_cases(device, data):
    B = data.draw(st.integers(0, 3), "B")
    M = data.draw(st.integers(0, 12), "M")
    N = data.draw(st.integers(0, 40), "N")
    k = data.draw(st.integers(1, 12), "k")
    side = data.draw(st.sampled_from([1, 2, 3, 1000]), "lattice side")  # few sites: ties and duplicates
    scale = data.draw(st.sampled_from([0.25, 1.0, 37.5]), "scale")
    offset = data.draw(st.sampled_from([0.0, 1000.0, -150.25]), "offset")
    dt = data.draw(st.sampled_from(FLOAT_DTYPES), "dtype")
    radius = data.draw(st.sampled_from([0.0, 0.5, 1.0, 1.5, 3.0]), "radius") * scale
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), "seed"))
    p = torch.from_numpy(rng.integers(0, side, (B, N, 3)) * scale + offset).to(device, dt)
    q = torch.from_numpy(rng.integers(0, side, (B, M, 3)) * scale + offset).to(device, dt)
    ql = torch.from_numpy(rng.integers(0, M + 1, B))
    pl = torch.from_numpy(rng.integers(0, N + 1, B))
    start = torch.from_numpy(rng.integers(0, np.maximum(pl.numpy(), 1)))
    e_knn = np_knn(q, p, k, ql, pl)
    e_ball = np_ball_query(q, p, radius, k, ql, pl)
    e_fps = np_fps(p, k, pl, start)
    for method in knn_methods(device):
        check_knn_like(lidarops.knn(q, p, k, ql.to(device), pl.to(device), method=method), e_knn, q, p, dt,
                       f"knn {method}")
    for method in KNN_METHODS:
        check_knn_like(lidarops.ball_query(q, p, radius, k, ql.to(device), pl.to(device), method=method), e_ball,
                       q, p, dt, f"ball_query {method}")
    for method in FPS_METHODS:
        assert_equal_report(lidarops.fps(p, k, pl.to(device), start.to(device), method=method), e_fps,
                            f"fps {method}")


@pytest.mark.parametrize("method", KNN_METHODS)
def test_far_outliers_stretch_the_grid(device, method):
    """A few outliers 1e4..1e6 m away make the bounding box huge (cells clamped per axis)."""
    pts = lidar_cloud(2, 4000, seed=95)
    pts[:, :3] = torch.tensor([[1.0e6, -2.0e4, 3.0], [-5.0e5, 1.0e4, -7.0e3], [0.0, 0.0, 2.5e5]], dtype=torch.float64)
    pts = pts.to(device, torch.float32)
    q = pts[:, ::20]
    for m in [method] + (["tree"] if method == "grid" and device == "cpu" else []):
        check_knn_like(lidarops.knn(q, pts, 8, method=m), np_knn(q, pts, 8), q, pts, torch.float32, "knn outliers")
    check_knn_like(lidarops.ball_query(q, pts, 0.75, 8, method=method), np_ball_query(q, pts, 0.75, 8), q, pts,
                   torch.float32, "ball_query outliers")


# ================================================================================================
# Gather
# ================================================================================================

GATHER_DTYPES = FLOAT_DTYPES + [torch.int64, torch.int32, torch.uint8, torch.bool]


@pytest.mark.parametrize("xdtype", GATHER_DTYPES, ids=str)
@pytest.mark.parametrize("idx_shape", [(3,), (3, 17), (3, 5, 4), (3, 2, 3, 2)], ids=str)
def test_gather_matches_reference(device, xdtype, idx_shape):
    g = torch.Generator().manual_seed(3)
    N, C = 11, 5
    x = (torch.randn(3, N, C, generator=g) * 10).to(xdtype).to(device)
    idx = torch.randint(-1, N, idx_shape, generator=g)
    idx.view(-1)[:2] = torch.tensor([-1, N - 1])  # both ends present
    out = lidarops.gather(x, idx.to(device))
    assert out.shape == (*idx_shape, C) and out.dtype == xdtype and out.device == x.device
    assert_equal_report(out, np_gather(x, idx), f"gather {xdtype} {idx_shape}")
    out32 = lidarops.gather(x, idx.to(device, torch.int32))  # int32 indices accepted
    assert_equal_report(out32, out, "gather int32 idx")


def test_gather_noncontiguous_and_empty(device):
    x = torch.randn(2, 9, 6, dtype=torch.float64, device=device)
    xt = noncontiguous(x, "transposed")
    idx = torch.randint(-1, 9, (2, 4, 10), device=device)
    it = idx.transpose(1, 2)
    assert not it.is_contiguous()
    assert_equal_report(lidarops.gather(xt, it), np_gather(x, it), "gather non-contiguous")
    assert_equal_report(lidarops.gather(x[..., ::2], idx), np_gather(x[..., ::2], idx), "gather strided channels")
    assert lidarops.gather(x[:0], idx[:0]).shape == (0, 4, 10, 6)
    assert lidarops.gather(x, idx[:, :0]).shape == (2, 0, 10, 6)
    assert lidarops.gather(x[..., :0], idx).shape == (2, 4, 10, 0)
    out = lidarops.gather(x[:, :0], torch.full((2, 3), -1, device=device))  # N = 0: only -1 is valid
    assert out.shape == (2, 3, 6) and (out == 0).all()


@pytest.mark.parametrize("dt", [torch.float64, torch.float32, torch.float16, torch.bfloat16], ids=str)
def test_gather_backward_is_scatter_add(device, dt):
    g = torch.Generator().manual_seed(0)
    B, N, C = 2, 7, 3
    idx = torch.randint(-1, N, (B, 40), generator=g)  # many repeats: contributions accumulate
    grad = torch.randn(B, 40, C, generator=g, dtype=torch.float64)
    x = torch.zeros(B, N, C, dtype=dt, device=device, requires_grad=True)
    lidarops.gather(x, idx.to(device)).backward(grad.to(device, dt))
    expected = torch.zeros(B, N, C, dtype=torch.float64)
    for b in range(B):
        keep = idx[b] >= 0
        expected[b].index_add_(0, idx[b][keep], grad.to(dt).double()[b][keep])
    assert x.grad.dtype == dt
    assert_close_report(x.grad, expected, TOL[dt].grad_rtol, TOL[dt].grad_atol, f"gather backward {dt}")
    direct = torch.ops.lidarops.gather_backward(grad.to(device, dt), idx.to(device), N)
    assert_equal_report(direct, x.grad, "gather_backward op")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gather_gradcheck(device, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(2, 6, 4, generator=g, dtype=torch.float64).to(device).requires_grad_()
    idx = torch.randint(-1, 6, (2, 5, 3), generator=g).to(device)
    fast = seed > 0  # one full Jacobian check, then the cheaper random-projection checks
    assert torch.autograd.gradcheck(lambda t: lidarops.gather(t, idx), (x,), fast_mode=fast)
    assert torch.autograd.gradgradcheck(lambda t: lidarops.gather(t, idx), (x,), fast_mode=fast)


# ================================================================================================
# Gradients of dist2 (knn, ball_query)
# ================================================================================================

def _masked_dist(fn, idx_holder):
    def f(q, p):
        dist, idx = fn(q, p)
        idx_holder.append(idx)
        return torch.where(idx >= 0, dist, torch.zeros((), dtype=dist.dtype, device=dist.device))
    return f


def _radius_away_from_boundary(q, p, lo, hi):
    """A radius in [lo, hi] with no point within a relative 1e-3 of the sphere (gradcheck moves points)."""
    d = torch.cdist(q.double().cpu(), p.double().cpu()).flatten()
    cands = torch.linspace(lo, hi, 200, dtype=torch.float64)
    gap = (d.unsqueeze(0) - cands.unsqueeze(1)).abs().amin(1) / cands
    best = int(gap.argmax())
    assert gap[best] > 1e-3
    return float(cands[best])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("op", ["knn", "ball_query"])
@pytest.mark.parametrize("method", ["brute", "grid"])
def test_dist2_gradcheck(device, seed, op, method):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(2, 6, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    p = torch.randn(2, 12, 3, generator=g, dtype=torch.float64).to(device).requires_grad_()
    ql, pl = torch.tensor([6, 4], device=device), torch.tensor([12, 3], device=device)  # padding rows too
    if op == "knn":
        fn = lambda a, b: lidarops.knn(a, b, 5, ql, pl, method=method)  # noqa: E731
    else:
        r = _radius_away_from_boundary(q.detach(), p.detach(), 0.8, 1.6)
        fn = lambda a, b: lidarops.ball_query(a, b, r, 4, ql, pl, method=method)  # noqa: E731
    seen = []
    assert torch.autograd.gradcheck(_masked_dist(fn, seen), (q, p), fast_mode=seed > 0)
    assert (seen[0] == -1).any() and (seen[0] >= 0).any()


@pytest.mark.parametrize("op", ["knn", "ball_query"])
def test_dist2_grad_matches_float64_formula(device, dtype, op):
    """Gradients for every dtype against autograd through the float64 formula |q - p[idx]|^2."""
    B, M, N = 2, 40, 300
    q = _cast(lidar_cloud(B, M, seed=5) * 0.05, device, dtype).requires_grad_()
    p = _cast(lidar_cloud(B, N, seed=6) * 0.05, device, dtype).requires_grad_()
    if op == "knn":
        dist, idx = lidarops.knn(q, p, 6)
    else:
        dist, idx = lidarops.ball_query(q, p, 1.5, 6)
    w = torch.randn(dist.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    valid = (idx >= 0).cpu()
    assert valid.any()
    (torch.where(idx >= 0, dist, torch.zeros_like(dist)) * w.to(device, dist.dtype)).sum().backward()
    q64 = q.detach().cpu().double().requires_grad_()
    p64 = p.detach().cpu().double().requires_grad_()
    i = idx.cpu().clamp_min(0)
    nbr = torch.stack([p64[b][i[b]] for b in range(B)])
    ref = ((q64.unsqueeze(2) - nbr) ** 2).sum(-1)
    (torch.where(valid, ref, torch.zeros_like(ref)) * w).sum().backward()
    tol = TOL[dtype]
    assert q.grad.dtype == dtype and p.grad.dtype == dtype
    assert_close_report(q.grad, q64.grad, tol.grad_rtol, tol.grad_atol * q64.grad.abs().max().item(), "grad query")
    assert_close_report(p.grad, p64.grad, tol.grad_rtol, tol.grad_atol * p64.grad.abs().max().item(), "grad points")


# ================================================================================================
# Bad input: a ValueError that names the argument, never a crash
# ================================================================================================

def _cloud(B=2, N=10, device="cpu", dtype=torch.float32):
    return uniform_cloud(B, N, seed=0).to(device, dtype)


def _bad_cases():
    """(id, callable, argument name that the message must contain)."""
    p, q = _cloud(), _cloud(N=4)
    x = torch.randn(2, 10, 5)
    nan_p = p.clone()
    nan_p[1, 3, 2] = float("nan")
    inf_p = p.clone()
    inf_p[0, 2, 0] = float("inf")
    ninf_q = q.clone()
    ninf_q[1, 0, 1] = -float("inf")
    nan_q = q.clone()
    nan_q[0, 1, 0] = float("nan")
    L = torch.tensor
    meta = p.to("meta")
    c = [
        # fps
        ("fps-rank", lambda: lidarops.fps(p[0], 3), "points"),
        ("fps-lastdim", lambda: lidarops.fps(p[..., :2], 3), "points"),
        ("fps-int-points", lambda: lidarops.fps(p.long(), 3), "points"),
        ("fps-not-tensor", lambda: lidarops.fps(p.tolist(), 3), "points"),
        ("fps-k0", lambda: lidarops.fps(p, 0), "k"),
        ("fps-kneg", lambda: lidarops.fps(p, -2), "k"),
        ("fps-kfloat", lambda: lidarops.fps(p, 2.0), "k"),
        ("fps-kbool", lambda: lidarops.fps(p, True), "k"),
        ("fps-kstr", lambda: lidarops.fps(p, "3"), "k"),
        ("fps-nan", lambda: lidarops.fps(nan_p, 3), "points"),
        ("fps-inf", lambda: lidarops.fps(inf_p, 3), "points"),
        ("fps-len-high", lambda: lidarops.fps(p, 3, lengths=L([10, 11])), "lengths"),
        ("fps-len-neg", lambda: lidarops.fps(p, 3, lengths=L([-1, 4])), "lengths"),
        ("fps-len-shape", lambda: lidarops.fps(p, 3, lengths=L([10, 10, 10])), "lengths"),
        ("fps-len-2d", lambda: lidarops.fps(p, 3, lengths=L([[10, 10]])), "lengths"),
        ("fps-len-float", lambda: lidarops.fps(p, 3, lengths=L([10.0, 10.0])), "lengths"),
        ("fps-len-bool", lambda: lidarops.fps(p, 3, lengths=L([True, True])), "lengths"),
        ("fps-len-device", lambda: lidarops.fps(p, 3, lengths=L([10, 10], device="meta")), "lengths"),
        ("fps-start-high", lambda: lidarops.fps(p, 3, start_idx=10), "start_idx"),
        ("fps-start-neg", lambda: lidarops.fps(p, 3, start_idx=-1), "start_idx"),
        ("fps-start-vs-len", lambda: lidarops.fps(p, 3, lengths=L([10, 4]), start_idx=L([9, 4])), "start_idx"),
        ("fps-start-float", lambda: lidarops.fps(p, 3, start_idx=L([0.0, 1.0])), "start_idx"),
        ("fps-start-shape", lambda: lidarops.fps(p, 3, start_idx=L([0, 1, 2])), "start_idx"),
        ("fps-start-str", lambda: lidarops.fps(p, 3, start_idx="0"), "start_idx"),
        ("fps-method", lambda: lidarops.fps(p, 3, method="grid"), "method"),
        # knn (and the shared pair checks)
        ("knn-q-rank", lambda: lidarops.knn(q[0], p, 3), "query"),
        ("knn-p-rank", lambda: lidarops.knn(q, p[0], 3), "points"),
        ("knn-q-lastdim", lambda: lidarops.knn(q[..., :2], p, 3), "query"),
        ("knn-p-lastdim", lambda: lidarops.knn(q, torch.zeros(2, 10, 4), 3), "points"),
        ("knn-batch", lambda: lidarops.knn(q, p[:1], 3), "points"),
        ("knn-dtype", lambda: lidarops.knn(q, p.double(), 3), "dtype"),
        ("knn-int", lambda: lidarops.knn(q.int(), p.int(), 3), "query"),
        ("knn-device", lambda: lidarops.knn(q, meta, 3), "points"),
        ("knn-k0", lambda: lidarops.knn(q, p, 0), "k"),
        ("knn-kfloat", lambda: lidarops.knn(q, p, 1.5), "k"),
        ("knn-knone", lambda: lidarops.knn(q, p, None), "k"),
        ("knn-nan-p", lambda: lidarops.knn(q, nan_p, 3), "points"),
        ("knn-nan-q", lambda: lidarops.knn(nan_q, p, 3), "query"),
        ("knn-inf-p", lambda: lidarops.knn(q, inf_p, 3), "points"),
        ("knn-inf-q", lambda: lidarops.knn(ninf_q, p, 3), "query"),
        ("knn-qlen-high", lambda: lidarops.knn(q, p, 3, query_lengths=L([5, 1])), "query_lengths"),
        ("knn-plen-neg", lambda: lidarops.knn(q, p, 3, point_lengths=L([-3, 1])), "point_lengths"),
        ("knn-plen-shape", lambda: lidarops.knn(q, p, 3, point_lengths=L([10])), "point_lengths"),
        ("knn-qlen-float", lambda: lidarops.knn(q, p, 3, query_lengths=L([1.0, 2.0])), "query_lengths"),
        ("knn-method", lambda: lidarops.knn(q, p, 3, method="kdtree"), "method"),
        # ball query
        ("bq-radius-neg", lambda: lidarops.ball_query(q, p, -0.1, 3), "radius"),
        ("bq-radius-nan", lambda: lidarops.ball_query(q, p, float("nan"), 3), "radius"),
        ("bq-radius-inf", lambda: lidarops.ball_query(q, p, float("inf"), 3), "radius"),
        ("bq-radius-str", lambda: lidarops.ball_query(q, p, "1", 3), "radius"),
        ("bq-radius-none", lambda: lidarops.ball_query(q, p, None, 3), "radius"),
        ("bq-k0", lambda: lidarops.ball_query(q, p, 0.5, 0), "k"),
        ("bq-batch", lambda: lidarops.ball_query(q[:1], p, 0.5, 3), "points"),
        ("bq-lastdim", lambda: lidarops.ball_query(q, p[..., :2], 0.5, 3), "points"),
        ("bq-nan", lambda: lidarops.ball_query(q, nan_p, 0.5, 3), "points"),
        ("bq-inf-q", lambda: lidarops.ball_query(ninf_q, p, 0.5, 3), "query"),
        ("bq-plen-high", lambda: lidarops.ball_query(q, p, 0.5, 3, point_lengths=L([11, 0])), "point_lengths"),
        ("bq-device", lambda: lidarops.ball_query(meta, p, 0.5, 3), "query"),
        ("bq-method", lambda: lidarops.ball_query(q, p, 0.5, 3, method="ball"), "method"),
        # gather
        ("gather-x-rank", lambda: lidarops.gather(x[0], torch.zeros(2, 3, dtype=torch.long)), "x"),
        ("gather-x-not-tensor", lambda: lidarops.gather(x.tolist(), torch.zeros(2, 3, dtype=torch.long)), "x"),
        ("gather-idx-batch", lambda: lidarops.gather(x, torch.zeros(3, 4, dtype=torch.long)), "idx"),
        ("gather-idx-0d", lambda: lidarops.gather(x, torch.tensor(1)), "idx"),
        ("gather-idx-float", lambda: lidarops.gather(x, torch.zeros(2, 4)), "idx"),
        ("gather-idx-bool", lambda: lidarops.gather(x, torch.zeros(2, 4, dtype=torch.bool)), "idx"),
        ("gather-idx-high", lambda: lidarops.gather(x, L([[0, 10], [1, 2]])), "idx"),
        ("gather-idx-low", lambda: lidarops.gather(x, L([[0, -2], [1, 2]])), "idx"),
        ("gather-idx-device", lambda: lidarops.gather(x, L([[0, 1], [1, 2]], device="meta")), "idx"),
        ("gather-idx-list", lambda: lidarops.gather(x, [[0, 1], [1, 2]]), "idx"),
    ]
    return c


BAD_CASES = _bad_cases()


@pytest.mark.parametrize("case", BAD_CASES, ids=[c[0] for c in BAD_CASES])
def test_bad_input_raises_value_error_naming_argument(case):
    _, call, name = case
    with pytest.raises(ValueError) as err:
        call()
    assert name in str(err.value), f"message does not name {name!r}: {err.value}"


def test_bad_input_messages_say_what_was_received():
    with pytest.raises(ValueError, match=r"\(2, 10, 2\)"):
        lidarops.knn(_cloud()[..., :2], _cloud(), 3)
    with pytest.raises(ValueError, match="float64"):
        lidarops.knn(_cloud(), _cloud(dtype=torch.float64), 3)
    with pytest.raises(ValueError, match=r"\[0, 10\]"):
        lidarops.fps(_cloud(), 3, lengths=torch.tensor([10, 11]))
    with pytest.raises(ValueError, match="meta"):
        lidarops.knn(_cloud(), _cloud(device="meta"), 3)


def test_bad_input_on_device(device):
    """The value checks also run (one host sync) for tensors on the accelerator."""
    p = _cloud(device=device)
    nan_p = p.clone()
    nan_p[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="points"):
        lidarops.knn(p, nan_p, 3)
    with pytest.raises(ValueError, match="lengths"):
        lidarops.fps(p, 3, lengths=torch.tensor([11, 1], device=device))
    with pytest.raises(ValueError, match="start_idx"):
        lidarops.fps(p, 3, start_idx=torch.tensor([0, 10], device=device))
    with pytest.raises(ValueError, match="idx"):
        lidarops.gather(p, torch.tensor([[0, 10]], device=device).expand(2, 2))
    with pytest.raises(ValueError, match="point_lengths"):
        lidarops.ball_query(p, p, 1.0, 3, point_lengths=torch.tensor([3, -1], device=device))


def test_accepted_argument_forms():
    p = _cloud()
    ref = lidarops.knn(p, p, 3)
    for k in (torch.tensor(3), np.int64(3)):  # 1-element tensors and NumPy integers are ints too
        assert torch.equal(lidarops.knn(p, p, k)[1], ref[1])
    assert torch.equal(lidarops.knn(p, p, 3, point_lengths=[10, 10])[1], ref[1])  # list lengths
    assert torch.equal(lidarops.ball_query(p, p, 1, 3)[1], lidarops.ball_query(p, p, 1.0, 3)[1])  # int radius
    assert torch.equal(lidarops.ball_query(p, p, np.float32(0.5), 3)[1], lidarops.ball_query(p, p, 0.5, 3)[1])


def test_meta_tensors_give_shapes():
    """Shape inference on the meta device (no data, so no value checks)."""
    p = torch.empty(2, 10, 3, device="meta")
    q = torch.empty(2, 4, 3, device="meta", dtype=torch.float16)
    assert lidarops.fps(p, 5).shape == (2, 5)
    dist, idx = lidarops.knn(q, q, 3)
    assert dist.shape == idx.shape == (2, 4, 3) and dist.dtype == torch.float32 and idx.dtype == torch.int64
    dist, idx = lidarops.ball_query(p.double(), p.double(), 0.5, 6)
    assert dist.shape == (2, 10, 6) and dist.dtype == torch.float64
    x = torch.empty(2, 10, 7, device="meta")
    assert lidarops.gather(x, torch.empty(2, 4, 3, dtype=torch.long, device="meta")).shape == (2, 4, 3, 7)


# ---- lidarops.validation(False) ----

def test_validation_context_manager_state():
    v = sys.modules["lidarops.ops.validation"]  # the module (lidarops.ops.validation is also the function)

    assert v.value_checks_enabled()
    with lidarops.validation(False):
        assert not v.value_checks_enabled()
        with lidarops.validation(True):
            assert v.value_checks_enabled()
        assert not v.value_checks_enabled()
    assert v.value_checks_enabled()
    with pytest.raises(KeyError):
        with lidarops.validation(False):
            raise KeyError("boom")
    assert v.value_checks_enabled()


def test_validation_off_skips_value_checks_only():
    p = _cloud()
    nan_p = p.clone()
    nan_p[0, 0, 0] = float("nan")
    with lidarops.validation(False):
        lidarops.knn(p, nan_p, 3, method="brute")  # value checks skipped: no ValueError
        lidarops.fps(nan_p, 3)
        with pytest.raises(ValueError, match="points"):  # shape checks still run
            lidarops.knn(p, p[..., :2], 3)
        with pytest.raises(ValueError, match="k"):
            lidarops.knn(p, p, 0)
        with pytest.raises(ValueError, match="radius"):
            lidarops.ball_query(p, p, -1.0, 3)


def test_validation_off_cpu_kernels_still_raise():
    """Without the Python value checks the CPU kernels still refuse out-of-range values (ValueError)."""
    p = _cloud()
    x = torch.randn(2, 10, 4)
    with lidarops.validation(False):
        cases = [
            lambda: lidarops.fps(p, 3, lengths=torch.tensor([10, 11])),
            lambda: lidarops.fps(p, 3, start_idx=torch.tensor([0, 10])),
            lambda: lidarops.fps(p, 3, start_idx=-1),
            lambda: lidarops.knn(p, p, 3, point_lengths=torch.tensor([10, 11])),
            lambda: lidarops.knn(p, p, 3, query_lengths=torch.tensor([-1, 3])),
            lambda: lidarops.ball_query(p, p, 0.5, 3, point_lengths=torch.tensor([12, 1])),
            lambda: lidarops.gather(x, torch.tensor([[0, 10], [0, 1]])),
            lambda: lidarops.gather(x, torch.tensor([[0, -5], [0, 1]])),
            lambda: torch.ops.lidarops.gather_backward(torch.ones(2, 2, 4), torch.tensor([[0, 7], [0, 1]]), 5),
        ]
        for i, call in enumerate(cases):
            with pytest.raises(ValueError):
                call()
    # the registered ops themselves reject bad arguments the wrappers never pass
    q = _cloud(N=4)
    L = torch.tensor([10, 10])
    bad = [
        lambda: torch.ops.lidarops.knn(q, p, L[:1].clone(), L, 3, 0),
        lambda: torch.ops.lidarops.knn(q, p, L.int(), L, 3, 0),
        lambda: torch.ops.lidarops.knn(q, p, torch.tensor([4, 4]), L, 0, 0),
        lambda: torch.ops.lidarops.knn(q, p, torch.tensor([4, 4]), L, 3, 7),
        lambda: torch.ops.lidarops.ball_query(q, p, torch.tensor([4, 4]), L, 3, -1.0, 0),
        lambda: torch.ops.lidarops.ball_query(q, p, torch.tensor([4, 4]), L, 3, float("nan"), 0),
        lambda: torch.ops.lidarops.fps(p, L, torch.tensor([0, 0]), 3, 9),
        lambda: torch.ops.lidarops.fps(p[..., :2], L, torch.tensor([0, 0]), 3, 0),
        lambda: torch.ops.lidarops.gather(x, torch.zeros(2, 3, dtype=torch.int32)),
        lambda: torch.ops.lidarops.gather(x, torch.zeros(3, 3, dtype=torch.long)),
    ]
    for call in bad:
        with pytest.raises(ValueError):
            call()


_NON_FINITE_SCRIPT = r"""
import sys, torch, lidarops
torch.manual_seed(0)
cases, checks, device = sys.argv[1].split(","), sys.argv[2] == "on", sys.argv[3]
for case in cases:
    p = torch.randn(1, 5000, 3, device=device) * 50
    q = p[:, :300].clone()
    p[0, 7, 0] = float(case)
    q[0, 7, 1] = float(case)
    steps = [(f"knn {m}", lambda m=m: lidarops.knn(q, p, 8, method=m)) for m in ("brute", "grid")]
    steps += [(f"knn finite queries {m}", lambda m=m: lidarops.knn(q[:, 100:], p, 8, method=m)) for m in ("brute", "grid")]
    steps += [(f"ball_query {m}", lambda m=m: lidarops.ball_query(q, p, 5.0, 8, method=m)) for m in ("brute", "grid")]
    steps += [(f"fps {m}", lambda m=m: lidarops.fps(p, 32, method=m)) for m in ("plain", "leaves")]
    with lidarops.validation(checks):
        for name, step in steps:
            print(f"{case}: {name}", flush=True)
            try:
                step()
                assert not checks, f"{case}: {name}: no ValueError with the value checks on"
            except ValueError as e:
                assert checks, e
            if device == "cuda":
                torch.cuda.synchronize()  # surface asynchronous kernel faults here
print("finished", flush=True)
"""


@pytest.mark.parametrize("cases,checks", [("nan,inf,-inf", "off"), ("inf,-inf", "on")])
def test_non_finite_coordinates_terminate(device, cases, checks):
    """NaN/inf coordinates must not hang or crash any path (results are unspecified when the value
    checks are off; with them on, a ValueError). Run in a subprocess with a deadline: a kernel stuck
    in an endless loop or a segfault cannot be caught in-process."""
    try:
        proc = subprocess.run([sys.executable, "-c", _NON_FINITE_SCRIPT, cases, checks, device], cwd=REPO,
                              env={**os.environ, "PYTHONPATH": REPO}, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired as e:
        out = (e.stdout or b"").decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        last = out.strip().splitlines()[-1:] or ["(before the first step)"]
        pytest.fail(f"value checks {checks}: hung for 60 s in step {last[0]!r}")
    if proc.returncode != 0 or "finished" not in proc.stdout:
        last = proc.stdout.strip().splitlines()[-1:] or ["(before the first step)"]
        pytest.fail(f"value checks {checks}: exit code {proc.returncode} in step {last[0]!r}\n{proc.stderr[-1500:]}")


# ================================================================================================
# CUDA: parity with CPU (bit-identical by design), streams, large LiDAR-like clouds
# ================================================================================================

# CUDA FPS paths: one block per cloud (points in registers, N <= 8192 float / 4096 double), a
# thread-block cluster of up to 16 blocks per cloud (sm_90+), one block with distances in global
# memory (method "plain" beyond one block, or clouds too big for a cluster).
@requires_cuda
@pytest.mark.parametrize("B,N,K,dt", [
    (1, 120000, 2048, torch.float32),  # cluster of 16
    (4, 30000, 1024, torch.float32),
    (16, 4096, 512, torch.float32),
    (160, 2000, 64, torch.float32),  # more clouds than SMs: one block each
    (1, 150000, 256, torch.float32),  # too big for a cluster
    (2, 70000, 256, torch.float64),
    (3, 9000, 300, torch.float16),
], ids=lambda v: DTYPE_IDS.get(v, str(v)) if isinstance(v, torch.dtype) else str(v))
def test_cuda_fps_parity_large(B, N, K, dt):
    pts = lidar_cloud(B, N, seed=100).to(dt)
    lengths = torch.full((B,), N)
    if B > 1:
        lengths[1] = N // 3 + 1
        lengths[-1] = K - 7  # fewer points than samples
    if B > 2:
        lengths[2] = 0
    start = torch.arange(B) * 3 % lengths.clamp_min(1)
    cpu = lidarops.fps(pts, K, lengths, start)
    check_fps_properties(cpu, K, lengths, start)
    for method in FPS_METHODS:
        gpu = lidarops.fps(pts.cuda(), K, lengths.cuda(), start.cuda(), method=method)
        assert_equal_report(gpu, cpu, f"fps cuda vs cpu B={B} N={N} K={K} {dt} method={method}")


@requires_cuda
@pytest.mark.parametrize("dt", FLOAT_DTYPES, ids=lambda d: DTYPE_IDS[d])
def test_cuda_fps_parity_dtypes_and_ties(dt):
    for pts in (lidar_cloud(2, 20000, seed=101), lattice_cloud(2, 5000, seed=102), identical_cloud(2, 3000)):
        pts = pts.to(dt)
        cpu = lidarops.fps(pts, 700)
        for method in FPS_METHODS:
            assert_equal_report(lidarops.fps(pts.cuda(), 700, method=method), cpu, f"fps cuda {dt} {method}")


@requires_cuda
@pytest.mark.parametrize("op", ["knn", "ball_query"])
@pytest.mark.parametrize("dt", FLOAT_DTYPES, ids=lambda d: DTYPE_IDS[d])
def test_cuda_knn_ball_parity_large(op, dt):
    B, N, M = 2, 50000, 50000
    pts = lidar_cloud(B, N, seed=110).to(dt)
    q = torch.cat([pts[:, : M // 2], lidar_cloud(B, M - M // 2, seed=111).to(dt)], 1)
    ql, pl = torch.tensor([M, M - M // 40]), torch.tensor([N, N // 2 + 1])
    args = [(16, None), (32, None)] if op == "knn" else [(32, 0.5), (16, 2.0), (64, 8.0)]
    for k, r in args:
        def run(dev, method):
            if op == "knn":
                return lidarops.knn(q.to(dev), pts.to(dev), k, ql.to(dev), pl.to(dev), method=method)
            return lidarops.ball_query(q.to(dev), pts.to(dev), r, k, ql.to(dev), pl.to(dev), method=method)
        cpu = run("cpu", "auto")
        for method in KNN_METHODS:
            if method == "brute" and dt != torch.float32:
                continue  # brute force at this size is slow on CPU; float32 covers it
            gpu = run("cuda", method)
            assert_equal_report(gpu[1], cpu[1], f"{op} cuda vs cpu {dt} k={k} r={r} method={method} idx")
            assert_equal_report(gpu[0], cpu[0], f"{op} cuda vs cpu {dt} k={k} r={r} method={method} dist2")


@requires_cuda
def test_cuda_knn_ball_parity_ties_and_offsets():
    clouds = [lattice_cloud(2, 40000, seed=120, side=30), duplicate_cloud(2, 40000, seed=121, unique=500),
              lidar_cloud(2, 40000, seed=122) + torch.tensor([1000.0, -1000.0, 5.0], dtype=torch.float64)]
    for pts64 in clouds:
        for dt in (torch.float32, torch.float64):
            pts = pts64.to(dt)
            q = pts[:, ::7]
            for method in ("grid", "auto"):
                for name, fn in (("knn", lambda d, m: lidarops.knn(q.to(d), pts.to(d), 24, method=m)),
                                 ("ball", lambda d, m: lidarops.ball_query(q.to(d), pts.to(d), 1.0, 24, method=m))):
                    cpu, gpu = fn("cpu", method), fn("cuda", method)
                    assert_equal_report(gpu[1], cpu[1], f"{name} ties cuda vs cpu {dt} {method} idx")
                    assert_equal_report(gpu[0], cpu[0], f"{name} ties cuda vs cpu {dt} {method} dist2")


# The CUDA kNN grid kernel gives each query a group of 4, 2 or 1 threads, depending on how many
# queries there are (B * M * S up to 256 threads per SM); each group size must give the CPU's answer.
@requires_cuda
@pytest.mark.parametrize("M", [1000, 20000, 50000, 150000])
def test_cuda_knn_grid_group_sizes(M):
    pts = lidar_cloud(1, 30000, seed=140)
    q = lidar_cloud(1, M, seed=141)
    n = min(pts.shape[1], (M + 2) // 3)
    q[0, : 3 * n : 3] = pts[0, :n]  # some queries on points (zero distances, ties)
    for k in (7, 16, 32, 40):
        cpu = lidarops.knn(q, pts, k)
        gpu = lidarops.knn(q.cuda(), pts.cuda(), k, method="grid")
        assert_equal_report(gpu[1], cpu[1], f"knn grid M={M} k={k} idx")
        assert_equal_report(gpu[0], cpu[0], f"knn grid M={M} k={k} dist2")


# Every CUDA kernel path of the four ops once, at sizes small enough for compute-sanitizer
# (memcheck, racecheck, synccheck): tools/device_run.sh selects this test with -k sanitize_paths.
@requires_cuda
def test_cuda_sanitize_paths():
    g = torch.Generator().manual_seed(7)
    pts = lidar_cloud(2, 6000, seed=130)  # >= 4096 points: the kNN grid refines its cells
    pl = torch.tensor([6000, 4500])
    q = torch.cat([pts[:, :400], lidar_cloud(2, 200, seed=131)], 1)
    ql = torch.tensor([600, 450])
    for dt in (torch.float32, torch.float64):
        p_, q_ = pts.to(dt), q.to(dt)
        for k in (5, 40, 80):  # register lists (merged sub-warp lists, one thread) and output-row lists
            for method in ("brute", "grid"):
                cpu = lidarops.knn(q_, p_, k, ql, pl)
                gpu = lidarops.knn(q_.cuda(), p_.cuda(), k, ql.cuda(), pl.cuda(), method=method)
                assert_equal_report(gpu[1], cpu[1], f"knn {dt} k={k} {method} idx")
                assert_equal_report(gpu[0], cpu[0], f"knn {dt} k={k} {method} dist2")
                cpu = lidarops.ball_query(q_, p_, 1.5, k, ql, pl)
                gpu = lidarops.ball_query(q_.cuda(), p_.cuda(), 1.5, k, ql.cuda(), pl.cuda(), method=method)
                assert_equal_report(gpu[1], cpu[1], f"ball {dt} k={k} {method} idx")
                assert_equal_report(gpu[0], cpu[0], f"ball {dt} k={k} {method} dist2")
    # FPS: one block per cloud, a cluster per cloud (float: pushes, double: cluster barrier), and
    # distances in global memory (too big for a cluster)
    for B, N, K, dt, methods in ((2, 3000, 200, torch.float32, FPS_METHODS),
                                 (2, 6000, 150, torch.float64, FPS_METHODS),
                                 (1, 150000, 16, torch.float32, ("auto",))):
        p_ = lidar_cloud(B, N, seed=132).to(dt)
        lengths = torch.tensor([N, N // 3 + 1][:B])
        cpu = lidarops.fps(p_, K, lengths)
        for method in methods:
            gpu = lidarops.fps(p_.cuda(), K, lengths.cuda(), method=method)
            assert_equal_report(gpu, cpu, f"fps B={B} N={N} {dt} {method}")
    # gather and its scatter-add backward
    x = torch.randn(2, 700, 24, generator=g, dtype=torch.float64, requires_grad=True)
    idx = torch.randint(-1, 700, (2, 300, 9), generator=g)
    xc = x.detach().cuda().requires_grad_()
    gout = torch.randn(2, 300, 9, 24, generator=g, dtype=torch.float64)
    lidarops.gather(x, idx).backward(gout)
    out = lidarops.gather(xc, idx.cuda())
    out.backward(gout.cuda())
    torch.testing.assert_close(out.detach().cpu(), lidarops.gather(x.detach(), idx), rtol=0, atol=0)
    torch.testing.assert_close(xc.grad.cpu(), x.grad, rtol=1e-12, atol=1e-12)


@requires_cuda
def test_cuda_gather_and_backward_parity():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 5000, 64, generator=g)
    idx = torch.randint(-1, 5000, (3, 2048, 32), generator=g)
    assert_equal_report(lidarops.gather(x.cuda(), idx.cuda()), lidarops.gather(x, idx), "gather cuda vs cpu")
    grad = torch.randn(3, 2048 * 32, 64, generator=g, dtype=torch.float64)
    flat = idx.reshape(3, -1)
    gpu = torch.ops.lidarops.gather_backward(grad.cuda(), flat.cuda(), 5000)
    cpu = torch.ops.lidarops.gather_backward(grad, flat, 5000)
    assert_close_report(gpu, cpu, 1e-12, 1e-12, "gather_backward cuda vs cpu (float64 sums, any order)")


@requires_cuda
def test_cuda_side_stream_and_current_device():
    """Kernels launch on the current stream: results on a side stream equal the default-stream ones."""
    pts = lidar_cloud(2, 30000, seed=130).float().cuda()
    ref = (lidarops.fps(pts, 256), *lidarops.knn(pts[:, :3000], pts, 16), *lidarops.ball_query(pts[:, :3000], pts, 1.0, 16))
    s = torch.cuda.Stream()
    s.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(s):
        out = (lidarops.fps(pts, 256), *lidarops.knn(pts[:, :3000], pts, 16),
               *lidarops.ball_query(pts[:, :3000], pts, 1.0, 16))
    torch.cuda.current_stream().wait_stream(s)
    torch.cuda.synchronize()
    for a, b in zip(out, ref):
        assert_equal_report(a, b, "side stream")
    if torch.cuda.device_count() > 1:
        p1 = pts.to("cuda:1")
        assert_equal_report(lidarops.fps(p1, 256), ref[0], "cuda:1 fps")
        assert_equal_report(lidarops.knn(p1[:, :3000], p1, 16)[1], ref[2], "cuda:1 knn")


@requires_cuda
def test_cuda_mixed_device_arguments():
    p = _cloud(device="cuda")
    with pytest.raises(ValueError, match="points"):
        lidarops.knn(p, p.cpu(), 3)
    with pytest.raises(ValueError, match="lengths"):
        lidarops.fps(p, 3, lengths=torch.tensor([10, 10]))
    with pytest.raises(ValueError, match="idx"):
        lidarops.gather(p, torch.zeros(2, 3, dtype=torch.long))
