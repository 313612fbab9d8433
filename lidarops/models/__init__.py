"""Models built on lidarops' ops.

* :class:`PointPillars` (:mod:`lidarops.models.detector`): the PointPillars detector, OpenPCDet-compatible.
* :class:`GraphedPointPillars` (:mod:`lidarops.models.graph`): its inference replayed as one CUDA graph.
* :mod:`lidarops.models.weights`: the shipped checkpoints (``weights.load("pointpillars_synth")``).
* :mod:`lidarops.models.boxes`: box coder, anchors, target assignment.
* :mod:`lidarops.models.pointpillars`: the pillar feature net and the dense / sparse backbone (SSCATeR's too).
* :mod:`lidarops.models.config`: YAML configs (OpenPCDet's schema).

Submodules are imported on first use.
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes

__all__ = ["PointPillars", "GraphedPointPillars", "PointPillarsConfig", "load_config", "weights"]

__getattr__, __dir__ = lazy_attributes(__name__, {
    "PointPillars": ("lidarops.models.detector", "PointPillars"),
    "GraphedPointPillars": ("lidarops.models.graph", "GraphedPointPillars"),
    "PointPillarsConfig": ("lidarops.models.config", "PointPillarsConfig"),
    "load_config": ("lidarops.models.config", "load_config"),
    "weights": "lidarops.models.weights",
}, globals())
