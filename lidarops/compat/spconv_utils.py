"""Drop-in face of spconv 2.x ``spconv.pytorch.utils.PointToVoxel``::

    # from spconv.pytorch.utils import PointToVoxel
    from lidarops.compat.spconv_utils import PointToVoxel

    gen = PointToVoxel(vsize_xyz=[0.16, 0.16, 4.0], coors_range_xyz=[0, -39.68, -3, 69.12, 39.68, 1],
                       num_point_features=4, max_num_voxels=16000, max_num_points_per_voxel=32,
                       device=torch.device("cuda"))
    voxels, indices, num_points = gen(pc)            # pc: (N, 4)
    voxels, indices, num_points, pc_voxel_id = gen.generate_voxel_with_id(pc)

What it reproduces (read from spconv 2.x ``PointToVoxel`` and its ``Point2Voxel``/``Point2VoxelCPU``
kernels):

- ``grid_size = round((max - min) / vsize)`` per axis, in float32, halves away from zero; the
  attributes ``vsize``, ``grid_size``, ``grid_stride`` and ``coors_range`` in spconv's (z, y, x) order.
- A point is voxelized when its cell ``floor((p - min) / vsize)`` (float32 arithmetic for float32
  points) lies in ``[0, grid_size)`` on every axis. spconv never compares with the upper bound of
  ``coors_range_xyz`` itself, so neither does this face (it matters only when the range is not a
  whole number of voxels). ``lidarops.voxelize`` additionally requires ``p < max``.
- Outputs: ``voxels`` float32 ``[V, max_num_points_per_voxel, num_point_features]`` (zeros, or the
  voxel's mean with ``empty_mean=True``, in unused slots), ``indices`` int32 ``[V, 3]`` (z, y, x),
  ``num_per_voxel`` int32 ``[V]``, ``pc_voxel_id`` int64 ``[N]`` (the row of the point's voxel, also
  for a point that did not fit in it, -1 if the voxel was not kept or the point is out of range).
- Order: voxels in first-seen order, the first points of each voxel in input order, as spconv's
  CPU path. spconv's CUDA path numbers voxels in hash-table order and fills slots in atomic order
  (not deterministic); there, lidarops' output is the same set of voxels, in a deterministic order.

Differences, on purpose:

- **Overflow raises by default.** spconv silently drops the points beyond
  ``max_num_points_per_voxel`` and the voxels beyond ``max_num_voxels``. A dropped point can be a
  missed obstacle, so this face raises :class:`lidarops.ops.voxelize.VoxelOverflowError` unless it
  is constructed with ``overflow="drop"``, which gives spconv's results; the call then returns a
  3-tuple that also carries the counts (``result.num_dropped``, ``result.info``).
- Each call returns new tensors; spconv returns views of buffers that its next call overwrites.
  ``clear_voxels`` is accepted and has no effect (unused slots are always zero or the mean).
- Only 3-D grids (``len(vsize_xyz) == 3``).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from lidarops.ops.validation import describe
from lidarops.ops.voxelize import (
    VoxelizeResult,
    check_capacity,
    check_overflow,
    check_points,
    float_list,
    voxelize_checked,
)

__all__ = ["PointToVoxel"]


def _spconv_meta(vsize_xyz: Sequence[float], coors_range_xyz: Sequence[float]):
    """spconv's calc_point2voxel_meta_data for 3-D, in float32: (vsize_xyz, lo_xyz, grid_xyz)."""
    vs = float_list(vsize_xyz, 3, "vsize_xyz")
    cr = float_list(coors_range_xyz, 6, "coors_range_xyz")
    if not all(math.isfinite(v) for v in vs + cr):
        raise ValueError(f"vsize_xyz and coors_range_xyz must be finite, got {vs} and {cr}")
    vs32 = [np.float32(v) for v in vs]
    lo32 = [np.float32(v) for v in cr[:3]]
    hi32 = [np.float32(v) for v in cr[3:]]
    if not all(v > 0 for v in vs32):
        raise ValueError(f"vsize_xyz must be 3 positive numbers, got {vs}")
    grid = []
    for a, axis in enumerate("xyz"):
        q = float(np.float32(hi32[a] - lo32[a]) / vs32[a])  # float32, as spconv
        g = math.floor(q + 0.5) if q >= 0 else -math.floor(-q + 0.5)  # std::round: halves away from 0
        if g < 1:
            raise ValueError(f"coors_range_xyz must span at least one voxel along {axis}: "
                             f"{axis}0={cr[a]}, {axis}1={cr[a + 3]}, vsize={vs[a]} gives {g} cells")
        if g > 1 << 24:
            raise ValueError(f"the grid has {g} cells along {axis}; at most 2^24 are supported")
        grid.append(int(g))
    return [float(v) for v in vs32], [float(v) for v in lo32], [float(v) for v in hi32], grid


class PointToVoxel:
    """spconv 2.x ``PointToVoxel`` call convention on lidarops' deterministic voxelization.

    Args:
        vsize_xyz (sequence of 3 floats): voxel size along x, y, z.
        coors_range_xyz (sequence of 6 floats): ``(x0, y0, z0, x1, y1, z1)``.
        num_point_features (int): C, columns of the point clouds passed to the calls.
        max_num_voxels (int): most voxels returned.
        max_num_points_per_voxel (int): slots per voxel.
        device (torch.device): device of the point clouds (checked like spconv).
        overflow (str): ``"raise"`` (default) or ``"drop"`` (spconv's silent behaviour, with the
            counts reported on the result). Keyword only: not a spconv argument.
    """

    def __init__(self, vsize_xyz: Sequence[float], coors_range_xyz: Sequence[float], num_point_features: int,
                 max_num_voxels: int, max_num_points_per_voxel: int, device: torch.device = torch.device("cpu:0"),
                 *, overflow: str = "raise"):
        if len(list(vsize_xyz)) != 3:
            raise ValueError(f"lidarops' PointToVoxel supports 3-D grids (vsize_xyz of length 3), got {vsize_xyz!r}")
        vs, lo, hi, grid = _spconv_meta(vsize_xyz, coors_range_xyz)
        self.ndim = 3
        self.device = torch.device(device)
        self.num_point_features = check_capacity(num_point_features, "num_point_features")
        self.max_num_voxels = check_capacity(max_num_voxels, "max_num_voxels")
        self.max_num_points_per_voxel = check_capacity(max_num_points_per_voxel, "max_num_points_per_voxel")
        check_overflow(overflow, False)
        self.overflow = overflow
        # spconv's metadata, (z, y, x) order
        self.vsize = vs[::-1]
        self.grid_size = grid[::-1]
        self.grid_stride = [grid[0] * grid[1], grid[0], 1]
        self.coors_range = lo[::-1] + hi[::-1]
        self._vsize_xyz = vs
        self._grid_xyz = grid
        # spconv tests only the cell against grid_size: no upper coordinate bound
        self._range_xyz = lo + [math.inf] * 3

    def __repr__(self) -> str:
        return (f"PointToVoxel(vsize_xyz={self._vsize_xyz}, grid_size(zyx)={self.grid_size}, "
                f"num_point_features={self.num_point_features}, max_num_voxels={self.max_num_voxels}, "
                f"max_num_points_per_voxel={self.max_num_points_per_voxel}, device={self.device}, "
                f"overflow={self.overflow!r})")

    def __call__(self, pc: Tensor, clear_voxels: bool = True, empty_mean: bool = False) -> VoxelizeResult:
        """Voxelize one point cloud.

        Args:
            pc (Tensor[N, num_point_features]): x, y, z first; float32 (float64/float16/bfloat16 work:
                float64 is voxelized in float64 with the float32 grid parameters, like spconv's CPU path).
            clear_voxels (bool): accepted for compatibility; outputs are always fresh tensors.
            empty_mean (bool): fill the unused slots of each voxel with the mean of its points.

        Returns:
            VoxelizeResult: ``(voxels float32 [V, P, C], indices int32 [V, 3] (z, y, x),
            num_per_voxel int32 [V])`` with ``.num_dropped`` and ``.info``.
        """
        return self._run(pc, empty_mean)

    def generate_voxel_with_id(self, pc: Tensor, clear_voxels: bool = True, empty_mean: bool = False):
        """As ``__call__``, plus ``pc_voxel_id`` (int64 [N]): the voxel row of each point, -1 if none."""
        res = self._run(pc, empty_mean)
        return res.voxels, res.coords, res.num_points, res.info.point_voxel

    def _run(self, pc: Tensor, empty_mean: bool) -> VoxelizeResult:
        check_points(pc)
        if pc.device.type != self.device.type:
            raise ValueError(f"pc is on {pc.device} but this PointToVoxel was built for {self.device} "
                             "(spconv: 'your pc device is wrong')")
        if pc.shape[1] != self.num_point_features:
            raise ValueError(f"pc must have num_point_features={self.num_point_features} columns, got {describe(pc)}")
        res = voxelize_checked(pc, self._vsize_xyz, self._range_xyz, self._grid_xyz, self.max_num_points_per_voxel,
                        self.max_num_voxels, self.overflow, False, 0,
                        ("voxel", "max_num_points_per_voxel", "max_num_voxels"), "PointToVoxel")
        voxels = res.voxels.to(torch.float32)
        if empty_mean and voxels.shape[0]:
            n = res.num_points.to(torch.float32).unsqueeze(1)
            mean = voxels.sum(1) / n  # unused slots are zero here
            empty = torch.arange(voxels.shape[1], device=voxels.device).unsqueeze(0) >= res.num_points.unsqueeze(1)
            voxels = torch.where(empty.unsqueeze(-1), mean.unsqueeze(1), voxels)
        return VoxelizeResult(voxels, res.coords, res.num_points, res.info)
