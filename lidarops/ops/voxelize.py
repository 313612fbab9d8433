"""Voxelization: points -> (voxels [V, P, C], coords int32 [V, 3] (z, y, x), num_points int32 [V]).

Conventions (identical on CPU and CUDA, deterministic):

- **Grid.** ``point_cloud_range = (x0, y0, z0, x1, y1, z1)`` must hold a whole number of voxels per axis:
  ``D_x = (x1 - x0) / vx`` and so on (up to float rounding). ``info.grid_shape = (D_z, D_y, D_x)``
  is the ``spatial_shape`` of the sparse tensor built from the coords.
- **Which points are voxelized.** A point is voxelized when ``x0 <= x < x1``, ``y0 <= y < y1`` and
  ``z0 <= z < z1``; its voxel is ``floor((x - x0) / vx)`` (and so on), evaluated in the computation
  dtype with IEEE rounding after each operation: float32 for float16/bfloat16/float32 points (with
  the bounds and sizes rounded to float32, as spconv and mmcv store them), float64 for float64. So a
  point exactly on a voxel boundary ``x = x0 + i * vx`` (exactly representable) goes to voxel ``i``,
  and ``x = x1`` is outside. Points outside the range (NaN and infinite coordinates included) are
  not voxelized; that is not a drop: they are counted in ``info.num_out_of_range``.
- **Order.** Voxels are numbered in first-seen order (the order of their first point in the input);
  the first ``max_points_per_voxel`` points of a voxel, in input order, fill its slots. This is
  spconv's CPU order (its CUDA order is not deterministic).
- **Overflow.** ``overflow="raise"`` (default) raises :class:`VoxelOverflowError` when a voxel would
  get more than ``max_points_per_voxel`` points or more than ``max_voxels`` voxels would be needed:
  a dropped point can be a missed obstacle. ``overflow="drop"`` keeps the first points / voxels as
  above, drops the rest, and reports how many in ``result.num_dropped`` and ``result.info``.
- **Outputs.** ``voxels`` has the dtype of ``points`` and zeros in unused slots; ``coords`` and
  ``num_points`` are int32 (spconv's and OpenPCDet's dtypes).
- **Bad input** raises ``ValueError`` naming the argument, before anything is allocated: sizes and
  ranges that are not sequences of real numbers (strings, sets, bools), a grid of more than 2^24
  cells along an axis or 2^62 in all, capacities that are not positive ints below 2^31, and
  capacities whose output ``voxels [rows, max_points_per_voxel, C]`` would exceed 2^31 - 1 entries
  (rows: ``max_voxels`` with ``padded=True``, else at most the number of points).

Output size: V depends on the data. The registered ops are shape-static (the assignment's outputs
are padded to ``max_voxels``; the scatter takes its row count as an argument), so they never read
data back to the host. The wrapper reads the 7 counts once (one device-to-host copy on CUDA, which
deciding ``overflow="raise"`` needs anyway) and returns exactly V rows. ``padded=True`` skips that
read (CUDA-graph capturable, ``torch.compile(fullgraph=True)``-friendly): ``max_voxels`` rows
(coords -1, num_points 0, zero voxels beyond V) and 0-d tensors in ``info``; it requires
``overflow="drop"``.
"""
from __future__ import annotations

import math
import numbers
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from lidarops import extension
from lidarops._moved import renamed_kwargs
from lidarops.ops.validation import check_output_size, check_positive_int, check_tensor, describe

extension.load()
from lidarops.ops import _registrations  # noqa: E402,F401  (fake kernels, autograd)

__all__ = ["voxelize", "VoxelizeResult", "VoxelizeInfo", "VoxelOverflowError", "voxel_grid_shape",
           "voxel_assignment", "VoxelAssignment"]

_METHODS = {"auto": 0, "dense": 1, "hash": 2}
_MAX_DIM = 1 << 24
_MAX_CELLS = 1 << 62  # voxel keys are int64 (csrc/include/lidarops/voxelize.h)
_INT32_MAX = 2**31 - 1

# indices into the stats output of lidarops::voxelize_assign (csrc/include/lidarops/voxelize.h)
_S_VOXELS, _S_NEEDED, _S_IN_GRID, _S_DROP_VOXELS, _S_DROP_POINTS, _S_FULLEST, _S_OVERFULL = range(7)


class VoxelOverflowError(ValueError):
    """Voxelization would drop points: a voxel got more than ``max_points_per_voxel`` points or more
    than ``max_voxels`` voxels were needed (and ``overflow="raise"``)."""


class VoxelizeInfo(NamedTuple):
    """What voxelization did. Python ints, or 0-d int64 tensors on the points' device when
    ``padded=True`` (nothing is read back then)."""

    num_voxels: int | Tensor            # V, voxels returned
    num_voxels_needed: int | Tensor     # distinct voxels holding a point in range (> V if some dropped)
    num_in_range: int | Tensor          # points inside point_cloud_range
    num_out_of_range: int | Tensor      # points outside point_cloud_range (not voxelized; not a drop)
    num_dropped: int | Tensor           # points in range that are not in the output
    num_dropped_max_voxels: int | Tensor   # ... because their voxel came after the first max_voxels
    num_dropped_max_points: int | Tensor   # ... because their voxel already had max_points_per_voxel
    max_points_in_voxel: int | Tensor   # largest number of points in one voxel (before truncation)
    num_overfull_voxels: int | Tensor   # returned voxels that had more than max_points_per_voxel points
    grid_shape: tuple[int, int, int]    # (D_z, D_y, D_x) cells: the spatial_shape of the coords
    point_voxel: Tensor                 # (N,) int64: row of each point's voxel, -1 if not returned
    point_slot: Tensor                  # (N,) int64: slot of each point in its voxel, -1 if not stored


class _VoxelTriple(NamedTuple):
    voxels: Tensor
    coords: Tensor
    num_points: Tensor


class VoxelizeResult(_VoxelTriple):
    """``(voxels, coords, num_points)``, a 3-tuple (``voxels, coords, num_points = voxelize(...)``
    works), with what voxelization did in ``.info`` (:class:`VoxelizeInfo`) and the shortcuts
    ``.num_dropped``, ``.num_out_of_range``, ``.point_voxel``."""

    info: VoxelizeInfo | None = None  # tuple methods such as _replace() return results without info

    def __new__(cls, voxels: Tensor, coords: Tensor, num_points: Tensor, info: VoxelizeInfo | None = None):
        self = super().__new__(cls, voxels, coords, num_points)
        self.info = info
        return self

    @property
    def num_dropped(self) -> int | Tensor:
        return self.info.num_dropped

    @property
    def num_out_of_range(self) -> int | Tensor:
        return self.info.num_out_of_range

    @property
    def point_voxel(self) -> Tensor:
        return self.info.point_voxel


# ---- argument handling ----

def float_list(value, n: int, name: str) -> list[float]:
    """``n`` real numbers from a list, tuple, array or tensor; strings, sets, dicts, bools and complex
    numbers are refused (``float("0.5")`` or a set's arbitrary order would pass silently)."""
    given = value
    if isinstance(value, Tensor):
        value = value.detach().cpu().reshape(-1).tolist()
    elif isinstance(value, np.ndarray):
        value = value.reshape(-1).tolist()
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence) or len(value) != n \
            or not all([isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) for v in value]):
        raise ValueError(f"{name} must be a sequence of {n} numbers, got {given!r}")
    return [float(v) for v in value]


def _check_voxel_size(voxel_size) -> list[float]:
    vs = float_list(voxel_size, 3, "voxel_size")
    if not all(math.isfinite(v) and v > 0 for v in vs):
        raise ValueError(f"voxel_size must be 3 finite positive numbers (x, y, z), got {vs}")
    return vs


def _check_point_range(point_cloud_range) -> list[float]:
    pr = float_list(point_cloud_range, 6, "point_cloud_range")
    if not all(math.isfinite(v) for v in pr):
        raise ValueError(f"point_cloud_range must be 6 finite numbers (x0, y0, z0, x1, y1, z1), got {pr}")
    for a, axis in enumerate("xyz"):
        if not pr[a] < pr[a + 3]:
            raise ValueError(f"point_cloud_range must be (x0, y0, z0, x1, y1, z1) with {axis}0 < {axis}1, got "
                             f"{axis}0={pr[a]}, {axis}1={pr[a + 3]} (inverted or empty range)")
    return pr


def _grid_size(voxel_size: list[float], point_cloud_range: list[float]) -> list[int]:
    """Cells along x, y, z; the range must be a whole number of voxels."""
    dims = []
    for a, axis in enumerate("xyz"):
        extent = point_cloud_range[a + 3] - point_cloud_range[a]
        n = extent / voxel_size[a]
        d = round(n)
        if d > _MAX_DIM:
            raise ValueError(f"point_cloud_range / voxel_size make a grid of {n:.4g} cells along {axis} (extent {extent:g}, "
                             f"voxel_size {voxel_size[a]:g}); at most 2^24 are supported")
        if d < 1 or abs(n - d) > 1e-3 + 1e-6 * d:
            raise ValueError(
                f"point_cloud_range must hold a whole number of voxels per axis: the {axis} extent "
                f"{extent:g} is {n:.6g} voxels of voxel_size {voxel_size[a]:g}; adjust point_cloud_range or voxel_size")
        dims.append(int(d))
    if math.prod(dims) >= _MAX_CELLS:
        raise ValueError(f"point_cloud_range / voxel_size make a grid of {dims[0]} x {dims[1]} x {dims[2]} = "
                         f"{math.prod(dims):.4g} cells; at most 2^62 are supported (larger voxels or a smaller range)")
    return dims


@renamed_kwargs(point_range="point_cloud_range")
def voxel_grid_shape(voxel_size: Sequence[float], point_cloud_range: Sequence[float]) -> tuple[int, int, int]:
    """``(D_z, D_y, D_x)``: cells of the grid along z, y, x (the ``spatial_shape`` of the coords).

    Raises ValueError when ``point_cloud_range`` is not a whole number of voxels per axis.
    """
    dx, dy, dz = _grid_size(_check_voxel_size(voxel_size), _check_point_range(point_cloud_range))
    return dz, dy, dx


def check_points(points) -> None:
    check_tensor(points, "points")
    if points.dim() != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be (N, C) with C >= 3 (x, y, z first), got {describe(points)}")
    if not points.is_floating_point():
        raise ValueError(f"points must be floating point (float32, float64, float16, bfloat16), got {describe(points)}")
    extension.check_device(points, "points")


def check_capacity(v, name: str) -> int:
    v = check_positive_int(v, name)
    if v > _INT32_MAX:
        raise ValueError(f"{name} must be below 2^31, got {v}")
    return v


def check_overflow(overflow, padded) -> None:
    if overflow not in ("raise", "drop"):
        raise ValueError(f"overflow must be 'raise' or 'drop', got {overflow!r}")
    if not isinstance(padded, bool):
        raise ValueError(f"padded must be a bool, got {padded!r}")
    if padded and overflow == "raise":
        raise ValueError("padded=True reads nothing back from the device, so it cannot raise on overflow: "
                         "pass overflow='drop' and check result.num_dropped (a 0-d tensor)")


# ---- the two steps, shared with pillarization and the spconv face ----

def _assign(points: Tensor, voxel_size: list[float], point_cloud_range: list[float], grid_size: list[int],
            max_points: int, max_voxels: int, overflow: str, padded: bool, method: int = 0,
            names: tuple[str, str, str] = ("voxel", "max_points_per_voxel", "max_voxels"), caller: str = "voxelize"):
    """Run lidarops::voxelize_assign; return (coords, num_points, point_voxel, point_slot, counts) where
    counts are Python ints (one host read) or, with ``padded``, 0-d tensors. Raises on overflow when
    asked. ``names`` = (what a voxel is called, the capacity arguments) for the messages."""
    # Without padding, at most N voxels can exist: a generous max_voxels costs no memory.
    rows = max_voxels if padded else max(1, min(max_voxels, points.shape[0]))
    noun, points_arg, voxels_arg = names
    asked = (f"{voxels_arg}={max_voxels} (padded=True) and {points_arg}={max_points}" if padded
             else f"{points_arg}={max_points} (up to {rows} {noun}s)")
    check_output_size((rows, max_points, points.shape[1]), asked, f"{noun}s",
                      f"lower {points_arg}" + (f" or {voxels_arg}" if padded else ""))
    coords, num_points, point_voxel, point_slot, stats = torch.ops.lidarops.voxelize_assign(
        points, voxel_size, point_cloud_range, grid_size, max_points, rows, method)
    counts = stats.unbind(0) if padded else stats.tolist()
    if not padded and overflow == "raise":
        _raise_on_overflow(counts, max_points, max_voxels, names, caller)
    return coords, num_points, point_voxel, point_slot, counts


def _raise_on_overflow(counts: list[int], max_points: int, max_voxels: int, names, caller: str) -> None:
    dropped_v, dropped_p = counts[_S_DROP_VOXELS], counts[_S_DROP_POINTS]
    if dropped_v == 0 and dropped_p == 0:
        return
    noun, points_arg, voxels_arg = names
    why, fix = [], []
    if dropped_p:
        n = counts[_S_OVERFULL]
        why.append(f"{n} {noun}{' holds' if n == 1 else 's hold'} more than {points_arg}={max_points} points "
                   f"(the fullest holds {counts[_S_FULLEST]}; {dropped_p} points over)")
        fix.append(f"{points_arg} to at least {counts[_S_FULLEST]}")
    if dropped_v:
        why.append(f"the points occupy {counts[_S_NEEDED]} {noun}s but {voxels_arg}={max_voxels} "
                   f"({dropped_v} points in the {noun}s beyond)")
        fix.append(f"{voxels_arg} to at least {counts[_S_NEEDED]}")
    raise VoxelOverflowError(
        f"{caller} would drop {dropped_v + dropped_p} of the {counts[_S_IN_GRID]} points in range: "
        + "; ".join(why) + ". A dropped point can be a missed obstacle: raise " + " and ".join(fix)
        + ", or pass overflow='drop' to keep the first points in input order and read the count from "
          "result.num_dropped")


def _info(counts, n_points: int, grid_size: list[int], point_voxel: Tensor, point_slot: Tensor) -> VoxelizeInfo:
    c = counts
    return VoxelizeInfo(
        num_voxels=c[_S_VOXELS], num_voxels_needed=c[_S_NEEDED], num_in_range=c[_S_IN_GRID],
        num_out_of_range=n_points - c[_S_IN_GRID], num_dropped=c[_S_DROP_VOXELS] + c[_S_DROP_POINTS],
        num_dropped_max_voxels=c[_S_DROP_VOXELS], num_dropped_max_points=c[_S_DROP_POINTS],
        max_points_in_voxel=c[_S_FULLEST], num_overfull_voxels=c[_S_OVERFULL],
        grid_shape=(grid_size[2], grid_size[1], grid_size[0]), point_voxel=point_voxel, point_slot=point_slot)


def voxelize_checked(points: Tensor, voxel_size: list[float], point_cloud_range: list[float], grid_size: list[int],
              max_points: int, max_voxels: int, overflow: str, padded: bool, method: int,
              names: tuple[str, str, str] = ("voxel", "max_points_per_voxel", "max_voxels"),
              caller: str = "voxelize") -> VoxelizeResult:
    coords, num_points, point_voxel, point_slot, counts = _assign(
        points, voxel_size, point_cloud_range, grid_size, max_points, max_voxels, overflow, padded, method, names, caller)
    rows = max_voxels if padded else counts[_S_VOXELS]
    voxels = torch.ops.lidarops.voxelize_scatter(points, point_voxel, point_slot, rows, max_points)
    if not padded:
        coords, num_points = coords[:rows], num_points[:rows]
    info = _info(counts, points.shape[0], grid_size, point_voxel, point_slot)
    return VoxelizeResult(voxels, coords, num_points, info)


def _checked(points, voxel_size, point_cloud_range, max_points_per_voxel, max_voxels):
    """The arguments :func:`voxelize` and :func:`voxel_assignment` share, checked: voxel size, range, grid
    (x, y, z cells) and the two capacities."""
    check_points(points)
    vs = _check_voxel_size(voxel_size)
    pr = _check_point_range(point_cloud_range)
    grid = _grid_size(vs, pr)
    return (vs, pr, grid, check_capacity(max_points_per_voxel, "max_points_per_voxel"),
            check_capacity(max_voxels, "max_voxels"))


@renamed_kwargs(point_range="point_cloud_range")
def voxelize(points: Tensor, voxel_size: Sequence[float], point_cloud_range: Sequence[float], max_points_per_voxel: int,
             max_voxels: int, overflow: str = "raise", *, padded: bool = False,
             method: str = "auto") -> VoxelizeResult:
    """Group points into voxels (hard voxelization, as in VoxelNet, SECOND and PointPillars).

    Args:
        points (Tensor[N, C]): C >= 3 features per point, x, y, z in columns 0..2 (e.g. x, y, z,
            intensity); float32/float64/float16/bfloat16, CPU or CUDA. Non-contiguous is fine.
        voxel_size (sequence of 3 floats): voxel edge along x, y, z (> 0). A z size equal to the z
            extent of ``point_cloud_range`` gives pillars (PointPillars): coords z is then 0.
        point_cloud_range (sequence of 6 floats): ``(x0, y0, z0, x1, y1, z1)``, a whole number of voxels
            per axis; points outside ``[x0, x1) x [y0, y1) x [z0, z1)`` are not voxelized.
        max_points_per_voxel (int): P, slots per voxel.
        max_voxels (int): most voxels returned.
        overflow (str): ``"raise"`` (default): raise :class:`VoxelOverflowError` rather than drop
            a point; ``"drop"``: keep the first P points of each voxel and the first ``max_voxels``
            voxels (input order) and report the rest in ``result.num_dropped``.
        padded (bool): return ``max_voxels`` rows without reading anything back from the device
            (needs ``overflow="drop"``); see the module docstring.
        method (str): ``"auto"``, ``"dense"`` or ``"hash"`` (the CPU first-seen table; for tests and
            benchmarks). CUDA has one path. Every method returns the same result.

    Returns:
        VoxelizeResult: unpacks as ``(voxels, coords, num_points)``:
            voxels (Tensor[V, P, C]): dtype of ``points``; the points of voxel v in input order,
                zeros in the unused slots.
            coords (int32 Tensor[V, 3]): voxel indices ``(z, y, x)``, voxels in first-seen order.
            num_points (int32 Tensor[V]): points stored per voxel, in [1, P].
        ``.info`` (:class:`VoxelizeInfo`): counts (out of range, dropped, ...), ``grid_shape`` and
        the per-point ``point_voxel`` / ``point_slot``; ``.num_dropped`` and ``.num_out_of_range``.

    Raises:
        ValueError: bad arguments (shape, dtype, device, non-positive voxel size, inverted range,
            a range that is not a whole number of voxels, a grid of more than 2^24 cells along an
            axis or 2^62 in all, capacities that are not positive ints below 2^31 or whose output
            would exceed 2^31 - 1 entries), raised before anything is allocated.
        VoxelOverflowError: with ``overflow="raise"``, when points would be dropped; the message
            says which capacity to raise and to what.

    Follows spconv 2.x ``PointToVoxel`` / mmcv ``Voxelization`` (hard) semantics: same cell formula
    in float32, same coords layout and dtypes, first-seen order as in their CPU paths; see
    ``lidarops.compat.spconv_utils.PointToVoxel`` for the drop-in face.
    """
    vs, pr, grid, P, M = _checked(points, voxel_size, point_cloud_range, max_points_per_voxel, max_voxels)
    check_overflow(overflow, padded)
    if not isinstance(method, str) or method not in _METHODS:
        raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    if points.device.type == "meta" and not padded:
        raise ValueError("points on the meta device: the voxel count is data, so meta tensors need padded=True")
    return voxelize_checked(points, vs, pr, grid, P, M, overflow, padded, _METHODS[method])


class VoxelAssignment(NamedTuple):
    """:func:`voxel_assignment`'s result: where each point goes, without the voxel table."""

    coords: Tensor       # (max_voxels, 3) int32: (z, y, x) of each voxel, first seen first; -1 rows unused
    num_points: Tensor   # (max_voxels,) int32: points stored per voxel (0 in unused rows)
    point_voxel: Tensor  # (N,) int64: the row of each point's voxel, -1 if not returned
    point_slot: Tensor   # (N,) int64: the slot of each point in its voxel, -1 if not stored


@renamed_kwargs(point_range="point_cloud_range")
def voxel_assignment(points: Tensor, voxel_size: Sequence[float], point_cloud_range: Sequence[float],
                     max_points_per_voxel: int, max_voxels: int) -> VoxelAssignment:
    """The first half of :func:`voxelize` with ``padded=True, overflow="drop"``: which voxel row and slot each
    point takes, and the voxels' coords and counts, without building the ``(max_voxels, P, C)`` table and
    without reading anything back from the device (CUDA-graph capturable). Rows hold 16 bytes each, so a
    generous ``max_voxels`` costs little; the table can then be built for the rows wanted
    (``torch.ops.lidarops.voxelize_scatter(features, point_voxel, point_slot, rows, P)``).

    Args: as :func:`voxelize` (x, y, z are read from ``points``; other columns are ignored).

    Returns:
        VoxelAssignment: ``coords``, ``num_points`` (``voxelize(..., padded=True)``'s, row for row), and the
        per-point ``point_voxel`` and ``point_slot`` (its ``info``'s).

    Raises:
        ValueError: as :func:`voxelize`.
    """
    vs, pr, grid, P, M = _checked(points, voxel_size, point_cloud_range, max_points_per_voxel, max_voxels)
    coords, num_points, point_voxel, point_slot, _ = _assign(points, vs, pr, grid, P, M, "drop", True)
    return VoxelAssignment(coords, num_points, point_voxel, point_slot)


# ---- pure-Python reference (dict-based first-seen loop), used by the tests ----

def _voxelize_reference(points: Tensor, voxel_size, point_cloud_range, max_points_per_voxel: int, max_voxels: int,
                        grid_size=None) -> dict:
    """NumPy reference of voxelize with overflow='drop'. ``grid_size`` (x, y, z) defaults to the
    whole number of voxels in ``point_cloud_range``; ``point_cloud_range`` upper bounds may be +inf."""
    ct = np.float64 if points.dtype == torch.float64 else np.float32
    p = points.detach().cpu().to(torch.float64 if ct is np.float64 else torch.float32).numpy()
    N, C = p.shape
    vs = np.array([float(v) for v in voxel_size], dtype=np.float64)
    pr = [float(v) for v in point_cloud_range]
    if grid_size is None:
        grid_size = [int(round((pr[a + 3] - pr[a]) / vs[a])) for a in range(3)]
    lo = np.array(pr[:3], dtype=ct)
    hi = np.array(pr[3:], dtype=ct)
    size = vs.astype(ct)
    cells = np.zeros((N, 3), dtype=np.int64)
    inside = np.ones(N, dtype=bool)
    with np.errstate(invalid="ignore"):
        for a in range(3):
            x = p[:, a]
            c = np.floor((x - lo[a]) / size[a])  # float32 ops round like the kernels
            ok = (x >= lo[a]) & (x < hi[a]) & (c >= 0) & (c < grid_size[a])
            inside &= ok
            cells[ok, a] = c[ok].astype(np.int64)
    first_seen: dict[tuple[int, int, int], int] = {}
    counts: list[int] = []
    zyx: list[tuple[int, int, int]] = []
    point_voxel = np.full(N, -1, dtype=np.int64)
    point_slot = np.full(N, -1, dtype=np.int64)
    for i in range(N):
        if not inside[i]:
            continue
        key = (int(cells[i, 2]), int(cells[i, 1]), int(cells[i, 0]))
        u = first_seen.setdefault(key, len(counts))
        if u == len(counts):
            counts.append(0)
            zyx.append(key)
        s = counts[u]
        counts[u] += 1
        if u < max_voxels:
            point_voxel[i] = u
            if s < max_points_per_voxel:
                point_slot[i] = s
    V = min(len(counts), max_voxels)
    src = points.detach().cpu().to(torch.float64).numpy()  # exact for every input dtype
    voxels = np.zeros((V, max_points_per_voxel, C), dtype=np.float64)
    for i in np.nonzero(point_slot >= 0)[0]:
        voxels[point_voxel[i], point_slot[i]] = src[i]
    kept = np.array(counts[:V], dtype=np.int64)
    beyond = np.array(counts[V:], dtype=np.int64)
    return {
        "voxels": voxels,
        "coords": np.array(zyx[:V], dtype=np.int32).reshape(V, 3),
        "num_points": np.minimum(kept, max_points_per_voxel).astype(np.int32),
        "point_voxel": point_voxel,
        "point_slot": point_slot,
        "num_voxels_needed": len(counts),
        "num_in_range": int(inside.sum()),
        "num_dropped_max_voxels": int(beyond.sum()),
        "num_dropped_max_points": int(np.maximum(kept - max_points_per_voxel, 0).sum()),
        "max_points_in_voxel": max(counts) if counts else 0,
        "num_overfull_voxels": int((kept > max_points_per_voxel).sum()),
    }
