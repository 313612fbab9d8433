"""Fake kernels of the streaming pillarization ops (schemas in csrc/ops/pillar_stream.cpp; the one-shot
``pillar_decorate``'s is in :mod:`lidarops.ops._registrations`).

Every op is shape-static: ``pillar_stream_gather``
returns one row per requested pillar, and ``pillar_stream_push`` returns an (H, W) change map, a fixed
stats vector and one count per run. The data-dependent parts (which pillars are active or changed)
are read by the wrapper (``lidarops.stream.pillar_stream``). No op is differentiable (the features are the
network's input), so there is no autograd formula, Python or C++ (``csrc/ops/autograd``). Imported by
``lidarops.extension.load()``.
"""
from __future__ import annotations

import torch

_NUM_STATS = 13  # kNumPillarStreamStats in csrc/include/lidarops/pillar_stream.h


@torch.library.register_fake("lidarops::pillar_stream_gather")
def _pillar_stream_gather_fake(pool_xyzi, head, count, cell_slot, cells):
    P = cells.shape[0]
    return (pool_xyzi.new_empty((P, pool_xyzi.shape[1], 4)), pool_xyzi.new_empty((P,), dtype=torch.int32))


@torch.library.register_fake("lidarops::pillar_stream_push")
def _pillar_stream_push_fake(pool_xyzi, pool_t, head, count, slot_cell, cell_slot, free_slots, num_free, log_cell,
                             log_t, points, t, runs, log_head, cutoff, point_range, pillar_size, grid_hw,
                             drop=False, scalars=None):
    H, W = grid_hw
    return (points.new_empty((H, W), dtype=torch.bool), points.new_empty((_NUM_STATS,), dtype=torch.int64),
            points.new_empty((runs.shape[0],), dtype=torch.int64))
