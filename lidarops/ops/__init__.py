"""Validated wrappers of the registered ops (``torch.ops.lidarops.*``)."""
from lidarops.ops.boxes import batched_nms_bev, box_iou_3d, box_iou_bev, box_overlap_bev, nms_bev, points_in_boxes
from lidarops.ops.neighbors import ball_query, fps, gather, knn
from lidarops.ops.validation import validation

__all__ = ["fps", "knn", "ball_query", "gather", "validation", "box_overlap_bev", "box_iou_bev", "box_iou_3d",
           "nms_bev", "batched_nms_bev", "points_in_boxes"]
