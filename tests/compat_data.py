"""Test data shared by the compat-face tests."""
from __future__ import annotations

import numpy as np


def lidar_like(n: int, rng: np.random.Generator, quant: float = 0.02) -> np.ndarray:
    """A spinning-LiDAR-like cloud: 32 beams on a ground plane and walls, a few clustered objects,
    coordinates quantised to 2 cm (so exact duplicates and equal distances occur)."""
    n_obj = n // 4
    n_scan = n - n_obj
    az = rng.uniform(-np.pi, np.pi, n_scan)
    elev = np.deg2rad(rng.choice(np.linspace(-25.0, 3.0, 32), n_scan))
    r = np.where(elev < -0.03, 1.8 / np.tan(np.clip(-elev, 0.03, None)), rng.uniform(5.0, 80.0, n_scan))
    r = np.minimum(r, 120.0)
    scan = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev)], 1)
    centers = rng.uniform(-40.0, 40.0, (4, 3)) * np.array([1.0, 1.0, 0.02])
    obj = centers[rng.integers(0, 4, n_obj)] + rng.normal(0.0, 0.6, (n_obj, 3))
    pts = np.concatenate([scan, obj])[rng.permutation(n)]
    return (np.round(pts / quant) * quant).astype(np.float32)
