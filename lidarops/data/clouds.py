"""LiDAR-like point clouds of any size for tests, benchmarks and tours of the ops: the one generator.

- :func:`simulated_sweep`: ``n`` points cut from the simulator's ``driving_city`` sweeps (ray-cast ground,
  buildings, vegetation, moving objects), what a rotating sensor sees;
- :func:`lidar_like_cloud`: a fast procedural stand-in (ground rings whose density falls with range, box
  surfaces, clutter) for sizes and seeds where simulating would cost too much.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["simulated_sweep", "lidar_like_cloud"]

_SENSOR_HEIGHT = 1.8  # metres above the ground


def lidar_like_cloud(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> Tensor:
    """A LiDAR-like cloud of exactly ``n`` points, in metres, in the sensor frame.

    About 55 % ground points on 48 rings (beam elevations -25 to -1.5 degrees, sensor 1.8 m above
    the ground, so ring radii run from 3.9 m to 69 m and the density falls with range), 35 % on the
    surfaces of boxes (cars, pedestrians, walls) 5-60 m away, 10 % in Gaussian clutter blobs. Points
    are ordered by azimuth, as a rotating sensor emits them. Deterministic for a given ``seed``.

    Args:
        n (int): number of points, >= 0.
        seed (int): random seed.
        dtype (torch.dtype): floating dtype of the result.

    Returns:
        Tensor[n, 3]: x, y, z coordinates.
    """
    g = torch.Generator().manual_seed(int(seed))

    def rand(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    def randn(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    n_obj, n_clutter = int(0.35 * n), int(0.10 * n)
    n_ground = n - n_obj - n_clutter
    parts = []

    # ground: equal azimuth sampling per beam, so far rings are sparse
    beams = 48
    elev = torch.linspace(math.radians(-25.0), math.radians(-1.5), beams, dtype=torch.float64)
    ring_r = _SENSOR_HEIGHT / torch.tan(-elev)
    beam = torch.arange(n_ground) % beams
    r = ring_r[beam] * (1.0 + 0.01 * randn(n_ground))
    az = 2 * math.pi * rand(n_ground)
    z = -_SENSOR_HEIGHT + 0.004 * r * torch.cos(az) + 0.03 * randn(n_ground)  # gentle slope
    parts.append(torch.stack([r * torch.cos(az), r * torch.sin(az), z], 1))

    # objects: boxes (length, width, height) at random positions, points spread over their surfaces
    if n_obj:
        kinds = torch.tensor([[4.5, 1.8, 1.6], [0.6, 0.6, 1.8], [20.0, 0.5, 6.0], [2.0, 2.0, 3.0]],
                             dtype=torch.float64)
        n_boxes = 40
        kind = torch.multinomial(torch.tensor([0.5, 0.25, 0.1, 0.15]), n_boxes, replacement=True, generator=g)
        size = kinds[kind] * (0.8 + 0.4 * rand(n_boxes, 3))
        dist = 5.0 + 55.0 * rand(n_boxes)
        ang = 2 * math.pi * rand(n_boxes)
        yaw = 2 * math.pi * rand(n_boxes)
        # nearer and larger boxes get more points, as they would from a sensor
        weight = (size[:, 0] * size[:, 2] + size[:, 1] * size[:, 2]) / dist.square()
        box = torch.multinomial(weight, n_obj, replacement=True, generator=g)
        u = rand(n_obj, 3) - 0.5
        face = torch.randint(0, 3, (n_obj,), generator=g)
        side = torch.where(rand(n_obj) < 0.5, -0.5, 0.5).to(torch.float64)
        u[torch.arange(n_obj), face] = side  # put each point on one face of its box
        local = u * size[box]
        c, s = torch.cos(yaw[box]), torch.sin(yaw[box])
        x = dist[box] * torch.cos(ang[box]) + c * local[:, 0] - s * local[:, 1]
        y = dist[box] * torch.sin(ang[box]) + s * local[:, 0] + c * local[:, 1]
        z = -_SENSOR_HEIGHT + size[box, 2] / 2 + local[:, 2]
        parts.append(torch.stack([x, y, z], 1))

    # clutter: vegetation-like blobs
    if n_clutter:
        blobs = 12
        centre = torch.stack([(8 + 50 * rand(blobs)) * torch.cos(2 * math.pi * rand(blobs)),
                              (8 + 50 * rand(blobs)) * torch.sin(2 * math.pi * rand(blobs)),
                              -_SENSOR_HEIGHT + 1.0 + 2.0 * rand(blobs)], 1)
        blob = torch.randint(0, blobs, (n_clutter,), generator=g)
        parts.append(centre[blob] + randn(n_clutter, 3) * torch.tensor([1.0, 1.0, 0.6], dtype=torch.float64))

    pts = torch.cat(parts) if parts else torch.zeros(0, 3, dtype=torch.float64)
    order = torch.argsort(torch.atan2(pts[:, 1], pts[:, 0]), stable=True)
    return pts[order].to(dtype)


_SIM_CACHE: dict = {}  # seed -> (simulator, list of sweep point tensors)


def _simulated_points(seed: int, min_points: int) -> Tensor:
    """Sweeps 0, 1, ... of the simulator's ``driving_city`` scene ``seed``, concatenated, >= min_points
    (cached per seed, so several sizes cut from one scene cost one simulation)."""
    if seed not in _SIM_CACHE:
        from lidarops.data.synthetic import Simulator

        sim = Simulator("driving_city", seed=seed)
        if len(_SIM_CACHE) >= 16:
            _SIM_CACHE.pop(next(iter(_SIM_CACHE)))
        _SIM_CACHE[seed] = (sim, [])
    sim, chunks = _SIM_CACHE[seed]
    while sum(c.shape[0] for c in chunks) < min_points and len(chunks) < 64:
        chunks.append(torch.as_tensor(sim.sweep(len(chunks)).points)[:, :3].to(torch.float32))
    return torch.cat(chunks) if len(chunks) > 1 else chunks[0]


def simulated_sweep(n: int, seed: int = 0) -> tuple[Tensor, str]:
    """A LiDAR sweep of exactly ``n`` points (float32, (n, 3)) and the name of its source.

    Uses ``lidarops.data.synthetic.Simulator("driving_city", seed=seed)``: its sweeps 0, 1, ... are
    concatenated until there are ``n`` points, then an order-preserving random subset of ``n`` is kept.
    Beyond what 64 sweeps hold: :func:`lidar_like_cloud`.
    """
    if n > 0:
        pts = _simulated_points(int(seed), int(n))
        if pts.shape[0] >= n:
            g = torch.Generator().manual_seed(int(seed))
            keep = torch.randperm(pts.shape[0], generator=g)[:n].sort().values
            return pts[keep].contiguous(), f'lidarops.data.synthetic.Simulator("driving_city", seed={seed})'
    return lidar_like_cloud(n, seed), "lidarops.data.clouds.lidar_like_cloud"
