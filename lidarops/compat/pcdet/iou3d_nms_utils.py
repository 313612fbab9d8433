"""Face of OpenPCDet's ``pcdet.ops.iou3d_nms.iou3d_nms_utils`` on lidarops' box kernels, CPU and CUDA::

    # from pcdet.ops.iou3d_nms import iou3d_nms_utils
    from lidarops.compat.pcdet import iou3d_nms_utils

Same names, arguments and return values (``nms_gpu`` returns ``(keep, None)``; ``boxes_bev_iou_cpu``
returns numpy for numpy input). Every function runs on CPU and CUDA tensors (OpenPCDet's ``*_gpu``
functions need CUDA, ``boxes_bev_iou_cpu`` needs the CPU), and float64 boxes are computed in float64
(OpenPCDet's kernels read float32 only). Deliberate differences (docs/compat.md):

* NMS visits equal scores lower index first (OpenPCDet sorts with the unstable ``torch.sort``, so its
  order among equal scores is unspecified);
* box values are checked (NaN, infinity, negative sizes raise ValueError naming the box);
* ``boxes_iou3d_gpu`` and its paired forms follow OpenPCDet's formula, ``overlap / max(union, 1e-6)``.
"""
from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from lidarops.compat.pcdet._common import check_boxes, to_torch
from lidarops.ops import boxes as _boxes
from lidarops.ops.boxes import check_box_values
from lidarops.ops.validation import check_same_device, describe, validation

__all__ = ["boxes_bev_iou_cpu", "boxes_iou_bev", "boxes_iou3d_gpu", "boxes_aligned_iou3d_gpu",
           "paired_boxes_iou3d_gpu", "nms_gpu", "nms_normal_gpu"]

# paired forms: the diagonal of the pairwise kernel, block by block (memory PAIR_BLOCK^2, not N^2)
PAIR_BLOCK = 256


def _pair(boxes_a, boxes_b) -> None:
    check_boxes(boxes_a, "boxes_a")
    check_boxes(boxes_b, "boxes_b")
    check_same_device([("boxes_a", boxes_a), ("boxes_b", boxes_b)])
    check_box_values(("boxes_a", boxes_a), ("boxes_b", boxes_b))


def _common_dtype(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor]:
    dt = torch.promote_types(a.dtype, b.dtype)
    if dt not in (torch.float32, torch.float64):
        dt = torch.float32
    return a.to(dt), b.to(dt)


def boxes_bev_iou_cpu(boxes_a, boxes_b):
    """Rotated BEV IoU, (N, M); numpy arrays in give a numpy array out.

    Args:
        boxes_a: (N, 7) [x, y, z, dx, dy, dz, heading], tensor or numpy array.
        boxes_b: (M, 7), same kind.
    """
    a, numpy_a = to_torch(boxes_a, "boxes_a")
    b, numpy_b = to_torch(boxes_b, "boxes_b")
    _pair(a, b)
    with validation(False):
        iou = _boxes.box_iou_bev(*_common_dtype(a, b))
    return iou.numpy() if numpy_a and numpy_b else iou


def boxes_iou_bev(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """Rotated BEV IoU, (N, M) (OpenPCDet: CUDA only; here any device)."""
    _pair(boxes_a, boxes_b)
    with validation(False):
        return _boxes.box_iou_bev(*_common_dtype(boxes_a, boxes_b))


def _iou3d_from_overlap(a: Tensor, b: Tensor, overlap_bev: Tensor, paired: bool) -> Tensor:
    # OpenPCDet's formula: height overlap x BEV overlap, over the union clamped at 1e-6
    shape_b = (-1, 1) if paired else (1, -1)
    a_max, a_min = (a[:, 2] + a[:, 5] / 2).view(-1, 1), (a[:, 2] - a[:, 5] / 2).view(-1, 1)
    b_max, b_min = (b[:, 2] + b[:, 5] / 2).view(shape_b), (b[:, 2] - b[:, 5] / 2).view(shape_b)
    overlap_h = torch.clamp(torch.min(a_max, b_max) - torch.max(a_min, b_min), min=0)
    overlap_3d = overlap_bev * overlap_h
    vol_a = (a[:, 3] * a[:, 4] * a[:, 5]).view(-1, 1)
    vol_b = (b[:, 3] * b[:, 4] * b[:, 5]).view(shape_b)
    return overlap_3d / torch.clamp(vol_a + vol_b - overlap_3d, min=1e-6)


def boxes_iou3d_gpu(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """3D IoU of upright rotated boxes, (N, M) (OpenPCDet: CUDA only; here any device)."""
    _pair(boxes_a, boxes_b)
    a, b = _common_dtype(boxes_a, boxes_b)
    with validation(False):
        return _iou3d_from_overlap(a, b, _boxes.box_overlap_bev(a, b), paired=False)


def _paired_overlap_bev(a: Tensor, b: Tensor) -> Tensor:
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"boxes_a and boxes_b must have the same number of boxes, got {a.shape[0]} and {b.shape[0]}")
    out = a.new_zeros((a.shape[0], 1))
    for s in range(0, a.shape[0], PAIR_BLOCK):
        out[s:s + PAIR_BLOCK, 0] = _boxes.box_overlap_bev(a[s:s + PAIR_BLOCK], b[s:s + PAIR_BLOCK]).diagonal()
    return out


def boxes_aligned_iou3d_gpu(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """3D IoU of ``boxes_a[i]`` with ``boxes_b[i]``, shape (N, 1)."""
    _pair(boxes_a, boxes_b)
    a, b = _common_dtype(boxes_a, boxes_b)
    with validation(False):
        return _iou3d_from_overlap(a, b, _paired_overlap_bev(a, b), paired=True)


def paired_boxes_iou3d_gpu(boxes_a: Tensor, boxes_b: Tensor) -> Tensor:
    """3D IoU of ``boxes_a[i]`` with ``boxes_b[i]``, shape (N,)."""
    return boxes_aligned_iou3d_gpu(boxes_a, boxes_b).view(-1)


def _nms_inputs(boxes, scores, thresh) -> None:
    if isinstance(thresh, bool) or not isinstance(thresh, numbers.Real) or not (math.isfinite(thresh) and thresh >= 0):
        raise ValueError(f"thresh must be a finite number >= 0 (the IoU above which a box is suppressed), got {thresh!r}")
    check_boxes(boxes, "boxes")
    if not isinstance(scores, Tensor) or scores.dim() != 1 or scores.shape[0] != boxes.shape[0]:
        raise ValueError(f"scores must be a (N,) tensor with N = {boxes.shape[0]} (one per box), got {describe(scores)}")


def nms_gpu(boxes: Tensor, scores: Tensor, thresh: float, pre_maxsize: int | None = None, **kwargs):
    """Rotated BEV NMS: ``(keep, None)``, ``keep`` int64 indices into ``boxes`` in descending score order.

    A box is suppressed when its BEV IoU with a kept box is greater than ``thresh``; only the
    ``pre_maxsize`` highest scores take part. Extra keyword arguments are ignored, as OpenPCDet's.
    """
    _nms_inputs(boxes, scores, thresh)
    return _boxes.nms_bev(boxes, scores, thresh, pre_max=pre_maxsize), None


def nms_normal_gpu(boxes: Tensor, scores: Tensor, thresh: float, **kwargs):
    """Axis-aligned BEV NMS (headings ignored): ``(keep, None)``, as ``nms_gpu``."""
    _nms_inputs(boxes, scores, thresh)
    upright = boxes.clone()
    upright[:, 6] = 0
    return _boxes.nms_bev(upright, scores, thresh), None
