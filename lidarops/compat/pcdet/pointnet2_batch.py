"""Face of OpenPCDet's ``pcdet.ops.pointnet2.pointnet2_batch.pointnet2_utils`` (PointNet++ on padded
``(B, N, 3)`` clouds, as PointRCNN's backbone uses them)::

    # from pcdet.ops.pointnet2.pointnet2_batch import pointnet2_utils
    from lidarops.compat.pcdet import pointnet2_batch as pointnet2_utils

OpenPCDet's batch kernels are mmcv's (mmcv took them from OpenPCDet), so this face is
``lidarops.compat.mmcv`` with OpenPCDet's names and argument orders: ``ball_query(radius, nsample, xyz,
new_xyz)`` is mmcv's ``ball_query(0, radius, ...)`` (``d2 < radius^2``, the first hit fills the row,
zeros for an empty ball), ``three_nn`` returns Euclidean distances, indices are int32. Runs on CPU and
CUDA (OpenPCDet's: CUDA only). ``gather_operation``, ``grouping_operation`` and ``three_interpolate``
are differentiable with respect to the features.
"""
from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor, nn

from lidarops.compat import mmcv as _mmcv
from lidarops.ops.validation import check_tensor, describe

__all__ = ["farthest_point_sample", "furthest_point_sample", "gather_operation", "three_nn", "three_interpolate",
           "grouping_operation", "ball_query", "QueryAndGroup", "GroupAll"]


def farthest_point_sample(xyz: Tensor, npoint: int) -> Tensor:
    """(B, N, 3) -> (B, npoint) int32: starts at point 0, then the point farthest from the chosen set
    (ties to the lowest index; index 0 once no distinct point is left, as the kernel)."""
    return _mmcv.furthest_point_sample(xyz, npoint)


furthest_point_sample = farthest_point_sample


def gather_operation(features: Tensor, idx: Tensor) -> Tensor:
    """features (B, C, N), idx (B, npoint) -> (B, C, npoint)."""
    return _mmcv.gather_points(features, idx)


def three_nn(unknown: Tensor, known: Tensor) -> Tuple[Tensor, Tensor]:
    """The three nearest ``known`` points of each ``unknown`` point: ``(dist, idx)``, both (B, N, 3);
    ``dist`` Euclidean, ascending (ties to the lower index)."""
    return _mmcv.three_nn(unknown, known)


def three_interpolate(features: Tensor, idx: Tensor, weight: Tensor) -> Tensor:
    """features (B, C, M), idx (B, n, 3) int, weight (B, n, 3) -> (B, C, n): the weighted sum of the three
    indexed feature columns."""
    check_tensor(features, "features")
    check_tensor(idx, "idx")
    check_tensor(weight, "weight")
    if features.dim() != 3:
        raise ValueError(f"features must be (B, C, M), got {describe(features)}")
    B = features.shape[0]
    if idx.dim() != 3 or idx.shape[0] != B or idx.shape[2] != 3 or idx.is_floating_point():
        raise ValueError(f"idx must be an integer (B, n, 3) tensor with B = {B}, got {describe(idx)}")
    if weight.shape != idx.shape or not weight.is_floating_point():
        raise ValueError(f"weight must be a floating tensor shaped like idx {tuple(idx.shape)}, got {describe(weight)}")
    grouped = _mmcv.grouping_operation(features, idx)  # (B, C, n, 3)
    return (grouped * weight.to(grouped.dtype)[:, None]).sum(-1)


def grouping_operation(features: Tensor, idx: Tensor) -> Tensor:
    """features (B, C, N), idx (B, npoint, nsample) -> (B, C, npoint, nsample)."""
    return _mmcv.grouping_operation(features, idx)


def ball_query(radius: float, nsample: int, xyz: Tensor, new_xyz: Tensor) -> Tensor:
    """Up to ``nsample`` points of ``xyz`` within ``radius`` (``d^2 < radius^2``) of each ``new_xyz``
    centre, in index order: (B, npoint, nsample) int32; the first hit fills the unused slots, an empty
    ball is all zeros."""
    return _mmcv.ball_query(0.0, radius, nsample, xyz, new_xyz)


class QueryAndGroup(nn.Module):
    """Ball query, then the neighbours' coordinates relative to their centre (and their features):
    ``(B, 3 + C, npoint, nsample)``."""

    def __init__(self, radius: float, nsample: int, use_xyz: bool = True):
        super().__init__()
        self.radius, self.nsample, self.use_xyz = radius, nsample, use_xyz

    def forward(self, xyz: Tensor, new_xyz: Tensor, features: Tensor = None) -> Tensor:
        idx = ball_query(self.radius, self.nsample, xyz, new_xyz)
        grouped_xyz = grouping_operation(xyz.transpose(1, 2).contiguous(), idx)
        grouped_xyz = grouped_xyz - new_xyz.transpose(1, 2).unsqueeze(-1)
        if features is None:
            if not self.use_xyz:
                raise ValueError("QueryAndGroup: use_xyz=False needs features (there would be nothing to group)")
            return grouped_xyz
        grouped_features = grouping_operation(features, idx)
        return torch.cat([grouped_xyz, grouped_features], dim=1) if self.use_xyz else grouped_features


class GroupAll(nn.Module):
    """Every point in one group: ``(B, 3 + C, 1, N)``."""

    def __init__(self, use_xyz: bool = True):
        super().__init__()
        self.use_xyz = use_xyz

    def forward(self, xyz: Tensor, new_xyz: Tensor = None, features: Tensor = None) -> Tensor:
        grouped_xyz = xyz.transpose(1, 2).unsqueeze(2)
        if features is None:
            return grouped_xyz
        grouped_features = features.unsqueeze(2)
        return torch.cat([grouped_xyz, grouped_features], dim=1) if self.use_xyz else grouped_features
