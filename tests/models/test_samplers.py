"""The samplers of lidarops.models.samplers: random (seeded), FPS, chunked FPS, the spatial segments and shares
they are built on, sample_features, and the argument checks every sampler shares."""
from __future__ import annotations

import math

import pytest
import torch

import lidarops
from lidarops.models.samplers import (ChunkedFPSSampler, FPSSampler, RandomSampler, sample_features,
                                      segment_shares, spatial_segments)
from lidarops.ops.neighbors import _fps_reference

from helpers.clouds import lidar_cloud, uniform_cloud
from helpers.devices import requires_cuda


pytestmark = pytest.mark.usefixtures("one_thread")  # tiny tensors: OpenMP wake-ups cost more than the work
SAMPLERS = [RandomSampler(3), FPSSampler(), ChunkedFPSSampler(16)]


def _with_intensity(xyz: torch.Tensor, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.cat([xyz, torch.rand(*xyz.shape[:2], 1, generator=g, dtype=xyz.dtype).to(xyz.device)], -1)


def _assert_valid_sample(idx: torch.Tensor, m: int, lengths: list[int]) -> None:
    """(B, m) int64; per cloud min(m, n) distinct indices in [0, n), then -1."""
    assert idx.dtype == torch.int64 and tuple(idx.shape) == (len(lengths), m)
    for b, n in enumerate(lengths):
        k = min(m, n)
        row = idx[b].cpu()
        assert bool((row[k:] == -1).all()), f"cloud {b}: expected -1 past {k}, got {row.tolist()}"
        head = row[:k]
        assert bool(((head >= 0) & (head < n)).all()), f"cloud {b}: indices out of [0, {n}): {head.tolist()}"
        assert head.unique().numel() == k, f"cloud {b}: repeated indices {head.tolist()}"


# ---- random sampling ----

def test_random_reproducible_and_distinct(device):
    pts = uniform_cloud(3, 50, seed=1).float().to(device)
    lengths = torch.tensor([50, 7, 0], device=device)
    a, b = RandomSampler(11), RandomSampler(11)
    first = [a(pts, 20, lengths) for _ in range(3)]
    second = [b(pts, 20, lengths) for _ in range(3)]
    for x, y in zip(first, second):
        assert torch.equal(x, y)
        assert x.device == pts.device
        _assert_valid_sample(x, 20, [50, 7, 0])
    assert not torch.equal(first[0], first[1]), "successive calls should draw new subsets"
    assert not torch.equal(first[0], RandomSampler(12)(pts, 20, lengths)), "another seed, same subset"
    a.reset()
    assert torch.equal(a(pts, 20, lengths), first[0])


def test_random_is_a_uniform_permutation():
    """Every point equally likely: over many draws each of 10 points is picked about m/n of the time."""
    s = RandomSampler(0)
    pts = torch.zeros(1, 10, 3)
    counts = torch.zeros(10)
    for _ in range(400):
        counts += torch.bincount(s(pts, 3)[0], minlength=10)
    assert counts.sum() == 1200
    assert bool(((counts - 120).abs() < 40).all()), counts.tolist()  # ~5 sigma


@requires_cuda
def test_random_cpu_and_cuda_agree():
    pts = uniform_cloud(2, 40).float()
    assert torch.equal(RandomSampler(5)(pts, 9).cpu(), RandomSampler(5)(pts.cuda(), 9).cpu())


# ---- FPS ----

@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fps_sampler_equals_lidarops_fps(device, dtype):
    xyz = lidar_cloud(2, 300, seed=2).to(device, dtype)
    pts = _with_intensity(xyz)
    lengths = torch.tensor([300, 123], device=device)
    got = FPSSampler()(pts, 40, lengths)
    assert torch.equal(got, lidarops.fps(xyz, 40, lengths=lengths))
    assert torch.equal(got.cpu(), _fps_reference(xyz.cpu(), 40, lengths.cpu()))
    _assert_valid_sample(got, 40, [300, 123])


def test_fps_sampler_pads_short_clouds():
    pts = uniform_cloud(1, 5).float()
    got = FPSSampler()(pts, 8)
    _assert_valid_sample(got, 8, [5])


# ---- spatial segments and shares ----

def test_spatial_segments_partition_balanced():
    xyz = lidar_cloud(1, 2000, seed=3)[0]
    for max_points in (1, 7, 500, 666, 667, 1999, 2000, 5000):
        segs = spatial_segments(xyz, max_points)
        assert len(segs) == math.ceil(2000 / max_points)
        sizes = [s.numel() for s in segs]
        assert max(sizes) <= max_points
        assert max(sizes) - min(sizes) <= 1 + int(math.log2(len(segs)) + 1), sizes
        together = torch.cat(segs)
        assert torch.equal(torch.sort(together).values, torch.arange(2000)), "not a partition"
        assert all(bool((s[1:] > s[:-1]).all()) for s in segs), "segment indices not ascending"


def test_spatial_segments_follow_space():
    """Two far clusters, each of half the points, interleaved in index order: two segments, one per cluster."""
    g = torch.Generator().manual_seed(0)
    a = torch.rand(100, 3, generator=g)
    b = torch.rand(100, 3, generator=g) + torch.tensor([50.0, 0, 0])
    xyz = torch.stack([a, b], 1).reshape(200, 3)  # a0, b0, a1, b1, ...
    segs = spatial_segments(xyz, 100)
    assert [s.numel() for s in segs] == [100, 100]
    assert torch.equal(segs[0], torch.arange(0, 200, 2)) and torch.equal(segs[1], torch.arange(1, 200, 2))
    # the longest axis is cut: spread along y instead, the cut follows
    segs_y = spatial_segments(xyz[:, [1, 0, 2]], 100)
    assert torch.equal(segs_y[0], torch.arange(0, 200, 2))
    assert spatial_segments(xyz[:0], 4) == []


def test_segment_shares():
    assert segment_shares([5, 5, 2], 7) == [2, 3, 2]
    assert sum(segment_shares([5, 5, 2], 7)) == 7
    assert segment_shares([5, 5, 2], 100) == [5, 5, 2]  # never more than a segment holds
    assert segment_shares([3, 3, 3], 9, caps=[1, 5, 5]) == [1, 3, 3]
    assert segment_shares([], 4) == [] and segment_shares([0, 0], 3) == [0, 0]
    g = torch.Generator().manual_seed(0)
    for _ in range(50):
        sizes = torch.randint(0, 30, (int(torch.randint(1, 6, (1,), generator=g)),), generator=g).tolist()
        k = int(torch.randint(0, 120, (1,), generator=g))
        sh = segment_shares(sizes, k)
        n = sum(sizes)
        assert sum(sh) == min(k, n) and all(0 <= x <= s for x, s in zip(sh, sizes))
        if n and k <= n:
            assert all(abs(x - k * s / n) < 1 for x, s in zip(sh, sizes)), (sizes, k, sh)


# ---- chunked FPS ----

def test_chunked_fps_picks_within_chunks(device):
    xyz = lidar_cloud(2, 300, seed=4).float().to(device)
    lengths = torch.tensor([300, 170], device=device)
    m = 50
    got = ChunkedFPSSampler(64)(_with_intensity(xyz), m, lengths)
    _assert_valid_sample(got, m, [300, 170])
    for b, n in enumerate([300, 170]):
        segs = spatial_segments(xyz[b, :n], 64)
        shares = segment_shares([s.numel() for s in segs], m)
        offset = 0
        for seg, k in zip(segs, shares):
            picks = got[b, offset:offset + k]
            # exactly FPS of the chunk (its points in index order), mapped back to the cloud
            want = seg[lidarops.fps(xyz[b, seg].unsqueeze(0), k)[0]]
            assert torch.equal(picks, want), f"cloud {b}, chunk at {offset}"
            offset += k
        assert offset == m


def test_chunked_fps_is_fps_when_one_chunk():
    xyz = lidar_cloud(2, 200, seed=5).float()
    lengths = torch.tensor([200, 99])
    assert torch.equal(ChunkedFPSSampler(200)(xyz, 30, lengths), FPSSampler()(xyz, 30, lengths))
    assert not torch.equal(ChunkedFPSSampler(50)(xyz, 30, lengths), FPSSampler()(xyz, 30, lengths))


def test_chunked_fps_short_and_empty_clouds():
    xyz = uniform_cloud(3, 40).float()
    got = ChunkedFPSSampler(8)(xyz, 30, torch.tensor([40, 12, 0]))
    _assert_valid_sample(got, 30, [40, 12, 0])


@requires_cuda
def test_chunked_fps_cpu_cuda_parity():
    xyz = lidar_cloud(2, 400, seed=6).float()
    lengths = torch.tensor([400, 301])
    s = ChunkedFPSSampler(100)
    assert torch.equal(s(xyz, 64, lengths), s(xyz.cuda(), 64, lengths.cuda()).cpu())


# ---- sample_features ----

def test_sample_features_rows_and_padding(device):
    pts = _with_intensity(uniform_cloud(2, 20).float()).to(device).requires_grad_()
    idx = torch.tensor([[3, 0, 19, -1], [5, 5, -1, -1]], device=device)
    out = sample_features(pts, idx)
    assert out.shape == (2, 4, 4)
    for b in range(2):
        for i in range(4):
            j = int(idx[b, i])
            want = pts[b, j] if j >= 0 else torch.zeros(4, device=device)
            assert torch.equal(out[b, i], want)
    out.sum().backward()
    counts = torch.zeros(2, 20, device=device)
    counts[0, [3, 0, 19]] = 1
    counts[1, 5] = 2
    assert torch.equal(pts.grad, counts.unsqueeze(-1).expand(2, 20, 4))


@pytest.mark.parametrize("features, indices, name", [
    ("not a tensor", torch.zeros(1, 2, dtype=torch.int64), "features"),
    (torch.zeros(1, 4), torch.zeros(1, 2, dtype=torch.int64), "features"),
    (torch.zeros(1, 4, 3), [[0, 1]], "indices"),
    (torch.zeros(1, 4, 3), torch.zeros(2, 2, dtype=torch.int64), "indices"),
    (torch.zeros(1, 4, 3), torch.zeros(1, 2), "indices"),
    (torch.zeros(1, 4, 3), torch.tensor([[0, 4]]), "indices"),
    (torch.zeros(1, 4, 3), torch.tensor([[-2, 0]]), "indices"),
])
def test_sample_features_errors(features, indices, name):
    with pytest.raises(ValueError, match=name):
        sample_features(features, indices)


# ---- the shared argument checks ----

@pytest.mark.parametrize("sampler", SAMPLERS, ids=repr)
@pytest.mark.parametrize("points, m, lengths, name", [
    ("cloud", 2, None, "points"),
    (torch.zeros(4, 3), 2, None, "points"),
    (torch.zeros(1, 4, 2), 2, None, "points"),
    (torch.zeros(1, 4, 3, dtype=torch.int64), 2, None, "points"),
    (torch.zeros(1, 4, 3), 0, None, "m"),
    (torch.zeros(1, 4, 3), -3, None, "m"),
    (torch.zeros(1, 4, 3), 1.5, None, "m"),
    (torch.zeros(1, 4, 3), True, None, "m"),
    (torch.zeros(1, 4, 3), "2", None, "m"),
    (torch.zeros(1, 4, 3), 2**40, None, "m"),
    (torch.zeros(1, 4, 3), 2, torch.tensor([1, 2]), "lengths"),
    (torch.zeros(1, 4, 3), 2, torch.tensor([1.0]), "lengths"),
    (torch.zeros(1, 4, 3), 2, torch.tensor([5]), "lengths"),
    (torch.zeros(1, 4, 3), 2, torch.tensor([-1]), "lengths"),
])
def test_sampler_errors(sampler, points, m, lengths, name):
    with pytest.raises(ValueError, match=name):
        sampler(points, m, lengths)


@pytest.mark.parametrize("sampler", [FPSSampler(), ChunkedFPSSampler(2)], ids=repr)
@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e30])
def test_geometric_samplers_refuse_bad_coordinates(sampler, bad):
    pts = torch.zeros(1, 4, 4)
    pts[0, 2, 1] = bad
    with pytest.raises(ValueError, match="points"):
        sampler(pts, 2)
    pts = torch.zeros(1, 4, 4)
    pts[0, 2, 3] = bad  # intensity: not a coordinate
    sampler(pts, 2)


@requires_cuda
@pytest.mark.parametrize("sampler", SAMPLERS, ids=repr)
def test_lengths_on_another_device(sampler):
    with pytest.raises(ValueError, match="lengths"):
        sampler(torch.zeros(1, 4, 3, device="cuda"), 2, torch.tensor([3]))


def test_constructor_errors():
    for bad in (-1, 1.5, "0", True):
        with pytest.raises(ValueError, match="seed"):
            RandomSampler(bad)
    for bad in (0, 2.0, None):
        with pytest.raises(ValueError, match="chunk"):
            ChunkedFPSSampler(bad)
    with pytest.raises(ValueError, match="method"):
        FPSSampler("tree")
    with pytest.raises(ValueError, match="max_points"):
        spatial_segments(torch.zeros(3, 3), 0)
