"""Metrics: :mod:`~lidarops.eval.kitti`, KITTI's object evaluation (AP R11/R40 of the 2D, BEV, 3D and
orientation metrics), and :mod:`~lidarops.eval.counting`, CounterNet's counting and query metrics over
per-frame counts (used by :mod:`lidarops.query.evaluate`), and :mod:`~lidarops.eval.classification`,
object classification accuracy (overall, mean per class, confusion matrix)::

    from lidarops.eval import kitti
    text, results = kitti.evaluate(gt_annos, dt_annos, classes=KITTI_CLASSES)   # lidarops.conventions
    print(text); results["Car_3d_moderate_R40"]

Submodules are imported on first use (``import lidarops.eval`` loads nothing else).
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes

__all__ = ["kitti", "counting", "classification", "evaluate_kitti", "evaluate_kitti_lidar"]

__getattr__, __dir__ = lazy_attributes(__name__, {
    "kitti": "lidarops.eval.kitti",
    "counting": "lidarops.eval.counting",
    "classification": "lidarops.eval.classification",
    "evaluate_kitti": ("lidarops.eval.kitti", "evaluate"),
    "evaluate_kitti_lidar": ("lidarops.eval.kitti", "evaluate_lidar"),
}, globals())
