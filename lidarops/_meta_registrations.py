"""Fake (meta) kernels: output shapes and dtypes of every op, for torch.compile and FakeTensor."""
from __future__ import annotations

import torch


def _dist_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


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


@torch.library.register_fake("lidarops::raycast_scene")
def _raycast_scene_fake(origins, dirs, times, origin_samples, ground_plane, wave_amp, wave_k, wave_phase, box_center,
                        box_half, box_yaw, box_velocity, box_yaw_rate, box_reflectivity, box_kind, box_object,
                        cyl_center_xy, cyl_z_min, cyl_z_max, cyl_radius, cyl_reflectivity, cyl_kind, ell_center,
                        ell_radii, ell_mean_free_path, ell_reflectivity, max_distance, foliage_key, num_objects,
                        ground_iterations, ground_tolerance):
    n = origins.shape[0]
    return (origins.new_empty((n,)), origins.new_empty((n,), dtype=torch.uint8),
            origins.new_empty((n,), dtype=torch.int32), origins.new_empty((n,)), origins.new_empty((n,)),
            origins.new_empty((num_objects,), dtype=torch.int64), origins.new_empty((num_objects,), dtype=torch.int64))
