"""lidarops: fast, tested PyTorch C++/CUDA ops for LiDAR point clouds.

Core ops (registered as ``torch.ops.lidarops.*``; these are their validated wrappers)::

    lidarops.fps(points, k)               farthest point sampling       -> idx (B, k)
    lidarops.knn(query, points, k)        k nearest neighbours          -> dist2, idx (B, M, k)
    lidarops.ball_query(q, p, radius, k)  first k points within radius  -> dist2, idx (B, M, k)
    lidarops.gather(x, idx)               grouping (PointNet++)         -> (B, *idx.shape[1:], C)
    lidarops.voxelize(points, voxel_size, point_cloud_range, max_points_per_voxel, max_voxels)
                                          hard voxelization             -> voxels, coords, num_points
    lidarops.pillarize(points, grid)      decorated pillars (PointPillars) -> features, coords, num_points
    lidarops.box_iou_bev(a, b)            rotated BEV IoU (also box_overlap_bev, box_iou_3d) -> (N, M)
    lidarops.nms_bev(boxes, scores, thr)  rotated NMS (also batched_nms_bev, nms_bev_frames)  -> keep (K,)
    lidarops.points_in_boxes(points, boxes)  box index of each point          -> (P,)
    lidarops.PillarStream(grid, window)   streaming pillarization (lidarops.stream)

The compiled library is loaded on first use, so ``import lidarops.data`` works without it.
"""
from __future__ import annotations

from lidarops import _moved
from lidarops._lazy import lazy_attributes

__version__ = "0.2.0"

_moved.install()  # old module paths (lidarops.models.detector, ...) import for one more release

_LAZY = {
    "fps": "lidarops.ops.neighbors",
    "knn": "lidarops.ops.neighbors",
    "ball_query": "lidarops.ops.neighbors",
    "gather": "lidarops.ops.neighbors",
    "greedy_assign": "lidarops.ops.assign",
    "voxelize": "lidarops.ops.voxelize",
    "box_overlap_bev": "lidarops.ops.boxes",
    "box_iou_bev": "lidarops.ops.boxes",
    "box_iou_3d": "lidarops.ops.boxes",
    "nms_bev": "lidarops.ops.boxes",
    "batched_nms_bev": "lidarops.ops.boxes",
    "nms_bev_frames": "lidarops.ops.boxes",
    "points_in_boxes": "lidarops.ops.boxes",
    "pillarize": "lidarops.ops.pillars",
    "PillarGrid": "lidarops.ops.pillars",
    "PillarStream": "lidarops.stream",
    "validation": "lidarops.ops.validation",
}

__all__ = sorted(_LAZY) + ["__version__"]


__getattr__, __dir__ = lazy_attributes(__name__, {name: (module, name) for name, module in _LAZY.items()}, globals())
