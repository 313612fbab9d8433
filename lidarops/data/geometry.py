"""Box and pose geometry shared by the simulator, the format readers and the datasets, on NumPy arrays:
the one home of box corners, and of points-in-boxes on NumPy arrays (computed by the op
:func:`lidarops.points_in_boxes`, whose float64 reference lives with the tests).

Box convention (LiDAR frame, :mod:`lidarops.conventions`): ``boxes (float[M, 7])`` holds
``x, y, z, dx, dy, dz, heading`` where ``(x, y, z)`` is the box *centre*, ``dx`` the length along the
heading, ``dy`` the width, ``dz`` the height, and ``heading`` the angle about +z measured from +x
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
        boxes (ndarray[M, 7]): boxes ``x, y, z, dx, dy, dz, heading``.

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
        boxes (ndarray[M, 7]): boxes ``x, y, z, dx, dy, dz, heading``.

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


def _box_tensors(points: np.ndarray, boxes: np.ndarray):
    """float64 tensors for the op (exact for float32 input: the op then rounds nothing the NumPy caller did
    not), boxes (M, 7)."""
    import torch

    p = torch.from_numpy(np.ascontiguousarray(np.asarray(points)[:, :3], dtype=np.float64))
    return p, torch.from_numpy(np.ascontiguousarray(boxes, dtype=np.float64))


def _first_box(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """:func:`lidarops.points_in_boxes` (the lowest box holding each point, -1 for none) on NumPy arrays."""
    from lidarops.ops.boxes import points_in_boxes

    if points.shape[0] == 0 or boxes.shape[0] == 0:
        return np.full(points.shape[0], -1, dtype=np.int64)
    return points_in_boxes(*_box_tensors(points, boxes)).numpy()


def _may_share_points(boxes: np.ndarray) -> np.ndarray:
    """Boxes whose bounding spheres' footprints and z ranges meet another box's: only those can hold a point
    that the op gives to a lower box (a superset of the overlapping boxes; exact results need no more)."""
    r = 0.5 * np.hypot(boxes[:, 3], boxes[:, 4])
    d = np.hypot(boxes[:, None, 0] - boxes[None, :, 0], boxes[:, None, 1] - boxes[None, :, 1])
    dz = np.abs(boxes[:, None, 2] - boxes[None, :, 2])
    near = (d <= r[:, None] + r[None, :] + 1e-9) & (dz <= 0.5 * (boxes[:, None, 5] + boxes[None, :, 5]) + 1e-9)
    np.fill_diagonal(near, False)
    return near.any(axis=1)


def _grown(boxes: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Boxes grown by ``margin`` on every half-size, and which of them still have sizes >= 0."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7).copy()
    if margin:
        boxes[:, 3:6] += 2.0 * margin
    return boxes, (boxes[:, 3:6] >= 0).all(axis=1)


def points_in_boxes_mask(points: np.ndarray, boxes: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Which points lie inside which boxes (closed boxes, optionally grown by ``margin``), computed by the op
    :func:`lidarops.points_in_boxes` (a point in two overlapping boxes is in both).

    Args:
        points (ndarray[N, >=3]): points; only x, y, z are used.
        boxes (ndarray[M, 7]): boxes.
        margin (float): metres added to every half-size (negative shrinks; a box shrunk below zero size holds
            nothing).

    Returns:
        ndarray[N, M] (bool).
    """
    points = np.asarray(points)
    boxes, valid = _grown(boxes, margin)
    mask = np.zeros((points.shape[0], boxes.shape[0]), dtype=bool)
    cols = np.flatnonzero(valid)
    if points.shape[0] == 0 or cols.size == 0:
        return mask
    first = _first_box(points, boxes[cols])
    inside = first >= 0
    mask[np.flatnonzero(inside), cols[first[inside]]] = True
    for j in np.flatnonzero(_may_share_points(boxes[cols])):  # the op names the lowest box only
        mask[:, cols[j]] = _first_box(points, boxes[cols[j]:cols[j] + 1]) == 0
    return mask


def count_points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Number of points inside each box (closed boxes; a point in two boxes counts for both), by the op
    :func:`lidarops.points_in_boxes`.

    Args:
        points (ndarray[N, >=3]): points.
        boxes (ndarray[M, 7]): boxes.

    Returns:
        ndarray[M] (int64).
    """
    points = np.asarray(points)
    boxes, valid = _grown(boxes, 0.0)
    counts = np.zeros(boxes.shape[0], dtype=np.int64)
    cols = np.flatnonzero(valid)
    if points.shape[0] == 0 or cols.size == 0:
        return counts
    first = _first_box(points, boxes[cols])
    counts[cols] = np.bincount(first[first >= 0], minlength=cols.size)
    for j in np.flatnonzero(_may_share_points(boxes[cols])):
        counts[cols[j]] = int((_first_box(points, boxes[cols[j]:cols[j] + 1]) == 0).sum())
    return counts


def box_index_of_points(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Index of the (first) box containing each point, ``-1`` for points in no box: :func:`lidarops.points_in_boxes`
    on NumPy arrays.

    Args:
        points (ndarray[N, >=3]): points.
        boxes (ndarray[M, 7]): boxes (sizes >= 0).

    Returns:
        ndarray[N] (int64).
    """
    return _first_box(np.asarray(points), np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
