"""Test data of the compat-face tests (tests/compat/)."""
from __future__ import annotations

import numpy as np
import torch

from helpers.clouds import lidar_points


def lidar_like(n: int, rng: np.random.Generator, quant: float = 0.02) -> np.ndarray:
    """A LiDAR-like cloud, float32 (n, 3) (:func:`helpers.clouds.lidar_points`, seeded from ``rng``),
    coordinates quantised to ``quant`` (2 cm: exact duplicates and equal distances can occur; the tie
    rules have their own tests with constructed ties)."""
    return lidar_points(n, int(rng.integers(2**31)), quant=quant)


def to_t(a, device, dtype=torch.float32) -> torch.Tensor:
    """An array as a tensor on ``device`` in ``dtype``."""
    return torch.as_tensor(np.asarray(a)).to(device=device, dtype=dtype)


def np_of(t: torch.Tensor) -> np.ndarray:
    """Exact values the op sees in its computation dtype (float64 stays float64, else float32)."""
    t = t.detach().cpu()
    return t.numpy() if t.dtype == torch.float64 else t.to(torch.float32).numpy()


def sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(M, D) x (N, D) -> (M, N): ((d0*d0 + d1*d1) + d2*d2) + ..., every step rounded (no FMA)."""
    d = a[:, None, :] - b[None, :, :]
    sq = d * d
    out = sq[..., 0].copy()
    for j in range(1, a.shape[1]):
        out = out + sq[..., j]
    return out


def assert_equal(got: torch.Tensor, want: np.ndarray, dtype: "torch.dtype | None" = None) -> None:
    """``got`` equals ``want`` exactly (and has ``dtype`` when given); the message names the first mismatch."""
    g = got.cpu().numpy()
    if dtype is not None:
        assert got.dtype == dtype, (got.dtype, dtype)
    assert g.shape == want.shape, (g.shape, want.shape)
    bad = np.argwhere(g != want)
    assert bad.size == 0, f"{len(bad)} mismatches, first at {tuple(bad[0])}: got {g[tuple(bad[0])]}, " \
                          f"want {want[tuple(bad[0])]}"
