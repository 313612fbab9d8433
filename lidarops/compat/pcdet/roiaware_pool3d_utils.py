"""Face of OpenPCDet's ``pcdet.ops.roiaware_pool3d.roiaware_pool3d_utils`` (the point-in-box tests)::

    # from pcdet.ops.roiaware_pool3d import roiaware_pool3d_utils
    from lidarops.compat.pcdet import roiaware_pool3d_utils

OpenPCDet's kernels test ``|z - cz| <= dz / 2`` and, in the box's frame, ``|local_x| < dx / 2 + margin``
and ``|local_y| < dy / 2 + margin``, with a margin of 1 cm on the CPU (``points_in_boxes_cpu``, used by
its data augmentation and database tools) and 1e-5 m on CUDA (``points_in_boxes_gpu``). The faces keep
each function's margin on every device. ``points_in_boxes_gpu`` runs lidarops' point-in-box kernel on
boxes widened by the margin (a point exactly on the widened edge counts as inside; OpenPCDet's strict
``<`` leaves it out). As in OpenPCDet, a zero-size padding box still holds points within the margin of
its centre. ``RoIAwarePool3d`` (Part-A2's RoI pooling) is not served.
"""
from __future__ import annotations

import torch
from torch import Tensor

from lidarops.compat.pcdet._common import check_boxes, check_points, to_torch
from lidarops.ops import boxes as _boxes
from lidarops.ops.boxes import check_box_values
from lidarops.ops.validation import check_same_device, describe, validation

__all__ = ["points_in_boxes_cpu", "points_in_boxes_gpu", "CPU_MARGIN", "GPU_MARGIN"]

#: OpenPCDet's in-box margins (``check_pt_in_box3d_cpu`` and ``check_pt_in_box3d``)
CPU_MARGIN = 1e-2
GPU_MARGIN = 1e-5
# the (boxes x points) mask is computed this many points at a time (bounded temporaries)
_CHUNK = 1 << 20


def _mask(points: Tensor, boxes: Tensor, margin: float) -> Tensor:
    """(N, P) int32, 1 where point p is in box n; float32 arithmetic, the rotation OpenPCDet's kernel uses."""
    out = torch.zeros((boxes.shape[0], points.shape[0]), dtype=torch.int32, device=points.device)
    if not boxes.shape[0] or not points.shape[0]:
        return out
    b = boxes[:, None, :]
    cos, sin = torch.cos(-b[..., 6]), torch.sin(-b[..., 6])
    step = max(1, _CHUNK // boxes.shape[0])
    for s in range(0, points.shape[0], step):
        p = points[None, s:s + step]
        sx, sy = p[..., 0] - b[..., 0], p[..., 1] - b[..., 1]
        local_x, local_y = sx * cos - sy * sin, sx * sin + sy * cos
        inside = ((p[..., 2] - b[..., 2]).abs() <= b[..., 5] / 2) & (local_x.abs() < b[..., 3] / 2 + margin) \
            & (local_y.abs() < b[..., 4] / 2 + margin)
        out[:, s:s + step] = inside.to(torch.int32)
    return out


def points_in_boxes_cpu(points, boxes):
    """Which boxes hold each point, as a mask.

    Args:
        points: (num_points, 3), tensor or numpy array.
        boxes: (N, 7) [x, y, z, dx, dy, dz, heading], same kind.

    Returns:
        (N, num_points) int32, 1 where the point is in the box (boxes may overlap); numpy for numpy input.
        Computed in float32, as OpenPCDet's kernel (which casts both inputs with ``.float()``).
    """
    p, numpy_p = to_torch(points, "points")
    b, numpy_b = to_torch(boxes, "boxes")
    check_points(p, "points")
    check_boxes(b, "boxes")
    check_same_device([("points", p), ("boxes", b)])
    check_box_values(("boxes", b))
    mask = _mask(p.float(), b.float(), CPU_MARGIN)
    return mask.numpy() if numpy_p or numpy_b else mask


def points_in_boxes_gpu(points: Tensor, boxes: Tensor) -> Tensor:
    """The first box holding each point, per batch element.

    Args:
        points: (B, M, 3).
        boxes: (B, T, 7) [x, y, z, dx, dy, dz, heading]; all T boxes are tested (pad with zero-size boxes).

    Returns:
        (B, M) int32: the index of the first box containing the point, -1 for none.
    """
    check_points(points, "points", batched=True)
    check_boxes(boxes, "boxes", batched=True)
    check_same_device([("points", points), ("boxes", boxes)])
    if boxes.shape[0] != points.shape[0]:
        raise ValueError(f"boxes and points must have the same batch size, got {describe(boxes)} and {describe(points)}")
    check_box_values(("boxes", boxes.reshape(-1, 7)))
    out = torch.full(points.shape[:2], -1, dtype=torch.int32, device=points.device)
    dtype = torch.promote_types(points.dtype, boxes.dtype)
    with validation(False):
        for i in range(points.shape[0]):
            wide = boxes[i].to(dtype).clone()
            wide[:, 3:5] += 2 * GPU_MARGIN
            out[i] = _boxes.points_in_boxes(points[i].to(dtype), wide).to(torch.int32)
    return out
