"""lidarops.compat.torch_cluster against NumPy re-implementations of torch_cluster's kernels.

The references follow rusty1s/pytorch_cluster: ``torch_cluster/fps.py`` + ``csrc/cpu/fps_cpu.cpp``
(per example ``ceil(float32(deg) * ratio)`` samples with ``ratio`` in ``src.dtype``; ``dist`` from the
start, then ``argmax`` / ``min`` updates, so the first row repeats once every distance is 0),
``csrc/cuda/knn_cuda.cu`` (per query, ascending distance with strict ``>`` insertion: ties to the
lower index; edge index [row = y, col = x]), ``csrc/cuda/radius_cuda.cu`` (x in index order,
``dist < r * r`` with ``r * r`` in double rounded to the point dtype, the first ``max_num_neighbors``).

Tests taking ``device`` run on cpu and, where lidarops has its CUDA kernels, cuda (the ``device``
fixture of ``tests/conftest.py``).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lidarops.compat import torch_cluster as tc
from helpers.compat import assert_equal, lidar_like, np_of, sqdist, to_t


def assert_equal_int64(got, want):
    """torch_cluster's indices are int64 and must equal the reference exactly."""
    assert_equal(got, want, torch.int64)


def flat_batch(kind, sizes, F, rng):
    """Concatenated examples (sizes may contain 0) and their sorted batch vector."""
    if kind == "uniform":
        parts = [rng.uniform(-1.0, 1.0, (n, F)).astype(np.float32) for n in sizes]
    else:
        parts = [lidar_like(n, rng) if n else np.zeros((0, 3), np.float32) for n in sizes]
    return np.concatenate(parts), np.repeat(np.arange(len(sizes)), sizes)


def ptr_of(batch, B):
    return np.concatenate([[0], np.cumsum(np.bincount(batch, minlength=B))])


# ---------------------------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------------------------

def ref_fps(src, batch, ratio32, starts=None):
    """``ratio32``: the ratio as torch_cluster uses it (a tensor of ``src.dtype``, multiplied in float32)."""
    B = int(batch.max()) + 1 if len(batch) else 1
    ptr = ptr_of(batch, B)
    out = []
    for b in range(B):
        p = src[ptr[b]:ptr[b + 1]]
        deg = len(p)
        n = int(np.ceil(np.float32(deg) * np.float32(ratio32)))
        if n == 0:
            continue
        s = 0 if starts is None else int(starts[b])
        sel = [s]
        dist = sqdist(p[s:s + 1], p)[0]
        for _ in range(1, n):
            a = int(np.argmax(dist))  # first maximum
            sel.append(a)
            dist = np.minimum(dist, sqdist(p[a:a + 1], p)[0])
        out.extend(ptr[b] + np.array(sel))
    return np.array(out, dtype=np.int64)


def ref_knn(x, y, k, bx, by, cosine=False):
    B = max(int(bx.max()) + 1 if len(bx) else 1, int(by.max()) + 1 if len(by) else 1)
    px, py = ptr_of(bx, B), ptr_of(by, B)
    rows, cols = [], []
    for b in range(B):
        xs = x[px[b]:px[b + 1]]
        for i in range(py[b], py[b + 1]):
            if not len(xs):
                continue
            if cosine:
                xx, yy = xs.astype(np.float64), y[i].astype(np.float64)
                d = 1 - xx @ yy / (np.linalg.norm(xx, axis=1) * np.linalg.norm(yy))
            else:
                d = sqdist(y[i:i + 1], xs)[0]
            order = np.argsort(d, kind="stable")[:k]
            rows.extend([i] * len(order))
            cols.extend(px[b] + order)
    return np.array([rows, cols], dtype=np.int64).reshape(2, -1)


def ref_radius(x, y, r, bx, by, max_nb, dtype=np.float32):
    B = max(int(bx.max()) + 1 if len(bx) else 1, int(by.max()) + 1 if len(by) else 1)
    px, py = ptr_of(bx, B), ptr_of(by, B)
    r2 = dtype(r * r)  # double product rounded to the point dtype
    rows, cols = [], []
    for b in range(B):
        xs = x[px[b]:px[b + 1]]
        for i in range(py[b], py[b + 1]):
            if not len(xs):
                continue
            hits = np.nonzero(sqdist(y[i:i + 1], xs)[0] < r2)[0][:max_nb]
            rows.extend([i] * len(hits))
            cols.extend(px[b] + hits)
    return np.array([rows, cols], dtype=np.int64).reshape(2, -1)


# ---------------------------------------------------------------------------------------------
# fps
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
@pytest.mark.parametrize("ratio", [0.5, 0.3, 1.0, 0.07])
def test_fps_matches_reference(device, kind, ratio):
    rng = np.random.default_rng(0)
    src, batch = flat_batch(kind, [120, 10, 0, 33, 1], 3, rng)
    got = tc.fps(to_t(src, device), to_t(batch, device, torch.int64), ratio, random_start=False)
    assert_equal_int64(got, ref_fps(src, batch, ratio))


def test_fps_rounding_follows_float32(device):
    # ceil(float32(deg) * float32(ratio)): 100 * 0.07 is exactly 7.0 in float32 (7 samples) where double
    # arithmetic gives 7.000000000000001 (8 samples)
    rng = np.random.default_rng(1)
    assert math.ceil(100 * 0.07) == 8
    for deg, ratio, n in [(10, 0.3, 3), (7, 0.1, 1), (100, 0.07, 7)]:
        assert int(np.ceil(np.float32(deg) * np.float32(ratio))) == n
        src = rng.uniform(-1, 1, (deg, 3)).astype(np.float32)
        got = tc.fps(to_t(src, device), None, ratio, random_start=False)
        assert got.numel() == n
        assert_equal_int64(got, ref_fps(src, np.zeros(deg, np.int64), ratio))


def test_fps_duplicates_repeat_first_row(device):
    rng = np.random.default_rng(2)
    base = rng.uniform(-2, 2, (3, 3)).astype(np.float32)
    a = base[rng.integers(0, 3, 20)]
    a[0] = base[1]
    b = np.full((12, 3), 4.0, np.float32)
    src, batch = np.concatenate([a, b]), np.repeat([0, 1], [20, 12])
    got = tc.fps(to_t(src, device), to_t(batch, device, torch.int64), 0.5, random_start=False)
    want = ref_fps(src, batch, 0.5)
    assert_equal_int64(got, want)
    assert (want[3:10] == 0).all() and (want[10:] == 20).all()


def test_fps_random_start(device):
    rng = np.random.default_rng(3)
    src, batch = flat_batch("uniform", [50, 30, 9], 3, rng)
    s, b = to_t(src, device), to_t(batch, device, torch.int64)
    torch.manual_seed(7)
    got = tc.fps(s, b, 0.4, random_start=True)
    torch.manual_seed(7)
    again = tc.fps(s, b, 0.4, random_start=True)
    assert torch.equal(got, again)
    # every example starts inside itself and continues as FPS from that start
    ptr = ptr_of(batch, 3)
    counts = [int(np.ceil(np.float32(n) * np.float32(0.4))) for n in (50, 30, 9)]
    firsts = np.cumsum([0] + counts[:-1])
    starts = got.cpu().numpy()[firsts] - ptr[:3]
    assert ((starts >= 0) & (starts < np.array([50, 30, 9]))).all()
    assert_equal_int64(got, ref_fps(src, batch, 0.4, starts))


@pytest.mark.parametrize("F", [1, 2, 6])
def test_fps_other_feature_sizes(device, F):
    rng = np.random.default_rng(4)
    src, batch = flat_batch("uniform", [40, 25], F, rng)
    x = to_t(src, device)
    if F == 1:
        x = x.view(-1)  # torch_cluster treats a vector as one feature per row
    got = tc.fps(x, to_t(batch, device, torch.int64), 0.25, random_start=False)
    assert_equal_int64(got, ref_fps(src, batch, 0.25))


def test_fps_ptr_tensor_ratio_and_dtypes(device):
    rng = np.random.default_rng(5)
    src, batch = flat_batch("uniform", [30, 20], 3, rng)
    want = ref_fps(src, batch, 0.5)
    assert_equal_int64(tc.fps(to_t(src, device), ptr=[0, 30, 50], ratio=0.5, random_start=False), want)
    ratio = torch.tensor(0.5, device=device)
    assert_equal_int64(tc.fps(to_t(src, device), to_t(batch, device, torch.int64), ratio, False), want)
    for dtype in (torch.float64, torch.float16):
        x = to_t(src * 50, device, dtype)
        got = tc.fps(x, to_t(batch, device, torch.int64), 0.3, random_start=False)
        ratio_in_dtype = torch.tensor(0.3, dtype=dtype).to(torch.float32).item()
        assert_equal_int64(got, ref_fps(np_of(x), batch, ratio_in_dtype))


def test_fps_bad_input():
    x = torch.rand(10, 3)
    with pytest.raises(ValueError, match="sorted"):
        tc.fps(x, torch.tensor([0, 0, 1, 1, 0, 1, 1, 1, 1, 1]))
    with pytest.raises(ValueError, match="ratio"):
        tc.fps(x, ratio=0.0)
    with pytest.raises(ValueError, match="ratio"):
        tc.fps(x, ratio=1.5)
    with pytest.raises(ValueError, match="batch"):
        tc.fps(x, torch.zeros(9, dtype=torch.int64))
    with pytest.raises(ValueError, match="batch"):
        tc.fps(x, torch.zeros(10))
    with pytest.raises(ValueError, match=">= 0"):
        tc.fps(x, torch.full((10,), -1))
    bad = x.clone()
    bad[3, 1] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        tc.fps(bad)


# ---------------------------------------------------------------------------------------------
# knn
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["uniform", "lidar"])
def test_knn_matches_reference(device, kind):
    rng = np.random.default_rng(10)
    x, bx = flat_batch(kind, [200, 0, 5, 60], 3, rng)
    y, by = flat_batch(kind, [30, 4, 8, 0], 3, rng)
    got = tc.knn(to_t(x, device), to_t(y, device), 7, to_t(bx, device, torch.int64), to_t(by, device, torch.int64))
    assert_equal_int64(got, ref_knn(x, y, 7, bx, by))


def test_knn_ties_single_example_and_empty(device):
    rng = np.random.default_rng(11)
    x = rng.integers(-2, 3, (50, 3)).astype(np.float32)  # lattice: equal distances
    y = rng.integers(-2, 3, (12, 3)).astype(np.float32)
    zeros = np.zeros(50, np.int64)
    got = tc.knn(to_t(x, device), to_t(y, device), 9)
    assert_equal_int64(got, ref_knn(x, y, 9, zeros, np.zeros(12, np.int64)))
    assert tc.knn(torch.zeros(0, 3, device=device), to_t(y, device), 3).shape == (2, 0)
    assert tc.knn(to_t(x, device), torch.zeros(0, 3, device=device), 3).shape == (2, 0)


@pytest.mark.parametrize("F", [2, 8])
def test_knn_features_and_cosine(device, F):
    rng = np.random.default_rng(12)
    x, bx = flat_batch("uniform", [40, 25], F, rng)
    y, by = flat_batch("uniform", [10, 6], F, rng)
    args = (to_t(bx, device, torch.int64), to_t(by, device, torch.int64))
    assert_equal_int64(tc.knn(to_t(x, device), to_t(y, device), 4, *args), ref_knn(x, y, 4, bx, by))
    got = tc.knn(to_t(x, device), to_t(y, device), 4, *args, cosine=True)
    assert_equal_int64(got, ref_knn(x, y, 4, bx, by, cosine=True))


def test_knn_bad_input():
    x, y = torch.rand(10, 3), torch.rand(4, 3)
    with pytest.raises(ValueError, match="both"):
        tc.knn(x, y, 2, torch.repeat_interleave(torch.tensor([0, 1]), 5), None)
    with pytest.raises(ValueError, match="sorted"):
        tc.knn(x, y, 2, torch.tensor([1, 1, 0, 0, 0, 0, 0, 0, 1, 1]), torch.tensor([0, 0, 1, 1]))
    with pytest.raises(ValueError, match="features"):
        tc.knn(x, torch.rand(4, 2), 2)
    with pytest.raises(ValueError, match="k"):
        tc.knn(x, y, 0)
    with pytest.raises(ValueError, match="dtype"):
        tc.knn(x, y.double(), 2)


# ---------------------------------------------------------------------------------------------
# radius
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kind,r,max_nb", [("uniform", 0.3, 32), ("uniform", 0.5, 5), ("lidar", 3.0, 16)])
def test_radius_matches_reference(device, kind, r, max_nb):
    rng = np.random.default_rng(20)
    x, bx = flat_batch(kind, [300, 7, 0, 90], 3, rng)
    y, by = flat_batch(kind, [40, 3, 5, 12], 3, rng)
    got = tc.radius(to_t(x, device), to_t(y, device), r, to_t(bx, device, torch.int64),
                    to_t(by, device, torch.int64), max_num_neighbors=max_nb)
    assert_equal_int64(got, ref_radius(x, y, r, bx, by, max_nb))


def test_radius_threshold_is_rounded_double_square(device):
    # torch_cluster compares with float32(r * r) computed in double (0.0099999998 for r = 0.1), not with
    # float32(r) * float32(r) (0.0100000007). Points at squared distance exactly float32(r * r) are
    # outside for torch_cluster and would be inside under the other rule.
    r = 0.1
    f = np.float32
    t_cluster, t_square = f(r * r), f(r) * f(r)
    assert t_cluster < t_square
    on_sphere = []
    for k in range(1, 200):
        b = f(k * 1e-4)
        a0 = f(math.sqrt(float(t_cluster) - float(b * b)))
        for a in (a0, np.nextafter(a0, f(0)), np.nextafter(a0, f(1))):
            if (a * a + b * b) + f(0) == t_cluster:
                on_sphere.append([a, b, 0])
                break
        if len(on_sphere) == 3:
            break
    assert on_sphere
    x = np.array(on_sphere + [[0.05, 0, 0], [0, 0.0999, 0]], np.float32)
    y = np.zeros((1, 3), np.float32)
    got = tc.radius(to_t(x, device), to_t(y, device), r)
    want = ref_radius(x, y, r, np.zeros(len(x), np.int64), np.zeros(1, np.int64), 32)
    assert want[1].tolist() == [len(on_sphere), len(on_sphere) + 1]
    assert_equal_int64(got, want)


def test_radius_many_candidates_and_features(device):
    rng = np.random.default_rng(21)
    # dense cluster: every query has far more than max_num_neighbors hits; the first ones in index
    # order are kept (torch_cluster's CUDA kernel)
    x = rng.normal(0, 0.05, (400, 3)).astype(np.float32)
    y = x[:20]
    z = np.zeros(400, np.int64)
    got = tc.radius(to_t(x, device), to_t(y, device), 0.2, max_num_neighbors=8)
    assert_equal_int64(got, ref_radius(x, y, 0.2, z, z[:20], 8))
    x5, bx = flat_batch("uniform", [60, 30], 5, rng)
    y5, by = flat_batch("uniform", [10, 10], 5, rng)
    got = tc.radius(to_t(x5, device), to_t(y5, device), 0.9, to_t(bx, device, torch.int64),
                    to_t(by, device, torch.int64), max_num_neighbors=6)
    assert_equal_int64(got, ref_radius(x5, y5, 0.9, bx, by, 6))
    x64 = to_t(x, device, torch.float64)
    got = tc.radius(x64, x64[:20], 0.2, max_num_neighbors=8)
    assert_equal_int64(got, ref_radius(np_of(x64), np_of(x64)[:20], 0.2, z, z[:20], 8, dtype=np.float64))


def test_radius_bad_input():
    x, y = torch.rand(10, 3), torch.rand(4, 3)
    with pytest.raises(ValueError, match="r must"):
        tc.radius(x, y, -1.0)
    with pytest.raises(ValueError, match="max_num_neighbors"):
        tc.radius(x, y, 0.5, max_num_neighbors=0)
    with pytest.raises(ValueError, match="sorted"):
        tc.radius(x, y, 0.5, torch.tensor([0, 1, 0, 1, 0, 1, 0, 1, 0, 1]), torch.tensor([0, 0, 1, 1]))
    with pytest.raises(ValueError, match="batch_y"):
        tc.radius(x, y, 0.5, torch.zeros(10, dtype=torch.int64), torch.zeros(3, dtype=torch.int64))
    bad = y.clone()
    bad[0, 0] = math.nan
    with pytest.raises(ValueError, match="NaN"):
        tc.radius(x, bad, 0.5)
    bad[0, 0] = math.inf
    with pytest.raises(ValueError, match="y contains NaN or infinite"):
        tc.knn(x, bad, 2)
