"""Fuzz: the OpenPCDet faces (lidarops.compat.pcdet) against float64 references of OpenPCDet's kernels.

Same rule as the rest of tests/fuzz: a clear ValueError naming the argument, or the reference's answer.
Decisions within rounding of a threshold (an IoU at the NMS threshold, a point on a widened box face)
are left out of the exact comparisons.
"""
from __future__ import annotations

import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.compat.pcdet import iou3d_nms_utils, pointnet2_stack, roiaware_pool3d_utils
from lidarops.ops.boxes import _box_iou_bev_reference, _box_overlap_bev_reference, _nms_bev_reference
from .fuzzing import assert_clear_error, assert_close, assert_no_error, assert_same, box_sets, fuzz, outcome
from .test_fuzz_boxes import _bad_names, _tolerance


def _iou3d_reference(a, b):
    a, b = a.double(), b.double()
    if not a.shape[0] or not b.shape[0]:
        return torch.zeros(a.shape[0], b.shape[0], dtype=torch.float64)
    h = (torch.minimum(a[:, None, 2] + a[:, None, 5] / 2, b[None, :, 2] + b[None, :, 5] / 2)
         - torch.maximum(a[:, None, 2] - a[:, None, 5] / 2, b[None, :, 2] - b[None, :, 5] / 2)).clamp_min(0)
    inter = _box_overlap_bev_reference(a, b) * h
    return inter / (a[:, 3:6].prod(1)[:, None] + b[:, 3:6].prod(1)[None] - inter).clamp_min(1e-6)


@fuzz
@given(data=st.data())
def test_iou_faces(device, data):
    op = data.draw(st.sampled_from(["boxes_iou_bev", "boxes_bev_iou_cpu", "boxes_iou3d_gpu"]), "op")
    a = data.draw(box_sets(), "a")
    b = data.draw(box_sets(dtype=a.boxes.dtype), "b")
    what = f"{op}(a {a.regime} {tuple(a.boxes.shape)}, b {b.regime} {tuple(b.boxes.shape)}, {a.boxes.dtype})"
    res, err = outcome(getattr(iou3d_nms_utils, op), a.boxes.to(device), b.boxes.to(device))
    bad = _bad_names(("boxes_a", a), ("boxes_b", b))
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    if op == "boxes_iou3d_gpu":
        expected = _iou3d_reference(a.boxes, b.boxes)
        # OpenPCDet's formula divides by max(union, 1e-6): tiny boxes amplify rounding
        assume(bool((a.boxes[:, 3:6].prod(1) > 1e-3).all()) and bool((b.boxes[:, 3:6].prod(1) > 1e-3).all()))
    else:
        expected = _box_iou_bev_reference(a.boxes, b.boxes)
    f32 = a.boxes.dtype != torch.float64
    assert_close(res, expected, rtol=2e-6 if f32 else 1e-9, atol=_tolerance(a, b) + (2e-6 if f32 else 0), what=what)


@fuzz
@given(data=st.data())
def test_nms_face(device, data):
    b = data.draw(box_sets(max_boxes=7), "boxes")
    n = b.boxes.shape[0]
    scores = torch.tensor(data.draw(st.lists(st.floats(0, 1, width=32) | st.sampled_from([float("nan")]),
                                             min_size=n, max_size=n)), dtype=torch.float32).reshape(n)
    thr = data.draw(st.sampled_from([0.0, 0.01, 0.1, 0.7]) | st.floats(-0.5, 1.5), "thresh")
    pre = data.draw(st.none() | st.integers(0, 5), "pre_maxsize")
    what = f"nms_gpu({b.regime} {tuple(b.boxes.shape)}, thresh={thr}, pre_maxsize={pre})"
    res, err = outcome(iou3d_nms_utils.nms_gpu, b.boxes.to(device), scores.to(device), thr, pre_maxsize=pre)
    bad = _bad_names(("boxes", b)) + ([] if bool(torch.isfinite(scores).all()) else ["scores"]) \
        + (["thresh"] if thr < 0 else [])
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    keep, second = res
    assert second is None, what
    if n:
        iou = _box_iou_bev_reference(b.boxes, b.boxes)
        assume(bool(((iou - thr).abs() > _tolerance(b) + 1e-6).all()))
    assert_same(keep, _nms_bev_reference(b.boxes, scores, thr, pre_max=pre), what)


@fuzz
@given(data=st.data())
def test_points_in_boxes_gpu_face(device, data):
    b = data.draw(box_sets(dtype=torch.float32), "boxes")
    n = data.draw(st.integers(0, 12), "M")
    pts = torch.tensor(data.draw(st.lists(st.floats(-5, 5, width=32), min_size=3 * n, max_size=3 * n)),
                       dtype=torch.float32).reshape(1, n, 3)
    what = f"points_in_boxes_gpu(points {tuple(pts.shape)}, boxes {b.regime} {tuple(b.boxes.shape)})"
    res, err = outcome(roiaware_pool3d_utils.points_in_boxes_gpu, pts.to(device), b.boxes[None].to(device))
    bad = _bad_names(("boxes", b))
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    p, bx = pts[0].double(), b.boxes.double()
    d = p[:, None, :2] - bx[None, :, :2]
    c, s = torch.cos(bx[:, 6]), torch.sin(bx[:, 6])
    lx, ly = (c * d[..., 0] + s * d[..., 1]).abs(), (-s * d[..., 0] + c * d[..., 1]).abs()
    lz = (p[:, None, 2] - bx[:, 2]).abs()
    m = roiaware_pool3d_utils.GPU_MARGIN
    ex, ey, ez = lx - bx[:, 3] / 2 - m, ly - bx[:, 4] / 2 - m, lz - bx[:, 5] / 2
    inside = (ex < 0) & (ey < 0) & (ez <= 0)
    eps = _tolerance(b) * 10 + 1e-5
    clear = ~((ex.abs() < eps) | (ey.abs() < eps) | (ez.abs() < eps)).any(1)
    first = torch.where(inside.any(1), inside.int().argmax(1), torch.full((n,), -1)) if inside.shape[1] \
        else torch.full((n,), -1)
    assert_same(res[0].cpu()[clear].long(), first[clear], what)


@fuzz
@given(data=st.data())
def test_stacked_counts_checked(device, data):
    """Counts that do not add up to the rows are named; counts that do give per-example answers."""
    counts = data.draw(st.lists(st.integers(0, 5), min_size=1, max_size=3), "xyz_batch_cnt")
    rows = data.draw(st.sampled_from([sum(counts), sum(counts) + 1]), "rows")
    xyz = torch.tensor(data.draw(st.lists(st.floats(-3, 3, width=32), min_size=3 * rows, max_size=3 * rows)),
                       dtype=torch.float32).reshape(rows, 3).to(device)
    cnt = torch.tensor(counts, dtype=torch.int32, device=device)
    npoint = data.draw(st.integers(0, 4), "npoint")
    what = f"stack_farthest_point_sample(xyz {tuple(xyz.shape)}, counts {counts}, npoint {npoint})"
    res, err = outcome(pointnet2_stack.stack_farthest_point_sample, xyz, cnt, npoint)
    if rows != sum(counts):
        return assert_clear_error(err, ValueError, ["xyz_batch_cnt"], what)
    assert_no_error(err, what)
    assert res.shape == (npoint * len(counts),), what
    start = 0
    for i, c in enumerate(counts):  # each example's picks lie in its own rows (or its start, when empty)
        picks = res[i * npoint:(i + 1) * npoint].cpu()
        assert bool(((picks >= start) & (picks < start + max(c, 1))).all()), what
        start += c
    res, err = outcome(pointnet2_stack.three_nn, xyz, cnt, xyz, cnt)
    assert_no_error(err, what)
    dist = res[0]
    assert bool((dist[:, 0] == 0).all()) if rows else True, f"{what}: a point is its own nearest neighbour"


_NOT_TENSORS = st.sampled_from([None, [[0.0] * 7], 3.0, "boxes", (1, 2, 3)])


@fuzz
@given(data=st.data())
def test_non_tensor_arguments_named(device, data):
    """A list, None or a string where a tensor goes: a ValueError naming the argument, never an
    AttributeError from inside the face."""
    good_boxes = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]], device=device)
    good_points = torch.zeros(1, 4, 3, device=device)
    bad = data.draw(_NOT_TENSORS, "bad")
    calls = [
        ("boxes_a", lambda: iou3d_nms_utils.boxes_iou_bev(bad, good_boxes)),
        ("boxes_b", lambda: iou3d_nms_utils.boxes_iou3d_gpu(good_boxes, bad)),
        ("boxes", lambda: iou3d_nms_utils.nms_gpu(bad, torch.ones(1, device=device), 0.1)),
        ("points", lambda: roiaware_pool3d_utils.points_in_boxes_gpu(bad, good_boxes[None])),
        ("boxes", lambda: roiaware_pool3d_utils.points_in_boxes_gpu(good_points, bad)),
    ]
    if device == "cpu":
        calls.append(("points", lambda: roiaware_pool3d_utils.points_in_boxes_cpu(bad, good_boxes)))
    name, call = data.draw(st.sampled_from(calls), "call")
    res, err = outcome(call)
    assert_clear_error(err, ValueError, [name], f"{name}={bad!r}")
