"""Grids and clouds of the voxelization tests and benchmarks/bm_voxelize.py."""
from __future__ import annotations

import numpy as np

from helpers.clouds import lidar_points

# KITTI PointPillars (OpenPCDet pointpillar.yaml) and SECOND (second.yaml) grids
KITTI_PILLARS = dict(voxel_size=(0.16, 0.16, 4.0), point_cloud_range=(0.0, -39.68, -3.0, 69.12, 39.68, 1.0))
KITTI_SECOND = dict(voxel_size=(0.05, 0.05, 0.1), point_cloud_range=(0.0, -40.0, -3.0, 70.4, 40.0, 1.0))


def lidar_sweep(n: int = 120_000, seed: int = 0) -> np.ndarray:
    """A LiDAR-like sweep, float32 (n, 4): x, y, z, intensity (:func:`helpers.clouds.lidar_points`). Its
    density falls with range, so voxels near the sensor hold many points (the case where a capacity
    overflows) and far ones few, as in real sweeps."""
    return lidar_points(n, seed, intensity=True)
