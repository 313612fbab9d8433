"""Float64 pure-PyTorch references of the ops, by their public names: slow, simple, written a different way
from the kernels, for checking a result on your own data (``lidarops tour`` does) and for the tests.

    from lidarops.ops import references
    idx = references.fps(points, 1024)            # what lidarops.fps must return, computed in float64

Each is its op's ``_<op>_reference`` beside the wrapper (the tie rules and padding of the op it checks).
"""
from __future__ import annotations

from lidarops.ops.boxes import _box_iou_3d_reference as box_iou_3d
from lidarops.ops.boxes import _box_iou_bev_reference as box_iou_bev
from lidarops.ops.boxes import _box_overlap_bev_reference as box_overlap_bev
from lidarops.ops.boxes import _nms_bev_reference as nms_bev
from lidarops.ops.boxes import _points_in_boxes_reference as points_in_boxes
from lidarops.ops.neighbors import _ball_query_reference as ball_query
from lidarops.ops.neighbors import _fps_reference as fps
from lidarops.ops.neighbors import _gather_reference as gather
from lidarops.ops.neighbors import _knn_reference as knn
from lidarops.ops.pillars import _pillarize_reference as pillarize
from lidarops.ops.voxelize import _voxelize_reference as voxelize

__all__ = ["fps", "knn", "ball_query", "gather", "voxelize", "pillarize", "box_overlap_bev", "box_iou_bev",
           "box_iou_3d", "nms_bev", "points_in_boxes"]
