"""voxelize_frames: the batch voxelized in one call (frames stacked along z) equals each frame voxelized on its
own and concatenated, frame by frame (the reference below calls the op once per frame)."""
import math

import pytest
import torch
from torch.nn import functional as F

from lidarops.models.config import PointPillarsConfig
from lidarops.models.pointpillars import voxelize_frames
from lidarops.ops.voxelize import voxelize
from tests.helpers.devices import DEVICES


def per_frame(points, batch_size, cfg, max_voxels):
    frame = points[:, 0].long()
    out = [[], [], []]
    for b in range(batch_size):
        v, c, n = voxelize(points[frame == b, 1:1 + cfg.num_point_features], cfg.voxel_size, cfg.point_cloud_range,
                           cfg.max_points_per_voxel, max_voxels, overflow="drop")
        for o, t in zip(out, (v, n, F.pad(c, (1, 0), value=b))):
            o.append(t)
    return tuple(torch.cat(o) for o in out)


def frames(sizes, seed, cfg, dtype=torch.float32, shuffle=True, device="cpu"):
    """Ragged frames of LiDAR-like points: most inside the range, some outside in x, y or z, some on the z
    bounds exactly, duplicates, frame index first."""
    g = torch.Generator().manual_seed(seed)
    r = cfg.point_cloud_range
    rows = []
    for b, n in enumerate(sizes):
        x = torch.rand(n, generator=g, dtype=torch.float64) * (r[3] - r[0] + 4) + r[0] - 2
        y = torch.rand(n, generator=g, dtype=torch.float64) * (r[4] - r[1] + 4) + r[1] - 2
        z = torch.rand(n, generator=g, dtype=torch.float64) * (r[5] - r[2] + 1) + r[2] - 0.5
        # clustered points: many to a pillar, so max_points_per_voxel drops some
        k = n // 3
        if k:
            x[:k] = x[0] + torch.rand(k, generator=g, dtype=torch.float64) * 0.1
            y[:k] = y[0] + torch.rand(k, generator=g, dtype=torch.float64) * 0.1
        edges = torch.tensor([r[2], r[5], math.nextafter(r[5], -math.inf), math.nextafter(r[2], -math.inf), math.nan],
                             dtype=torch.float64)
        m = min(len(edges), n)
        z[-m:] = edges[:m]
        pts = torch.stack([torch.full((n,), float(b), dtype=torch.float64), x, y, z,
                           torch.rand(n, generator=g, dtype=torch.float64)], 1)
        if n > 4:
            pts[1] = pts[0]  # a duplicate point
        rows.append(pts)
    pts = torch.cat(rows).to(dtype)
    if shuffle:
        pts = pts[torch.randperm(len(pts), generator=g)]
    return pts.to(device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sizes,shuffle", [([300, 17, 950], True), ([1, 2], False), ([500] * 6, True),
                                           ([40, 0, 60], True)])
@pytest.mark.parametrize("training", [False, True])
def test_batch_equals_frame_by_frame(device, dtype, sizes, shuffle, training):
    cfg = PointPillarsConfig(max_points_per_voxel=4, max_voxels_train=200, max_voxels_test=400)
    pts = frames(sizes, sum(sizes), cfg, dtype, shuffle, device)
    got = voxelize_frames(pts, len(sizes), cfg, training)
    want = per_frame(pts, len(sizes), cfg, cfg.max_voxels_train if training else cfg.max_voxels_test)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert torch.equal(g, w)


@pytest.mark.parametrize("device", DEVICES)
def test_a_frame_over_max_voxels_drops_as_alone(device):
    # frame 1 needs more pillars than max_voxels: its last ones are dropped, the other frames keep all theirs
    cfg = PointPillarsConfig(max_points_per_voxel=2, max_voxels_test=30)
    pts = frames([20, 400, 25], 3, cfg, device=device)
    got = voxelize_frames(pts, 3, cfg, False)
    want = per_frame(pts, 3, cfg, 30)
    assert (torch.bincount(got[2][:, 0].long()) <= 30).all()
    for g, w in zip(got, want):
        assert torch.equal(g, w)


@pytest.mark.parametrize("device", DEVICES)
def test_half(device):
    # float16 points (a model.half()): z could not hold the stacked slabs exactly, so frame by frame
    cfg = PointPillarsConfig(max_points_per_voxel=4)
    half = frames([200, 300], 6, cfg, device=device).half()
    for g, w in zip(voxelize_frames(half, 2, cfg, False), per_frame(half, 2, cfg, cfg.max_voxels_test)):
        assert torch.equal(g, w)
