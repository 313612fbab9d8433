"""Synthetic point clouds of the tests (also used by ``benchmarks/``); every one is seeded.

One LiDAR-like generator: :func:`lidar_cloud`, which cuts its clouds from
:func:`lidarops.data.clouds.lidar_like_cloud` (ground rings whose density falls with range, box surfaces,
clutter; the generator the benchmarks and ``lidarops tour`` use) and shuffles their points. The forms other
tests want are views of it: :func:`lidar_points` (one NumPy cloud, float32, optionally with an intensity
column and quantised coordinates), ``helpers.voxelize.lidar_sweep`` and ``helpers.compat.lidar_like``.

The batched generators return a float64 CPU tensor ``(B, N, 3)`` cast by the caller with
``.to(device, dtype)``, so a reference computed on the cast values sees exactly what the kernel sees.
"""
from __future__ import annotations

import numpy as np
import torch

from lidarops.data.clouds import lidar_like_cloud


def lidar_cloud(B: int, N: int, seed: int = 0) -> torch.Tensor:
    """(B, N, 3) float64 LiDAR-like scans (:func:`lidarops.data.clouds.lidar_like_cloud`, seeds
    ``1000 * seed + b``), each row's points in a seeded random order (not the sensor's azimuth order).
    Coordinates reach about +-70 m; z from about -3 m to 5 m."""
    out = torch.empty(B, N, 3, dtype=torch.float64)
    for b in range(B):
        g = torch.Generator().manual_seed(1000 * seed + b)
        out[b] = lidar_like_cloud(N, 1000 * seed + b, torch.float64)[torch.randperm(N, generator=g)]
    return out


def lidar_points(n: int, seed: int = 0, intensity: bool = False, quant: float | None = None) -> np.ndarray:
    """One LiDAR-like cloud as NumPy float32 ``(n, 3)`` (``(n, 4)`` with an intensity column uniform in
    [0, 1) when ``intensity``): :func:`lidar_cloud`'s row, with its coordinates rounded to multiples of
    ``quant`` metres when given (exact duplicates and equal distances then occur)."""
    xyz = lidar_cloud(1, n, seed)[0].numpy()
    if quant is not None:
        xyz = np.round(xyz / quant) * quant
    if intensity:
        rng = np.random.default_rng(seed)
        xyz = np.concatenate([xyz, rng.uniform(0.0, 1.0, (n, 1))], 1)
    return xyz.astype(np.float32)


def uniform_cloud(B: int, N: int, seed: int = 0, scale: float = 1.0) -> torch.Tensor:
    """Points uniform in the cube [-scale, scale]^3."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.uniform(-scale, scale, size=(B, N, 3)))


def lattice_cloud(B: int, N: int, seed: int = 0, side: int = 5) -> torch.Tensor:
    """Points on the integer lattice {0..side-1}^3: exact distance ties everywhere, many duplicates."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.integers(0, side, size=(B, N, 3)).astype(np.float64))


def duplicate_cloud(B: int, N: int, seed: int = 0, unique: int | None = None, scale: float = 1.0) -> torch.Tensor:
    """N points drawn with repetition from ``unique`` (default N // 4) distinct uniform points."""
    rng = np.random.default_rng(seed)
    u = max(1, N // 4 if unique is None else unique)
    base = rng.uniform(-scale, scale, size=(B, u, 3))
    pick = rng.integers(0, u, size=(B, N))
    return torch.from_numpy(np.take_along_axis(base, pick[..., None], axis=1))


def identical_cloud(B: int, N: int, value: tuple[float, float, float] = (1.5, -2.0, 0.25)) -> torch.Tensor:
    """N copies of one point: every distance ties."""
    return torch.tensor(value, dtype=torch.float64).expand(B, N, 3).clone()


CLOUD_KINDS = ("uniform", "lidar", "lattice", "duplicates")


def make_cloud(kind: str, B: int, N: int, seed: int = 0) -> torch.Tensor:
    if kind == "uniform":
        return uniform_cloud(B, N, seed)
    if kind == "lidar":
        return lidar_cloud(B, N, seed)
    if kind == "lattice":
        return lattice_cloud(B, N, seed)
    if kind == "duplicates":
        return duplicate_cloud(B, N, seed)
    if kind == "identical":
        return identical_cloud(B, N)
    raise ValueError(f"unknown cloud kind {kind!r}")


def ragged_lengths(B: int, N: int, seed: int = 0) -> torch.Tensor:
    """(B,) int64 lengths in [0, N]: the first row is full, the second (if any) empty, the rest random."""
    rng = np.random.default_rng(seed + 1000)
    lengths = rng.integers(0, N + 1, size=B)
    if B > 0:
        lengths[0] = N
    if B > 1:
        lengths[1] = 0
    return torch.from_numpy(lengths.astype(np.int64))


def noncontiguous(x: torch.Tensor, how: str) -> torch.Tensor:
    """The same values as ``x`` (B, N, C) in a non-contiguous layout."""
    if how == "transposed":  # stored (B, C, N)
        y = x.transpose(1, 2).contiguous().transpose(1, 2)
    elif how == "strided":  # every other row of a twice-as-long buffer
        buf = torch.zeros((x.shape[0], 2 * x.shape[1], x.shape[2]), dtype=x.dtype, device=x.device)
        buf[:, ::2] = x
        y = buf[:, ::2]
    elif how == "channels":  # a (B, N, 3) slice of a wider (B, N, 5) buffer
        buf = torch.zeros((*x.shape[:2], x.shape[2] + 2), dtype=x.dtype, device=x.device)
        buf[..., 1:-1] = x
        y = buf[..., 1:-1]
    else:
        raise ValueError(how)
    assert torch.equal(y, x) and (x.numel() == 0 or not y.is_contiguous())
    return y
