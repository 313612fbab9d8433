"""Fake (meta) kernels and autograd formulas of the ops wrapped in :mod:`lidarops.ops`.

Schemas: ``csrc/ops/neighbors.cpp`` (fps, knn, ball_query, gather, gather_backward), ``checks.cpp``
(value_flags), ``voxelize.cpp`` (voxelize_assign, voxelize_scatter), ``boxes.cpp`` (box_overlap_bev,
box_iou_bev, box_iou_3d, nms_bev, nms_bev_padded, nms_bev_padded_batched, nms_bev_checked, points_in_boxes), ``pillar_stream.cpp``
(pillar_decorate, the one-shot pillarization's decoration), ``assign.cpp`` (greedy_assign, fill_repeats). No op of this
package has a C++ autograd kernel (``csrc/ops/autograd``): every formula is here, and every backward is
made of registered ops (gather / gather_backward) or ATen ops, so it works on every device, under
torch.compile, and twice (double backward).

The voxelization ops are shape-static, so their fake kernels need no dynamic sizes: ``voxelize_assign``
pads its per-voxel outputs to ``max_voxels`` and returns the data-dependent voxel count V in ``stats[0]``;
``voxelize_scatter`` takes its row count as an argument. The data dependence lives in the wrapper
(``lidarops.ops.voxelize``), which reads ``stats`` once and slices; under ``torch.compile`` that read is a
graph break (or an unbacked size with ``capture_scalar_outputs``) unless ``padded=True``. The box ops are
not differentiable; ``nms_bev`` keeps a data-dependent number of boxes (an unbacked size),
``nms_bev_padded`` pads its kept list to a size fixed by the shapes and counts on the device;
``nms_bev_checked`` is ``nms_bev_padded`` with its inputs' value flags beside the count (one read back).

Imported by :func:`lidarops.extension.load` (and by :mod:`lidarops.ops.voxelize`).
"""
from __future__ import annotations

import torch

_ops = torch.ops.lidarops
_NUM_VOXEL_STATS = 7  # kNumVoxelStats in csrc/include/lidarops/voxelize.h


# ---- fake kernels -------------------------------------------------------------------------------

def _dist_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


@torch.library.register_fake("lidarops::greedy_assign")
def _greedy_assign_fake(rows, cols, num_rows, num_cols, limit):
    return rows.new_empty((num_rows,), dtype=torch.int64)


@torch.library.register_fake("lidarops::fill_repeats")
def _fill_repeats_fake(points, idx):
    return torch.empty_like(idx)


@torch.library.register_fake("lidarops::fps")
def _fps_fake(points, lengths, start_idx, k, method=0):
    torch._check(k > 0, lambda: f"k must be positive, got {k}")
    return points.new_empty((points.shape[0], k), dtype=torch.int64)


@torch.library.register_fake("lidarops::knn")
def _knn_fake(query, points, query_lengths, point_lengths, k, method=0):
    torch._check(k > 0, lambda: f"k must be positive, got {k}")
    B, M = query.shape[0], query.shape[1]
    return (query.new_empty((B, M, k), dtype=_dist_dtype(query.dtype)),
            query.new_empty((B, M, k), dtype=torch.int64))


@torch.library.register_fake("lidarops::ball_query")
def _ball_query_fake(query, points, query_lengths, point_lengths, k, radius, method=0):
    torch._check(k > 0, lambda: f"k must be positive, got {k}")
    B, M = query.shape[0], query.shape[1]
    return (query.new_empty((B, M, k), dtype=_dist_dtype(query.dtype)),
            query.new_empty((B, M, k), dtype=torch.int64))


@torch.library.register_fake("lidarops::gather")
def _gather_fake(x, idx):
    return x.new_empty((x.shape[0], idx.shape[1], x.shape[2]))


@torch.library.register_fake("lidarops::gather_backward")
def _gather_backward_fake(grad, idx, n):
    return grad.new_empty((grad.shape[0], n, grad.shape[2]))


@torch.library.register_fake("lidarops::value_flags")
def _value_flags_fake(finite, ranged, lo, hi):
    tensors = list(finite) + list(ranged)
    device = tensors[0].device if tensors else torch.device("cpu")
    return torch.empty((len(tensors),), dtype=torch.int32, device=device)


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
            points.new_empty((_NUM_VOXEL_STATS,), dtype=torch.int64))


@torch.library.register_fake("lidarops::voxelize_scatter")
def _voxelize_scatter_fake(features, point_voxel, point_slot, num_voxels, max_points_per_voxel):
    torch._check(num_voxels >= 0, lambda: f"num_voxels must be >= 0, got {num_voxels}")
    torch._check(max_points_per_voxel >= 1, lambda: f"max_points_per_voxel must be >= 1, got {max_points_per_voxel}")
    return features.new_empty((num_voxels, max_points_per_voxel, features.shape[1]))


def _pair_dtype(a):
    return torch.float64 if a.dtype == torch.float64 else torch.float32


@torch.library.register_fake("lidarops::box_overlap_bev")
def _box_overlap_bev_fake(a, b):
    return a.new_empty((a.shape[0], b.shape[0]), dtype=_pair_dtype(a))


@torch.library.register_fake("lidarops::box_iou_bev")
def _box_iou_bev_fake(a, b):
    return a.new_empty((a.shape[0], b.shape[0]), dtype=_pair_dtype(a))


@torch.library.register_fake("lidarops::box_iou_3d")
def _box_iou_3d_fake(a, b):
    return a.new_empty((a.shape[0], b.shape[0]), dtype=_pair_dtype(a))


@torch.library.register_fake("lidarops::nms_bev")
def _nms_bev_fake(boxes, scores, idxs, iou_threshold, pre_max=-1, post_max=-1):
    # the number kept depends on the values: an unbacked size
    kept = torch.library.get_ctx().new_dynamic_size()
    return boxes.new_empty((kept,), dtype=torch.int64)


@torch.library.register_fake("lidarops::nms_bev_padded")
def _nms_bev_padded_fake(boxes, scores, idxs, iou_threshold, score_threshold=None, pre_max=-1, post_max=-1):
    return boxes.new_empty((_padded_k(boxes.shape[0], pre_max, post_max),), dtype=torch.int64), \
        boxes.new_empty((), dtype=torch.int64)


def _padded_k(n, pre_max: int, post_max: int):
    """A padded NMS's size, fixed by the shapes: K = min(N, pre_max, post_max) (-1: no limit)."""
    if pre_max >= 0:
        n = torch.sym_min(n, pre_max)
    if post_max >= 0:
        n = torch.sym_min(n, post_max)
    return n


@torch.library.register_fake("lidarops::nms_bev_padded_batched")
def _nms_bev_padded_batched_fake(boxes, scores, iou_threshold, score_threshold=None, pre_max=-1, post_max=-1):
    return (boxes.new_empty((boxes.shape[0], _padded_k(boxes.shape[1], pre_max, post_max)), dtype=torch.int64),
            boxes.new_empty((boxes.shape[0],), dtype=torch.int64))


@torch.library.register_fake("lidarops::nms_bev_checked")
def _nms_bev_checked_fake(boxes, scores, idxs, iou_threshold, score_threshold=None, pre_max=-1, post_max=-1):
    keep, _ = _nms_bev_padded_fake(boxes, scores, idxs, iou_threshold, score_threshold, pre_max, post_max)
    return keep, boxes.new_empty((4,), dtype=torch.int64)


@torch.library.register_fake("lidarops::points_in_boxes")
def _points_in_boxes_fake(points, boxes):
    return points.new_empty((points.shape[0],), dtype=torch.int64)


# ---- autograd -----------------------------------------------------------------------------------

# ---- gather: d x = scatter-add of d out ----

def _gather_setup(ctx, inputs, output):
    x, idx = inputs
    ctx.save_for_backward(idx)
    ctx.n = x.shape[1]


def _gather_backward(ctx, grad):
    (idx,) = ctx.saved_tensors
    if not ctx.needs_input_grad[0]:
        return None, None
    return _ops.gather_backward(grad.contiguous(), idx, ctx.n), None


torch.library.register_autograd("lidarops::gather", _gather_backward, setup_context=_gather_setup)


def _gather_bw_setup(ctx, inputs, output):
    grad, idx, n = inputs
    ctx.save_for_backward(idx)


def _gather_bw_backward(ctx, gg):
    (idx,) = ctx.saved_tensors
    return _ops.gather(gg.contiguous(), idx), None, None


torch.library.register_autograd("lidarops::gather_backward", _gather_bw_backward, setup_context=_gather_bw_setup)


# ---- knn / ball_query: dist2 = |q - p[idx]|^2 ----

def _neighbor_setup(ctx, inputs, output):
    query, points = inputs[0], inputs[1]
    _, idx = output
    ctx.save_for_backward(query, points, idx)
    ctx.mark_non_differentiable(idx)


def _neighbor_backward(ctx, grad_dist, _grad_idx):
    query, points, idx = ctx.saved_tensors
    B, M, K = idx.shape
    if grad_dist is None:
        return (None,) * 7
    flat = idx.reshape(B, M * K)
    ct = grad_dist.dtype
    neighbours = _ops.gather(points.to(ct).contiguous(), flat).reshape(B, M, K, 3)
    # padded entries (idx -1, dist2 +inf) carry no gradient
    g = torch.where(idx >= 0, grad_dist, torch.zeros((), dtype=ct, device=grad_dist.device))
    diff = query.to(ct).unsqueeze(2) - neighbours
    w = (2.0 * g).unsqueeze(-1) * diff
    grad_query = w.sum(2).to(query.dtype) if ctx.needs_input_grad[0] else None
    grad_points = None
    if ctx.needs_input_grad[1]:
        grad_points = _ops.gather_backward((-w).reshape(B, M * K, 3).contiguous(), flat, points.shape[1])
        grad_points = grad_points.to(points.dtype)
    return (grad_query, grad_points) + (None,) * 5


torch.library.register_autograd("lidarops::knn", _neighbor_backward, setup_context=_neighbor_setup)
torch.library.register_autograd("lidarops::ball_query", _neighbor_backward, setup_context=_neighbor_setup)


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


# pillars (lidarops.ops.pillars; schema in csrc/ops/pillar_stream.cpp): keeps the (P, N) of its input
@torch.library.register_fake("lidarops::pillar_decorate")
def _pillar_decorate_fake(raw, num_points, coords, pillar_size, origin):
    torch._check(raw.dim() == 3 and raw.shape[2] == 4, lambda: f"raw must be (P, N, 4), got {raw.shape}")
    return raw.new_empty((raw.shape[0], raw.shape[1], 9))
