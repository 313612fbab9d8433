"""Box and pose geometry shared by the simulator, the format readers and the datasets (NumPy only).

Box convention (LiDAR frame, the whole of :mod:`lidarops.data`): ``boxes (float[M, 7])`` holds
``x, y, z, dx, dy, dz, yaw`` where ``(x, y, z)`` is the box *centre*, ``dx`` the length along the
heading, ``dy`` the width, ``dz`` the height, and ``yaw`` the heading angle about +z measured from +x
towards +y (radians).
"""
from __future__ import annotations

import numpy as np

__all__ = [
    "rotation_z",
    "euler_to_matrix",
    "pose_matrix",
    "transform_points",
    "transform_boxes",
    "box_corners",
    "points_in_boxes_mask",
    "count_points_in_boxes",
    "box_index_of_points",
    "wrap_angle",
]


def wrap_angle(angle: np.ndarray | float) -> np.ndarray | float:
    """Wraps angles to ``[-pi, pi)``.

    Args:
        angle (float or ndarray): angles in radians.

    Returns:
        The same angles wrapped to ``[-pi, pi)``.
    """
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def rotation_z(yaw: np.ndarray | float) -> np.ndarray:
    """Rotation matrices about +z.

    Args:
        yaw (float or ndarray[...]): angles in radians.

    Returns:
        ndarray[..., 3, 3]: rotation matrices.
    """
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros(yaw.shape + (3, 3))
    out[..., 0, 0] = c
    out[..., 0, 1] = -s
    out[..., 1, 0] = s
    out[..., 1, 1] = c
    out[..., 2, 2] = 1.0
    return out


def euler_to_matrix(roll: np.ndarray | float, pitch: np.ndarray | float, yaw: np.ndarray | float) -> np.ndarray:
    """Rotation matrices ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (z-y-x intrinsic, aerospace convention).

    Args:
        roll, pitch, yaw (float or ndarray[...]): angles in radians (broadcastable).

    Returns:
        ndarray[..., 3, 3]: rotation matrices.
    """
    roll, pitch, yaw = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw)))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    out = np.empty(roll.shape + (3, 3))
    out[..., 0, 0] = cy * cp
    out[..., 0, 1] = cy * sp * sr - sy * cr
    out[..., 0, 2] = cy * sp * cr + sy * sr
    out[..., 1, 0] = sy * cp
    out[..., 1, 1] = sy * sp * sr + cy * cr
    out[..., 1, 2] = sy * sp * cr - cy * sr
    out[..., 2, 0] = -sp
    out[..., 2, 1] = cp * sr
    out[..., 2, 2] = cp * cr
    return out


def pose_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Builds homogeneous 4x4 transforms.

    Args:
        rotation (ndarray[..., 3, 3]): rotations.
        translation (ndarray[..., 3]): translations.

    Returns:
        ndarray[..., 4, 4]: ``[[R, t], [0, 1]]``.
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    out = np.zeros(rotation.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def transform_points(transform: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Applies a 4x4 (or 3x4) transform to points.

    Args:
        transform (ndarray[4, 4] or ndarray[3, 4]): ``p' = R p + t``.
        xyz (ndarray[N, 3]): points.

    Returns:
        ndarray[N, 3] (float64): transformed points.
    """
    transform = np.asarray(transform, dtype=np.float64)
    xyz = np.asarray(xyz, dtype=np.float64)
    return xyz @ transform[:3, :3].T + transform[:3, 3]


def transform_boxes(transform: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Moves boxes by a rigid transform whose rotation is (close to) a rotation about z.

    Only the yaw part of the rotation changes the box heading; boxes stay upright.

    Args:
        transform (ndarray[4, 4]): rigid transform.
        boxes (ndarray[M, 7]): boxes ``x, y, z, dx, dy, dz, yaw``.

    Returns:
        ndarray[M, 7] with the dtype of ``boxes``.
    """
    transform = np.asarray(transform, dtype=np.float64)
    boxes = np.asarray(boxes)
    out = boxes.astype(np.float64, copy=True).reshape(-1, 7)
    out[:, :3] = transform_points(transform, out[:, :3])
    yaw_offset = np.arctan2(transform[1, 0], transform[0, 0])
    out[:, 6] = wrap_angle(out[:, 6] + yaw_offset)
    return out.astype(boxes.dtype if boxes.dtype.kind == "f" else np.float64)


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners of boxes.

    Args:
        boxes (ndarray[M, 7]): boxes ``x, y, z, dx, dy, dz, yaw``.

    Returns:
        ndarray[M, 8, 3] (float64): corners; 0-3 the bottom ones, counter-clockwise seen from above
        starting at front-left (+x, +y in the box frame), 4-7 the top corners above them.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    signs = np.array(
        [[1, 1, -1], [-1, 1, -1], [-1, -1, -1], [1, -1, -1], [1, 1, 1], [-1, 1, 1], [-1, -1, 1], [1, -1, 1]],
        dtype=np.float64,
    )
    local = signs[None] * (boxes[:, None, 3:6] / 2.0)
    rot = rotation_z(boxes[:, 6])
    return np.einsum("mij,mkj->mki", rot, local) + boxes[:, None, :3]


def _inside(x: np.ndarray, y: np.ndarray, z: np.ndarray, boxes: np.ndarray, margin: float,
            box: np.ndarray | int) -> np.ndarray:
    """Whether point ``i`` (float64 ``x, y, z``) lies in the closed box ``box[i]`` (or in box ``box`` for all)
    grown by ``margin``."""
    c, s = np.cos(boxes[:, 6])[box], np.sin(boxes[:, 6])[box]
    cx, cy, cz = (boxes[:, i][box] for i in range(3))
    hx, hy, hz = ((boxes[:, i] / 2.0 + margin)[box] for i in range(3, 6))
    dx, dy = x - cx, y - cy
    inside = np.abs(c * dx + s * dy) <= hx
    inside &= np.abs(-s * dx + c * dy) <= hy
    inside &= np.abs(z - cz) <= hz
    return inside


_FEW_BOXES = 4  # up to this many boxes, every point is tested against every box (no grid)


def _point_box_pairs(points: np.ndarray, boxes: np.ndarray, margin: float,
                     cell: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """``(box, point)`` index pairs of the points inside each (closed, grown) box.

    With more than a few boxes, the candidates of a box are the points in the grid cells (``cell`` metres)
    overlapping its bounding square, found by binary search on the points sorted by cell, for all boxes at
    once; the candidates are then tested exactly.  Coordinates are taken in float64.
    """
    x, y, z = (np.asarray(points[:, i], dtype=np.float64) for i in range(3))
    m = boxes.shape[0]
    if m <= _FEW_BOXES:
        inside = [np.flatnonzero(_inside(x, y, z, boxes, margin, j)) for j in range(m)]
        return np.repeat(np.arange(m), [i.size for i in inside]), np.concatenate(inside)
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + max(margin, 0.0) + 1e-6
    x_lo, x_hi, y_lo, y_hi = (np.floor((boxes[:, i] + sign * radius) / cell).astype(np.int64)
                              for i, sign in ((0, -1), (0, 1), (1, -1), (1, 1)))
    # cells numbered row-major over the boxes' extent; points outside it get -1 and are never candidates
    x0, y0 = int(x_lo.min()), int(y_lo.min())
    nx, ny = int(x_hi.max()) - x0 + 1, int(y_hi.max()) - y0 + 1
    ix = np.floor(x / cell) - x0
    iy = np.floor(y / cell) - y0
    key = np.where((ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny), ix * ny + iy, -1.0)
    # few enough cells for int16 keys: NumPy's stable argsort is then a radix sort, several times faster
    key = key.astype(np.int16 if nx * ny < 32767 else np.int64)
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    # one slice of sorted points per (box, row of cells)
    rows = x_hi - x_lo + 1
    box_of_row = np.repeat(np.arange(m), rows)
    row = np.repeat(x_lo - x0 - np.cumsum(rows) + rows, rows) + np.arange(int(rows.sum()))
    lo = np.searchsorted(key_sorted, (row * ny + (y_lo[box_of_row] - y0)).astype(key.dtype), side="left")
    hi = np.searchsorted(key_sorted, (row * ny + (y_hi[box_of_row] - y0)).astype(key.dtype), side="right")
    counts = hi - lo
    box = np.repeat(box_of_row, counts)
    point = order[np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts - lo, counts)]
    inside = _inside(x[point], y[point], z[point], boxes, margin, box)
    return box[inside], point[inside]


def points_in_boxes_mask(points: np.ndarray, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which points lie inside which boxes (closed boxes, optionally grown by ``margin``).

    Args:
        points (ndarray[N, >=3]): points; only x, y, z are used.
        boxes (ndarray[M, 7]): boxes.
        margin (float): metres added to every half-size (negative shrinks).

    Returns:
        ndarray[N, M] (bool).
    """
    points = np.asarray(points)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    mask = np.zeros((points.shape[0], boxes.shape[0]), dtype=bool)
    if points.shape[0] and boxes.shape[0]:
        box, point = _point_box_pairs(points, boxes, margin)
        mask[point, box] = True
    return mask


def count_points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Number of points inside each box (closed boxes; a point in two boxes counts for both).

    Args:
        points (ndarray[N, >=3]): points.
        boxes (ndarray[M, 7]): boxes.

    Returns:
        ndarray[M] (int64).
    """
    points = np.asarray(points)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if not (points.shape[0] and boxes.shape[0]):
        return np.zeros(boxes.shape[0], dtype=np.int64)
    box, _ = _point_box_pairs(points, boxes, 0.0)
    return np.bincount(box, minlength=boxes.shape[0]).astype(np.int64)


def box_index_of_points(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Index of the (first) box containing each point, ``-1`` for points in no box.

    Args:
        points (ndarray[N, >=3]): points.
        boxes (ndarray[M, 7]): boxes.

    Returns:
        ndarray[N] (int64).
    """
    mask = points_in_boxes_mask(points, boxes)
    if mask.shape[1] == 0:
        return np.full(mask.shape[0], -1, dtype=np.int64)
    return np.where(mask.any(axis=1), mask.argmax(axis=1), -1).astype(np.int64)
