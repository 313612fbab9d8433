"""LiDAR data for lidarops: a synthetic LiDAR simulator with per-point timestamps, readers and writers of
the real dataset formats, object-level classification sets and PyTorch datasets.

Python/NumPy; nothing here needs the compiled extension, but the simulator's ray caster uses it when it
is built (``torch.ops.lidarops.raycast_scene``, loaded with torch on the first cast; ``LIDAROPS_DATA_NATIVE=0``
keeps to NumPy: see :mod:`lidarops.data._raycast`).  ``import lidarops.data`` loads only NumPy; the
simulator, the formats, torch datasets (torch) and plotting (matplotlib) are imported on first use::

    from lidarops.data import Simulator, CLASSES
    frame = Simulator("driving_city", seed=0).sweep(0)

Submodules: :mod:`~lidarops.data.synthetic` (``Simulator``), :mod:`~lidarops.data.sensors`,
:mod:`~lidarops.data.scene`, :mod:`~lidarops.data.formats` (KITTI, PandaSet, nuScenes, ModelNet40),
:mod:`~lidarops.data.objects`, :mod:`~lidarops.data.datasets` (torch), :mod:`~lidarops.data.detection`
(OpenPCDet-style detection training data, torch), :mod:`~lidarops.data.viz`
(matplotlib), :mod:`~lidarops.data.cli`.
"""
from __future__ import annotations

import importlib
from typing import Any

from lidarops.data.frame import CLASS_COLORS, CLASSES, Frame, class_index
from lidarops.data.geometry import box_corners, count_points_in_boxes, points_in_boxes_mask

__all__ = [
    "CLASSES",
    "CLASS_COLORS",
    "Frame",
    "class_index",
    "box_corners",
    "count_points_in_boxes",
    "points_in_boxes_mask",
    # lazily imported
    "Simulator",
    "SyntheticFrames",
    "SCENARIOS",
    "SpinningLidar",
    "RisleyLidar",
    "hdl64",
    "pandar64",
    "avia",
    "open_frames",
    "read_frame",
    "KittiDataset",
    "PandaSetSequence",
    "ModelNet40",
    "ObjectSet",
    "extract_objects",
    "split_balanced",
    "DetectionDataset",
    "ObjectDataset",
    "StreamDataset",
    "collate_detection",
    "collate_objects",
    "KittiDetectionDataset",
    "DetectionConfig",
    "train_val_datasets",
    "save_bev",
]

_LAZY = {
    "Simulator": "lidarops.data.synthetic",
    "SyntheticFrames": "lidarops.data.synthetic",
    "SCENARIOS": "lidarops.data.scenarios",
    "SpinningLidar": "lidarops.data.sensors",
    "RisleyLidar": "lidarops.data.sensors",
    "hdl64": "lidarops.data.sensors",
    "pandar64": "lidarops.data.sensors",
    "avia": "lidarops.data.sensors",
    "open_frames": "lidarops.data.formats",
    "read_frame": "lidarops.data.formats",
    "KittiDataset": "lidarops.data.formats",
    "PandaSetSequence": "lidarops.data.formats",
    "ModelNet40": "lidarops.data.formats",
    "ObjectSet": "lidarops.data.objects",
    "extract_objects": "lidarops.data.objects",
    "split_balanced": "lidarops.data.objects",
    "DetectionDataset": "lidarops.data.datasets",
    "ObjectDataset": "lidarops.data.datasets",
    "StreamDataset": "lidarops.data.datasets",
    "collate_detection": "lidarops.data.datasets",
    "collate_objects": "lidarops.data.datasets",
    "KittiDetectionDataset": "lidarops.data.detection",
    "DetectionConfig": "lidarops.data.detection",
    "train_val_datasets": "lidarops.data.detection",
    "save_bev": "lidarops.data.viz",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'lidarops.data' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
