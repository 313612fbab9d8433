"""Box sets shared by the box tests (tests/ops/test_boxes.py) and benchmarks/bm_boxes.py (seeded, float64, CPU)."""
from __future__ import annotations

import math

import torch


def random_boxes(n: int, seed: int, extent: float = 6.0, dtype=torch.float64) -> torch.Tensor:
    """Cluttered boxes: centres in a small square so that many pairs overlap, any heading."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * extent
    z = torch.rand(n, 1, generator=g, dtype=torch.float64) * 2 - 1
    size = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([4.0, 2.0, 2.0]) + 0.2
    heading = (torch.rand(n, 1, generator=g, dtype=torch.float64) - 0.5) * 4 * math.pi
    return torch.cat([xy, z, size, heading], 1).to(dtype)


def lidar_boxes(n: int, seed: int, objects: int | None = None) -> torch.Tensor:
    """KITTI-like detections: car-sized boxes clustered around ``objects`` objects (default n / 12) in a
    70 x 80 m range, several near-duplicates per object (as an anchor head's pre-NMS output)."""
    g = torch.Generator().manual_seed(seed)
    objects = max(1, n // 12) if objects is None else objects
    centres = torch.rand(objects, 2, generator=g, dtype=torch.float64) * torch.tensor([70.0, 80.0]) - torch.tensor(
        [0.0, 40.0])
    which = torch.randint(0, objects, (n,), generator=g)
    xy = centres[which] + torch.randn(n, 2, generator=g, dtype=torch.float64) * 0.4
    z = torch.full((n, 1), -1.0, dtype=torch.float64) + torch.randn(n, 1, generator=g, dtype=torch.float64) * 0.1
    size = torch.tensor([3.9, 1.6, 1.56], dtype=torch.float64) * (1 + 0.1 * torch.randn(n, 3, generator=g,
                                                                                           dtype=torch.float64))
    heading = (torch.rand(objects, 1, generator=g, dtype=torch.float64)[which] * 2 * math.pi
               + 0.2 * torch.randn(n, 1, generator=g, dtype=torch.float64))
    return torch.cat([xy, z, size, heading], 1)
