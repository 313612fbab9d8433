"""Fake (meta) kernel of ``lidarops::kitti_match`` (schema in csrc/ops/kitti_eval.cpp); imported by
:func:`lidarops.extension.load`. Not differentiable: no autograd formula, Python or C++ (``csrc/ops/autograd``)."""
from __future__ import annotations

import torch


@torch.library.register_fake("lidarops::kitti_match")
def _kitti_match_fake(overlaps, overlap_offsets, gt_offsets, dt_offsets, ignored_gt, ignored_dt, dt_scores,
                      dt_dontcare, gt_alpha, dt_alpha, thresholds, min_overlap, compute_fp, compute_aos):
    g = 0 if compute_fp else ignored_gt.shape[0]
    t = thresholds.shape[0] if compute_fp else 0
    return overlaps.new_empty((g,), dtype=torch.float64), overlaps.new_empty((t, 4), dtype=torch.float64)
