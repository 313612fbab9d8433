"""Models built on lidarops' ops.

* :class:`PointPillars` (:mod:`lidarops.models.detector`): the PointPillars detector, OpenPCDet-compatible.
* :mod:`lidarops.models.weights`: the shipped checkpoints (``weights.load("pointpillars_synth")``).
* :mod:`lidarops.models.boxes`: box coder, anchors, target assignment.
* :mod:`lidarops.models.pointpillars`: the pillar feature net and the dense / sparse backbone (SSCATeR's too).
* :mod:`lidarops.models.config`: YAML configs (OpenPCDet's schema).

Submodules are imported on first use.
"""
from __future__ import annotations

import importlib
from typing import Any

__all__ = ["PointPillars", "PointPillarsConfig", "load_config", "weights"]

_LAZY = {
    "PointPillars": ("lidarops.models.detector", "PointPillars"),
    "PointPillarsConfig": ("lidarops.models.config", "PointPillarsConfig"),
    "load_config": ("lidarops.models.config", "load_config"),
}


def __getattr__(name: str) -> Any:
    if name == "weights":
        value = importlib.import_module("lidarops.models.weights")
    elif name in _LAZY:
        module, attr = _LAZY[name]
        value = getattr(importlib.import_module(module), attr)
    else:
        raise AttributeError(f"module 'lidarops.models' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
