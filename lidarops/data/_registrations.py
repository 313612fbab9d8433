"""Fake (meta) kernels of the ray caster ``lidarops::raycast_scene`` and the shape tracer ``lidarops::trace_shapes``
(schemas in csrc/ops/raycast.cpp; called by :mod:`lidarops.data._raycast` and :mod:`lidarops.data.shapes`). It is not differentiable: no autograd formula, Python or C++
(``csrc/ops/autograd``). Imported by :func:`lidarops.extension.load`, never by ``import lidarops.data``
(which stays free of torch).
"""
from __future__ import annotations

import torch


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


@torch.library.register_fake("lidarops::trace_shapes")
def _trace_shapes_fake(kind, entry, d, half, u):
    n = entry.shape[0]
    return entry.new_empty((n,)), entry.new_empty((n,), dtype=torch.bool), entry.new_empty((n,))
