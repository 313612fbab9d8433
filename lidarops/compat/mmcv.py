"""Drop-in face of the point-cloud ops of ``mmcv.ops``: ``furthest_point_sample``, ``ball_query``,
``knn``, ``three_nn``, ``gather_points``, ``grouping_operation``.

Reproduces mmcv's conventions (read from open-mmlab/mmcv ``mmcv/ops/{furthest_point_sample,
ball_query,knn,three_nn,gather_points,group_points}.py`` and the kernels
``mmcv/ops/csrc/common/cuda/{furthest_point_sample,ball_query,knn,three_nn,gather_points,
group_points,stack_group_points}_cuda_kernel.cuh``):

* index outputs are int32 and never -1: mmcv pads with valid indices (0, or the first hit);
* no ragged lengths: every cloud has all its N points;
* ``knn`` returns ``(B, k, npoint)`` (neighbours along dim 1);
* ``three_nn`` returns Euclidean distances (the square root of the squared distances), not squared.

The work runs on the lidarops core ops (exact, grid-accelerated, CPU and CUDA; mmcv's own ops are
CUDA-only). Known deviations are listed in ``docs/compat.md``.
"""
from __future__ import annotations

import math
import numbers
from typing import Optional, Tuple

import torch
from torch import Tensor

from lidarops.compat.pytorch3d import (
    _ball_query_filtered,
    _check_positive_int,
    _compute_dtype,
    _f32_square,
    _repeat_first_after_exhaustion,
)
from lidarops.ops.neighbors import ball_query as _core_ball_query
from lidarops.ops.neighbors import fps as _core_fps
from lidarops.ops.neighbors import gather as _core_gather
from lidarops.ops.neighbors import knn as _core_knn
from lidarops.ops.validation import check_cloud, check_same_device, check_tensor, coordinate_checks, describe, \
    run_value_checks, validation, value_checks_enabled

__all__ = ["furthest_point_sample", "ball_query", "knn", "three_nn", "gather_points", "grouping_operation"]


def _check_pair(xyz: Tensor, xyz_name: str, centers: Tensor, centers_name: str) -> None:
    check_cloud(xyz, xyz_name)
    check_cloud(centers, centers_name, batch=xyz.shape[0])
    check_same_device([(xyz_name, xyz), (centers_name, centers)])
    if xyz.dtype != centers.dtype:
        raise ValueError(f"{xyz_name} and {centers_name} must have the same dtype, got {xyz.dtype} and "
                         f"{centers.dtype}")


def _check_finite_coordinates(*named: Tuple[str, Tensor]) -> None:
    """One host sync: finite coordinates within the core ops' bound, so that squared distances cannot
    overflow (messages in mmcv's argument names)."""
    if value_checks_enabled():
        run_value_checks(coordinate_checks(named))


def _check_index(t, name: str) -> None:
    check_tensor(t, name)
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor (int32 in mmcv), got {describe(t)}")


def furthest_point_sample(points_xyz: Tensor, num_points: int) -> Tensor:
    """Furthest point sampling as ``mmcv.ops.furthest_point_sample``.

    Args:
        points_xyz (Tensor[B, N, 3]): float32/float64 (float16/bfloat16 computed in float32).
        num_points (int): samples per cloud (0 gives an empty result).

    Returns:
        Tensor[B, num_points] int32: starts at index 0; each step takes the point with the largest
        squared distance to the selected set (ties to the lowest index). Once every distinct location
        has been taken (duplicates, or ``num_points > N``), mmcv's kernel returns index 0 for every
        further sample, and so does this face. Not differentiable (like mmcv).
    """
    check_cloud(points_xyz, "points_xyz")
    if isinstance(num_points, bool) or not isinstance(num_points, numbers.Integral) or num_points < 0:
        raise ValueError(f"num_points must be an int >= 0, got {num_points!r}")
    num_points = int(num_points)
    B = points_xyz.shape[0]
    if num_points == 0 or B == 0:
        return torch.zeros((B, num_points), dtype=torch.int32, device=points_xyz.device)
    _check_finite_coordinates(("points_xyz", points_xyz))
    with validation(False):
        idx = _core_fps(points_xyz, num_points)
        idx = _repeat_first_after_exhaustion(points_xyz, idx, fill=0)
    return idx.clamp_min(0).to(torch.int32)


def ball_query(min_radius: float, max_radius: float, sample_num: int, xyz: Tensor,
               center_xyz: Tensor) -> Tensor:
    """Ball query as ``mmcv.ops.ball_query``.

    Args:
        min_radius (float): >= 0, inner radius.
        max_radius (float): > min_radius, outer radius.
        sample_num (int): samples per ball.
        xyz (Tensor[B, N, 3]): points.
        center_xyz (Tensor[B, npoint, 3]): ball centres, same dtype and device.

    Returns:
        Tensor[B, npoint, sample_num] int32: the first ``sample_num`` points in index order with
        ``d2 == 0 or (min_radius**2 <= d2 < max_radius**2)`` (mmcv's kernel rule; the squares are
        taken in float32 as mmcv does). The slots after the last hit repeat the first hit; a ball with
        no hit is all zeros. With ``min_radius > 0`` the core query is repeated with more candidates
        until the filtered result is exact.
    """
    _check_pair(xyz, "xyz", center_xyz, "center_xyz")
    for name, r in (("min_radius", min_radius), ("max_radius", max_radius)):
        if isinstance(r, bool) or not isinstance(r, numbers.Real) or not math.isfinite(r):
            raise ValueError(f"{name} must be a finite number, got {r!r}")
    if min_radius < 0:
        raise ValueError(f"min_radius must be >= 0, got {min_radius}")
    if not min_radius < max_radius:
        raise ValueError(f"min_radius must be < max_radius, got min_radius={min_radius}, max_radius={max_radius}")
    sample_num = _check_positive_int(sample_num, "sample_num")
    ct = _compute_dtype(xyz.dtype)
    min_r2 = _f32_square(float(min_radius))
    max_r2 = _f32_square(float(max_radius))
    _check_finite_coordinates(("xyz", xyz), ("center_xyz", center_xyz))
    with validation(False):
        if min_radius == 0 and ct == torch.float32:
            # the core's rule (d2 < float32(r) * float32(r)) is mmcv's rule here
            _, idx = _core_ball_query(center_xyz, xyz, float(max_radius), sample_num)
        else:
            # float64 input compares with float32 squares (as mmcv does); query a slightly larger ball and
            # filter exactly
            def keep(d2):
                return (d2 < max_r2) & ((d2 == 0) | (d2 >= min_r2))
            _, idx = _ball_query_filtered(center_xyz, xyz, float(max_radius) * (1 + 1e-6), sample_num, keep)
    first = idx[..., :1]
    fill = torch.where(first >= 0, first, torch.zeros_like(first))
    return torch.where(idx >= 0, idx, fill).to(torch.int32)


def knn(k: int, xyz: Tensor, center_xyz: Optional[Tensor] = None, transposed: bool = False) -> Tensor:
    """k nearest neighbours as ``mmcv.ops.knn``.

    Args:
        k (int): neighbours (mmcv asserts ``k < 100``; any k >= 1 works here).
        xyz (Tensor[B, N, 3] | Tensor[B, 3, N] if transposed): points.
        center_xyz (Tensor[B, npoint, 3] | Tensor[B, 3, npoint], optional): queries; default ``xyz``.
        transposed (bool): inputs are channel-first.

    Returns:
        Tensor[B, k, npoint] int32: ``out[b, j, i]`` is the j-th nearest point to centre i (ascending
        squared distance, ties to the lower index); index 0 where fewer than k points exist (mmcv's
        kernel keeps its initial index 0 there). Not differentiable.
    """
    k = _check_positive_int(k, "k")
    if center_xyz is None:
        center_xyz = xyz
    check_tensor(xyz, "xyz")
    check_tensor(center_xyz, "center_xyz")
    if transposed:
        for name, t in (("xyz", xyz), ("center_xyz", center_xyz)):
            if t.dim() != 3 or t.shape[1] != 3:
                raise ValueError(f"{name} must be (B, 3, N) when transposed=True, got {describe(t)}")
        xyz = xyz.transpose(2, 1)
        center_xyz = center_xyz.transpose(2, 1)
    _check_pair(xyz, "xyz", center_xyz, "center_xyz")
    _check_finite_coordinates(("xyz", xyz), ("center_xyz", center_xyz))
    with validation(False):
        _, idx = _core_knn(center_xyz, xyz, k)
    return idx.clamp_min(0).transpose(1, 2).contiguous().to(torch.int32)


def three_nn(target: Tensor, source: Tensor) -> Tuple[Tensor, Tensor]:
    """The three nearest neighbours as ``mmcv.ops.three_nn``.

    Args:
        target (Tensor[B, N, 3]): points that look for neighbours.
        source (Tensor[B, M, 3]): points searched, same dtype and device.

    Returns:
        dist (Tensor[B, N, 3]): Euclidean distances (mmcv returns ``sqrt(dist2)``), ascending; +inf
            where M < 3 (mmcv's 1e40 sentinel, which is +inf in float32). float64 for float64 input,
            else float32. Not differentiable (mmcv's backward returns None).
        idx (Tensor[B, N, 3] int32): ties to the lower index; 0 where M < 3.
    """
    _check_pair(source, "source", target, "target")
    _check_finite_coordinates(("target", target), ("source", source))
    with validation(False):
        d2, idx = _core_knn(target, source, 3)
    return torch.sqrt(d2.detach()), idx.clamp_min(0).to(torch.int32)


def gather_points(features: Tensor, indices: Tensor) -> Tensor:
    """``mmcv.ops.gather_points``: pick columns of channel-first features.

    Args:
        features (Tensor[B, C, N]): any dtype.
        indices (Tensor[B, M] integer): in [0, N) (-1 is also accepted and gives zeros).

    Returns:
        Tensor[B, C, M]: ``out[b, :, m] = features[b, :, indices[b, m]]`` (contiguous). Differentiable
        with respect to ``features``; the backward is the registered scatter-add
        ``lidarops::gather_backward`` (mmcv: atomicAdd into a zero tensor).
    """
    check_tensor(features, "features")
    _check_index(indices, "indices")
    if features.dim() != 3:
        raise ValueError(f"features must be (B, C, N), got {describe(features)}")
    if indices.dim() != 2 or indices.shape[0] != features.shape[0]:
        raise ValueError(f"indices must be (B, M) with B = {features.shape[0]}, got {describe(indices)}")
    out = _core_gather(features.transpose(1, 2), indices)  # (B, M, C)
    return out.transpose(1, 2).contiguous()


def grouping_operation(features: Tensor, indices: Tensor, features_batch_cnt: Optional[Tensor] = None,
                       indices_batch_cnt: Optional[Tensor] = None) -> Tensor:
    """``mmcv.ops.grouping_operation``: group channel-first features by neighbourhood indices.

    Args:
        features (Tensor[B, C, N]): features, any dtype. Stacked mode: Tensor[N1 + N2 + ..., C].
        indices (Tensor[B, npoint, nsample] integer): indices into each cloud's N points (-1 gives zeros).
            Stacked mode: Tensor[M1 + M2 + ..., nsample] of indices local to each example.
        features_batch_cnt (Tensor[B] integer, optional): stacked mode, points per example (N1, N2, ...).
        indices_batch_cnt (Tensor[B] integer, optional): stacked mode, centres per example (M1, M2, ...).

    Returns:
        Tensor[B, C, npoint, nsample] (stacked mode: Tensor[M1 + M2 + ..., C, nsample]), contiguous.
        Differentiable with respect to ``features`` through the registered scatter-add backward.
    """
    check_tensor(features, "features")
    _check_index(indices, "indices")
    stacked = features_batch_cnt is not None or indices_batch_cnt is not None
    if not stacked:
        if features.dim() != 3:
            raise ValueError(f"features must be (B, C, N), got {describe(features)}")
        if indices.dim() != 3 or indices.shape[0] != features.shape[0]:
            raise ValueError(f"indices must be (B, npoint, nsample) with B = {features.shape[0]}, "
                             f"got {describe(indices)}")
        out = _core_gather(features.transpose(1, 2), indices)  # (B, npoint, nsample, C)
        return out.permute(0, 3, 1, 2).contiguous()

    if features_batch_cnt is None or indices_batch_cnt is None:
        raise ValueError("stacked mode needs both features_batch_cnt and indices_batch_cnt")
    _check_index(features_batch_cnt, "features_batch_cnt")
    _check_index(indices_batch_cnt, "indices_batch_cnt")
    if features.dim() != 2:
        raise ValueError(f"features must be (N1 + N2 + ..., C) in stacked mode, got {describe(features)}")
    if indices.dim() != 2:
        raise ValueError(f"indices must be (M1 + M2 + ..., nsample) in stacked mode, got {describe(indices)}")
    B = features_batch_cnt.shape[0] if features_batch_cnt.dim() == 1 else -1
    if features_batch_cnt.dim() != 1 or indices_batch_cnt.shape != (B,):
        raise ValueError(f"features_batch_cnt and indices_batch_cnt must both be (B,), got "
                         f"{describe(features_batch_cnt)} and {describe(indices_batch_cnt)}")
    check_same_device([("features", features), ("indices", indices), ("features_batch_cnt", features_batch_cnt),
                       ("indices_batch_cnt", indices_batch_cnt)])
    fcnt = features_batch_cnt.to(torch.int64)
    icnt = indices_batch_cnt.to(torch.int64)
    if value_checks_enabled():
        run_value_checks([
            ((fcnt < 0).any() | (fcnt.sum() != features.shape[0]),
             lambda: f"features_batch_cnt must be >= 0 and sum to {features.shape[0]}, got {fcnt.tolist()}"),
            ((icnt < 0).any() | (icnt.sum() != indices.shape[0]),
             lambda: f"indices_batch_cnt must be >= 0 and sum to {indices.shape[0]}, got {icnt.tolist()}"),
        ])
    offsets = torch.cumsum(fcnt, 0) - fcnt  # first global row of each example
    example = torch.repeat_interleave(torch.arange(B, device=indices.device), icnt,
                                      output_size=indices.shape[0])
    local = indices.to(torch.int64)
    if value_checks_enabled() and local.numel():
        n_of_row = fcnt[example][:, None]
        run_value_checks([(((local < -1) | (local >= n_of_row)).any(),
                           "indices must lie in [-1, N_b) of their example in stacked mode")])
    glob = torch.where(local >= 0, local + offsets[example][:, None], torch.full_like(local, -1))
    out = _core_gather(features.unsqueeze(0), glob.unsqueeze(0))[0]  # (M, nsample, C)
    return out.permute(0, 2, 1).contiguous()
