"""Fuzz: rotated-box ops (lidarops.ops.boxes) against their float64 world-frame references.

The kernels compute in the frame of a box and the references clip polygons in the world frame, so
results agree to rounding, which grows with the coordinates' magnitude against the boxes' sizes.
Ambiguous decisions (an IoU within rounding of the NMS threshold, a point within rounding of a box
face) are left out of the exact comparisons.
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

import lidarops
from lidarops.ops.boxes import (_box_iou_3d_reference, _box_iou_bev_reference, _box_overlap_bev_reference,
                                _nms_bev_reference, _points_in_boxes_reference)
from .fuzzing import (Boxes, assert_clear_error, assert_close, assert_no_error, assert_same, box_sets, fuzz, outcome,
                     scalars)

_PAIR_OPS = {"box_overlap_bev": (lidarops.box_overlap_bev, _box_overlap_bev_reference),
             "box_iou_bev": (lidarops.box_iou_bev, _box_iou_bev_reference),
             "box_iou_3d": (lidarops.box_iou_3d, _box_iou_3d_reference)}


def _bad_names(*named: tuple) -> list:
    """Names of box sets that must be rejected: NaN / infinite values, negative sizes, or values beyond the
    supported range (docs/boxes.md)."""
    return [name for name, b in named if not (b.finite() and b.nonnegative() and b.in_range())]


def _tolerance(*sets: Boxes) -> float:
    """Absolute tolerance of areas / IoUs: rounding of the corner coordinates (|c| * 2^-52 each) over
    the smallest positive size, times a margin."""
    t = torch.cat([b.boxes.double() for b in sets]) if sets else torch.zeros(0, 7)
    if t.numel() == 0:
        return 1e-9
    scale = float(t[:, :3].abs().max()) + float(t[:, 3:6].abs().max()) + 1.0
    return 1e-9 + 64 * scale * 2.0**-52 * max(1.0, float(t[:, 3:5].abs().max()))


@fuzz
@given(data=st.data())
def test_pairwise_overlap_and_iou(device, data):
    op = data.draw(st.sampled_from(sorted(_PAIR_OPS)), "op")
    a = data.draw(box_sets(), "a")
    b = data.draw(box_sets(dtype=a.boxes.dtype), "b")
    fn, ref = _PAIR_OPS[op]
    what = f"{op}(a {a.regime} {tuple(a.boxes.shape)}, b {b.regime} {tuple(b.boxes.shape)}, {a.boxes.dtype})"
    res, err = outcome(fn, a.boxes.to(device), b.boxes.to(device))
    bad = _bad_names(("a", a), ("b", b))
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    assert res.dtype == (torch.float64 if a.boxes.dtype == torch.float64 else torch.float32), what
    expected = ref(a.boxes, b.boxes)
    f32 = a.boxes.dtype != torch.float64
    assert_close(res, expected, rtol=2e-6 if f32 else 1e-9, atol=_tolerance(a, b) + (1e-6 if f32 else 0), what=what)
    if op != "box_overlap_bev" and res.numel():
        assert bool(((res >= 0) & (res <= 1)).all()), f"{what}: IoU outside [0, 1]: {res}"


@fuzz
@given(data=st.data())
def test_identical_boxes_have_iou_one(device, data):
    """Documented: two identical boxes have IoU exactly 1 at any heading (zero-size boxes: 0)."""
    a = data.draw(box_sets(min_boxes=1, regime=data.draw(st.sampled_from(["normal", "zero", "huge"]))), "a")
    t = a.boxes.to(device)
    iou = lidarops.box_iou_bev(t, t).diagonal().cpu()
    positive = (a.boxes[:, 3] > 0) & (a.boxes[:, 4] > 0)
    assert_same(iou, positive.to(iou.dtype), "box_iou_bev(a, a) diagonal")


def _nms_args(data, grouped: bool):
    b = data.draw(box_sets(max_boxes=7), "boxes")
    n = b.boxes.shape[0]
    score = st.sampled_from([0.5, 0.9, 0.1]) | st.floats(0, 1, width=32) | st.sampled_from([math.nan, math.inf])
    scores = torch.tensor(data.draw(st.lists(score, min_size=n, max_size=n)), dtype=torch.float32).reshape(n)
    if data.draw(st.booleans()):
        scores = scores.to(b.boxes.dtype)
    thr = data.draw(st.sampled_from([0.0, 0.01, 0.1, 0.5, 0.7, 1.0]) | st.floats(-0.5, 1.5), "iou_threshold")
    idxs = torch.tensor(data.draw(st.lists(st.integers(0, 2), min_size=n, max_size=n)), dtype=torch.int64).reshape(n) \
        if grouped else None
    pre = data.draw(st.none() | st.integers(0, 5), "pre_max")
    post = data.draw(st.none() | st.integers(0, 5), "post_max")
    return b, scores, thr, idxs, pre, post


@fuzz
@given(data=st.data(), grouped=st.booleans())
def test_nms(device, data, grouped):
    b, scores, thr, idxs, pre, post = _nms_args(data, grouped)
    what = f"{'batched_' if grouped else ''}nms_bev({b.regime} {tuple(b.boxes.shape)}, thr={thr}, pre={pre}, post={post})"
    t, s = b.boxes.to(device), scores.to(device)
    if grouped:
        res, err = outcome(lidarops.batched_nms_bev, t, s, idxs.to(device), thr, pre, post)
    else:
        res, err = outcome(lidarops.nms_bev, t, s, thr, pre, post)
    bad = _bad_names(("boxes", b)) + ([] if bool(torch.isfinite(scores).all()) else ["scores"]) \
        + (["iou_threshold"] if thr < 0 else [])
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    n = b.boxes.shape[0]
    if n:  # an IoU within rounding of the threshold may go either way: not compared
        iou = _box_iou_bev_reference(b.boxes, b.boxes)
        assume(bool(((iou - thr).abs() > _tolerance(b) + 1e-6).all()))
    expected = _nms_bev_reference(b.boxes, scores, thr, idxs, pre, post)
    assert_same(res, expected, what)


@fuzz
@given(data=st.data())
def test_nms_frames(device, data):
    """nms_bev_frames on 1-3 frames (the drawn boxes in a drawn order per frame, each frame its own scores and
    a common score threshold): bad values raise naming boxes / scores / iou_threshold; else row b is the
    float64 reference of frame b, thresholded first, with the pre / post caps, padded with -1."""
    b, scores, thr, _, pre, post = _nms_args(data, False)
    n = b.boxes.shape[0]
    frames = data.draw(st.integers(1, 3), "frames")
    perms = [torch.tensor(data.draw(st.permutations(list(range(n))), f"order {f}"), dtype=torch.int64).reshape(n)
             for f in range(1, frames)]
    boxes = torch.stack([b.boxes] + [b.boxes[p] for p in perms])
    allscores = torch.stack([scores] + [scores[p].flip(0) for p in perms])
    st_ = data.draw(st.none() | st.sampled_from([0.1, 0.5, 0.95]), "score_threshold")
    what = f"nms_bev_frames({b.regime} {tuple(boxes.shape)}, thr={thr}, pre={pre}, post={post}, score={st_})"
    res, err = outcome(lidarops.nms_bev_frames, boxes.to(device), allscores.to(device), thr, pre, post,
                       score_threshold=st_)
    bad = _bad_names(("boxes", b)) + ([] if bool(torch.isfinite(scores).all()) else ["scores"]) \
        + (["iou_threshold"] if thr < 0 else [])
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    keep, count = res
    if n:  # an IoU within rounding of the threshold may go either way: not compared
        iou = _box_iou_bev_reference(b.boxes, b.boxes)
        assume(bool(((iou - thr).abs() > _tolerance(b) + 1e-6).all()))
    size = min(n, n if pre is None else pre, n if post is None else post)
    assert keep.shape == (frames, size) and count.shape == (frames,), what
    for f in range(frames):
        s_f = allscores[f]
        order = sorted(range(n), key=lambda i: (-float(s_f[i]), i))[:n if pre is None else pre]
        cand = torch.tensor([i for i in order if st_ is None or float(s_f[i]) >= st_], dtype=torch.int64)
        want = cand[_nms_bev_reference(boxes[f, cand], s_f[cand], thr)] if cand.numel() else cand
        want = want if post is None else want[:post]
        assert_same(keep[f].cpu(), torch.cat([want, torch.full((size - want.numel(),), -1)]), f"{what} frame {f}")
        assert int(count[f]) == want.numel(), f"{what} frame {f}"


@fuzz
@given(data=st.data())
def test_unsupported_boxes_flags_what_the_ops_refuse(device, data):
    """unsupported_boxes(b) flags a row exactly when the box ops refuse the set for it: each row on its own is
    accepted or refused by nms_bev as its flag says (non-finite, negative or out-of-range values)."""
    from lidarops.ops.boxes import unsupported_boxes
    b = data.draw(box_sets(), "boxes")
    flags = unsupported_boxes(b.boxes.to(device)).cpu()
    assert flags.shape == (b.boxes.shape[0],) and flags.dtype == torch.bool
    assert bool(flags.any()) == bool(_bad_names(("boxes", b))), f"{b.regime}: {b.boxes} -> {flags}"
    for i in range(b.boxes.shape[0]):
        row = b.boxes[i:i + 1].to(device)
        _, err = outcome(lidarops.nms_bev, row, torch.ones(1, device=device), 0.5)
        assert (err is not None) == bool(flags[i]), f"row {i} {b.boxes[i].tolist()}: flag {bool(flags[i])}, {err!r}"


def test_unsupported_boxes_bad_input():
    from lidarops.ops.boxes import unsupported_boxes
    for bad, match in ((torch.zeros(3, 6), r"\(N, 7\) boxes"), (torch.zeros(3, 7, dtype=torch.int64), "floating"),
                       ([[0.0] * 7], "torch.Tensor")):
        with pytest.raises(ValueError, match=match):
            unsupported_boxes(bad)


@fuzz
@given(data=st.data())
def test_points_in_boxes(device, data):
    b = data.draw(box_sets(), "boxes")
    regime = data.draw(st.sampled_from(["normal", "lattice", "nonfinite", "huge"]), "points regime")
    n = data.draw(st.integers(0, 12), "P")
    C = data.draw(st.integers(3, 5), "C")
    elem = scalars(regime, b.boxes.dtype) if regime != "normal" else st.floats(-5, 5, width=32)
    pts = torch.tensor(data.draw(st.lists(elem, min_size=n * C, max_size=n * C)), dtype=torch.float64)
    pts = pts.reshape(n, C).to(b.boxes.dtype)
    what = f"points_in_boxes(points {regime} {tuple(pts.shape)}, boxes {b.regime} {tuple(b.boxes.shape)})"
    res, err = outcome(lidarops.points_in_boxes, pts.to(device), b.boxes.to(device))
    bad = _bad_names(("boxes", b))
    if bad:
        return assert_clear_error(err, ValueError, bad, what)
    assert_no_error(err, what)
    expected = _points_in_boxes_reference(pts, b.boxes)
    # points within rounding of a face may go either way: compare the others
    if n and b.boxes.shape[0]:
        p, bx = pts[:, :3].double(), b.boxes.double()
        d = p[:, None, :2] - bx[None, :, :2]
        c, s = torch.cos(bx[:, 6]), torch.sin(bx[:, 6])
        lx, ly = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
        lz = p[:, None, 2] - bx[:, 2]
        eps = _tolerance(b) * (1 + p.abs().max().nan_to_num(0, 0, 0).item())
        near = ((lx.abs() - bx[:, 3] / 2).abs() < eps) | ((ly.abs() - bx[:, 4] / 2).abs() < eps) \
            | ((lz.abs() - bx[:, 5] / 2).abs() < eps)
        clear = ~near.any(1)
        assert_same(res.cpu()[clear], expected[clear], what)
    else:
        assert_same(res, expected, what)
