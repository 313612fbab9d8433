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
    _compute_dtype,
    _f32_square,
    _repeat_first_after_exhaustion,
)
from lidarops.ops.neighbors import ball_query as _core_ball_query
from lidarops.ops.neighbors import fps as _core_fps
from lidarops.ops.neighbors import gather as _core_gather
from lidarops.ops.neighbors import knn as _core_knn
from lidarops.ops.validation import check_cloud, check_positive_int, check_same_device, check_tensor, coordinate_checks, describe, \
    run_value_checks, validation, value_checks_enabled

__all__ = ["furthest_point_sample", "furthest_point_sample_with_dist", "ball_query", "knn", "three_nn", "gather_points", "grouping_operation"]


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


def furthest_point_sample_with_dist(points_dist: Tensor, num_points: int) -> Tensor:
    """Furthest point sampling on a precomputed distance matrix, as
    ``mmcv.ops.furthest_point_sample_with_dist`` (used on feature-space distances, e.g. by 3DSSD's
    F-FPS).

    Args:
        points_dist (Tensor[B, N, N]): floating; ``points_dist[b, i, j]`` the distance from point i to
            point j (mmcv passes squared distances; any non-negative values work).
        num_points (int): samples per cloud (0 gives an empty result).

    Returns:
        Tensor[B, num_points] int32: starts at index 0; each step takes the point whose smallest
        distance to the selected set is largest (ties to the lowest index; mmcv's kernel may take
        another of the tied points). Index 0 once every point's distance is 0, as mmcv's kernel.
    """
    check_tensor(points_dist, "points_dist")
    if points_dist.dim() != 3 or points_dist.shape[1] != points_dist.shape[2] or not points_dist.is_floating_point():
        raise ValueError(f"points_dist must be a floating (B, N, N) tensor, got {describe(points_dist)}")
    if isinstance(num_points, bool) or not isinstance(num_points, numbers.Integral) or num_points < 0:
        raise ValueError(f"num_points must be an int >= 0, got {num_points!r}")
    B, N = points_dist.shape[:2]
    out = torch.zeros((B, int(num_points)), dtype=torch.int32, device=points_dist.device)
    if num_points == 0 or B == 0 or N == 0:
        return out
    if value_checks_enabled():
        run_value_checks([(~torch.isfinite(points_dist).all(),
                           f"points_dist contains NaN or infinite values ({describe(points_dist)})")])
    d = points_dist.float() if points_dist.dtype in (torch.float16, torch.bfloat16) else points_dist
    rows = torch.arange(B, device=d.device)
    nearest = torch.full((B, N), 1e10, dtype=d.dtype, device=d.device)  # mmcv's initial distance
    last = torch.zeros(B, dtype=torch.long, device=d.device)
    for i in range(1, int(num_points)):  # num_points steps of O(N) each, on the device
        nearest = torch.minimum(nearest, d[rows, last])
        last = nearest.argmax(dim=1)  # the first maximum: the lowest index among ties
        out[:, i] = last.to(torch.int32)
    return out


def ball_query(min_radius: float, max_radius: float, sample_num: int, xyz: Tensor,
               center_xyz: Tensor, xyz_batch_cnt: Optional[Tensor] = None,
               center_xyz_batch_cnt: Optional[Tensor] = None) -> Tensor:
    """Ball query as ``mmcv.ops.ball_query``, batch and stacked modes.

    Args:
        min_radius (float): >= 0, inner radius.
        max_radius (float): > min_radius, outer radius.
        sample_num (int): samples per ball.
        xyz (Tensor[B, N, 3]): points. Stacked mode: Tensor[N1 + N2 + ..., 3].
        center_xyz (Tensor[B, npoint, 3]): ball centres, same dtype and device. Stacked mode:
            Tensor[M1 + M2 + ..., 3].
        xyz_batch_cnt (Tensor[B] integer, optional): stacked mode, points per example (N1, N2, ...).
        center_xyz_batch_cnt (Tensor[B] integer, optional): stacked mode, centres per example.

    Returns:
        Batch mode: Tensor[B, npoint, sample_num] int32: the first ``sample_num`` points in index order
        with ``d2 == 0 or (min_radius**2 <= d2 < max_radius**2)`` (mmcv's kernel rule; the squares are
        taken in float32 as mmcv does). The slots after the last hit repeat the first hit; a ball with
        no hit is all zeros. With ``min_radius > 0`` the core query is repeated with more candidates
        until the filtered result is exact.

        Stacked mode (OpenPCDet's and mmcv's ``stack_ball_query``): Tensor[M1 + M2 + ..., sample_num]
        int32 of indices local to each example (0 is the example's first point), with the same rule,
        the same first-hit filling, and a ball with no hit (or in an example without points) gives
        ``[-1, 0, 0, ...]`` as mmcv's stack kernel writes. mmcv's stack kernel ignores ``min_radius``;
        here it applies as in batch mode (the same result for ``min_radius == 0``).
    """
    if xyz_batch_cnt is not None or center_xyz_batch_cnt is not None:
        return _stacked_ball_query(min_radius, max_radius, sample_num, xyz, center_xyz, xyz_batch_cnt,
                                   center_xyz_batch_cnt)
    _check_pair(xyz, "xyz", center_xyz, "center_xyz")
    min_r2, max_r2, sample_num = _ball_args(min_radius, max_radius, sample_num)
    ct = _compute_dtype(xyz.dtype)
    _check_finite_coordinates(("xyz", xyz), ("center_xyz", center_xyz))
    with validation(False):
        if min_radius == 0 and ct == torch.float32:
            # the core's rule (d2 < float32(r) * float32(r)) is mmcv's rule here
            _, idx = _core_ball_query(center_xyz, xyz, float(max_radius), sample_num)
        else:
            _, idx = _mmcv_ball(center_xyz, xyz, max_radius, sample_num, min_r2, max_r2)
    first = idx[..., :1]
    fill = torch.where(first >= 0, first, torch.zeros_like(first))
    return torch.where(idx >= 0, idx, fill).to(torch.int32)


def _mmcv_ball(center_xyz: Tensor, xyz: Tensor, max_radius: float, sample_num: int, min_r2: float, max_r2: float,
               center_lengths: Optional[Tensor] = None, xyz_lengths: Optional[Tensor] = None):
    """mmcv's rule (``d2 == 0 or min_r2 <= d2 < max_r2``, float32 squares, also for float64 points):
    query a slightly larger ball and filter exactly."""
    def keep(d2):
        return (d2 < max_r2) & ((d2 == 0) | (d2 >= min_r2))
    return _ball_query_filtered(center_xyz, xyz, float(max_radius) * (1 + 1e-6), sample_num, keep,
                                center_lengths, xyz_lengths)


def _ball_args(min_radius, max_radius, sample_num) -> Tuple[float, float, int]:
    for name, r in (("min_radius", min_radius), ("max_radius", max_radius)):
        if isinstance(r, bool) or not isinstance(r, numbers.Real) or not math.isfinite(r):
            raise ValueError(f"{name} must be a finite number, got {r!r}")
    if min_radius < 0:
        raise ValueError(f"min_radius must be >= 0, got {min_radius}")
    if not min_radius < max_radius:
        raise ValueError(f"min_radius must be < max_radius, got min_radius={min_radius}, max_radius={max_radius}")
    sample_num = check_positive_int(sample_num, "sample_num")
    return _f32_square(float(min_radius)), _f32_square(float(max_radius)), sample_num


def _stacked_counts(cnt, name: str, rows: int, rows_name: str) -> Tensor:
    """A (B,) integer count tensor, >= 0, summing to ``rows`` (value check), as int64."""
    _check_index(cnt, name)
    if cnt.dim() != 1:
        raise ValueError(f"{name} must be (B,), got {describe(cnt)}")
    c = cnt.to(torch.int64)
    if value_checks_enabled():
        run_value_checks([((c < 0).any() | (c.sum() != rows),
                           lambda: f"{name} must be >= 0 and sum to {rows} (the rows of {rows_name}), "
                                   f"got {c.tolist()}")])
    return c


def _stacked_to_padded(flat: Tensor, counts: Tensor) -> Tensor:
    """(N1 + N2 + ..., C) rows grouped by example -> (B, max N_b, C), zero padding."""
    B = counts.shape[0]
    n_max = int(counts.max()) if B else 0
    padded = flat.new_zeros(B, n_max, flat.shape[1])
    if flat.shape[0]:
        example = torch.repeat_interleave(torch.arange(B, device=flat.device), counts, output_size=flat.shape[0])
        start = torch.cumsum(counts, 0) - counts
        pos = torch.arange(flat.shape[0], device=flat.device) - start[example]
        padded[example, pos] = flat
    return padded


def _stacked_ball_query(min_radius, max_radius, sample_num, xyz, center_xyz, xyz_batch_cnt,
                        center_xyz_batch_cnt) -> Tensor:
    if xyz_batch_cnt is None or center_xyz_batch_cnt is None:
        raise ValueError("stacked mode needs both xyz_batch_cnt and center_xyz_batch_cnt")
    for name, t in (("xyz", xyz), ("center_xyz", center_xyz)):
        check_tensor(t, name)
        if t.dim() != 2 or t.shape[1] != 3 or not t.is_floating_point():
            raise ValueError(f"{name} must be a floating (N1 + N2 + ..., 3) tensor in stacked mode, "
                             f"got {describe(t)}")
    if xyz.dtype != center_xyz.dtype:
        raise ValueError(f"xyz and center_xyz must have the same dtype, got {xyz.dtype} and {center_xyz.dtype}")
    check_same_device([("xyz", xyz), ("center_xyz", center_xyz), ("xyz_batch_cnt", xyz_batch_cnt),
                       ("center_xyz_batch_cnt", center_xyz_batch_cnt)])
    min_r2, max_r2, sample_num = _ball_args(min_radius, max_radius, sample_num)
    ncnt = _stacked_counts(xyz_batch_cnt, "xyz_batch_cnt", xyz.shape[0], "xyz")
    mcnt = _stacked_counts(center_xyz_batch_cnt, "center_xyz_batch_cnt", center_xyz.shape[0], "center_xyz")
    if ncnt.shape != mcnt.shape:
        raise ValueError(f"xyz_batch_cnt and center_xyz_batch_cnt must have the same length B, got "
                         f"{describe(xyz_batch_cnt)} and {describe(center_xyz_batch_cnt)}")
    M = center_xyz.shape[0]
    if M == 0:
        return torch.zeros((0, sample_num), dtype=torch.int32, device=xyz.device)
    _check_finite_coordinates(("xyz", xyz), ("center_xyz", center_xyz))
    points = _stacked_to_padded(xyz, ncnt)
    centers = _stacked_to_padded(center_xyz, mcnt)
    with validation(False):
        _, idx = _mmcv_ball(centers, points, max_radius, sample_num, min_r2, max_r2, mcnt, ncnt)
    first = idx[..., :1]
    # mmcv's stack kernel: the first hit fills every slot; no hit writes -1 into slot 0 of a zero row
    fill = torch.where(first >= 0, first, torch.zeros_like(first))
    out = torch.where(idx >= 0, idx, fill)
    out[..., 0] = torch.where(first[..., 0] >= 0, out[..., 0], torch.full_like(out[..., 0], -1))
    take = torch.arange(centers.shape[1], device=xyz.device)[None, :] < mcnt[:, None]
    return out[take].to(torch.int32)


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
    k = check_positive_int(k, "k")
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
            Stacked mode: Tensor[M1 + M2 + ..., nsample] of indices local to each example; -1 and
            indices past their example (``>= N_b``) give zeros, as mmcv's stack kernel (which zero-fills
            its output and skips them), and no gradient; below -1 raises.
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
        run_value_checks([((local < -1).any(), "indices must be >= -1 in stacked mode (-1 and indices past "
                                               "their example give zeros)")])
    # mmcv's stack kernel leaves the (zero-initialised) output untouched for indices past the example
    inside = (local >= 0) & (local < fcnt[example][:, None])
    glob = torch.where(inside, local + offsets[example][:, None], torch.full_like(local, -1))
    out = _core_gather(features.unsqueeze(0), glob.unsqueeze(0))[0]  # (M, nsample, C)
    return out.permute(0, 2, 1).contiguous()
