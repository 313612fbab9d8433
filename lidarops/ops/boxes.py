"""Rotated 3D boxes: pairwise overlap and IoU, rotated non-maximum suppression, points in boxes.

Box convention (OpenPCDet's and :mod:`lidarops.data`'s): ``boxes (Tensor[N, 7])`` holds
``x, y, z, dx, dy, dz, heading`` in the LiDAR frame: ``(x, y, z)`` the box centre, ``dx`` the length
along the heading, ``dy`` the width, ``dz`` the height, ``heading`` in radians counter-clockwise from +x.
float32 and float64 are accepted (float16/bfloat16 are computed like float32); every op computes in
float64 and returns float64 for float64 boxes, float32 otherwise.

The CPU and CUDA kernels share their geometry bit for bit (the same float64 operations, no fused
multiply-adds, the same sine/cosine polynomial), so IoUs agree exactly and NMS keeps the same boxes on
every device. Two identical boxes have IoU exactly 1 at any heading; boxes with a zero size overlap
nothing (0, never NaN).
"""
from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from lidarops import extension
from lidarops.ops.validation import (DeferredChecks, check_output_size, check_tensor, check_values, describe,
                                      value_checks_enabled)

extension.load()

__all__ = ["box_overlap_bev", "box_iou_bev", "box_iou_3d", "nms_bev", "nms_bev_frames", "batched_nms_bev",
           "points_in_boxes", "unsupported_boxes"]


def _check_boxes(boxes, name: str) -> None:
    check_tensor(boxes, name)
    if boxes.dim() != 2 or boxes.shape[1] != 7:
        raise ValueError(f"{name} must be (N, 7) boxes (x, y, z, dx, dy, dz, heading), got {describe(boxes)}")
    if not boxes.is_floating_point():
        raise ValueError(f"{name} must be floating point (float32, float64, float16, bfloat16), got {describe(boxes)}")
    extension.check_device(boxes, name)


#: The values a box may hold (rows of ``(x, y, z, dx, dy, dz, heading)``): centres within this many metres of
#: the origin, sizes 0 or in [MIN_BOX_SIZE, MAX_BOX_SIZE] metres, headings within this many radians.
#: Inside them every box op is exact to its documented rounding (the kernels reduce headings exactly up to
#: 2^20 * pi / 2 and keep every area and coordinate a normal double); beyond them it is refused by name.
MAX_ABS_BOX_CENTRE = 1e6
MIN_BOX_SIZE, MAX_BOX_SIZE = 1e-6, 1e6
MAX_ABS_HEADING = 1e6


def _box_out_of_range(boxes: Tensor) -> Tensor:
    """(N,) True where a box is finite but outside the supported values (see :data:`MAX_ABS_HEADING`)."""
    size = boxes[:, 3:6]
    return ((boxes[:, :3].abs() > MAX_ABS_BOX_CENTRE).any(1) | (boxes[:, 6].abs() > MAX_ABS_HEADING)
            | ((size != 0) & ((size < MIN_BOX_SIZE) | (size > MAX_BOX_SIZE))).any(1))


def unsupported_boxes(boxes: Tensor) -> Tensor:
    """Which boxes the box ops refuse (with their value checks on): a NaN or infinite value, or a value outside
    the supported range (a centre beyond :data:`MAX_ABS_BOX_CENTRE`, a size neither 0 nor in [:data:`MIN_BOX_SIZE`,
    :data:`MAX_BOX_SIZE`], a heading beyond :data:`MAX_ABS_HEADING`). On the boxes' device, with no host read, so
    it can run inside a CUDA graph where the ops' own checks cannot.

    Args:
        boxes (Tensor[N, 7]): ``(x, y, z, dx, dy, dz, heading)``, floating point.

    Returns:
        Tensor[N] bool.
    """
    _check_boxes(boxes, "boxes")
    return ~torch.isfinite(boxes).all(1) | _box_out_of_range(boxes)


def _value_out_of_range(v: float, column: int) -> bool:
    """The rule of :func:`_box_out_of_range` for one value of a column (0-6)."""
    if column < 3:
        return abs(v) > MAX_ABS_BOX_CENTRE
    if column < 6:
        return v != 0 and not MIN_BOX_SIZE <= v <= MAX_BOX_SIZE
    return abs(v) > MAX_ABS_HEADING


def _box_messages(boxes: Tensor, name: str) -> tuple:
    """The messages of the box value checks (non-finite values, values out of range), built when raised."""
    def out_of_range() -> str:
        rows = torch.nonzero(_box_out_of_range(boxes)).flatten()[:3].tolist()
        first = boxes[rows[0]].tolist() if rows else []
        column = next((c for c in range(7) if _value_out_of_range(first[c], c)), None) if first else None
        what = ""
        if column is not None:
            field, v = ("x", "y", "z", "dx", "dy", "dz", "heading")[column], first[column]
            what = f"; row {rows[0]} has {field} = {v!r}" + (" (a negative size)" if 3 <= column < 6 and v < 0 else "")
        return (f"{name} must hold centres within {MAX_ABS_BOX_CENTRE:g} m, sizes dx, dy, dz of 0 or in "
                f"[{MIN_BOX_SIZE:g}, {MAX_BOX_SIZE:g}] m and headings within {MAX_ABS_HEADING:g} rad; rows "
                f"{rows} are not{what} ({describe(boxes)})")

    return lambda: f"{name} contains NaN or infinite values ({describe(boxes)})", out_of_range


def _box_value_checks(boxes: Tensor, name: str) -> tuple[list, list]:
    """NaN/inf anywhere and values out of the supported range: (finite checks, extra checks) for check_values."""
    nonfinite, out_of_range = _box_messages(boxes, name)
    return [(boxes, nonfinite)], [(_box_out_of_range(boxes).any(), out_of_range)]


def check_box_values(*named: tuple[str, Tensor]) -> None:
    """ValueError naming the first of ``(name, boxes)`` that holds NaN, infinite or out-of-range values
    (see :data:`MAX_ABS_HEADING`), with one host read for all; nothing with the value checks off. For code
    wrapping the box ops under other argument names (the OpenPCDet faces)."""
    if not value_checks_enabled():
        return
    finite, extra = [], []
    for name, boxes in named:
        f, e = _box_value_checks(boxes, name)
        finite += f
        extra += e
    check_values(finite=finite, extra=extra)


def _pair_args(a, b) -> None:
    _check_boxes(a, "a")
    _check_boxes(b, "b")
    if a.device != b.device:
        raise ValueError(f"b is on {b.device} but a is on {a.device}; move them to one device")
    if a.dtype != b.dtype:
        raise ValueError(f"a and b must have the same dtype, got {a.dtype} and {b.dtype}")
    check_output_size([a.shape[0], b.shape[0]], f"a ({a.shape[0]} boxes) and b ({b.shape[0]} boxes)",
                      "the pairwise matrix", "compare in chunks of a")
    if value_checks_enabled():
        fa, ea = _box_value_checks(a, "a")
        fb, eb = _box_value_checks(b, "b")
        check_values(finite=fa + fb, extra=ea + eb)


def box_overlap_bev(a: Tensor, b: Tensor) -> Tensor:
    """Intersection area of the bird's-eye-view rectangles of two sets of rotated boxes.

    Args:
        a (Tensor[N, 7]), b (Tensor[M, 7]): boxes, same dtype and device.

    Returns:
        Tensor[N, M]: areas in m^2 (float64 for float64 boxes, else float32).
    """
    _pair_args(a, b)
    return torch.ops.lidarops.box_overlap_bev(a, b)


def box_iou_bev(a: Tensor, b: Tensor) -> Tensor:
    """Rotated bird's-eye-view IoU of two sets of boxes (OpenPCDet's ``boxes_iou_bev``).

    Args:
        a (Tensor[N, 7]), b (Tensor[M, 7]): boxes, same dtype and device.

    Returns:
        Tensor[N, M]: intersection / union of the BEV rectangles, in [0, 1]; 0 where the union is empty.
        ``box_iou_bev(a, b)[i, j]`` equals ``box_iou_bev(b, a)[j, i]`` up to rounding (the overlap is
        computed in the frame of the box from ``a``).
    """
    _pair_args(a, b)
    return torch.ops.lidarops.box_iou_bev(a, b)


def box_iou_3d(a: Tensor, b: Tensor) -> Tensor:
    """Rotated 3D IoU (upright boxes): BEV intersection x overlap in z / union of the volumes
    (OpenPCDet's ``boxes_iou3d_gpu``, KITTI's 3D overlap).

    Args:
        a (Tensor[N, 7]), b (Tensor[M, 7]): boxes, same dtype and device.

    Returns:
        Tensor[N, M] in [0, 1]; 0 where the union is empty.
    """
    _pair_args(a, b)
    return torch.ops.lidarops.box_iou_3d(a, b)


def _optional_count(v, name: str) -> int:
    if v is None:
        return -1
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < 0:
        raise ValueError(f"{name} must be None or an int >= 0, got {v!r}")
    return int(v)


def _nms_args(boxes, scores, iou_threshold, idxs=None) -> float:
    """Checks of shapes, dtypes, devices and the threshold (no values read); the threshold as a float."""
    _check_boxes(boxes, "boxes")
    check_tensor(scores, "scores")
    n = boxes.shape[0]
    if scores.dim() != 1 or scores.shape[0] != n or not scores.is_floating_point():
        raise ValueError(f"scores must be a floating (N,) tensor with N = {n}, got {describe(scores)}")
    if scores.device != boxes.device:
        raise ValueError(f"scores is on {scores.device} but boxes is on {boxes.device}")
    if idxs is not None:
        check_tensor(idxs, "idxs")
        if idxs.shape != (n,) or idxs.is_floating_point() or idxs.is_complex() or idxs.dtype == torch.bool:
            raise ValueError(f"idxs must be an integer (N,) tensor with N = {n}, got {describe(idxs)}")
        if idxs.device != boxes.device:
            raise ValueError(f"idxs is on {idxs.device} but boxes is on {boxes.device}")
    if isinstance(iou_threshold, bool) or not isinstance(iou_threshold, numbers.Real) \
            or not (math.isfinite(iou_threshold) and iou_threshold >= 0):
        # an IoU lies in [0, 1]: below 0 even boxes that do not touch would suppress each other
        raise ValueError(f"iou_threshold must be a finite number >= 0, got {iou_threshold!r}")
    return float(iou_threshold)


def _nms_value_messages(boxes, scores, name: str = "boxes") -> list:
    """The messages of NMS' value checks, in the order of nms_bev_checked's status[1:] and check_values'."""
    nonfinite, out_of_range = _box_messages(boxes, name)
    return [nonfinite, lambda: f"scores contains NaN or infinite values ({describe(scores)})", out_of_range]


def _check_nms_values(boxes, scores, name: str = "boxes") -> None:
    """``boxes (N, 7)`` finite and in the supported range, ``scores`` finite (one host read); ``name`` is what
    the messages call the boxes."""
    if value_checks_enabled():
        messages = _nms_value_messages(boxes, scores, name)
        check_values(finite=[(boxes, messages[0]), (scores, messages[1])],
                     extra=[(_box_out_of_range(boxes).any(), messages[2])])


def _score_threshold(v) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isnan(v):
        raise ValueError(f"score_threshold must be None or a number (not NaN), got {v!r}")
    return float(v)


def nms_bev(boxes: Tensor, scores: Tensor, iou_threshold: float, pre_max: int | None = None,
            post_max: int | None = None, *, score_threshold: float | None = None, padded: bool = False):
    """Rotated non-maximum suppression on the bird's-eye-view IoU (OpenPCDet's ``nms_gpu``).

    Boxes are visited in descending score order (equal scores: lower index first); the first
    ``pre_max`` of that order whose score is at least ``score_threshold`` take part; a box is suppressed
    when its BEV IoU with an already kept box is **strictly greater** than ``iou_threshold``
    (PointPillars runs 0.01); at most ``post_max`` boxes are kept. On CUDA: a bitmask kernel and one
    warp-level reduction, no per-box host loop; one read back to the host (the number kept, with the
    value checks' flags), none with ``padded=True``. With the value checks off, NaN scores are visited
    last and never pass a ``score_threshold``.

    Args:
        boxes (Tensor[N, 7]): boxes.
        scores (Tensor[N]): scores, same device (any floating dtype).
        iou_threshold (float): suppression threshold.
        pre_max (int, optional): boxes taking part, highest scores first (OpenPCDet's ``NMS_PRE_MAXSIZE``).
        post_max (int, optional): boxes kept at most (``NMS_POST_MAXSIZE``).
        score_threshold (float, optional): only boxes scoring at least this take part (OpenPCDet's
            ``SCORE_THRESH``). The same as thresholding first: boxes below it would come after every box
            above it in the visiting order, where they cannot suppress anything.
        padded (bool): return ``(keep, count)`` of sizes fixed by the shapes instead, with nothing read
            back to the host (the call can be captured in a CUDA graph, and ``torch.compile`` needs no
            dynamic size; the value checks, when on, read back once before the op: turn them off with
            ``lidarops.validation(False)`` inside a capture): ``keep (Tensor[K])`` with
            ``K = min(N, pre_max, post_max)``, its first ``count`` entries the kept indices and the rest
            -1; ``count (Tensor[])`` int64.

    Returns:
        Tensor[K] int64: indices of the kept boxes, in descending score order (``padded=False``).
    """
    threshold = _nms_args(boxes, scores, iou_threshold)
    pre, post = _optional_count(pre_max, "pre_max"), _optional_count(post_max, "post_max")
    score_threshold = _score_threshold(score_threshold)
    if not isinstance(padded, bool):  # padded="no" is truthy: it would silently return (keep, count)
        raise ValueError(f"padded must be True or False, got {padded!r}")
    if boxes.device.type == "meta" and not padded:
        raise ValueError("boxes on the meta device: the number of boxes kept is data, so meta tensors need padded=True")
    if padded:
        _check_nms_values(boxes, scores)
        return torch.ops.lidarops.nms_bev_padded(boxes, scores, None, threshold, score_threshold, pre, post)
    if not value_checks_enabled():
        keep, count = torch.ops.lidarops.nms_bev_padded(boxes, scores, None, threshold, score_threshold, pre, post)
        return keep[:int(count)]
    # the op computes the value flags beside the number kept: one launch for the checks, one read back
    # for both (the kernels are safe on any values)
    keep, status = torch.ops.lidarops.nms_bev_checked(boxes, scores, None, threshold, score_threshold, pre, post)
    host = status.tolist()
    if any(host[1:]):
        DeferredChecks(None, _nms_value_messages(boxes, scores)).raise_first(host[1:])
    return keep[:host[0]]


def nms_bev_frames(boxes: Tensor, scores: Tensor, iou_threshold: float, pre_max: int | None = None,
                   post_max: int | None = None, *, score_threshold: float | None = None) -> tuple[Tensor, Tensor]:
    """:func:`nms_bev` with ``padded=True`` on each of B frames of N boxes, in one call: a detector's
    post-processing of a batch. On CUDA the frames share every launch (one sort of all their scores, one
    bitmask kernel, one reduction block per frame), where a loop over the frames makes a set of launches per
    frame, run one after the other. Nothing is read back to the host (the call can be captured in a CUDA
    graph) except the value checks' one read, when on.

    Args:
        boxes (Tensor[B, N, 7]): each frame's boxes.
        scores (Tensor[B, N]): their scores, same device (any floating dtype).
        iou_threshold, pre_max, post_max, score_threshold: as :func:`nms_bev`, per frame.

    Returns:
        tuple: ``keep (Tensor[B, K])`` int64 and ``count (Tensor[B])`` int64, ``K = min(N, pre_max,
        post_max)``: row b's first ``count[b]`` entries are the indices (into frame b's N boxes) that
        ``nms_bev(boxes[b], scores[b], ..., padded=True)`` keeps, in descending score order, the rest -1.
    """
    check_tensor(boxes, "boxes")
    check_tensor(scores, "scores")
    if boxes.dim() != 3 or boxes.shape[2] != 7 or not boxes.is_floating_point():
        raise ValueError(f"boxes must be a floating (B, N, 7) tensor (x, y, z, dx, dy, dz, heading per frame), "
                         f"got {describe(boxes)}")
    if scores.shape != boxes.shape[:2] or not scores.is_floating_point():
        raise ValueError(f"scores must be a floating (B, N) tensor with (B, N) = {tuple(boxes.shape[:2])}, "
                         f"got {describe(scores)}")
    if scores.device != boxes.device:
        raise ValueError(f"scores is on {scores.device} but boxes is on {boxes.device}")
    extension.check_device(boxes, "boxes")
    flat = boxes.reshape(-1, 7)
    threshold = _nms_args(flat, scores.reshape(-1), iou_threshold)
    pre, post = _optional_count(pre_max, "pre_max"), _optional_count(post_max, "post_max")
    if boxes.numel():
        _check_nms_values(flat, scores, "boxes (as (B * N, 7))")
    return torch.ops.lidarops.nms_bev_padded_batched(boxes, scores, threshold, _score_threshold(score_threshold),
                                                     pre, post)


def _rank_in_group(groups: Tensor) -> Tensor:
    """Position of each entry among the entries of its group, in the given order."""
    perm = torch.sort(groups, stable=True).indices
    g = groups[perm]
    pos = torch.arange(g.numel(), device=g.device)
    new_run = torch.ones_like(g, dtype=torch.bool)
    new_run[1:] = g[1:] != g[:-1]
    run_start = torch.cummax(torch.where(new_run, pos, torch.zeros_like(pos)), 0).values
    rank = torch.empty_like(pos)
    rank[perm] = pos - run_start
    return rank


def batched_nms_bev(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float, pre_max: int | None = None,
                    post_max: int | None = None) -> Tensor:
    """Rotated NMS within groups (per class or per frame), like ``torchvision.ops.batched_nms``: boxes
    of different ``idxs`` never suppress each other. The groups are handled in one kernel launch (no
    coordinate offsets).

    Args:
        boxes (Tensor[N, 7]), scores (Tensor[N]): as :func:`nms_bev`.
        idxs (Tensor[N]): integer group of each box.
        iou_threshold (float): suppression threshold (strictly greater suppresses).
        pre_max, post_max (int, optional): per group, as OpenPCDet's multi-class NMS applies them.

    Returns:
        Tensor[K] int64: kept indices in descending score order (equal scores: lower index first).
    """
    threshold = _nms_args(boxes, scores, iou_threshold, idxs)
    if boxes.device.type == "meta":
        raise ValueError("boxes on the meta device: the number of boxes batched_nms_bev keeps is data (use "
                         "nms_bev(..., padded=True) per group)")
    _check_nms_values(boxes, scores)
    pre, post = _optional_count(pre_max, "pre_max"), _optional_count(post_max, "post_max")
    idxs = idxs.to(torch.int64)
    if pre < 0:
        keep = torch.ops.lidarops.nms_bev(boxes, scores, idxs, threshold, -1, -1)
    else:
        order = torch.sort(scores.float() + 0.0 if scores.dtype != torch.float64 else scores + 0.0,
                           stable=True, descending=True).indices
        sel = order[_rank_in_group(idxs[order]) < pre]
        keep = sel[torch.ops.lidarops.nms_bev(boxes[sel], scores[sel], idxs[sel], threshold, -1, -1)]
    if post >= 0:
        keep = keep[_rank_in_group(idxs[keep]) < post]
    return keep


def points_in_boxes(points: Tensor, boxes: Tensor) -> Tensor:
    """Which box holds each point (OpenPCDet's ``points_in_boxes_cpu/gpu``, closed boxes).

    Args:
        points (Tensor[P, C >= 3]): x, y, z in the first three columns (other columns are ignored).
        boxes (Tensor[M, 7]): boxes, same device.

    Returns:
        Tensor[P] int64: the lowest index of the boxes containing each point (boundaries included),
        -1 for points in no box. NaN points are in no box.
    """
    check_tensor(points, "points")
    if points.dim() != 2 or points.shape[1] < 3 or not points.is_floating_point():
        raise ValueError(f"points must be a floating (P, C >= 3) tensor, got {describe(points)}")
    extension.check_device(points, "points")
    _check_boxes(boxes, "boxes")
    if boxes.device != points.device:
        raise ValueError(f"boxes is on {boxes.device} but points is on {points.device}")
    if value_checks_enabled():
        finite, extra = _box_value_checks(boxes, "boxes")
        check_values(finite=finite, extra=extra)
    return torch.ops.lidarops.points_in_boxes(points, boxes)


# ---------------------------------------------------------------------------------------------
# float64 references (tests): world-frame polygon clipping, a different route from the kernels'
# ---------------------------------------------------------------------------------------------
def _corners_bev_reference(box) -> list[tuple[float, float]]:
    x, y, _, dx, dy, _, h = (float(v) for v in box)
    c, s = math.cos(h), math.sin(h)
    out = []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):  # counter-clockwise
        lx, ly = sx * dx / 2, sy * dy / 2
        out.append((x + c * lx - s * ly, y + s * lx + c * ly))
    return out


def _clip_reference(poly: list, a: tuple, b: tuple) -> list:
    """Keeps the part of ``poly`` left of the directed line a -> b (Sutherland-Hodgman)."""
    def side(p):
        return (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])

    out = []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        sp, sq = side(p), side(q)
        if sp >= 0:
            out.append(p)
        if (sp < 0 < sq) or (sq < 0 < sp):
            t = sp / (sp - sq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _polygon_area_reference(poly: list) -> float:
    # shoelace about the first vertex: in world coordinates (|x| ~ 1e6) the cross products would be
    # ~1e12 and cancel to an error of ~1e-4 m^2
    x0, y0 = poly[0]
    rel = [(x - x0, y - y0) for x, y in poly]
    return 0.5 * sum(p[0] * q[1] - q[0] * p[1] for p, q in zip(rel, rel[1:] + rel[:1]))


def _box_overlap_bev_reference(a: Tensor, b: Tensor) -> Tensor:
    """float64 (N, M) BEV intersection areas, one pair at a time."""
    out = torch.zeros(a.shape[0], b.shape[0], dtype=torch.float64)
    for i, ba in enumerate(a.double().tolist()):
        ca = _corners_bev_reference(ba)
        for j, bb in enumerate(b.double().tolist()):
            if min(ba[3], ba[4], bb[3], bb[4]) <= 0:
                continue
            poly = _corners_bev_reference(bb)
            for k in range(4):
                if len(poly) < 3:
                    break
                poly = _clip_reference(poly, ca[k], ca[(k + 1) % 4])
            out[i, j] = max(_polygon_area_reference(poly), 0.0) if len(poly) >= 3 else 0.0
    return out


def _box_iou_bev_reference(a: Tensor, b: Tensor) -> Tensor:
    inter = _box_overlap_bev_reference(a, b)
    area_a = (a[:, 3] * a[:, 4]).double()[:, None]
    area_b = (b[:, 3] * b[:, 4]).double()[None, :]
    union = area_a + area_b - inter
    return torch.where(union > 0, inter / union.clamp_min(1e-300), torch.zeros_like(inter))


def _box_iou_3d_reference(a: Tensor, b: Tensor) -> Tensor:
    inter = _box_overlap_bev_reference(a, b)
    a, b = a.double(), b.double()
    top = torch.minimum(a[:, None, 2] + a[:, None, 5] / 2, b[None, :, 2] + b[None, :, 5] / 2)
    bottom = torch.maximum(a[:, None, 2] - a[:, None, 5] / 2, b[None, :, 2] - b[None, :, 5] / 2)
    inter3 = inter * (top - bottom).clamp_min(0)
    union = (a[:, 3] * a[:, 4] * a[:, 5])[:, None] + (b[:, 3] * b[:, 4] * b[:, 5])[None, :] - inter3
    return torch.where((union > 0) & (inter3 > 0), inter3 / union.clamp_min(1e-300), torch.zeros_like(inter3))


def _nms_bev_reference(boxes: Tensor, scores: Tensor, iou_threshold: float, idxs: Tensor | None = None,
                       pre_max: int | None = None, post_max: int | None = None) -> Tensor:
    """Greedy NMS over the float64 reference IoU, one box at a time (per-group pre/post max)."""
    n = boxes.shape[0]
    groups = [0] * n if idxs is None else [int(v) for v in idxs.tolist()]

    def first_per_group(indices: list, cap: int | None) -> list:
        if cap is None:
            return indices
        seen: dict = {}
        out = []
        for i in indices:
            seen[groups[i]] = seen.get(groups[i], 0) + 1
            if seen[groups[i]] <= cap:
                out.append(i)
        return out

    order = first_per_group(sorted(range(n), key=lambda i: (-float(scores[i]), i)), pre_max)
    iou = _box_iou_bev_reference(boxes, boxes) if n else torch.zeros(0, 0)
    keep: list[int] = []
    for i in order:
        if any(groups[k] == groups[i] and iou[k, i] > iou_threshold for k in keep):
            continue
        keep.append(i)
    keep = first_per_group(keep, post_max)
    return torch.tensor(keep, dtype=torch.int64)


def _points_in_boxes_reference(points: Tensor, boxes: Tensor) -> Tensor:
    """float64 (P,) lowest containing box, -1 for none."""
    p, b = points[:, :3].double(), boxes.double()
    d = p[:, None, :2] - b[None, :, :2]
    c, s = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    lx = c * d[..., 0] + s * d[..., 1]
    ly = -s * d[..., 0] + c * d[..., 1]
    inside = (lx.abs() <= b[:, 3] / 2) & (ly.abs() <= b[:, 4] / 2) & ((p[:, None, 2] - b[:, 2]).abs() <= b[:, 5] / 2)
    first = torch.where(inside, torch.arange(b.shape[0]).expand_as(inside), b.shape[0]).min(1).values if b.shape[0] \
        else torch.zeros(p.shape[0], dtype=torch.int64)
    return torch.where(first < b.shape[0], first, -1).to(torch.int64) if b.shape[0] else \
        torch.full((p.shape[0],), -1, dtype=torch.int64)
