"""Face of OpenPCDet's ``pcdet.ops.pointnet2.pointnet2_stack.pointnet2_utils`` (PointNet++ on stacked
clouds ``(N1 + N2 + ..., 3)`` with per-example counts, as PV-RCNN's voxel set abstraction uses them)::

    # from pcdet.ops.pointnet2.pointnet2_stack import pointnet2_utils as pointnet2_stack_utils
    from lidarops.compat.pcdet import pointnet2_stack as pointnet2_stack_utils

OpenPCDet's conventions, read from its ``pointnet2_stack`` kernels: ``ball_query`` returns indices local
to each example and an ``empty_ball_mask`` (an empty ball's row is zeros); ``grouping_operation``
takes ``(features, features_batch_cnt, idx, idx_batch_cnt)``; ``three_nn`` returns indices into the
whole stacked ``known`` array; ``stack_farthest_point_sample`` returns stacked indices into the whole
``xyz``. Runs on CPU and CUDA. Not served: the voxel query and vector-pool ops of PV-RCNN++.
"""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor, nn

from lidarops.compat import mmcv as _mmcv
from lidarops.compat.mmcv import _repeat_first_after_exhaustion, _stacked_counts, _stacked_to_padded
from lidarops.compat.pcdet.pointnet2_batch import farthest_point_sample, furthest_point_sample
from lidarops.ops.neighbors import fps as _core_fps
from lidarops.ops.neighbors import knn as _core_knn
from lidarops.ops.validation import check_tensor, describe, validation

__all__ = ["ball_query", "grouping_operation", "QueryAndGroup", "farthest_point_sample", "furthest_point_sample",
           "stack_farthest_point_sample", "three_nn", "three_interpolate"]


def _stacked_xyz(t: Tensor, name: str) -> None:
    check_tensor(t, name)
    if t.dim() != 2 or t.shape[1] != 3 or not t.is_floating_point():
        raise ValueError(f"{name} must be a floating (N1 + N2 + ..., 3) tensor, got {describe(t)}")


def ball_query(radius: float, nsample: int, xyz: Tensor, xyz_batch_cnt: Tensor, new_xyz: Tensor,
               new_xyz_batch_cnt: Tensor) -> Tuple[Tensor, Tensor]:
    """Up to ``nsample`` points of each centre's example within ``radius`` (``d^2 < radius^2``).

    Returns:
        idx (M1 + M2 + ..., nsample) int32, local to the example, the first hit filling unused slots;
        empty_ball_mask (M1 + M2 + ...) bool, True where no point was found (that row is all zeros).
    """
    idx = _mmcv.ball_query(0.0, radius, nsample, xyz, new_xyz, xyz_batch_cnt, new_xyz_batch_cnt)
    empty = idx[:, 0] == -1 if idx.shape[1] else torch.zeros(idx.shape[0], dtype=torch.bool, device=idx.device)
    idx[empty] = 0
    return idx, empty


def grouping_operation(features: Tensor, features_batch_cnt: Tensor, idx: Tensor, idx_batch_cnt: Tensor) -> Tensor:
    """features (N1 + N2 + ..., C), idx (M1 + M2 + ..., nsample) local to each example ->
    (M1 + M2 + ..., C, nsample); differentiable with respect to ``features``."""
    return _mmcv.grouping_operation(features, idx, features_batch_cnt, idx_batch_cnt)


class QueryAndGroup(nn.Module):
    """Stacked ball query and grouping: ``(new_features (M, 3 + C, nsample), idx)``; empty balls give zeros."""

    def __init__(self, radius: float, nsample: int, use_xyz: bool = True):
        super().__init__()
        self.radius, self.nsample, self.use_xyz = radius, nsample, use_xyz

    def forward(self, xyz: Tensor, xyz_batch_cnt: Tensor, new_xyz: Tensor, new_xyz_batch_cnt: Tensor,
                features: Tensor = None):
        idx, empty = ball_query(self.radius, self.nsample, xyz, xyz_batch_cnt, new_xyz, new_xyz_batch_cnt)
        grouped_xyz = grouping_operation(xyz, xyz_batch_cnt, idx, new_xyz_batch_cnt) - new_xyz.unsqueeze(-1)
        grouped_xyz[empty] = 0
        if features is None:
            if not self.use_xyz:
                raise ValueError("QueryAndGroup: use_xyz=False needs features (there would be nothing to group)")
            return grouped_xyz, idx
        grouped_features = grouping_operation(features, xyz_batch_cnt, idx, new_xyz_batch_cnt)
        grouped_features[empty] = 0
        out = torch.cat([grouped_xyz, grouped_features], dim=1) if self.use_xyz else grouped_features
        return out, idx


def stack_farthest_point_sample(xyz: Tensor, xyz_batch_cnt: Tensor, npoint) -> Tensor:
    """Farthest point sampling per example of a stacked cloud.

    Args:
        xyz: (N1 + N2 + ..., 3).
        xyz_batch_cnt: (B,) integer, [N1, N2, ...].
        npoint: int (every example), a list or a (B,) integer tensor [M1, M2, ...].

    Returns:
        (M1 + M2 + ...) int32 indices into the whole ``xyz`` (each example starts at its first point).
    """
    _stacked_xyz(xyz, "xyz")
    counts = _stacked_counts(xyz_batch_cnt, "xyz_batch_cnt", xyz.shape[0], "xyz")
    B = counts.shape[0]
    if isinstance(npoint, Tensor):
        m = [int(v) for v in npoint.tolist()]
    elif isinstance(npoint, (list, tuple)):
        m = [int(v) for v in npoint]
    else:
        m = [int(npoint)] * B
    if len(m) != B or any(v < 0 for v in m):
        raise ValueError(f"npoint must be an int >= 0 or B = {B} of them, got {npoint!r}")
    k = max(m, default=0)
    if k == 0 or B == 0:
        return torch.zeros(sum(m), dtype=torch.int32, device=xyz.device)
    start = torch.cumsum(counts, 0) - counts
    if xyz.shape[0] == 0:  # the kernel writes each example's start index throughout
        return torch.cat([start[b].repeat(m[b]) for b in range(B)]).to(torch.int32)
    padded = _stacked_to_padded(xyz, counts)
    with validation(False):
        idx = _core_fps(padded, k, lengths=counts.to(padded.device))
        idx = _repeat_first_after_exhaustion(padded, idx, fill=0).clamp_min(0)
    idx = idx + start[:, None]
    return torch.cat([idx[b, :m[b]] for b in range(B)]).to(torch.int32)


def three_nn(unknown: Tensor, unknown_batch_cnt: Tensor, known: Tensor, known_batch_cnt: Tensor
             ) -> Tuple[Tensor, Tensor]:
    """The three nearest ``known`` points of each ``unknown`` point, within its example.

    Returns:
        dist (N1 + N2 + ..., 3) Euclidean, ascending; idx (N1 + N2 + ..., 3) int32 into the whole ``known``
        (ties to the lower index; an example with fewer than three known points repeats its first index
        with distance +inf, as the kernel's initial values).
    """
    _stacked_xyz(unknown, "unknown")
    _stacked_xyz(known, "known")
    ucnt = _stacked_counts(unknown_batch_cnt, "unknown_batch_cnt", unknown.shape[0], "unknown")
    kcnt = _stacked_counts(known_batch_cnt, "known_batch_cnt", known.shape[0], "known")
    if ucnt.shape != kcnt.shape:
        raise ValueError(f"unknown_batch_cnt and known_batch_cnt must have the same length, got "
                         f"{describe(unknown_batch_cnt)} and {describe(known_batch_cnt)}")
    if unknown.dtype != known.dtype:
        raise ValueError(f"unknown and known must have the same dtype, got {unknown.dtype} and {known.dtype}")
    if unknown.shape[0] == 0:
        return unknown.new_zeros((0, 3)), torch.zeros((0, 3), dtype=torch.int32, device=unknown.device)
    _mmcv._check_finite_coordinates(("unknown", unknown), ("known", known))
    q, p = _stacked_to_padded(unknown, ucnt), _stacked_to_padded(known, kcnt)
    with validation(False):
        d2, idx = _core_knn(q, p, 3, query_lengths=ucnt.to(q.device), point_lengths=kcnt.to(q.device))
    d2 = torch.where(idx >= 0, d2.detach(), torch.full_like(d2, float("inf")))
    kstart = torch.cumsum(kcnt, 0) - kcnt
    idx = idx.clamp_min(0) + kstart[:, None, None]
    take = torch.arange(q.shape[1], device=q.device)[None, :] < ucnt[:, None]
    return torch.sqrt(d2[take]), idx[take].to(torch.int32)


def three_interpolate(features: Tensor, idx: Tensor, weight: Tensor) -> Tensor:
    """features (M1 + M2 + ..., C), idx (N1 + N2 + ..., 3) into the whole ``features``, weight
    (N1 + N2 + ..., 3) -> (N1 + N2 + ..., C); differentiable with respect to ``features``."""
    for name, t in (("features", features), ("idx", idx), ("weight", weight)):
        check_tensor(t, name)
    if features.dim() != 2:
        raise ValueError(f"features must be (M1 + M2 + ..., C), got {describe(features)}")
    if idx.dim() != 2 or idx.shape[1] != 3 or idx.is_floating_point():
        raise ValueError(f"idx must be an integer (N1 + N2 + ..., 3) tensor, got {describe(idx)}")
    if weight.shape != idx.shape or not weight.is_floating_point():
        raise ValueError(f"weight must be a floating tensor shaped like idx {tuple(idx.shape)}, got {describe(weight)}")
    grouped = _mmcv.gather_points(features.t().unsqueeze(0), idx.reshape(1, -1))  # (1, C, 3N)
    grouped = grouped[0].view(features.shape[1], idx.shape[0], 3)
    return (grouped * weight.to(grouped.dtype)[None]).sum(-1).t().contiguous()
