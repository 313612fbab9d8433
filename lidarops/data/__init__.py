"""LiDAR data for lidarops: a synthetic LiDAR simulator with per-point timestamps, readers and writers of
the real dataset formats, object-level classification sets and PyTorch datasets.

Python/NumPy on top of the ops floor: the simulator's ray caster and points-in-boxes counts use the
compiled ops (``torch.ops.lidarops.raycast_scene``, :func:`lidarops.points_in_boxes`; ``LIDAROPS_DATA_NATIVE=0``
keeps the ray caster to NumPy: see :mod:`lidarops.data._raycast`). ``import lidarops.data`` loads only
NumPy; the simulator, the formats, torch datasets (torch) and plotting (matplotlib) are imported on first
use::

    from lidarops.data import Simulator, CLASSES
    frame = Simulator("driving_city", seed=0).sweep(0)

Submodules: :mod:`~lidarops.data.synthetic` (``Simulator``), :mod:`~lidarops.data.sensors`,
:mod:`~lidarops.data.scene`, :mod:`~lidarops.data.formats` (KITTI, PandaSet, nuScenes, ModelNet40),
:mod:`~lidarops.data.objects`, :mod:`~lidarops.data.datasets` (torch datasets and :func:`collate_batch`,
the one batch dialect), :mod:`~lidarops.data.detection` (OpenPCDet-style detection training data, torch),
:mod:`~lidarops.data.augment` (flips, rotations, scaling, gt sampling), :mod:`~lidarops.data.viz`
(matplotlib). The command line is :mod:`lidarops.cli.data`.
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes
from lidarops.data.frame import CLASS_COLORS, CLASSES, Frame, class_index
from lidarops.data.geometry import box_corners, count_points_in_boxes, points_in_boxes_mask

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
    "collate_batch": "lidarops.data.datasets",
    "collate_detection": "lidarops.data.datasets",
    "collate_objects": "lidarops.data.datasets",
    "KittiDetectionDataset": "lidarops.data.detection",
    "DetectionConfig": "lidarops.data.detection",
    "train_val_datasets": "lidarops.data.detection",
    "GtDatabase": "lidarops.data.augment",
    "GtSampler": "lidarops.data.augment",
    "build_gt_database": "lidarops.data.augment",
    "save_bev": "lidarops.data.viz",
    "ObjectClassificationDataset": "lidarops.data.object_sets",
    "ObjectSetRecipe": "lidarops.data.object_sets",
    "build_object_set": "lidarops.data.object_sets",
    "collate_classification": "lidarops.data.object_sets",
}

__all__ = ["CLASSES", "CLASS_COLORS", "Frame", "class_index", "box_corners", "count_points_in_boxes",
           "points_in_boxes_mask", *_LAZY]

__getattr__, __dir__ = lazy_attributes(__name__, {name: (module, name) for name, module in _LAZY.items()}, globals())
