"""Validated wrappers of the registered ops (``torch.ops.lidarops.*``)."""
from lidarops.ops.neighbors import ball_query, fps, gather, knn
from lidarops.ops.validation import validation

__all__ = ["fps", "knn", "ball_query", "gather", "validation"]
