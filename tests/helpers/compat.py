"""Test data of the compat-face tests (tests/compat/)."""
from __future__ import annotations

import numpy as np

from helpers.clouds import lidar_points


def lidar_like(n: int, rng: np.random.Generator, quant: float = 0.02) -> np.ndarray:
    """A LiDAR-like cloud, float32 (n, 3) (:func:`helpers.clouds.lidar_points`, seeded from ``rng``),
    coordinates quantised to ``quant`` (2 cm: exact duplicates and equal distances can occur; the tie
    rules have their own tests with constructed ties)."""
    return lidar_points(n, int(rng.integers(2**31)), quant=quant)
