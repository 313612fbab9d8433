"""Pillar grids and one-shot pillarization (the PointPillars front end).

Conventions (identical on CPU and CUDA, and identical for :func:`pillarize` and
:class:`~lidarops.stream.PillarStream`):

- **Grid.** ``PillarGrid(point_cloud_range=(x0, y0, z0, x1, y1, z1), voxel_size=(vx, vy))`` has
  ``H = (y1 - y0) / vy`` rows and ``W = (x1 - x0) / vx`` columns (whole numbers); ``.shape == (H, W)``.
- **Which pillar.** Exactly :func:`lidarops.voxelize` with ``voxel_size = (vx, vy, z1 - z0)``: a point
  is in the grid when ``x0 <= x < x1``, ``y0 <= y < y1``, ``z0 <= z < z1`` and its cells
  ``floor((x - x0) / vx)`` (and so on, z included) fall in the grid, evaluated in float32 for float32
  points (float64 for float64). Other points (NaN and infinite coordinates included) are in no pillar;
  they are counted (``Pillars.num_outside``, ``StreamUpdate.points_outside``), never an error.
- **Pillar order.** Pillars are sorted by their linear key ``y * W + x`` (deterministic, the same for
  ``pillarize`` and the stream). ``coords`` are int32 ``(batch=0, y, x)``, spconv's 2D layout.
- **Point order inside a pillar.** ``pillarize``: input order. The stream: time order, ties in
  arrival order. For a time-ordered input the two agree.
- **Features** ``(P, max_points_per_pillar, 9)``, the points' dtype: ``x, y, z, intensity``, the
  offsets ``x - x_mean, y - y_mean, z - z_mean`` to the arithmetic mean of the pillar's points, and
  ``x - x_centre, y - y_centre`` to the pillar centre ``x0 + (ix + 0.5) vx`` (the PointPillars
  decoration). Each feature is computed in float64 from the stored points and rounded once; padding
  slots are zero in all 9 features.
- **Invalid values** (the input policy, :func:`invalid_points`, shared by :func:`pillarize` and the
  stream): a point whose intensity is not finite or has ``|intensity| > MAX_ABS_INTENSITY`` (1e6), or
  (in a stream) whose timestamp is not finite or has ``|t| > MAX_ABS_TIME`` (1e10 s), is dropped and
  counted (``Pillars.num_invalid``, ``StreamUpdate.points_invalid``), never an error: it never enters
  a pillar, the window or ``t_newest``. A point is counted once, in the first of: invalid, outside,
  late (stream), entered.
- **Overflow** raises :class:`PillarOverflowError` (a :class:`ValueError`) naming the capacity and the
  count needed: no random sampling (a dropped point can be a missed drone). A stream may instead be
  created with ``overflow="drop"``: a deterministic, documented rule drops the points that do not fit
  and counts them (:class:`~lidarops.stream.PillarStream`; ``docs/stream.md``, "Overflow policy").
"""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from lidarops import extension
from lidarops._moved import renamed_kwargs, warn_renamed
from lidarops.ops.validation import describe
from lidarops.ops.voxelize import (
    _S_DROP_POINTS,
    _S_DROP_VOXELS,
    _S_FULLEST,
    _S_IN_GRID,
    _S_NEEDED,
    _S_VOXELS,
    VoxelOverflowError,
    _assign,
    check_capacity,
    _check_point_range,
    float_list,
)

extension.load()

__all__ = ["PillarGrid", "Pillars", "pillarize", "PillarOverflowError", "invalid_points", "MAX_ABS_INTENSITY",
           "MAX_ABS_TIME"]

# The input policy (docs/stream.md, "Input policy"), defined here once for pillarize and PillarStream.
# Sensors report intensity as 8- or 16-bit counts (<= 65535) or normalised to [0, 1] or [0, 100]; no
# driver produces 1e6, so a value beyond it (or NaN / inf: no return, saturation flags, a bad decode)
# is a fault. It would also wreck SSCATeR's recycled float32 sums: a 1e30 intensity that enters and
# leaves the window leaves a residue of about 1e30 * 2^-24 behind.
MAX_ABS_INTENSITY = 1e6
# Timestamps are seconds. 1e10 s is year 2286 in Unix time; a millisecond or nanosecond clock passed
# as seconds lands beyond it (every point is then dropped and counted, which the counts show), and
# so does garbage such as 1e30, which would otherwise become t_newest and expire every later point.
MAX_ABS_TIME = 1e10


def invalid_points(points: Tensor, t: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
    """The input policy, per point (elementwise on the points' device, no host synchronisation).

    Args:
        points (Tensor[n, 4]): ``x, y, z, intensity``.
        t (Tensor[n], optional): timestamps in seconds.

    Returns:
        (bad_intensity, bad_t): bool Tensor[n], True where the intensity is NaN, infinite or
        ``|i| > MAX_ABS_INTENSITY``; and the same for ``t`` against ``MAX_ABS_TIME`` (None without
        ``t``). Such points are dropped and counted. Coordinates need no rule here: a NaN, infinite or
        huge x, y or z is outside every grid (``points_outside``).
    """
    # NaN compares false, so "not (|v| <= bound)" catches NaN, inf and huge values in one comparison
    bad_intensity = ~(points[:, 3].abs() <= MAX_ABS_INTENSITY)
    return bad_intensity, (None if t is None else ~(t.abs() <= MAX_ABS_TIME))


def without_invalid(points: Tensor, invalid: Tensor) -> Tensor:
    """The points with the invalid ones moved outside every grid (NaN coordinates and intensity), so
    that the kernels skip them without a data-dependent compaction; the caller subtracts their count
    from the kernels' outside count."""
    return torch.where(invalid[:, None], torch.full((), float("nan"), dtype=points.dtype, device=points.device),
                       points)


class PillarOverflowError(VoxelOverflowError):
    """Pillarization would drop points: a pillar would hold more than ``max_points_per_pillar``
    points or more than ``max_pillars`` pillars would be occupied. A :class:`ValueError`."""


class PillarGrid:
    """A bird's-eye-view grid of ``H x W`` pillars (H along y, W along x).

    Args:
        point_cloud_range (6 floats): ``(x0, y0, z0, x1, y1, z1)``; a whole number of pillars along x and y.
        voxel_size (2 or 3 floats): ``(vx, vy)`` in metres, or OpenPCDet's ``(vx, vy, vz)`` with ``vz`` the
            range's z extent (one pillar in z).

    The old keyword names ``point_range=`` and ``pillar_size=`` are accepted with a deprecation warning.

    Attributes:
        point_cloud_range (tuple of 6 floats), voxel_size ``(vx, vy, z1 - z0)`` (the equivalent
        :func:`lidarops.voxelize` voxel), pillar_size ``(vx, vy)``, shape ``(H, W)``.
    """

    @renamed_kwargs(point_range="point_cloud_range", pillar_size="voxel_size")
    def __init__(self, point_cloud_range: Sequence[float], voxel_size: Sequence[float]) -> None:
        pr = _check_point_range(point_cloud_range)
        try:
            n = len(voxel_size)
        except TypeError:
            n = 0
        ps = float_list(voxel_size, 3 if n == 3 else 2, "voxel_size")
        if not all(math.isfinite(v) and v > 0 for v in ps):
            raise ValueError(f"voxel_size must be finite positive numbers (vx, vy[, vz]), got {ps}")
        if len(ps) == 3 and not math.isclose(ps[2], pr[5] - pr[2], rel_tol=1e-6, abs_tol=1e-9):
            raise ValueError(f"voxel_size z ({ps[2]:g}) must be the z extent of point_cloud_range "
                             f"({pr[5] - pr[2]:g}): a pillar spans the whole range in z")
        dims = []
        for a, axis in enumerate("xy"):
            extent = pr[a + 3] - pr[a]
            n = extent / ps[a]
            d = round(n)
            if d < 1 or abs(n - d) > 1e-3 + 1e-6 * d:
                raise ValueError(f"point_cloud_range must hold a whole number of pillars along {axis}: the extent "
                                 f"{extent:g} is {n:.6g} pillars of {ps[a]:g}; adjust point_cloud_range or voxel_size")
            dims.append(int(d))
        if dims[0] * dims[1] >= 2**31:
            raise ValueError(f"the grid has {dims[1]} x {dims[0]} pillars; at most 2^31 - 1 are supported")
        self.point_cloud_range: tuple[float, ...] = tuple(pr)
        self.pillar_size: tuple[float, float] = (ps[0], ps[1])
        self.shape: tuple[int, int] = (dims[1], dims[0])

    @property
    def point_range(self) -> tuple[float, ...]:
        """Deprecated name of :attr:`point_cloud_range`."""
        warn_renamed("PillarGrid.point_range", "PillarGrid.point_cloud_range")
        return self.point_cloud_range

    # ---- presets ----
    @classmethod
    def drone(cls) -> "PillarGrid":
        """x in [0, 81.92), y in [-40.96, 40.96), z in [-10, 10), 0.16 m pillars: 512 x 512."""
        return cls((0.0, -40.96, -10.0, 81.92, 40.96, 10.0), (0.16, 0.16))

    @classmethod
    def kitti(cls) -> "PillarGrid":
        """The PointPillars KITTI grid: x in [0, 69.12), y in [-39.68, 39.68), z in [-3, 1), 0.16 m:
        H = 496, W = 432."""
        return cls((0.0, -39.68, -3.0, 69.12, 39.68, 1.0), (0.16, 0.16))

    @classmethod
    def driving(cls) -> "PillarGrid":
        """All around a car (e.g. ``Simulator("driving_city")``): x, y in [-51.2, 51.2), z in [-5, 3),
        0.16 m pillars: 640 x 640."""
        return cls((-51.2, -51.2, -5.0, 51.2, 51.2, 3.0), (0.16, 0.16))

    @classmethod
    def driving_ahead(cls) -> "PillarGrid":
        """Ahead of a car from 10 m: x in [10.24, 61.44), y in [-25.6, 25.6), z in [-3, 3), 0.16 m:
        320 x 320. Nearer a spinning sensor, ground pillars hold hundreds of points per 100 ms, which
        makes (P, N, 9) pillar tensors large; the tests and benchmarks of streams use this crop."""
        return cls((10.24, -25.6, -3.0, 61.44, 25.6, 3.0), (0.16, 0.16))

    # ---- derived ----
    @property
    def H(self) -> int:
        return self.shape[0]

    @property
    def W(self) -> int:
        return self.shape[1]

    @property
    def num_pillars(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def voxel_size(self) -> tuple[float, float, float]:
        return (self.pillar_size[0], self.pillar_size[1], self.point_cloud_range[5] - self.point_cloud_range[2])

    @property
    def grid_size(self) -> list[int]:
        """Cells along x, y, z for ``voxelize_assign``: ``[W, H, 1]``."""
        return [self.shape[1], self.shape[0], 1]

    def __repr__(self) -> str:
        return (f"PillarGrid(point_cloud_range={self.point_cloud_range}, voxel_size={self.pillar_size}, "
                f"shape={self.shape})")

    def __eq__(self, other) -> bool:
        return (isinstance(other, PillarGrid) and self.point_cloud_range == other.point_cloud_range
                and self.pillar_size == other.pillar_size)

    def __hash__(self) -> int:
        return hash((self.point_cloud_range, self.pillar_size))


class _PillarTriple(NamedTuple):
    features: Tensor
    coords: Tensor
    num_points: Tensor


class Pillars(_PillarTriple):
    """``(features, coords, num_points)``, a NamedTuple:

    - features (Tensor[P, max_points_per_pillar, 9]): the decorated points (see the module docstring),
      zeros in the padding slots;
    - coords (int32 Tensor[P, 3]): ``(batch=0, y, x)``, sorted by ``y * W + x``;
    - num_points (int32 Tensor[P]): points per pillar, in ``[1, max_points_per_pillar]``.

    ``.num_outside`` (int or None): valid points of the input outside the grid (pillarize only).
    ``.num_invalid`` (int or None): points dropped by the input policy (:func:`invalid_points`;
    pillarize only). Both are read from the device on first access (pillarize does not wait for them).
    """

    def __new__(cls, features: Tensor, coords: Tensor, num_points: Tensor, num_outside: int | Tensor | None = None,
                num_invalid: int | Tensor | None = None):
        self = super().__new__(cls, features, coords, num_points)
        self._num_outside, self._num_invalid = num_outside, num_invalid
        return self

    # tuple methods such as _replace() return Pillars without the counts: None
    @property
    def num_outside(self) -> int | None:
        v = getattr(self, "_num_outside", None)
        if isinstance(v, Tensor):
            v = self._num_outside = int(v)
        return v

    @property
    def num_invalid(self) -> int | None:
        v = getattr(self, "_num_invalid", None)
        if isinstance(v, Tensor):
            v = self._num_invalid = int(v)
        return v


def check_grid(grid) -> PillarGrid:
    if not isinstance(grid, PillarGrid):
        raise ValueError(f"grid must be a lidarops.stream.PillarGrid, got {type(grid).__name__}")
    return grid


def _check_pillar_points(points) -> None:
    if not isinstance(points, Tensor):
        raise ValueError(f"points must be a torch.Tensor (n, 4): x, y, z, intensity, got {type(points).__name__}")
    if points.dim() != 2 or points.shape[1] != 4:
        raise ValueError(f"points must be (n, 4): x, y, z, intensity, got {describe(points)}")
    if points.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"points must be float32 or float64, got {describe(points)}")
    extension.check_device(points, "points")
    if points.device.type == "meta":
        raise ValueError("points on the meta device: the number of pillars is data, so pillarize needs real tensors")


def decorate_pillars(raw: Tensor, num_points: Tensor, coords: Tensor, grid: PillarGrid) -> Tensor:
    return torch.ops.lidarops.pillar_decorate(raw, num_points, coords, list(grid.pillar_size),
                                              [grid.point_cloud_range[0], grid.point_cloud_range[1]])


def overflow_message(caller: str, what: str, needed_points: int, P: int, needed_pillars: int, M: int) -> str:
    why, fix = [], []
    if needed_points > P:
        why.append(f"a pillar would hold {needed_points} points but max_points_per_pillar={P}")
        fix.append(f"max_points_per_pillar to at least {needed_points}")
    if needed_pillars > M:
        why.append(f"{needed_pillars} pillars would be occupied but max_pillars={M}")
        fix.append(f"max_pillars to at least {needed_pillars}")
    return (f"{caller} would drop points of {what}: " + "; ".join(why) + ". A dropped point can be a missed "
            "obstacle, so nothing is sampled away: raise " + " and ".join(fix))


def pillarize(points: Tensor, grid: PillarGrid, max_points_per_pillar: int = 100, max_pillars: int = 12000) -> Pillars:
    """Group a whole window of points into decorated pillars (PointPillars, Lang et al. 2019).

    Args:
        points (Tensor[n, 4]): ``x, y, z, intensity``, float32 or float64, CPU or CUDA.
        grid (PillarGrid): the pillar grid.
        max_points_per_pillar (int): N, slots per pillar.
        max_pillars (int): the most occupied pillars.

    Returns:
        Pillars: ``features (P, N, 9)`` in the points' dtype, ``coords`` int32 ``(P, 3)`` = (0, y, x)
        sorted by ``y * W + x``, ``num_points`` int32 ``(P,)``; points of a pillar in input order;
        ``.num_invalid`` = points dropped by the input policy (intensity NaN, infinite or beyond
        ``MAX_ABS_INTENSITY``: :func:`invalid_points`), ``.num_outside`` = the other points outside the
        grid (neither is an error). ``PillarStream`` applies the same policy, so ``pillarize`` of the
        points pushed in a window equals the stream's pillars.

    Raises:
        ValueError: bad arguments.
        PillarOverflowError: a pillar would get more than ``max_points_per_pillar`` points or more
            than ``max_pillars`` pillars would be occupied (the message says to what to raise them).

    Uses ``voxelize_assign`` / ``voxelize_scatter`` with one voxel along z (the cells are exactly those
    of :func:`lidarops.voxelize`), sorts the pillars by key and decorates them with ``pillar_decorate``.
    """
    _check_pillar_points(points)
    grid = check_grid(grid)
    P = check_capacity(max_points_per_pillar, "max_points_per_pillar")
    M = check_capacity(max_pillars, "max_pillars")
    n = points.shape[0]
    bad_intensity, _ = invalid_points(points)
    num_invalid = bad_intensity.sum()
    points = without_invalid(points, bad_intensity)
    coords, num_points, point_voxel, point_slot, counts = _assign(
        points, list(grid.voxel_size), list(grid.point_cloud_range), grid.grid_size, P, M, "drop", False, 0,
        ("pillar", "max_points_per_pillar", "max_pillars"), "pillarize")
    if counts[_S_DROP_VOXELS] or counts[_S_DROP_POINTS]:
        raise PillarOverflowError(overflow_message("pillarize", f"the {counts[_S_IN_GRID]} points in the grid",
                                                    counts[_S_FULLEST], P, counts[_S_NEEDED], M))
    V = counts[_S_VOXELS]
    coords, num_points = coords[:V], num_points[:V]
    W = grid.shape[1]
    key = coords[:, 1].to(torch.int64) * W + coords[:, 2].to(torch.int64)
    perm = torch.argsort(key)
    # pillar numbers in first-seen order -> numbers in key order; entry V maps "no pillar" (-1) to -1
    rank = torch.full((V + 1,), -1, dtype=torch.int64, device=perm.device)
    rank[perm] = torch.arange(V, device=perm.device)
    pv = rank.index_select(0, torch.where(point_voxel >= 0, point_voxel, V))
    raw = torch.ops.lidarops.voxelize_scatter(points, pv, point_slot, V, P)
    coords = coords.index_select(0, perm)
    coords[:, 0] = 0  # z of the one-cell-high voxels is the batch index 0
    num_points = num_points.index_select(0, perm)
    return Pillars(decorate_pillars(raw, num_points, coords, grid), coords, num_points, n - counts[_S_IN_GRID] - num_invalid,
                   num_invalid)


# ---- pure NumPy reference (float64 features), used by the tests ----

def _pillar_keys_reference(points: np.ndarray, grid: PillarGrid) -> np.ndarray:
    """Linear key y * W + x of every point, -1 outside; cells computed like the kernels (float32
    arithmetic for float32 points)."""
    ct = np.float64 if points.dtype == np.float64 else np.float32
    p = points.astype(ct, copy=False)
    pr = grid.point_cloud_range
    vs = grid.voxel_size
    dims = [grid.shape[1], grid.shape[0], 1]
    inside = np.ones(p.shape[0], dtype=bool)
    cells = np.zeros((p.shape[0], 3), dtype=np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        for a in range(3):
            x = p[:, a]
            lo, hi, size = ct(pr[a]), ct(pr[a + 3]), ct(vs[a])
            c = np.floor((x - lo) / size)
            ok = (x >= lo) & (x < hi) & (c >= 0) & (c < dims[a])
            inside &= ok
            cells[ok, a] = c[ok].astype(np.int64)
    return np.where(inside, cells[:, 1] * dims[0] + cells[:, 0], -1)


def _pillarize_reference(points, grid: PillarGrid, max_points_per_pillar: int) -> dict:
    """NumPy reference of pillarize (no capacity limit on the number of pillars; raises AssertionError
    if a pillar overflows). Returns float64 ``features`` (P, N, 9), ``coords`` (P, 3), ``num_points``
    (P,), ``num_outside`` and ``num_invalid``; points of a pillar in input order."""
    p = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    with np.errstate(invalid="ignore"):
        invalid = ~(np.abs(p[:, 3]) <= MAX_ABS_INTENSITY)
    key = np.where(invalid, -1, _pillar_keys_reference(p, grid))
    inside = key >= 0
    idx = np.nonzero(inside)[0]
    order = idx[np.argsort(key[idx], kind="stable")]
    keys, starts, counts = np.unique(key[order], return_index=True, return_counts=True)
    N = max_points_per_pillar
    assert counts.size == 0 or counts.max() <= N, f"a pillar holds {counts.max()} > {N} points"
    P = keys.size
    W = grid.shape[1]
    x0, y0 = grid.point_cloud_range[0], grid.point_cloud_range[1]
    vx, vy = grid.pillar_size
    feats = np.zeros((P, N, 9), dtype=np.float64)
    src = p.astype(np.float64)
    slot = np.arange(order.size) - np.repeat(starts, counts)
    pil = np.repeat(np.arange(P), counts)
    pts = src[order]
    sums = np.zeros((P, 3))
    np.add.at(sums, pil, pts[:, :3])
    mean = sums / np.maximum(counts, 1)[:, None]
    iy, ix = keys // W, keys % W
    cx = x0 + (ix + 0.5) * vx
    cy = y0 + (iy + 0.5) * vy
    f = np.concatenate([pts, pts[:, :3] - mean[pil], (pts[:, 0] - cx[pil])[:, None],
                        (pts[:, 1] - cy[pil])[:, None]], 1)
    feats[pil, slot] = f
    coords = np.stack([np.zeros(P, dtype=np.int64), iy, ix], 1).astype(np.int32)
    return {"features": feats, "coords": coords, "num_points": counts.astype(np.int32),
            "num_outside": int((~inside).sum() - invalid.sum()), "num_invalid": int(invalid.sum())}
