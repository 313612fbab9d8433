"""Box machinery shared by the anchor-based detectors: residual box coder, anchors, nearest-BEV IoU,
the axis-aligned target assigner and the direction-bin targets.

Boxes are ``(x, y, z, dx, dy, dz, heading)`` in the LiDAR frame: (x, y, z) the box centre, dx the
length along the heading, heading in radians counter-clockwise from +x; extra columns (velocities)
may follow. Everything is plain PyTorch, runs on any device, and follows OpenPCDet's semantics
(``ResidualCoder``, ``AnchorGenerator``, ``AxisAlignedTargetAssigner`` with ``POS_FRACTION: -1``,
``boxes3d_nearest_bev_iou``, ``get_direction_target`` and the direction decode of
``AnchorHeadTemplate.generate_predicted_boxes``), so OpenPCDet configs, habits and checkpoints carry
over. The code is written from that description, not copied.

Deliberate differences from OpenPCDet (none changes a result on well-formed input):

- :meth:`ResidualCoder.encode` does not clamp the caller's tensors in place; leading dims broadcast;
  anchors may have 7 columns when the boxes have extras (those anchor extras count as zero, what
  OpenPCDet's head pads them with).
- Anchor centres are ``start + i * step`` for ``i < n``: exactly ``nx`` and ``ny`` of them (OpenPCDet's
  ``torch.arange(start, stop + 1e-5, step)`` can give one more or one fewer when the step is tiny
  or rounding goes the wrong way). ``align_center: False`` needs at least 2 cells per axis.
- The assigner is batched over frames: no data-dependent shapes, one host sync (the class-id value
  check, off under ``lidarops.validation(False)``). A ground-truth row is padding when its class id
  is 0, wherever it stands (OpenPCDet trims trailing rows whose 7 box values sum to 0, and would
  match a class-0 row left before them to the last class name); class ids outside
  ``0..len(class_names)`` raise ``ValueError``. Labels are int64 (OpenPCDet: int32).
  ``match_height=True`` matches by rotated 3D IoU (:func:`lidarops.box_iou_3d`, OpenPCDet's
  ``boxes_iou3d_gpu``), which anchors stacked in height (several ``anchor_bottom_heights``) need: in bird's-eye
  view they are all alike. ``POS_FRACTION`` sampling is not implemented.
- ``norm_by_num_examples`` divides the positives' weight by the number of anchors that are not
  ignored (label >= 0) of that class in that frame, as OpenPCDet does (not by the positives alone).
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Optional, Sequence

import torch
from torch import Tensor

from lidarops.ops.boxes import box_iou_3d
from lidarops.ops.validation import (check_positive_int, check_tensor, describe, run_value_checks, validation,
                                     value_checks_enabled)

__all__ = ["limit_period", "ResidualCoder", "AnchorGenerator", "flatten_anchors", "boxes3d_nearest_bev_iou",
           "AxisAlignedTargetAssigner", "get_direction_target", "decode_direction"]

DIR_OFFSET = 0.78539  # OpenPCDet pointpillar.yaml's DIR_OFFSET (pi / 4, as written there)


def limit_period(val, offset: float = 0.5, period: float = 2 * math.pi):
    """``val - floor(val / period + offset) * period``: ``val`` wrapped into
    ``[-offset * period, (1 - offset) * period)`` (OpenPCDet's helper).

    Args:
        val (Tensor | float): angles (any shape).
        offset (float): 0.5 wraps to ``[-period / 2, period / 2)``, 0 to ``[0, period)``.
        period (float): the period.

    Returns:
        Tensor (same shape and dtype) or float, as ``val``.
    """
    if isinstance(val, Tensor):
        return val - torch.floor(val / period + offset) * period
    return val - math.floor(val / period + offset) * period


# ---- validation helpers ----

def _check_float(t, name: str, min_dim: int = 1) -> None:
    check_tensor(t, name)
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point (float32 or float64), got {describe(t)}")
    if t.dim() < min_dim:
        raise ValueError(f"{name} must have at least {min_dim} dims, got {describe(t)}")


def _check_columns(t, name: str, allowed: Sequence[int], layout: str, at_least: bool = False) -> None:
    """``t`` is a floating tensor whose last dim is one of ``allowed`` (or >= ``allowed[0]``)."""
    _check_float(t, name)
    n = t.shape[-1]
    if not (n >= allowed[0] if at_least else n in allowed):
        want = f">= {allowed[0]}" if at_least else " or ".join(str(a) for a in allowed)
        raise ValueError(f"{name} must be (..., {layout}) with {want} columns, got {describe(t)}")


def _check_pair(a: Tensor, name_a: str, b: Tensor, name_b: str, lead: int = 1) -> None:
    """Same device and dtype; the dims before the last ``lead`` broadcast."""
    if a.device != b.device:
        raise ValueError(f"{name_b} is on {b.device} but {name_a} is on {a.device}; move them to one device")
    if a.dtype != b.dtype:
        raise ValueError(f"{name_b} has dtype {b.dtype} but {name_a} has dtype {a.dtype}; cast one of them")
    try:
        torch.broadcast_shapes(a.shape[:-lead], b.shape[:-lead])
    except RuntimeError:
        raise ValueError(f"the leading dims of {name_a} ({describe(a)}) and {name_b} ({describe(b)}) "
                         "do not broadcast") from None


# ---- box coder ----

class ResidualCoder:
    """OpenPCDet's residual box coder: anchor-relative offsets, log size ratios, heading difference.

    Encoding of a box g against an anchor a (dims clamped to >= 1e-5 first, boxes' and anchors'),
    with ``diagonal = sqrt(dxa^2 + dya^2)``: ``xt = (xg - xa) / diagonal``, ``yt = (yg - ya) / diagonal``,
    ``zt = (zg - za) / dza``, ``dxt = log(dxg / dxa)`` (same for dy, dz), ``rt = rg - ra`` (or
    ``cos rg - cos ra, sin rg - sin ra`` when ``encode_angle_by_sincos``), then the extra columns as
    differences ``g - a``. :meth:`decode` inverts it (anchors not clamped, as in OpenPCDet).

    Args:
        code_size (int): columns of a box (7, or more with extras such as velocities).
        encode_angle_by_sincos (bool): encode the heading as two columns (cos and sin differences).

    Attributes:
        box_size (int): columns of a box (``code_size`` as passed).
        code_size (int): columns of an encoding: ``box_size``, plus 1 with ``encode_angle_by_sincos``
            (OpenPCDet's meaning of the attribute).
    """

    def __init__(self, code_size: int = 7, encode_angle_by_sincos: bool = False):
        box_size = check_positive_int(code_size, "code_size")
        if box_size < 7:
            raise ValueError(f"code_size must be >= 7 (x, y, z, dx, dy, dz, heading), got {box_size}")
        self.box_size = box_size
        self.encode_angle_by_sincos = bool(encode_angle_by_sincos)
        self.code_size = box_size + int(self.encode_angle_by_sincos)

    def __repr__(self) -> str:
        return (f"ResidualCoder(code_size={self.box_size}, "
                f"encode_angle_by_sincos={self.encode_angle_by_sincos})")

    def _anchors(self, anchors: Tensor, other: Tensor, other_name: str) -> Tensor:
        _check_columns(anchors, "anchors", (7, self.box_size), "x, y, z, dx, dy, dz, heading[, extras]")
        _check_pair(other, other_name, anchors, "anchors")
        if anchors.shape[-1] < self.box_size:  # missing extras are zero, as OpenPCDet's head pads them
            anchors = torch.cat([anchors, anchors.new_zeros(*anchors.shape[:-1], self.box_size - 7)], -1)
        return anchors

    def encode(self, boxes: Tensor, anchors: Tensor) -> Tensor:
        """Encode boxes against anchors.

        Args:
            boxes (Tensor[..., box_size]): ground-truth boxes.
            anchors (Tensor[..., 7 or box_size]): anchors; leading dims broadcast with the boxes'.

        Returns:
            Tensor[..., code_size] in the inputs' dtype.
        """
        _check_columns(boxes, "boxes", (self.box_size,), "x, y, z, dx, dy, dz, heading[, extras]")
        anchors = self._anchors(anchors, boxes, "boxes")
        xa, ya, za, ra = anchors[..., 0], anchors[..., 1], anchors[..., 2], anchors[..., 6]
        dxa, dya, dza = anchors[..., 3:6].clamp_min(1e-5).unbind(-1)
        xg, yg, zg, rg = boxes[..., 0], boxes[..., 1], boxes[..., 2], boxes[..., 6]
        dxg, dyg, dzg = boxes[..., 3:6].clamp_min(1e-5).unbind(-1)
        diagonal = torch.sqrt(dxa ** 2 + dya ** 2)
        cols = [(xg - xa) / diagonal, (yg - ya) / diagonal, (zg - za) / dza,
                torch.log(dxg / dxa), torch.log(dyg / dya), torch.log(dzg / dza)]
        if self.encode_angle_by_sincos:
            cols += [torch.cos(rg) - torch.cos(ra), torch.sin(rg) - torch.sin(ra)]
        else:
            cols.append(rg - ra)
        out = torch.stack(torch.broadcast_tensors(*cols), -1)
        if self.box_size > 7:
            extras = boxes[..., 7:] - anchors[..., 7:]
            out = torch.cat([out, extras.expand(*out.shape[:-1], -1)], -1)
        return out

    def decode(self, deltas: Tensor, anchors: Tensor) -> Tensor:
        """Decode encodings back to boxes (the inverse of :meth:`encode`).

        Args:
            deltas (Tensor[..., code_size]): encodings (e.g. the head's box regression).
            anchors (Tensor[..., 7 or box_size]): anchors; leading dims broadcast with the deltas'.

        Returns:
            Tensor[..., box_size] in the inputs' dtype. With ``encode_angle_by_sincos`` the heading is
            ``atan2`` of the decoded sine and cosine, in ``(-pi, pi]``.
        """
        _check_columns(deltas, "deltas", (self.code_size,), "encoded box")
        anchors = self._anchors(anchors, deltas, "deltas")
        xa, ya, za, ra = anchors[..., 0], anchors[..., 1], anchors[..., 2], anchors[..., 6]
        dxa, dya, dza = anchors[..., 3], anchors[..., 4], anchors[..., 5]
        xt, yt, zt, dxt, dyt, dzt = deltas[..., :6].unbind(-1)
        diagonal = torch.sqrt(dxa ** 2 + dya ** 2)
        shape = torch.broadcast_shapes(deltas.shape[:-1], anchors.shape[:-1])
        if not (torch.is_grad_enabled() and (deltas.requires_grad or anchors.requires_grad)):
            # each column's last operation writes its column of the result: no (N, 7) stacking pass, whose
            # interleaved writes cost more than the arithmetic (out= has no gradient: autograd takes the stack)
            out = deltas.new_empty(*shape, self.box_size, dtype=torch.promote_types(deltas.dtype, anchors.dtype))
            torch.add(xt * diagonal, xa, out=out[..., 0])
            torch.add(yt * diagonal, ya, out=out[..., 1])
            torch.add(zt * dza, za, out=out[..., 2])
            torch.mul(torch.exp(dxt), dxa, out=out[..., 3])
            torch.mul(torch.exp(dyt), dya, out=out[..., 4])
            torch.mul(torch.exp(dzt), dza, out=out[..., 5])
            if self.encode_angle_by_sincos:
                # into a temporary: a CPU atan2 into strided memory rounds differently from the vectorised one
                out[..., 6] = torch.atan2(deltas[..., 7] + torch.sin(ra), deltas[..., 6] + torch.cos(ra))
            else:
                torch.add(deltas[..., 6], ra, out=out[..., 6])
            if self.box_size > 7:
                torch.add(deltas[..., self.code_size - (self.box_size - 7):], anchors[..., 7:], out=out[..., 7:])
            return out
        if self.encode_angle_by_sincos:
            rg = torch.atan2(deltas[..., 7] + torch.sin(ra), deltas[..., 6] + torch.cos(ra))
        else:
            rg = deltas[..., 6] + ra
        cols = [xt * diagonal + xa, yt * diagonal + ya, zt * dza + za,
                torch.exp(dxt) * dxa, torch.exp(dyt) * dya, torch.exp(dzt) * dza, rg]
        out = torch.stack(torch.broadcast_tensors(*cols), -1)
        if self.box_size > 7:
            extras = deltas[..., self.code_size - (self.box_size - 7):] + anchors[..., 7:]
            out = torch.cat([out, extras.expand(*out.shape[:-1], -1)], -1)
        return out


# ---- anchors ----

_MISSING = object()


def _cfg(config: Mapping, key: str, index: int, default: Any = _MISSING) -> Any:
    if not isinstance(config, Mapping):
        raise ValueError(f"anchor_generator_config[{index}] must be a mapping (dict) with OpenPCDet's keys, "
                         f"got {type(config).__name__}")
    if key in config:
        return config[key]
    if default is _MISSING:
        raise ValueError(f"anchor_generator_config[{index}] ({config.get('class_name', '?')!r}) has no key "
                         f"{key!r}")
    return default


def _number_list(values, name: str) -> list[float]:
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of numbers, got {values!r}") from None
    if not out:
        raise ValueError(f"{name} must not be empty")
    return out


class AnchorGenerator:
    """OpenPCDet's anchor generator: per class, a grid of anchors over the feature map, every
    combination of size and rotation at every location and bottom height.

    Args:
        anchor_range (Sequence[float]): ``[x_min, y_min, z_min, x_max, y_max, z_max]`` (the point
            cloud range).
        anchor_generator_config (Sequence[Mapping]): one mapping per class with OpenPCDet's keys:
            ``class_name``, ``anchor_sizes`` (list of ``[dx, dy, dz]``), ``anchor_rotations`` (list),
            ``anchor_bottom_heights`` (list), ``align_center`` (bool, default False),
            ``feature_map_stride`` (for :meth:`feature_map_sizes`); the assigner's
            ``matched_threshold`` and ``unmatched_threshold`` may be there too.

    Centres along x (y alike) for a feature map of ``nx`` cells: ``x_min + (i + 0.5) * (x_max - x_min) / nx``
    with ``align_center``, else ``x_min + i * (x_max - x_min) / (nx - 1)`` (the range's corners are
    anchor centres), ``i < nx``: computed in float64, then cast. An anchor's z is its bottom height
    plus ``dz / 2`` (the box centre).
    """

    def __init__(self, anchor_range: Sequence[float], anchor_generator_config: Sequence[Mapping]):
        rng = _number_list(anchor_range, "anchor_range")
        if len(rng) != 6 or not (rng[3] > rng[0] and rng[4] > rng[1]):
            raise ValueError(f"anchor_range must be [x_min, y_min, z_min, x_max, y_max, z_max] with x_max > x_min "
                             f"and y_max > y_min, got {list(anchor_range)}")
        if isinstance(anchor_generator_config, Mapping) or not len(anchor_generator_config):
            raise ValueError("anchor_generator_config must be a non-empty list of per-class mappings")
        self.anchor_range = tuple(rng)
        self.anchor_generator_cfg = list(anchor_generator_config)
        self.class_names, self.anchor_sizes, self.anchor_rotations = [], [], []
        self.anchor_heights, self.align_center, self.feature_map_strides = [], [], []
        for i, c in enumerate(self.anchor_generator_cfg):
            name = _cfg(c, "class_name", i)
            sizes = _cfg(c, "anchor_sizes", i)
            try:
                sizes = [_number_list(s, f"anchor_generator_config[{i}].anchor_sizes[{j}]")
                         for j, s in enumerate(sizes)]
            except TypeError:
                raise ValueError(f"anchor_generator_config[{i}].anchor_sizes must be a list of [dx, dy, dz], "
                                 f"got {sizes!r}") from None
            if not sizes or any(len(s) != 3 for s in sizes):
                raise ValueError(f"anchor_generator_config[{i}].anchor_sizes must be a non-empty list of "
                                 f"[dx, dy, dz], got {sizes!r}")
            self.class_names.append(name)
            self.anchor_sizes.append(sizes)
            self.anchor_rotations.append(_number_list(_cfg(c, "anchor_rotations", i),
                                                      f"anchor_generator_config[{i}].anchor_rotations"))
            self.anchor_heights.append(_number_list(_cfg(c, "anchor_bottom_heights", i),
                                                    f"anchor_generator_config[{i}].anchor_bottom_heights"))
            self.align_center.append(bool(_cfg(c, "align_center", i, False)))
            self.feature_map_strides.append(_cfg(c, "feature_map_stride", i, None))
        self.num_of_anchor_sets = len(self.anchor_generator_cfg)

    def feature_map_sizes(self, grid_size: Sequence[int]) -> list[tuple[int, int]]:
        """Each class's feature map ``(nx, ny) = grid_size[:2] // feature_map_stride`` (OpenPCDet's
        anchor head), for a voxel grid ``grid_size = (nx, ny[, nz])``."""
        if len(grid_size) < 2:
            raise ValueError(f"grid_size must be (nx, ny[, nz]), got {grid_size!r}")
        nx, ny = (check_positive_int(g, f"grid_size[{k}]") for k, g in enumerate(grid_size[:2]))
        out = []
        for i, stride in enumerate(self.feature_map_strides):
            if stride is None:
                raise ValueError(f"anchor_generator_config[{i}] ({self.class_names[i]!r}) has no key "
                                 "'feature_map_stride'")
            s = check_positive_int(stride, f"anchor_generator_config[{i}].feature_map_stride")
            out.append((nx // s, ny // s))
        return out

    def generate_anchors(self, grid_sizes: Sequence[Sequence[int]], device: Optional[torch.device] = None,
                         dtype: torch.dtype = torch.float32) -> tuple[list[Tensor], list[int]]:
        """Anchors of every class.

        Args:
            grid_sizes (Sequence[(nx, ny)]): one feature-map size per class.
            device, dtype: of the returned anchors (float32 by default, as OpenPCDet).

        Returns:
            (anchors_list, num_anchors_per_location): per class a Tensor[nz, ny, nx, num_sizes,
            num_rotations, 7] (nz = number of bottom heights) and the int ``nz * num_sizes *
            num_rotations``.
        """
        if not dtype.is_floating_point:
            raise ValueError(f"dtype must be a floating dtype, got {dtype}")
        if len(grid_sizes) != self.num_of_anchor_sets:
            raise ValueError(f"grid_sizes must hold one (nx, ny) per class ({self.num_of_anchor_sets}), "
                             f"got {len(grid_sizes)}")
        x0, y0, _, x1, y1, _ = self.anchor_range
        anchors_list, per_location = [], []
        for i, grid in enumerate(grid_sizes):
            if len(grid) < 2:
                raise ValueError(f"grid_sizes[{i}] must be (nx, ny), got {grid!r}")
            nx, ny = (check_positive_int(g, f"grid_sizes[{i}][{k}]") for k, g in enumerate(grid[:2]))
            align = self.align_center[i]
            x = _centres(x0, x1, nx, align, f"grid_sizes[{i}][0]", device).to(dtype)
            y = _centres(y0, y1, ny, align, f"grid_sizes[{i}][1]", device).to(dtype)
            sizes = torch.tensor(self.anchor_sizes[i], dtype=dtype, device=device)  # (S, 3)
            rots = torch.tensor(self.anchor_rotations[i], dtype=dtype, device=device)  # (R,)
            bottoms = torch.tensor(self.anchor_heights[i], dtype=dtype, device=device)  # (Z,)
            nz, S, R = bottoms.shape[0], sizes.shape[0], rots.shape[0]
            shape = (nz, ny, nx, S, R)
            cols = [x.view(1, 1, nx, 1, 1), y.view(1, ny, 1, 1, 1),
                    bottoms.view(nz, 1, 1, 1, 1) + sizes[:, 2].view(1, 1, 1, S, 1) / 2,
                    *(sizes[:, k].view(1, 1, 1, S, 1) for k in range(3)), rots.view(1, 1, 1, 1, R)]
            anchors_list.append(torch.stack([c.expand(shape) for c in cols], -1))
            per_location.append(nz * S * R)
        return anchors_list, per_location

    def flat_anchors(self, grid_size: Sequence[int], device: Optional[torch.device] = None,
                     dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
        """Every class's anchors for a voxel grid, flattened as the head's outputs are:
        :meth:`feature_map_sizes`, :meth:`generate_anchors`, then :func:`flatten_anchors`."""
        anchors, _ = self.generate_anchors(self.feature_map_sizes(grid_size), device, dtype)
        return flatten_anchors(anchors)


def _centres(lo: float, hi: float, n: int, align_center: bool, name: str, device) -> Tensor:
    """``n`` anchor centres along one axis, float64 (see :class:`AnchorGenerator`)."""
    i = torch.arange(n, dtype=torch.float64, device=device)
    if align_center:
        step = (hi - lo) / n
        return (lo + step / 2) + i * step
    if n < 2:
        raise ValueError(f"{name} must be >= 2 with align_center False (the range's corners are the first and "
                         f"last centres), got {n}")
    return lo + i * ((hi - lo) / (n - 1))


def _check_anchor_grids(anchors_list: Sequence[Tensor], name: str) -> None:
    """Per-class anchors (nz, ny, nx, num_sizes, num_rotations, 7) sharing (nz, ny, nx), device, dtype."""
    if isinstance(anchors_list, Tensor) or not len(anchors_list):
        raise ValueError(f"{name} must be a non-empty list of per-class anchor tensors "
                         "(nz, ny, nx, num_sizes, num_rotations, 7)")
    for i, a in enumerate(anchors_list):
        _check_float(a, f"{name}[{i}]")
        if a.dim() != 6 or a.shape[-1] < 7:
            raise ValueError(f"{name}[{i}] must be (nz, ny, nx, num_sizes, num_rotations, 7), got {describe(a)}")
        if i:
            a0 = anchors_list[0]
            if a.shape[:3] != a0.shape[:3]:
                raise ValueError(f"{name}[{i}] has (nz, ny, nx) = {tuple(a.shape[:3])} but {name}[0] has "
                                 f"{tuple(a0.shape[:3])}: the classes' anchors must share one grid")
            _check_pair(a0, f"{name}[0]", a, f"{name}[{i}]", lead=a.dim())
            if a.shape[-1] != a0.shape[-1]:
                raise ValueError(f"{name}[{i}] has {a.shape[-1]} columns but {name}[0] has {a0.shape[-1]}")


def _heights_per_location(t: Tensor, z_dim: int) -> Tensor:
    """(..., nz, ny, nx, k, ...) with nz at ``z_dim`` -> (..., ny, nx, nz * k, ...): a location's anchors of
    every bottom height side by side, as the head's channels hold them."""
    t = t.movedim(z_dim, z_dim + 2)  # (..., ny, nx, nz, k, ...)
    return t.flatten(z_dim + 2, z_dim + 3)


def _concat_per_location(parts: Sequence[Tensor], loc_dim: int) -> Tensor:
    """Per-class tensors (..., ny, nx, k_c, ...) joined along the per-location axis ``loc_dim``
    (order per location: class, then the class's own order), then (ny, nx, k) flattened."""
    return torch.cat(list(parts), dim=loc_dim).flatten(loc_dim - 2, loc_dim)


def flatten_anchors(anchors_list: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """The classes' anchors in the order of the head's outputs.

    The order is (y, x, class, z, size, rotation), the order of ``conv_cls``'s output after
    ``permute(0, 2, 3, 1).reshape(B, -1, num_class)``: with one bottom height, OpenPCDet's
    ``torch.cat(anchors, dim=-3)`` flattened. With several (the Aerial-PointPillars' stacked layers), a
    location's heights are its channels too; OpenPCDet's own flattening puts z outermost there, which
    pairs anchors with the wrong outputs.

    Args:
        anchors_list (Sequence[Tensor[nz, ny, nx, S_c, R_c, 7]]): per class, sharing (nz, ny, nx).

    Returns:
        (anchors, anchor_class): Tensor[N, 7] and the int64 Tensor[N] index of each anchor's class in
        ``anchors_list`` (0-based), N = nz * ny * nx * sum_c(S_c * R_c).
    """
    _check_anchor_grids(anchors_list, "anchors_list")
    flat = [_heights_per_location(a.reshape(*a.shape[:3], -1, a.shape[-1]), 0) for a in anchors_list]
    cls = [torch.full(f.shape[:3], c, dtype=torch.int64, device=f.device) for c, f in enumerate(flat)]
    return _concat_per_location(flat, 2), _concat_per_location(cls, 2)


# ---- nearest-BEV IoU ----

def _aligned_bev(boxes: Tensor) -> Tensor:
    """(..., 7+) boxes -> (..., 4) ``x1, y1, x2, y2``: each box turned to its nearest axis-aligned
    orientation (dx and dy swapped when |heading| mod pi, wrapped to [-pi/2, pi/2), is >= pi/4)."""
    rot = limit_period(boxes[..., 6], 0.5, math.pi).abs()
    dims = torch.where((rot < math.pi / 4)[..., None], boxes[..., 3:5], boxes[..., [4, 3]])
    centre = boxes[..., 0:2]
    return torch.cat([centre - dims / 2, centre + dims / 2], -1)


def _iou_3d(anchors: Tensor, gt_boxes: Tensor) -> Tensor:
    """Rotated 3D IoU of anchors (A, 7+) against each frame's boxes (B, M, 7+): (B, A, M)."""
    with validation(False):  # the gts were checked; padding rows (zero boxes) give 0
        a = anchors[:, :7].contiguous()
        return torch.stack([box_iou_3d(a, g[:, :7].contiguous()) for g in gt_boxes])


def _nearest_bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    a, b = _aligned_bev(boxes_a).unsqueeze(-2), _aligned_bev(boxes_b).unsqueeze(-3)
    w = (torch.minimum(a[..., 2], b[..., 2]) - torch.maximum(a[..., 0], b[..., 0])).clamp_min(0)
    h = (torch.minimum(a[..., 3], b[..., 3]) - torch.maximum(a[..., 1], b[..., 1])).clamp_min(0)
    inter = w * h
    area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
    area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    return inter / (area_a + area_b - inter).clamp_min(1e-6)


def boxes3d_nearest_bev_iou(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """OpenPCDet's "nearest BEV" IoU: each box turned to its nearest axis-aligned orientation, then the
    IoU of the resulting bird's-eye-view rectangles.

    A box keeps (dx, dy) when ``|limit_period(heading, 0.5, pi)| < pi / 4`` and swaps them otherwise
    (so exactly pi/4 swaps); its rectangle is ``x -+ dx / 2, y -+ dy / 2``. The union is clamped to
    >= 1e-6 (OpenPCDet's guard), so zero-size boxes give 0, never NaN.

    Args:
        boxes_a (Tensor[..., N, 7+]): boxes (columns past 7 ignored).
        boxes_b (Tensor[..., M, 7+]): boxes, same dtype and device; leading dims broadcast.

    Returns:
        Tensor[..., N, M] in the inputs' dtype.
    """
    for t, name in ((boxes_a, "boxes_a"), (boxes_b, "boxes_b")):
        _check_float(t, name, min_dim=2)
        _check_columns(t, name, (7,), "N, x, y, z, dx, dy, dz, heading[, extras]", at_least=True)
    _check_pair(boxes_a, "boxes_a", boxes_b, "boxes_b", lead=2)
    return _nearest_bev_iou(boxes_a, boxes_b)


# ---- target assignment ----

class AxisAlignedTargetAssigner:
    """OpenPCDet's ``AxisAlignedTargetAssigner`` without sampling (``POS_FRACTION: -1``): per frame and
    class, anchors are matched to that class's ground-truth boxes by nearest-BEV IoU.

    For the anchors and ground truths of one class in one frame (overlaps (A, G)): every anchor's best
    gt (first on ties) and its IoU ``anchor_max``; every gt's best IoU over the anchors, -1 where it is
    0 (such a gt forces nothing). Force-matched anchors are those whose IoU with some gt equals that
    gt's best (every tied anchor). Labels start at -1 (ignored); force-matched anchors and anchors with
    ``anchor_max >= matched_threshold`` take the class id of their best gt; anchors with ``anchor_max <
    unmatched_threshold`` become 0 (background); force-matched anchors then take their class back.
    With no gt of the class every label is 0. Regression targets of the force-matched and positive
    anchors are ``box_coder.encode(best gt, anchor)``, zeros elsewhere; ``reg_weights`` are 1 where the
    label is > 0 (divided by max(1, anchors not ignored of that class in that frame) with
    ``norm_by_num_examples``), else 0.

    Args:
        anchor_generator_config (Sequence[Mapping]): per class, OpenPCDet's keys ``class_name``,
            ``matched_threshold``, ``unmatched_threshold`` (the :class:`AnchorGenerator` config).
        class_names (Sequence[str]): the dataset's classes: a gt of class id k (1-based) is matched to
            the anchors of the config whose ``class_name`` is ``class_names[k - 1]``, and labelled k.
        box_coder (ResidualCoder): encodes the regression targets.
        match_height (bool): match by rotated 3D IoU (:func:`lidarops.box_iou_3d`) instead of nearest-BEV IoU.
        norm_by_num_examples (bool): normalise ``reg_weights`` as described above.
    """

    def __init__(self, anchor_generator_config: Sequence[Mapping], class_names: Sequence[str],
                 box_coder: ResidualCoder, match_height: bool = False, norm_by_num_examples: bool = False):
        if isinstance(anchor_generator_config, Mapping) or not len(anchor_generator_config):
            raise ValueError("anchor_generator_config must be a non-empty list of per-class mappings")
        if isinstance(class_names, str) or not len(class_names):
            raise ValueError(f"class_names must be a non-empty list of names, got {class_names!r}")
        if not hasattr(box_coder, "encode") or not hasattr(box_coder, "code_size"):
            raise ValueError(f"box_coder must be a box coder such as ResidualCoder, got {type(box_coder).__name__}")
        cfgs = list(anchor_generator_config)
        self.box_coder = box_coder
        self.match_height = bool(match_height)
        self.norm_by_num_examples = bool(norm_by_num_examples)
        self.class_names = list(class_names)
        self.anchor_class_names = [_cfg(c, "class_name", i) for i, c in enumerate(cfgs)]
        self.matched_thresholds = [float(_cfg(c, "matched_threshold", i)) for i, c in enumerate(cfgs)]
        self.unmatched_thresholds = [float(_cfg(c, "unmatched_threshold", i)) for i, c in enumerate(cfgs)]
        # row c: which class ids (0 = padding) belong to config c's anchors
        self._class_of_config = torch.tensor([[False] + [n == name for n in self.class_names]
                                              for name in self.anchor_class_names])

    def assign_targets(self, all_anchors: Sequence[Tensor], gt_boxes_with_classes: Tensor) -> dict[str, Tensor]:
        """Classification and regression targets of every anchor of every frame.

        Args:
            all_anchors (Sequence[Tensor[nz, ny, nx, S_c, R_c, 7]]): per class config, as
                :meth:`AnchorGenerator.generate_anchors` returns them (sharing nz, ny, nx).
            gt_boxes_with_classes (Tensor[B, M, box_size + 1]): boxes then the class id (1-based; rows
                with class id 0 are padding), same dtype and device as the anchors.

        Returns:
            dict with, in the order of :func:`flatten_anchors` ((y, x, class, z, size, rotation), A
            anchors in all):
            ``box_cls_labels`` (int64 Tensor[B, A]: -1 ignored, 0 background, else the class id),
            ``box_reg_targets`` (Tensor[B, A, code_size]), ``reg_weights`` (Tensor[B, A]).
        """
        _check_anchor_grids(all_anchors, "all_anchors")
        if len(all_anchors) != len(self.anchor_class_names):
            raise ValueError(f"all_anchors must hold one tensor per class config ({len(self.anchor_class_names)}), "
                             f"got {len(all_anchors)}")
        gt = gt_boxes_with_classes
        _check_float(gt, "gt_boxes_with_classes")
        box_size = getattr(self.box_coder, "box_size", 7)
        if gt.dim() != 3 or gt.shape[-1] != box_size + 1:
            raise ValueError(f"gt_boxes_with_classes must be (B, M, {box_size + 1}) (box, class id), "
                             f"got {describe(gt)}")
        _check_pair(all_anchors[0], "all_anchors[0]", gt, "gt_boxes_with_classes", lead=all_anchors[0].dim())
        gt_boxes, cls_f = gt[..., :-1], gt[..., -1]
        if value_checks_enabled() and cls_f.numel():
            n = len(self.class_names)
            bad = ((cls_f < 0) | (cls_f > n) | (cls_f != cls_f.round())).any()
            run_value_checks([(bad, lambda: f"gt_boxes_with_classes' class ids (last column) must be integers in "
                                            f"0..{n} (0 = padding), got {sorted(set(cls_f.unique().tolist()))}")])
        gt_cls = cls_f.long()
        of_config = self._class_of_config.to(gt.device)
        B, labels, targets, weights = gt.shape[0], [], [], []
        for c, anchors in enumerate(all_anchors):
            grid = anchors.shape[:3]
            lab, tgt, w = self._assign_class(anchors.reshape(-1, anchors.shape[-1]), gt_boxes, gt_cls,
                                             of_config[c][gt_cls], c)
            labels.append(_heights_per_location(lab.view(B, *grid, -1), 1))
            targets.append(_heights_per_location(tgt.view(B, *grid, -1, tgt.shape[-1]), 1))
            weights.append(_heights_per_location(w.view(B, *grid, -1), 1))
        return {"box_cls_labels": _concat_per_location(labels, 3),
                "box_reg_targets": _concat_per_location(targets, 3),
                "reg_weights": _concat_per_location(weights, 3)}

    def _assign_class(self, anchors: Tensor, gt_boxes: Tensor, gt_cls: Tensor, valid: Tensor,
                      c: int) -> tuple[Tensor, Tensor, Tensor]:
        """One class config's anchors (A, 7) against every frame's gts (B, M, box_size), ``valid`` (B, M)
        marking the gts of this class: labels (B, A), targets (B, A, code_size), weights (B, A)."""
        (B, M), A = valid.shape, anchors.shape[0]
        labels = torch.zeros(B, A, dtype=torch.int64, device=anchors.device)
        targets = anchors.new_zeros(B, A, self.box_coder.code_size)
        weights = anchors.new_zeros(B, A)
        if A == 0 or M == 0:
            return labels, targets, weights
        # other classes' gts and padding get -1: below any IoU, so argmax picks this class's gts when any
        iou = _iou_3d(anchors, gt_boxes) if self.match_height else _nearest_bev_iou(anchors, gt_boxes)
        iou = iou.masked_fill(~valid[:, None, :], -1)  # (B, A, M)
        anchor_to_gt = iou.argmax(2)
        anchor_max = iou.gather(2, anchor_to_gt[..., None]).squeeze(2)
        gt_max = iou.amax(1)
        gt_max = gt_max.masked_fill(gt_max == 0, -1)
        force = ((iou == gt_max[:, None, :]) & valid[:, None, :]).any(2)
        best_label = gt_cls.gather(1, anchor_to_gt)
        fg = force | (anchor_max >= self.matched_thresholds[c])
        labels = torch.where(fg, best_label, -1)
        labels = torch.where(anchor_max < self.unmatched_thresholds[c], 0, labels)
        labels = torch.where(force, best_label, labels)
        best_gt = gt_boxes.gather(1, anchor_to_gt[..., None].expand(-1, -1, gt_boxes.shape[-1]))
        # OpenPCDet takes the foreground before background is reset: identical unless matched < unmatched
        targets = torch.where(fg[..., None], self.box_coder.encode(best_gt, anchors), targets)
        weights = (labels > 0).to(anchors.dtype)
        if self.norm_by_num_examples:
            weights = weights / (labels >= 0).sum(1, keepdim=True).clamp_min(1).to(anchors.dtype)
        return labels, targets, weights


# ---- direction bins ----

def _check_bins(num_bins) -> int:
    return check_positive_int(num_bins, "num_bins")


def get_direction_target(anchors: Tensor, reg_targets: Tensor, one_hot: bool = True,
                         dir_offset: float = DIR_OFFSET, num_bins: int = 2) -> Tensor:
    """Direction-bin targets (OpenPCDet's ``get_direction_target``).

    ``rot_gt = reg_targets[..., 6] + anchors[..., 6]`` (the gt heading for the residual coder without
    sin/cos), ``offset_rot = limit_period(rot_gt - dir_offset, 0, 2 pi)``, bin =
    ``floor(offset_rot / (2 pi / num_bins))`` clamped to ``[0, num_bins - 1]``.

    Args:
        anchors (Tensor[..., 7+]): anchors, leading dims broadcast with ``reg_targets``' (e.g. (A, 7)
            or (B, A, 7)).
        reg_targets (Tensor[..., code_size]): the assigner's ``box_reg_targets``.
        one_hot (bool): return one-hot rows instead of bin indices.
        dir_offset (float): heading where the bins start (pointpillar.yaml: 0.78539).
        num_bins (int): number of direction bins.

    Returns:
        one_hot: Tensor[..., num_bins] in the anchors' dtype; else int64 Tensor[...].
    """
    _check_columns(anchors, "anchors", (7,), "x, y, z, dx, dy, dz, heading[, extras]", at_least=True)
    _check_columns(reg_targets, "reg_targets", (7,), "encoded box", at_least=True)
    _check_pair(anchors, "anchors", reg_targets, "reg_targets")
    num_bins = _check_bins(num_bins)
    rot_gt = reg_targets[..., 6] + anchors[..., 6]
    offset_rot = limit_period(rot_gt - dir_offset, 0, 2 * math.pi)
    bins = torch.floor(offset_rot / (2 * math.pi / num_bins)).long().clamp(0, num_bins - 1)
    if one_hot:
        return torch.nn.functional.one_hot(bins, num_bins).to(anchors.dtype)
    return bins


def decode_direction(box_preds_heading: Tensor, dir_labels: Tensor, dir_offset: float = DIR_OFFSET,
                     dir_limit_offset: float = 0.0, num_bins: int = 2) -> Tensor:
    """Headings from regressed headings and predicted direction bins (OpenPCDet's
    ``generate_predicted_boxes``): ``limit_period(heading - dir_offset, dir_limit_offset, period) +
    dir_offset + period * dir_labels`` with ``period = 2 pi / num_bins``.

    Args:
        box_preds_heading (Tensor[...]): decoded headings (column 6 of the decoded boxes).
        dir_labels (Tensor[...]): integer bin of each box (argmax of the direction classifier),
            broadcasting with the headings.
        dir_offset (float), dir_limit_offset (float), num_bins (int): OpenPCDet's ``DIR_OFFSET``,
            ``DIR_LIMIT_OFFSET``, ``NUM_DIR_BINS``.

    Returns:
        Tensor (the broadcast shape) in the headings' dtype.
    """
    _check_float(box_preds_heading, "box_preds_heading", min_dim=0)
    check_tensor(dir_labels, "dir_labels")
    if dir_labels.is_floating_point() or dir_labels.is_complex() or dir_labels.dtype == torch.bool:
        raise ValueError(f"dir_labels must be an integer tensor, got {describe(dir_labels)}")
    if dir_labels.device != box_preds_heading.device:
        raise ValueError(f"dir_labels is on {dir_labels.device} but box_preds_heading is on "
                         f"{box_preds_heading.device}; move them to one device")
    try:
        torch.broadcast_shapes(box_preds_heading.shape, dir_labels.shape)
    except RuntimeError:
        raise ValueError(f"box_preds_heading ({describe(box_preds_heading)}) and dir_labels "
                         f"({describe(dir_labels)}) do not broadcast") from None
    period = 2 * math.pi / _check_bins(num_bins)
    dir_rot = limit_period(box_preds_heading - dir_offset, dir_limit_offset, period)
    return dir_rot + dir_offset + period * dir_labels.to(box_preds_heading.dtype)
