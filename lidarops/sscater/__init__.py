"""SSCATeR: sparse scatter-based convolution with temporal data recycling (Hunt et al.).

- :class:`lidarops.sscater.delta.DeltaBackbone`: the recycling state of a PointPillars backbone.
- :class:`lidarops.sscater.pointpillars.SSCATeRPointPillars`: stream -> pillars -> PFN -> backbone,
  recomputing only what changed.

Imports are lazy so that loading the extension (which imports this package's fake kernels) stays light.
"""
from __future__ import annotations

import importlib

__all__ = ["DeltaBackbone", "Change", "LayerStats", "SSCATeRPointPillars"]

_WHERE = {"DeltaBackbone": "delta", "Change": "delta", "LayerStats": "delta", "SSCATeRPointPillars": "pointpillars"}


def __getattr__(name):
    if name in _WHERE:
        return getattr(importlib.import_module(f"lidarops.sscater.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'lidarops.sscater' has no attribute {name!r}")
