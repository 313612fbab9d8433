"""SSCATeR: sparse scatter-based convolution with temporal data recycling (Hunt et al.).

- :class:`lidarops.sscater.delta.DeltaBackbone`: the recycling state of a PointPillars backbone.
- :class:`lidarops.sscater.pointpillars.SSCATeRPointPillars`: stream -> pillars -> PFN -> backbone,
  recomputing only what changed.
- :mod:`lidarops.sscater.ops`: validated wrappers of the ``torch.ops.lidarops.sscater_*`` ops and their
  float64 references.
- :mod:`lidarops.sscater.models`: seeded PointPillars fronts and the BatchNorm calibration for a ReLU zero
  share (used by ``lidarops stream``, ``benchmarks/bm_sscater.py`` and ``benchmarks/profile/``).

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
