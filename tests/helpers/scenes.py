"""The simulator's static scenery, measured from its primitives for tests."""
from __future__ import annotations

import numpy as np

#: where the roadside structures may stand (y from, to; the road's frame), by scenario: clear of every labelled lane
STRUCTURE_ZONES = {"driving_city": ((-15.8, -14.6), (-11.2, -10.8), (10.8, 11.2), (14.6, 15.8)),
                   "driving_highway": ((-17.0, -13.5), (16.4, 19.5))}


def in_zones(lo, hi, zones) -> np.ndarray:
    """Whether each extent ``[lo, hi]`` lies within one of ``zones``."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    return np.any([(lo >= a - 1e-9) & (hi <= b + 1e-9) for a, b in zones], axis=0).reshape(lo.shape)


def primitive_extents(prims):
    """Each static primitive's extent across the road (y from, to), from its own geometry (float64[K, 2])."""
    out = []
    b = prims.boxes
    for c, h, yaw in zip(b.center, b.half, b.yaw):
        reach = abs(np.sin(yaw)) * h[0] + abs(np.cos(yaw)) * h[1]
        out.append((c[1] - reach, c[1] + reach))
    cyl = prims.cylinders
    for (_, y), r in zip(cyl.center_xy, cyl.radius):
        out.append((y - r, y + r))
    e = prims.ellipsoids
    for c, r in zip(e.center, e.radii):
        out.append((c[1] - r[1], c[1] + r[1]))
    return np.asarray(out).reshape(-1, 2)
