"""Metrics: :mod:`~lidarops.eval.kitti`, KITTI's object evaluation (AP R11/R40 of the 2D, BEV, 3D and
orientation metrics)::

    from lidarops.eval import kitti
    text, results = kitti.evaluate(gt_annos, dt_annos, classes=("Car", "Pedestrian", "Cyclist"))
    print(text); results["Car_3d_moderate_R40"]

Submodules are imported on first use (``import lidarops.eval`` loads nothing else).
"""
from __future__ import annotations

import importlib
from typing import Any

__all__ = ["kitti", "evaluate_kitti", "evaluate_kitti_lidar"]

_LAZY = {
    "evaluate_kitti": ("lidarops.eval.kitti", "evaluate"),
    "evaluate_kitti_lidar": ("lidarops.eval.kitti", "evaluate_lidar"),
}


def __getattr__(name: str) -> Any:
    if name == "kitti":
        value = importlib.import_module("lidarops.eval.kitti")
    elif name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
    else:
        raise AttributeError(f"module 'lidarops.eval' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
