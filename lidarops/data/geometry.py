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


def _local_coords(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    c, s = np.cos(box[6]), np.sin(box[6])
    d = xyz - box[:3]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)


def _in_box(xyz: np.ndarray, box: np.ndarray, margin: float) -> np.ndarray:
    """Which of the points ``xyz`` lie in the closed box grown by ``margin``."""
    local = _local_coords(xyz, box)
    half = box[3:6] / 2.0 + margin
    return (np.abs(local[:, 0]) <= half[0]) & (np.abs(local[:, 1]) <= half[1]) & (np.abs(local[:, 2]) <= half[2])


_FEW_BOXES = 4  # up to this many boxes, count_points_in_boxes tests every point against every box


def _inside_per_box(points: np.ndarray, boxes: np.ndarray, margin: float, cell: float = 4.0):
    """Yields ``(j, candidate_indices, inside)`` per box: the points in the grid cells (``cell`` metres,
    found by binary search on points sorted by cell) overlapping box ``j``'s bounding square, and which
    of them lie in the (closed, grown) box."""
    points = np.ascontiguousarray(points)  # (np.take on a strided view would copy the whole array)
    ix = np.floor(points[:, 0] / cell).astype(np.int64)
    iy = np.floor(points[:, 1] / cell).astype(np.int64)
    offset = 1 << 20
    key = (ix + offset) * (2 * offset) + (iy + offset)
    order = np.argsort(key)
    key_sorted = key[order]
    radius = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4]) + max(margin, 0.0) + 1e-6
    for j, box in enumerate(boxes):
        x_lo, x_hi = int(np.floor((box[0] - radius[j]) / cell)), int(np.floor((box[0] + radius[j]) / cell))
        y_lo, y_hi = int(np.floor((box[1] - radius[j]) / cell)), int(np.floor((box[1] + radius[j]) / cell))
        rows = np.arange(x_lo, x_hi + 1, dtype=np.int64) + offset
        lo = np.searchsorted(key_sorted, rows * (2 * offset) + (y_lo + offset), side="left")
        hi = np.searchsorted(key_sorted, rows * (2 * offset) + (y_hi + offset), side="right")
        parts = [order[a:b] for a, b in zip(lo.tolist(), hi.tolist()) if b > a]
        if not parts:
            yield j, order[:0], np.zeros(0, bool)
            continue
        near = np.concatenate(parts) if len(parts) > 1 else parts[0]
        yield j, near, _in_box(np.take(points, near, axis=0)[:, :3].astype(np.float64), box, margin)


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
        for j, near, inside in _inside_per_box(points, boxes, margin):
            mask[near[inside], j] = True
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
    counts = np.zeros(boxes.shape[0], dtype=np.int64)
    if points.shape[0] and boxes.shape[0] <= _FEW_BOXES:
        # a handful of boxes (drone frames): testing every point is cheaper than sorting them into cells; the
        # arithmetic of _in_box on contiguous components (N x 3 arrays run NumPy's loops several times slower)
        x, y, z = (points[:, i].astype(np.float64) for i in range(3))
        for j, box in enumerate(boxes):
            c, s = np.cos(box[6]), np.sin(box[6])
            dx, dy = x - box[0], y - box[1]
            inside = np.abs(c * dx + s * dy) <= box[3] / 2.0
            inside &= np.abs(-s * dx + c * dy) <= box[4] / 2.0
            inside &= np.abs(z - box[2]) <= box[5] / 2.0
            counts[j] = int(np.count_nonzero(inside))
    elif points.shape[0]:
        for j, _, inside in _inside_per_box(points, boxes, 0.0):
            counts[j] = int(np.count_nonzero(inside))
    return counts


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
