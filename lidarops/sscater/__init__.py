"""SSCATeR: sparse scatter-based convolution with temporal data recycling (Hunt et al.), the engine.

- :class:`lidarops.sscater.delta.DeltaBackbone`: the recycling state of a BEV backbone, built from a list
  of :class:`~lidarops.sscater.delta.DeltaLayer` (what it reads of each convolution); it imports no model.
- :mod:`lidarops.sscater.ops`: validated wrappers of the ``torch.ops.lidarops.sscater_*`` ops and their
  float64 references.

The streaming detector front built on it (stream -> pillars -> PFN -> DeltaBackbone) is
:class:`lidarops.models.SSCATeRPointPillars`. Imports are lazy so that loading the extension (which
imports this package's fake kernels) stays light.
"""
from __future__ import annotations

from lidarops._lazy import lazy_attributes
from lidarops._moved import moved_attributes

__all__ = ["DeltaBackbone", "DeltaLayer", "Change", "LayerStats"]

_lazy_getattr, __dir__ = lazy_attributes(__name__, {
    "DeltaBackbone": ("lidarops.sscater.delta", "DeltaBackbone"),
    "DeltaLayer": ("lidarops.sscater.delta", "DeltaLayer"),
    "Change": ("lidarops.sscater.delta", "Change"),
    "LayerStats": ("lidarops.sscater.delta", "LayerStats"),
}, globals())
__getattr__ = moved_attributes(__name__, fallback=_lazy_getattr)
