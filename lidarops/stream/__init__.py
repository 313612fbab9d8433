"""Streaming pillarization (the front end of SSCATeR): ``PillarStream``, a sliding time window kept as
per-pillar queues, over the pillar grids of :mod:`lidarops.ops.pillars` (re-exported here). See
``docs/stream.md``.

    PillarGrid(point_cloud_range, voxel_size)  H x W pillars; presets PillarGrid.drone(), .kitti(), .driving()
    pillarize(points, grid, ...)           -> Pillars(features [P, N, 9], coords int32 [P, 3], num_points [P])
    PillarStream(grid, window=0.1, ...)    .push(points, t) -> StreamUpdate; .pillars(coords) -> Pillars

Pillars are sorted by the linear key ``y * W + x``; coords are ``(batch=0, y, x)``.
"""
from __future__ import annotations

from lidarops.ops.pillars import (
    MAX_ABS_INTENSITY,
    MAX_ABS_TIME,
    PillarGrid,
    PillarOverflowError,
    Pillars,
    invalid_points,
    pillarize,
)
from lidarops.stream.pillar_stream import PillarStream, StreamCounts, StreamUpdate

__all__ = ["PillarGrid", "Pillars", "pillarize", "PillarStream", "StreamUpdate", "StreamCounts", "PillarOverflowError",
           "invalid_points", "MAX_ABS_INTENSITY", "MAX_ABS_TIME"]
