"""Point clouds for the voxelization tests and benchmarks (importable from both)."""
from __future__ import annotations

import numpy as np

# KITTI PointPillars (OpenPCDet pointpillar.yaml) and SECOND (second.yaml) grids
KITTI_PILLARS = dict(voxel_size=(0.16, 0.16, 4.0), point_cloud_range=(0.0, -39.68, -3.0, 69.12, 39.68, 1.0))
KITTI_SECOND = dict(voxel_size=(0.05, 0.05, 0.1), point_cloud_range=(0.0, -40.0, -3.0, 70.4, 40.0, 1.0))


def lidar_sweep(n: int = 120_000, seed: int = 0, beams: int = 64, sensor_height: float = 1.73,
                objects: int = 40, max_range: float = 80.0) -> np.ndarray:
    """A LiDAR-like sweep, float32 (n, 4): x, y, z, intensity.

    A spinning sensor ``sensor_height`` above flat ground at z = -sensor_height: beams from -24.9 to
    +2 degrees, jittered azimuths; beams that hit one of ``objects`` vertical surfaces (azimuth
    sectors at 3-45 m) stop there, downward beams otherwise hit the ground, upward ones go to
    ``max_range``. The density falls as 1/r^2, so voxels near the sensor hold many points (the case
    where a capacity overflows) and far ones few, as in real sweeps.
    """
    rng = np.random.default_rng(seed)
    per_beam = -(-n // beams)
    elev = np.deg2rad(np.linspace(-24.9, 2.0, beams))[:, None].repeat(per_beam, 1)
    az = (np.linspace(-np.pi, np.pi, per_beam, endpoint=False)[None, :]
          + rng.normal(0.0, 2e-4, size=(beams, per_beam)))
    ground = np.where(elev < 0, sensor_height / np.tan(np.maximum(-elev, 1e-6)), np.inf)
    r = np.minimum(ground, max_range)
    centers = rng.uniform(-np.pi, np.pi, objects)
    widths = rng.uniform(0.02, 0.25, objects)
    dists = rng.uniform(3.0, 45.0, objects)
    heights = rng.uniform(0.5, 4.0, objects)
    for c, w, d, h in zip(centers, widths, dists, heights):
        in_sector = np.abs(np.angle(np.exp(1j * (az - c)))) < w / 2
        z_at_d = d * np.tan(elev)  # height relative to the sensor where the beam reaches distance d
        hits = in_sector & (z_at_d > -sensor_height) & (z_at_d < h - sensor_height) & (d < r)
        r = np.where(hits, d, r)
    r = r * (1.0 + rng.normal(0.0, 0.002, size=r.shape))
    x = r * np.cos(elev) * np.cos(az)
    y = r * np.cos(elev) * np.sin(az)
    z = r * np.sin(elev)
    intensity = rng.uniform(0.0, 1.0, size=r.shape)
    pts = np.stack([x, y, z, intensity], -1).reshape(-1, 4)[:n]
    return pts.astype(np.float32)
