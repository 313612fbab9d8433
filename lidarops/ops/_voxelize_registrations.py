"""Fake kernels and autograd of the voxelization ops (schemas in csrc/ops/voxelize.cpp).

Both ops are shape-static, so the fake kernels need no dynamic sizes: ``voxelize_assign`` pads its
per-voxel outputs to ``max_voxels`` and returns the data-dependent voxel count V in ``stats[0]``;
``voxelize_scatter`` takes its row count as an argument. The data dependence lives in the wrapper
(``lidarops.ops.voxelize``), which reads ``stats`` once and slices; under ``torch.compile`` that read
is a graph break (or an unbacked size with ``capture_scalar_outputs``) unless ``padded=True``.

Imported by ``lidarops.ops.voxelize`` after ``lidarops.extension.load()``.
"""
from __future__ import annotations

import torch

_NUM_STATS = 7  # kNumVoxelStats in csrc/include/lidarops/voxelize.h


@torch.library.register_fake("lidarops::voxelize_assign")
def _voxelize_assign_fake(points, voxel_size, point_range, grid_size, max_points_per_voxel, max_voxels, method=0):
    torch._check(points.dim() == 2 and points.shape[1] >= 3, lambda: f"points must be (N, C >= 3), got {points.shape}")
    torch._check(max_points_per_voxel >= 1, lambda: f"max_points_per_voxel must be >= 1, got {max_points_per_voxel}")
    torch._check(max_voxels >= 1, lambda: f"max_voxels must be >= 1, got {max_voxels}")
    n = points.shape[0]
    return (points.new_empty((max_voxels, 3), dtype=torch.int32),
            points.new_empty((max_voxels,), dtype=torch.int32),
            points.new_empty((n,), dtype=torch.int64),
            points.new_empty((n,), dtype=torch.int64),
            points.new_empty((_NUM_STATS,), dtype=torch.int64))


@torch.library.register_fake("lidarops::voxelize_scatter")
def _voxelize_scatter_fake(features, point_voxel, point_slot, num_voxels, max_points_per_voxel):
    torch._check(num_voxels >= 0, lambda: f"num_voxels must be >= 0, got {num_voxels}")
    torch._check(max_points_per_voxel >= 1, lambda: f"max_points_per_voxel must be >= 1, got {max_points_per_voxel}")
    return features.new_empty((num_voxels, max_points_per_voxel, features.shape[1]))


# ---- voxelize_scatter: d features[i] = d voxels[point_voxel[i], point_slot[i]] (0 if not stored) ----

def _scatter_setup(ctx, inputs, output):
    _, point_voxel, point_slot, num_voxels, max_points = inputs
    ctx.save_for_backward(point_voxel, point_slot)
    ctx.num_voxels, ctx.max_points = num_voxels, max_points


def _scatter_backward(ctx, grad):
    point_voxel, point_slot = ctx.saved_tensors
    if not ctx.needs_input_grad[0]:
        return None, None, None, None, None
    V, P = ctx.num_voxels, ctx.max_points
    C = grad.shape[-1]
    stored = (point_voxel >= 0) & (point_voxel < V) & (point_slot >= 0) & (point_slot < P)
    # Row V * P is a zero row for the points that were not stored (ATen ops: any device, deterministic,
    # differentiable again).
    row = torch.where(stored, point_voxel * P + point_slot, torch.full_like(point_voxel, V * P))
    rows = torch.cat([grad.reshape(V * P, C), grad.new_zeros((1, C))])
    return rows.index_select(0, row), None, None, None, None


torch.library.register_autograd("lidarops::voxelize_scatter", _scatter_backward, setup_context=_scatter_setup)
