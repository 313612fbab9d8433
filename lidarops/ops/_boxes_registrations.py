"""Fake (meta) kernels of the rotated-box ops (schemas in csrc/ops/boxes.cpp); none is differentiable."""
from __future__ import annotations

import torch


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


@torch.library.register_fake("lidarops::points_in_boxes")
def _points_in_boxes_fake(points, boxes):
    return points.new_empty((points.shape[0],), dtype=torch.int64)
