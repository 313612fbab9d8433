"""Validated wrappers of the registered ops (``torch.ops.lidarops.*``), filed by what they are:
neighbourhoods, voxels and pillars, rotated boxes."""
from lidarops.ops.assign import greedy_assign
from lidarops.ops.boxes import (batched_nms_bev, box_iou_3d, box_iou_bev, box_overlap_bev, nms_bev, nms_bev_frames,
                                 points_in_boxes)
from lidarops.ops.neighbors import ball_query, fps, gather, knn
from lidarops.ops.pillars import PillarGrid, PillarOverflowError, Pillars, invalid_points, pillarize
from lidarops.ops.validation import validation
from lidarops.ops.voxelize import VoxelOverflowError, voxelize

__all__ = ["greedy_assign", "fps", "knn", "ball_query", "gather", "validation", "box_overlap_bev", "box_iou_bev", "box_iou_3d",
           "nms_bev", "nms_bev_frames", "batched_nms_bev", "points_in_boxes", "voxelize", "VoxelOverflowError", "pillarize",
           "PillarGrid", "Pillars", "PillarOverflowError", "invalid_points"]
