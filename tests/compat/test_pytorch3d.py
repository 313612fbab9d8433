"""lidarops.compat.pytorch3d against NumPy re-implementations of PyTorch3D's conventions.

The references follow facebookresearch/pytorch3d: ``csrc/sample_farthest_points/
sample_farthest_points_cpu.cpp`` (FPS loop: selected points get distance 0, ``std::max_element`` takes
the first maximum), ``ops/knn.py`` (``knn_points`` padding 0/0, ``knn_gather`` masks by slot),
``csrc/ball_query/ball_query_cpu.cpp`` (first K hits in index order, ``dist2 < radius2`` with
``radius2 = radius * radius`` in float32, padding -1/0). Ties: lowest index first (PyTorch3D's FPS
does the same; its kNN leaves ties unspecified and lidarops documents lower index first).

Tests taking ``device`` run on cpu and, where lidarops has its CUDA kernels, cuda (the ``device``
fixture of ``tests/conftest.py``).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lidarops.compat import pytorch3d as p3
from helpers.compat import lidar_like, np_of, sqdist, to_t


# ---------------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------------


def make_batch(kind: str, B: int, P: int, D: int, rng) -> np.ndarray:
    if kind == "uniform":
        return rng.uniform(-1.0, 1.0, (B, P, D)).astype(np.float32)
    assert D == 3
    return np.stack([lidar_like(P, rng) for _ in range(B)])


def l1dist(a, b):
    d = np.abs(a[:, None, :] - b[None, :, :])
    out = d[..., 0].copy()
    for j in range(1, a.shape[1]):
        out = out + d[..., j]
    return out


# ---------------------------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------------------------

def ref_fps(points: np.ndarray, lengths, K, starts) -> np.ndarray:
    """PyTorch3D's CPU FPS loop, cloud by cloud. Deviation kept by lidarops (docs/compat.md): an empty
    cloud gives -1 (PyTorch3D writes its start index 0 into slot 0)."""
    B = points.shape[0]
    k_list = [K] * B if isinstance(K, int) else list(K)
    k_max = max(k_list) if B else 0
    out = np.full((B, k_max), -1, dtype=np.int64)
    for b in range(B):
        n = int(lengths[b])
        kn = min(n, k_list[b])
        if kn == 0:
            continue
        p = points[b, :n]
        dists = np.full(n, np.inf, dtype=p.dtype)
        taken = np.zeros(n, dtype=bool)
        last = int(starts[b])
        out[b, 0] = last
        taken[last] = True
        for k in range(1, kn):
            d = sqdist(p[last:last + 1], p)[0]
            dists = np.where(taken, 0.0, np.minimum(dists, d)).astype(p.dtype)
            last = int(np.argmax(dists))  # std::max_element: first maximum
            out[b, k] = last
            taken[last] = True
    return out


def ref_knn(p1, p2, l1, l2, K, norm):
    B, P1 = p1.shape[:2]
    dist = np.zeros((B, P1, K), dtype=p1.dtype)
    idx = np.zeros((B, P1, K), dtype=np.int64)
    for b in range(B):
        n1, n2 = int(l1[b]), int(l2[b])
        if n1 == 0 or n2 == 0:
            continue
        d = (sqdist if norm == 2 else l1dist)(p1[b, :n1], p2[b, :n2])
        order = np.argsort(d, axis=1, kind="stable")[:, :K]
        kk = order.shape[1]
        idx[b, :n1, :kk] = order
        dist[b, :n1, :kk] = np.take_along_axis(d, order, 1)
    return dist, idx


def ref_knn_gather(x, idx, lengths):
    B, L, K = idx.shape
    out = np.stack([x[b][idx[b]] for b in range(B)]) if B else np.zeros((0, L, K, x.shape[2]), x.dtype)
    mask = np.arange(K)[None, :] >= np.asarray(lengths)[:, None]
    out[np.broadcast_to(mask[:, None, :], (B, L, K))] = 0
    return out


def ref_ball(p1, p2, l1, l2, K, radius):
    """PyTorch3D's kernels square a C++ float radius in float, for every point dtype."""
    B, P1 = p1.shape[:2]
    r2 = p1.dtype.type(np.float32(radius) * np.float32(radius))
    dist = np.zeros((B, P1, K), dtype=p1.dtype)
    idx = np.full((B, P1, K), -1, dtype=np.int64)
    for b in range(B):
        n1, n2 = int(l1[b]), int(l2[b])
        if n1 == 0 or n2 == 0:
            continue
        d = sqdist(p1[b, :n1], p2[b, :n2])
        for i in range(n1):
            hits = np.nonzero(d[i] < r2)[0][:K]
            idx[b, i, :len(hits)] = hits
            dist[b, i, :len(hits)] = d[i, hits]
    return dist, idx


def assert_equal_idx(got: torch.Tensor, want: np.ndarray):
    got = got.cpu().numpy()
    assert got.shape == want.shape, (got.shape, want.shape)
    bad = np.argwhere(got != want)
    assert bad.size == 0, f"{len(bad)} mismatches, first at {tuple(bad[0])}: got {got[tuple(bad[0])]}, " \
                          f"want {want[tuple(bad[0])]}"


def assert_close_np(got: torch.Tensor, want: np.ndarray, rtol=0.0, atol=0.0):
    g = got.detach().cpu().to(torch.float64).numpy()
    w = want.astype(np.float64)
    assert g.shape == w.shape, (g.shape, w.shape)
    diff = np.abs(g - w)
    tol = atol + rtol * np.abs(w)
    if (diff > tol).any():
        at = np.unravel_index(np.argmax(diff - tol), diff.shape)
        raise AssertionError(f"max difference {diff.max():.3g} at {at}: got {g[at]}, want {w[at]}")


# ---------------------------------------------------------------------------------------------
# sample_farthest_points
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_fps_matches_reference_ragged(device, kind):
    rng = np.random.default_rng(0)
    pts = make_batch(kind, 4, 300, 3, rng)
    lengths = np.array([300, 41, 0, 7])
    points = to_t(pts, device)
    sel_pts, idx = p3.sample_farthest_points(points, to_t(lengths, device, torch.int64), K=48)
    want = ref_fps(pts, lengths, 48, [0] * 4)
    assert idx.dtype == torch.int64 and idx.shape == (4, 48)
    assert_equal_idx(idx, want)
    want_pts = np.where((want >= 0)[..., None], np.take_along_axis(pts, np.maximum(want, 0)[..., None], 1), 0.0)
    assert sel_pts.dtype == points.dtype
    assert_close_np(sel_pts, want_pts)


def test_fps_duplicates_repeat_index_zero(device):
    # 5 distinct locations, each repeated: after 5 picks PyTorch3D's kernels return index 0 again
    rng = np.random.default_rng(1)
    base = rng.uniform(-5, 5, (5, 3)).astype(np.float32)
    cloud = base[rng.integers(0, 5, 60)]
    cloud[0] = base[0]
    same = np.zeros((60, 3), np.float32) + 3.0
    pts = np.stack([cloud, same])
    points = to_t(pts, device)
    _, idx = p3.sample_farthest_points(points, K=12)
    want = ref_fps(pts, [60, 60], 12, [0, 0])
    assert_equal_idx(idx, want)
    assert (want[0, 5:] == 0).all() and len(set(want[0, :5])) == 5
    assert (want[1] == 0).all()


def test_fps_per_cloud_k_and_k_larger_than_lengths(device):
    rng = np.random.default_rng(2)
    pts = make_batch("uniform", 3, 50, 3, rng)
    lengths = np.array([50, 9, 30])
    Ks = [20, 15, 0]
    points = to_t(pts, device)
    want = ref_fps(pts, lengths, Ks, [0, 0, 0])
    for K in (Ks, torch.tensor(Ks, device=device)):
        sel_pts, idx = p3.sample_farthest_points(points, to_t(lengths, device, torch.int64), K=K)
        assert idx.shape == (3, 20) and sel_pts.shape == (3, 20, 3)
        assert_equal_idx(idx, want)
        assert (sel_pts[idx < 0] == 0).all()
    _, idx = p3.sample_farthest_points(points, K=0)
    assert idx.shape == (3, 0)


def test_fps_random_start_follows_pytorch3d_rng(device):
    rng = np.random.default_rng(3)
    pts = make_batch("uniform", 3, 80, 3, rng)
    lengths = np.array([80, 33, 1])
    torch.manual_seed(1234)
    _, idx = p3.sample_farthest_points(to_t(pts, device), to_t(lengths, device, torch.int64), K=10,
                                       random_start_point=True)
    # PyTorch3D: start_idxs[n] = torch.randint(high=lengths[n], size=(1,)).item(), cloud by cloud
    torch.manual_seed(1234)
    starts = [torch.randint(high=int(n), size=(1,)).item() for n in lengths]
    assert_equal_idx(idx, ref_fps(pts, lengths, 10, starts))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
def test_fps_dtypes(device, dtype):
    rng = np.random.default_rng(4)
    points = to_t(make_batch("uniform", 2, 120, 3, rng) * 10, device, dtype)
    sel, idx = p3.sample_farthest_points(points, K=16)
    assert sel.dtype == dtype
    assert_equal_idx(idx, ref_fps(np_of(points), [120, 120], 16, [0, 0]))


@pytest.mark.parametrize("D", [1, 2, 5])
def test_fps_other_dimensions(device, D):
    rng = np.random.default_rng(5)
    pts = make_batch("uniform", 2, 70, D, rng)
    pts[1, 10:20] = pts[1, 0]  # duplicates
    lengths = np.array([70, 25])
    _, idx = p3.sample_farthest_points(to_t(pts, device), to_t(lengths, device, torch.int64), K=30)
    assert_equal_idx(idx, ref_fps(pts, lengths, 30, [0, 0]))


def test_fps_non_contiguous_and_gradient(device):
    rng = np.random.default_rng(6)
    base = torch.as_tensor(rng.uniform(-1, 1, (2, 3, 40))).to(device)
    points = base.transpose(1, 2)  # (2, 40, 3), not contiguous
    assert not points.is_contiguous()
    _, idx = p3.sample_farthest_points(points, K=8)
    assert_equal_idx(idx, ref_fps(np_of(points), [40, 40], 8, [0, 0]))
    small = points[:, :12].clone().requires_grad_(True)
    lengths = torch.tensor([12, 5], device=device)
    assert torch.autograd.gradcheck(lambda p: p3.sample_farthest_points(p, lengths, K=7)[0], (small,),
                                    fast_mode=True)


def test_fps_bad_input(device):
    p = torch.rand(2, 10, 3, device=device)
    with pytest.raises(ValueError, match="points"):
        p3.sample_farthest_points(p[0], K=3)
    with pytest.raises(ValueError, match="lengths"):
        p3.sample_farthest_points(p, torch.tensor([10], device=device), K=3)
    with pytest.raises(ValueError, match="lengths"):
        p3.sample_farthest_points(p, torch.tensor([11, 3], device=device), K=3)
    with pytest.raises(ValueError, match="K"):
        p3.sample_farthest_points(p, K=[3])
    with pytest.raises(ValueError, match="K"):
        p3.sample_farthest_points(p, K=-1)
    with pytest.raises(ValueError, match="K"):
        p3.sample_farthest_points(p, K=torch.tensor([1.0, 2.0]))
    bad = p.clone()
    bad[1, 3, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        p3.sample_farthest_points(bad, K=3)


# ---------------------------------------------------------------------------------------------
# knn_points / knn_gather
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
@pytest.mark.parametrize("norm", [2, 1])
def test_knn_points_matches_reference(device, kind, norm):
    rng = np.random.default_rng(10)
    a = make_batch(kind, 3, 150, 3, rng)
    b = make_batch(kind, 3, 200, 3, rng)
    l1, l2 = np.array([150, 60, 0]), np.array([200, 5, 40])
    out = p3.knn_points(to_t(a, device), to_t(b, device), to_t(l1, device, torch.int64),
                        to_t(l2, device, torch.int64), norm=norm, K=8, return_nn=True)
    want_d, want_i = ref_knn(a, b, l1, l2, 8, norm)
    assert isinstance(out, p3._KNN) and out.idx.dtype == torch.int64
    assert_equal_idx(out.idx, want_i)
    # same left-to-right rounding as the reference: the core kernel (norm 2) and the dense path (norm 1)
    assert_close_np(out.dists, want_d)
    assert_close_np(out.knn, ref_knn_gather(b, want_i, l2))


def test_knn_points_ties_lower_index_first(device):
    # integer lattice: many exactly equal distances
    rng = np.random.default_rng(11)
    b = rng.integers(-2, 3, (1, 60, 3)).astype(np.float32)
    a = rng.integers(-2, 3, (1, 20, 3)).astype(np.float32)
    for norm in (2, 1):
        out = p3.knn_points(to_t(a, device), to_t(b, device), norm=norm, K=10)
        want_d, want_i = ref_knn(a, b, [20], [60], 10, norm)
        assert_equal_idx(out.idx, want_i)
        assert_close_np(out.dists, want_d)


def test_knn_points_padding_and_empty(device):
    rng = np.random.default_rng(12)
    a = make_batch("uniform", 2, 10, 3, rng)
    b = make_batch("uniform", 2, 4, 3, rng)
    out = p3.knn_points(to_t(a, device), to_t(b, device), to_t([10, 3], device, torch.int64),
                        to_t([4, 2], device, torch.int64), K=6)
    want_d, want_i = ref_knn(a, b, [10, 3], [4, 2], 6, 2)
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d)
    assert (out.idx[1, 3:] == 0).all() and (out.dists[1, 3:] == 0).all()  # padded query rows
    assert out.knn is None
    empty = p3.knn_points(to_t(a, device), torch.zeros(2, 0, 3, device=device), K=3)
    assert empty.idx.shape == (2, 10, 3) and (empty.idx == 0).all() and (empty.dists == 0).all()
    none = p3.knn_points(torch.zeros(2, 0, 3, device=device), to_t(b, device), K=3)
    assert none.dists.shape == (2, 0, 3)


@pytest.mark.parametrize("D", [2, 5])
def test_knn_points_other_dimensions(device, D):
    rng = np.random.default_rng(13)
    a = make_batch("uniform", 2, 40, D, rng)
    b = make_batch("uniform", 2, 70, D, rng)
    l1, l2 = np.array([40, 13]), np.array([70, 3])
    for norm in (1, 2):
        out = p3.knn_points(to_t(a, device), to_t(b, device), to_t(l1, device, torch.int64),
                            to_t(l2, device, torch.int64), norm=norm, K=5)
        want_d, want_i = ref_knn(a, b, l1, l2, 5, norm)
        assert_equal_idx(out.idx, want_i)
        assert_close_np(out.dists, want_d, rtol=1e-6 if D > 4 else 0.0)  # D > 4 sums with torch.sum


@pytest.mark.parametrize("dtype", [torch.float64, torch.float16, torch.bfloat16])
def test_knn_points_dtypes(device, dtype):
    rng = np.random.default_rng(14)
    a = to_t(make_batch("uniform", 2, 30, 3, rng) * 4, device, dtype)
    b = to_t(make_batch("uniform", 2, 50, 3, rng) * 4, device, dtype)
    out = p3.knn_points(a, b, K=4)
    assert out.dists.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    want_d, want_i = ref_knn(np_of(a), np_of(b), [30, 30], [50, 50], 4, 2)
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d)


@pytest.mark.parametrize("norm,D", [(2, 3), (1, 3), (2, 4)])
def test_knn_points_gradients(device, norm, D):
    gen = torch.Generator().manual_seed(15)
    a = torch.rand(2, 6, D, generator=gen, dtype=torch.float64).to(device).requires_grad_(True)
    b = torch.rand(2, 9, D, generator=gen, dtype=torch.float64).to(device).requires_grad_(True)
    l1 = torch.tensor([6, 4], device=device)
    l2 = torch.tensor([9, 2], device=device)
    assert torch.autograd.gradcheck(lambda x, y: p3.knn_points(x, y, l1, l2, norm=norm, K=3).dists, (a, b),
                                    fast_mode=True)
    # padded neighbours and padded query rows carry no gradient
    p3.knn_points(a, b, l1, l2, norm=norm, K=3).dists.sum().backward()
    assert (a.grad[1, 4:] == 0).all() and (b.grad[1, 2:] == 0).all()


def test_knn_gather_masks_by_slot(device):
    rng = np.random.default_rng(16)
    x = rng.normal(size=(2, 7, 5)).astype(np.float32)
    idx = rng.integers(0, 7, (2, 4, 6))
    lengths = np.array([7, 3])
    got = p3.knn_gather(to_t(x, device), to_t(idx, device, torch.int64), to_t(lengths, device, torch.int64))
    assert got.shape == (2, 4, 6, 5)
    assert_close_np(got, ref_knn_gather(x, idx, lengths))
    xt = to_t(x, device, torch.float64).requires_grad_(True)
    it = to_t(idx, device, torch.int64)
    lt = to_t(lengths, device, torch.int64)
    assert torch.autograd.gradcheck(lambda v: p3.knn_gather(v, it, lt), (xt,), fast_mode=True)


def test_knn_points_bad_input():
    a, b = torch.rand(2, 5, 3), torch.rand(2, 6, 3)
    # squared distances of 1e20 coordinates overflow float32: refused, not returned as 0 or inf
    with pytest.raises(ValueError, match="p2 has a coordinate of magnitude"):
        p3.knn_points(a, b * 1e20, K=2)
    with pytest.raises(ValueError, match="p1 has a coordinate of magnitude"):
        p3.ball_query(a * 1e20, b, K=2, radius=0.5)
    with pytest.raises(ValueError, match="points has a coordinate of magnitude"):
        p3.sample_farthest_points(a * 1e20, K=2)
    with pytest.raises(ValueError, match="random_start_point must be True or False"):
        p3.sample_farthest_points(a, K=2, random_start_point="no")
    with pytest.raises(ValueError, match="Support for 1 or 2 norm"):
        p3.knn_points(a, b, norm=3)
    with pytest.raises(ValueError, match="batch"):
        p3.knn_points(a, torch.rand(3, 6, 3))
    with pytest.raises(ValueError, match="point dimension"):
        p3.knn_points(a, torch.rand(2, 6, 4))
    with pytest.raises(ValueError, match="dtype"):
        p3.knn_points(a, b.double())
    with pytest.raises(ValueError, match="K"):
        p3.knn_points(a, b, K=0)
    with pytest.raises(ValueError, match="lengths2"):
        p3.knn_points(a, b, lengths2=torch.tensor([7, 1]))
    with pytest.raises(ValueError, match="p1"):
        p3.knn_points(a[0], b)
    with pytest.raises(ValueError, match="idx"):
        p3.knn_gather(torch.rand(2, 5, 3), torch.zeros(2, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match="idx"):
        p3.knn_gather(torch.rand(2, 5, 3), torch.full((2, 4, 2), 5))


# ---------------------------------------------------------------------------------------------
# ball_query
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind,radius", [("uniform", 0.3), ("lidar", 2.5)])
def test_ball_query_matches_reference(device, kind, radius):
    rng = np.random.default_rng(20)
    a = make_batch(kind, 3, 100, 3, rng)
    b = make_batch(kind, 3, 400, 3, rng)
    l1, l2 = np.array([100, 31, 5]), np.array([400, 90, 0])
    out = p3.ball_query(to_t(a, device), to_t(b, device), to_t(l1, device, torch.int64),
                        to_t(l2, device, torch.int64), K=12, radius=radius)
    want_d, want_i = ref_ball(a, b, l1, l2, 12, radius)
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d)
    want_nn = np.where((want_i >= 0)[..., None],
                       np.stack([b[i][np.maximum(want_i[i], 0)] for i in range(3)]), 0.0)
    assert_close_np(out.knn, want_nn)


def test_ball_query_strict_radius_and_index_order(device):
    # points exactly on the sphere are outside (dist2 == radius2 is not < radius2); hits are the first
    # K in index order, not the nearest
    a = torch.zeros(1, 1, 3, device=device)
    b = torch.tensor([[[0.5, 0, 0], [0.4, 0, 0], [0, 0.5, 0], [0.3, 0, 0], [0.01, 0, 0], [0, 0, 0.1]]],
                     device=device)
    out = p3.ball_query(a, b, K=2, radius=0.5)
    assert out.idx.tolist() == [[[1, 3]]]
    out = p3.ball_query(a, b, K=6, radius=0.5)
    assert out.idx.tolist() == [[[1, 3, 4, 5, -1, -1]]]
    assert out.dists[0, 0, 4:].tolist() == [0.0, 0.0]
    assert out.knn[0, 0, 4:].abs().sum().item() == 0


def test_ball_query_other_dimensions_dtypes_and_gradient(device):
    rng = np.random.default_rng(21)
    a = make_batch("uniform", 2, 30, 5, rng)
    b = make_batch("uniform", 2, 60, 5, rng)
    out = p3.ball_query(to_t(a, device), to_t(b, device), K=7, radius=0.9)
    want_d, want_i = ref_ball(a, b, [30, 30], [60, 60], 7, 0.9)
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d, rtol=1e-6)  # D > 4 sums with torch.sum
    a64 = to_t(make_batch("uniform", 2, 20, 3, rng), device, torch.float64)
    b64 = to_t(make_batch("uniform", 2, 30, 3, rng), device, torch.float64)
    out = p3.ball_query(a64, b64, K=5, radius=0.6)
    want_d, want_i = ref_ball(np_of(a64), np_of(b64), [20, 20], [30, 30], 5, 0.6)
    assert out.dists.dtype == torch.float64
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d)
    x = a64[:, :5].clone().requires_grad_(True)
    y = b64.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u, v: p3.ball_query(u, v, K=4, radius=0.7).dists, (x, y),
                                    fast_mode=True)


def test_ball_query_float64_uses_float32_radius_square(device):
    # for float64 points PyTorch3D still compares with float32(r) * float32(r): a point between the
    # float64 square and that value is inside
    r = 0.1
    lo64, hi32 = r * r, float(np.float32(r) * np.float32(r))
    assert lo64 < hi32
    x = math.sqrt((lo64 + hi32) / 2)
    b = torch.tensor([[[0.0, x, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0, 0.2]]], dtype=torch.float64, device=device)
    a = torch.zeros(1, 1, 3, dtype=torch.float64, device=device, requires_grad=True)
    out = p3.ball_query(a, b, K=3, radius=r)
    want_d, want_i = ref_ball(np_of(a), np_of(b), [1], [3], 3, r)
    assert want_i.tolist() == [[[0, 1, -1]]]
    assert_equal_idx(out.idx, want_i)
    assert_close_np(out.dists, want_d)
    out.dists.sum().backward()  # the filtered path keeps the distances differentiable
    torch.testing.assert_close(a.grad[0, 0], -2 * (b[0, 0] + b[0, 1]))


def test_ball_query_bad_input():
    a, b = torch.rand(2, 5, 3), torch.rand(2, 6, 3)
    with pytest.raises(ValueError, match="radius"):
        p3.ball_query(a, b, radius=-0.1)
    with pytest.raises(ValueError, match="radius"):
        p3.ball_query(a, b, radius=float("nan"))
    with pytest.raises(ValueError, match="K"):
        p3.ball_query(a, b, K=0)
    with pytest.raises(ValueError, match="batch"):
        p3.ball_query(a, torch.rand(1, 6, 3))
    bad = b.clone()
    bad[0, 0, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        p3.ball_query(a, bad)
    bad[0, 0, 0] = math.inf
    with pytest.raises(ValueError, match="p2 contains NaN or infinite"):
        p3.ball_query(a, bad)
    with pytest.raises(ValueError, match="p1 contains NaN or infinite"):
        p3.knn_points(bad, b, norm=1)


def test_import_is_light():
    import subprocess
    import sys
    code = "import sys, lidarops.compat as c; assert 'torch' not in sys.modules; " \
           "assert sorted(c.__all__) == ['mmcv', 'pcdet', 'pytorch3d', 'spconv', 'spconv_utils', 'torch_cluster']"
    subprocess.run([sys.executable, "-c", code], check=True)
