"""Rotated-box ops (lidarops.ops.boxes) against float64 references: world-frame polygon clipping written
in lidarops.ops.boxes (a different route from the kernels' local-frame clipping), shapely and
torchvision's rotated box_iou where installed, and hand-computed cases; CPU/CUDA identity."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lidarops
from helpers.boxes import lidar_boxes, random_boxes
from helpers.compare import assert_close_report, assert_equal_report
from helpers.devices import CUDA_VISIBLE, LIDAROPS_CUDA
from lidarops.ops.boxes import (
    _box_iou_3d_reference,
    _box_iou_bev_reference,
    _box_overlap_bev_reference,
    _nms_bev_reference,
    _points_in_boxes_reference,
)

PAIR_OPS = {
    "overlap_bev": (lidarops.box_overlap_bev, _box_overlap_bev_reference),
    "iou_bev": (lidarops.box_iou_bev, _box_iou_bev_reference),
    "iou_3d": (lidarops.box_iou_3d, _box_iou_3d_reference),
}
DTYPES = {"f32": torch.float32, "f64": torch.float64, "f16": torch.float16, "bf16": torch.bfloat16}


def _tol(dtype) -> float:
    return 1e-12 if dtype == torch.float64 else 2e-6


# ---------------------------------------------------------------------------------------------
# pairwise overlap / IoU
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("op", list(PAIR_OPS))
@pytest.mark.parametrize("dt", list(DTYPES))
def test_pairwise_matches_reference(device, op, dt):
    fn, ref = PAIR_OPS[op]
    dtype = DTYPES[dt]
    a = random_boxes(23, seed=1).to(dtype)
    b = random_boxes(17, seed=2).to(dtype)
    got = fn(a.to(device), b.to(device))
    assert got.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    expected = ref(a.double(), b.double())  # the reference sees exactly the (cast) values the kernel sees
    assert (expected > 0).float().mean() > 0.2, "the cases must overlap often to test anything"
    scale = 1.0 if op != "overlap_bev" else float(expected.abs().max())
    assert_close_report(got, expected, 0, _tol(dtype) * scale, f"{op} {dt}")


@pytest.mark.parametrize("op", list(PAIR_OPS))
def test_pairwise_lidar_like(device, op):
    fn, ref = PAIR_OPS[op]
    b = lidar_boxes(60, seed=3)
    got = fn(b.to(device), b.to(device))
    assert_close_report(got, ref(b, b), 0, 1e-12 * (1 if op != "overlap_bev" else 10), op)


def test_shapely_oracle(device):
    shapely = pytest.importorskip("shapely")
    from shapely.geometry import Polygon

    a, b = random_boxes(12, seed=4), lidar_boxes(12, seed=5) * torch.tensor([0.1, 0.1, 1, 1, 1, 1, 1])

    def poly(box):
        x, y, _, dx, dy, _, h = box.tolist()
        c, s = math.cos(h), math.sin(h)
        return Polygon([(x + c * u - s * v, y + s * u + c * v)
                        for u, v in ((dx / 2, dy / 2), (-dx / 2, dy / 2), (-dx / 2, -dy / 2), (dx / 2, -dy / 2))])

    for p, q in ((a, a), (a, b), (b, b)):
        expected = torch.tensor([[poly(u).intersection(poly(v)).area / poly(u).union(poly(v)).area
                                  for v in q] for u in p], dtype=torch.float64)
        assert_close_report(lidarops.box_iou_bev(p.to(device), q.to(device)), expected, 0, 1e-12, "shapely")
    assert shapely.__version__


def test_torchvision_rotated_iou_oracle(device):
    torchvision = pytest.importorskip("torchvision")
    try:
        torchvision.ops.box_iou(torch.zeros(1, 5), torch.zeros(1, 5), fmt="cxcywhr")
    except (TypeError, ValueError) as e:
        pytest.skip(f"torchvision {torchvision.__version__} has no rotated box_iou: {e}")
    a, b = random_boxes(30, seed=6), random_boxes(25, seed=7)

    def cxcywhr(x):  # torchvision takes degrees, counter-clockwise
        return torch.stack([x[:, 0], x[:, 1], x[:, 3], x[:, 4], torch.rad2deg(x[:, 6])], 1)

    expected = torchvision.ops.box_iou(cxcywhr(a).float(), cxcywhr(b).float(), fmt="cxcywhr").double()
    got = lidarops.box_iou_bev(a.to(device), b.to(device)).cpu()
    # torchvision computes in float32 from float32 corners
    assert_close_report(got, expected, 0, 2e-4, "torchvision cxcywhr")


@pytest.mark.parametrize("heading", [0.0, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 3.1415925, 1e-7, 2.5])
@pytest.mark.parametrize("dt", ["f32", "f64"])
def test_identical_boxes_give_exactly_one(device, heading, dt):
    """OpenPCDet #972: numba's rotate_iou gave ~0 for identical boxes near pi."""
    box = torch.tensor([[12.3, -4.1, -0.7, 4.2, 1.7, 1.5, heading], [-1e4, 1e4, 3.0, 0.8, 0.6, 1.73, heading]],
                       dtype=DTYPES[dt], device=device)
    for fn in (lidarops.box_iou_bev, lidarops.box_iou_3d):
        iou = fn(box, box)
        assert iou[0, 0].item() == 1.0 and iou[1, 1].item() == 1.0, (fn.__name__, iou)
    area = lidarops.box_overlap_bev(box, box).diagonal().cpu().double()
    assert torch.equal(area, (box[:, 3] * box[:, 4]).cpu().double()) or dt == "f32"
    assert_close_report(area, (box[:, 3].double() * box[:, 4].double()).cpu(), 1e-6, 0, "self overlap")


def test_symmetric_headings_give_one(device):
    """A box and the same box turned by pi or pi/2 with sizes swapped is the same rectangle."""
    a = torch.tensor([[3.0, 2.0, 0.0, 4.0, 2.0, 1.0, 0.3]], dtype=torch.float64, device=device)
    turned = a.clone()
    turned[0, 6] += math.pi
    swapped = a[:, [0, 1, 2, 4, 3, 5, 6]].clone()
    swapped[0, 6] += math.pi / 2
    for b in (turned, swapped):
        assert abs(lidarops.box_iou_bev(a, b).item() - 1.0) < 1e-12
        assert abs(lidarops.box_iou_3d(a, b).item() - 1.0) < 1e-12


def test_hand_computed_cases(device):
    f = torch.float64
    unit = [0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]
    cases = [
        # touching edges and a touching corner: no area
        ([unit], [[2.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]], 0.0, 0.0),
        ([unit], [[2.0, 2.0, 0.0, 2.0, 2.0, 2.0, 0.0]], 0.0, 0.0),
        # containment: a 1 x 1 box inside the 2 x 2 one
        ([unit], [[0.1, -0.1, 0.0, 1.0, 1.0, 2.0, 0.7]], 1.0, 0.25),
        # half overlap along x: 1 x 2 shared of 4 + 4 - 2
        ([unit], [[1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]], 2.0, 2.0 / 6.0),
        # a square turned by 45 degrees inside the square it is inscribed in: side 2 inside side 2 sqrt 2
        ([[0.0, 0.0, 0.0, 2 * math.sqrt(2), 2 * math.sqrt(2), 2.0, 0.0]],
         [[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, math.pi / 4]], 4.0, 0.5),
        # the unit square and itself turned by 45 degrees: a regular octagon of area 8 (sqrt 2 - 1)
        ([unit], [[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, math.pi / 4]], 8 * (math.sqrt(2) - 1),
         8 * (math.sqrt(2) - 1) / (8 - 8 * (math.sqrt(2) - 1))),
    ]
    for a, b, area, iou in cases:
        a, b = torch.tensor(a, dtype=f, device=device), torch.tensor(b, dtype=f, device=device)
        assert abs(lidarops.box_overlap_bev(a, b).item() - area) < 1e-12, (a, b)
        assert abs(lidarops.box_iou_bev(a, b).item() - iou) < 1e-12, (a, b)
        assert abs(lidarops.box_iou_bev(b, a).item() - iou) < 1e-12, (b, a)


def test_3d_overlap_in_z(device):
    f = torch.float64
    a = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]], dtype=f, device=device)
    cases = [(1.0, 1.0 / 3.0), (2.0, 0.0), (-2.5, 0.0), (0.5, 1.5 / 2.5)]  # z shift -> IoU (same BEV)
    for dz, iou in cases:
        b = a.clone()
        b[0, 2] += dz
        assert abs(lidarops.box_iou_3d(a, b).item() - iou) < 1e-12, dz
        assert lidarops.box_iou_bev(a, b).item() == 1.0


def test_zero_size_boxes_give_zero(device):
    boxes = torch.tensor([[0, 0, 0, 0, 2, 2, 0.3], [0, 0, 0, 2, 0, 2, 0], [0, 0, 0, 2, 2, 0, 0], [0, 0, 0, 0, 0, 0, 0],
                          [0, 0, 0, 2, 2, 2, 0]], dtype=torch.float32, device=device)
    for fn in (lidarops.box_overlap_bev, lidarops.box_iou_bev, lidarops.box_iou_3d):
        out = fn(boxes, boxes).cpu()
        assert not out.isnan().any(), fn.__name__
    iou3 = lidarops.box_iou_3d(boxes, boxes).cpu()
    assert iou3[:4].abs().sum() == 0 and iou3[:, :4].abs().sum() == 0 and iou3[4, 4] == 1
    iou = lidarops.box_iou_bev(boxes, boxes).cpu()
    assert iou[:2].abs().sum() == 0 and iou[2, 2] == 1  # a zero-height box still has a BEV rectangle


@pytest.mark.parametrize("offset", [1e3, 1e4])
def test_huge_coordinates(device, offset):
    a, b = random_boxes(10, seed=8), random_boxes(12, seed=9)
    shift = torch.tensor([offset, -offset, 0.0, 0, 0, 0, 0], dtype=torch.float64)
    near = lidarops.box_iou_bev(a.to(device), b.to(device)).cpu()
    far = lidarops.box_iou_bev((a + shift).to(device), (b + shift).to(device)).cpu()
    assert_close_report(far, near, 0, 1e-9, f"IoU moved by {offset} m")
    # float32 at 1e4 m: the reference on the rounded coordinates
    a32, b32 = (a + shift).float(), (b + shift).float()
    assert_close_report(lidarops.box_iou_bev(a32.to(device), b32.to(device)), _box_iou_bev_reference(a32, b32), 0,
                        2e-6, "float32 at 1e4 m")


@pytest.mark.parametrize("eps", [0.0, 1e-9, 1e-7, 1e-5, -1e-6])
def test_near_axis_aligned(device, eps):
    """second.pytorch #90/#294: wrong IoU for nearly axis-aligned and nearly parallel boxes."""
    a = torch.tensor([[10.0, 5.0, 0.0, 4.0, 2.0, 1.0, 0.0], [10.0, 5.0, 0.0, 4.0, 2.0, 1.0, math.pi / 2]],
                     dtype=torch.float64)
    b = torch.tensor([[10.3, 5.1, 0.0, 4.0, 2.0, 1.0, eps], [10.0, 6.0, 0.0, 4.0, 2.0, 1.0, math.pi / 2 + eps],
                      [12.0, 5.0, 0.0, 4.0, 2.0, 1.0, eps]], dtype=torch.float64)
    got = lidarops.box_iou_bev(a.to(device), b.to(device))
    assert_close_report(got, _box_iou_bev_reference(a, b), 0, 1e-12, f"eps={eps}")
    assert abs(got[0, 0].item() - (3.7 * 1.9) / (16 - 3.7 * 1.9)) < 1e-6


def test_pair_shapes_and_empty(device):
    a = random_boxes(5, seed=1).to(device)
    for fn, _ in PAIR_OPS.values():
        assert fn(a, a[:0]).shape == (5, 0)
        assert fn(a[:0], a).shape == (0, 5)
        nc = a.t().contiguous().t()  # the same values, column-major
        assert not nc.is_contiguous() and torch.equal(fn(nc, a), fn(a, a))


def test_pairwise_larger_than_a_tile(device):
    """More rows than one launch's grid rows per block and ragged tiles."""
    a, b = lidar_boxes(300, seed=11), lidar_boxes(70, seed=12)
    got = lidarops.box_iou_bev(a.to(device), b.to(device)).cpu()
    assert_equal_report(got, lidarops.box_iou_bev(a, b), "device vs CPU") if device != "cpu" else None
    sub = torch.arange(0, 300, 37)
    assert_close_report(got[sub], _box_iou_bev_reference(a[sub], b), 0, 1e-12, "rows")


# ---------------------------------------------------------------------------------------------
# NMS
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("threshold", [0.01, 0.1, 0.5, 0.7])
@pytest.mark.parametrize("seed", [0, 1])
def test_nms_matches_reference(device, threshold, seed):
    boxes = lidar_boxes(90, seed=seed)
    scores = torch.rand(90, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    keep = lidarops.nms_bev(boxes.to(device), scores.to(device), threshold)
    expected = _nms_bev_reference(boxes, scores, threshold)
    assert 1 < expected.numel() < 90, "the case must both keep and suppress"
    assert_equal_report(keep.cpu(), expected, f"keep thr={threshold}")


def test_nms_pre_and_post_max(device):
    boxes = lidar_boxes(120, seed=3)
    scores = torch.rand(120, generator=torch.Generator().manual_seed(3)).float()
    for pre, post in ((None, 5), (40, None), (40, 3), (0, None), (None, 0), (500, 500)):
        keep = lidarops.nms_bev(boxes.to(device), scores.to(device), 0.1, pre_max=pre, post_max=post)
        assert_equal_report(keep.cpu(), _nms_bev_reference(boxes, scores, 0.1, pre_max=pre, post_max=post),
                            f"pre={pre} post={post}")


def test_nms_equal_scores_keep_lower_index(device):
    box = torch.tensor([[1.0, 2.0, 0.0, 4.0, 2.0, 1.5, 0.4]])
    boxes = box.repeat(5, 1)
    scores = torch.tensor([0.3, 0.9, 0.9, 0.1, 0.9])
    keep = lidarops.nms_bev(boxes.to(device), scores.to(device), 0.5)
    assert keep.tolist() == [1]
    # -0.0 and 0.0 are equal scores
    keep = lidarops.nms_bev(boxes[:2].to(device), torch.tensor([-0.0, 0.0], device=device), 0.5)
    assert keep.tolist() == [0]
    # far apart: all kept, in score order, ties by index
    spread = box.repeat(4, 1)
    spread[:, 0] = torch.arange(4) * 10.0
    keep = lidarops.nms_bev(spread.to(device), torch.tensor([0.5, 0.7, 0.5, 0.7], device=device), 0.01)
    assert keep.tolist() == [1, 3, 0, 2]


def test_nms_threshold_is_strict(device):
    a = torch.tensor([[0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0], [1.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0]], dtype=torch.float64)
    iou = lidarops.box_iou_bev(a[:1], a[1:]).item()
    assert abs(iou - 1.0 / 3.0) < 1e-15
    scores = torch.tensor([0.9, 0.8], dtype=torch.float64)
    assert lidarops.nms_bev(a.to(device), scores.to(device), iou).tolist() == [0, 1]  # IoU == threshold: kept
    below = float(np.nextafter(iou, 0.0))
    assert lidarops.nms_bev(a.to(device), scores.to(device), below).tolist() == [0]


def test_nms_empty_and_single(device):
    boxes = torch.zeros(0, 7, device=device)
    assert lidarops.nms_bev(boxes, torch.zeros(0, device=device), 0.5).shape == (0,)
    one = torch.tensor([[0.0, 0, 0, 1, 1, 1, 0]], device=device)
    assert lidarops.nms_bev(one, torch.ones(1, device=device), 0.5).tolist() == [0]


@pytest.mark.parametrize("pre,post", [(None, None), (7, None), (None, 2), (5, 3)])
def test_batched_nms_matches_reference(device, pre, post):
    boxes = lidar_boxes(100, seed=4)
    g = torch.Generator().manual_seed(4)
    scores = torch.rand(100, generator=g)
    idxs = torch.randint(0, 3, (100,), generator=g)
    keep = lidarops.batched_nms_bev(boxes.to(device), scores.to(device), idxs.to(device), 0.2, pre_max=pre,
                                    post_max=post)
    expected = _nms_bev_reference(boxes, scores, 0.2, idxs=idxs, pre_max=pre, post_max=post)
    assert_equal_report(keep.cpu(), expected, f"batched pre={pre} post={post}")
    # groups are independent: the same boxes in one group suppress more
    assert lidarops.nms_bev(boxes, scores, 0.2).numel() < _nms_bev_reference(boxes, scores, 0.2, idxs=idxs).numel()


def test_nms_many_boxes_against_iou_matrix(device):
    """Several 64-box words and a ragged last one: greedy over the op's own IoU matrix."""
    boxes = lidar_boxes(700, seed=5)
    scores = torch.rand(700, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    keep = lidarops.nms_bev(boxes.to(device), scores.to(device), 0.05).cpu()
    iou = lidarops.box_iou_bev(boxes, boxes)
    order = torch.sort(scores, stable=True, descending=True).indices.tolist()
    removed = torch.zeros(700, dtype=torch.bool)
    expected = []
    for i in order:
        if removed[i]:
            continue
        expected.append(i)
        removed |= iou[i] > 0.05
    assert_equal_report(keep, torch.tensor(expected), "700 boxes")


def _padded_expected(boxes, scores, iou_thr, score_thr, pre, post, idxs=None):
    """Threshold first, then the reference greedy NMS, then the global pre/post caps (nms_bev_padded's
    definition, written the straightforward way)."""
    n = boxes.shape[0]
    order = sorted(range(n), key=lambda i: (-float(scores[i]), i))
    if pre is not None:
        order = order[:pre]
    cand = torch.tensor([i for i in order if float(scores[i]) >= score_thr], dtype=torch.int64)
    if cand.numel() == 0:
        return cand
    keep = cand[_nms_bev_reference(boxes[cand], scores[cand], iou_thr,
                                   idxs=None if idxs is None else idxs[cand])]
    return keep if post is None else keep[:post]


@pytest.mark.parametrize("score_thr,pre,post", [(-math.inf, None, None), (0.5, None, None), (0.5, 40, 6),
                                                (0.3, 70, None), (0.99, None, 10), (2.0, 50, 50), (0.0, 0, 5)])
@pytest.mark.parametrize("grouped", [False, True])
def test_nms_padded_is_threshold_then_nms(device, score_thr, pre, post, grouped):
    boxes = lidar_boxes(120, seed=11)
    g = torch.Generator().manual_seed(11)
    scores = (torch.rand(120, generator=g) * 20).round() / 20  # ties, some exactly at the thresholds
    idxs = torch.randint(0, 3, (120,), generator=g) if grouped else None
    keep, count = torch.ops.lidarops.nms_bev_padded(boxes.to(device), scores.to(device),
                                                    None if idxs is None else idxs.to(device), 0.1, score_thr,
                                                    -1 if pre is None else pre, -1 if post is None else post)
    expected = _padded_expected(boxes, scores, 0.1, score_thr, pre, post, idxs)
    size = min(120, 120 if pre is None else pre, 120 if post is None else post)
    assert keep.shape == (size,) and count.shape == () and count.dtype == torch.int64
    assert int(count) == expected.numel()
    assert_equal_report(keep[:int(count)].cpu(), expected, f"thr={score_thr} pre={pre} post={post}")
    assert (keep[int(count):] == -1).all()
    if not grouped:  # the wrapper: padded and unpadded forms agree with thresholding first
        k2 = lidarops.nms_bev(boxes.to(device), scores.to(device), 0.1, pre_max=pre, post_max=post,
                              score_threshold=None if score_thr == -math.inf else score_thr)
        assert_equal_report(k2.cpu(), expected, "wrapper")


def test_nms_padded_equals_threshold_first_on_detector_like_scores(device):
    """What PointPillars' post-processing relies on: top pre_max of all scores, then NMS among those above
    the threshold, equals NMS of the top pre_max among the boxes above the threshold."""
    boxes = lidar_boxes(600, seed=12)
    scores = torch.rand(600, generator=torch.Generator().manual_seed(12)) ** 4
    above = torch.nonzero(scores >= 0.1).squeeze(1)
    for pre, post in ((50, 20), (200, 500), (None, None)):
        expected = above[lidarops.nms_bev(boxes[above], scores[above], 0.01, pre_max=pre, post_max=post)]
        keep, count = lidarops.nms_bev(boxes.to(device), scores.to(device), 0.01, pre_max=pre, post_max=post,
                                       score_threshold=0.1, padded=True)
        assert 0 < int(count) < above.numel()
        assert_equal_report(keep[:int(count)].cpu(), expected, f"pre={pre} post={post}")


def test_nms_nan_scores_with_checks_off(device):
    """With the value checks off, NaN scores are visited last (after -inf) and never pass a score
    threshold; the NaN boxes stand apart, so they are kept whenever they take part."""
    boxes = lidar_boxes(80, seed=13)
    scores = torch.rand(80, generator=torch.Generator().manual_seed(13))
    nan = torch.zeros(80, dtype=torch.bool)
    nan[::9] = True
    scores[nan] = float("nan")
    scores[5] = -math.inf
    boxes[5, 0] = 400.0
    boxes[nan, 0] = 500.0 + 20.0 * torch.arange(int(nan.sum()), dtype=boxes.dtype)
    ok = torch.nonzero(~nan).squeeze(1)
    b, s = boxes.to(device), scores.to(device)
    with lidarops.validation(False):  # -inf scores are refused too when the checks are on
        plain = ok[_nms_bev_reference(boxes[ok], scores[ok], 0.1)]
        assert plain[-1] == 5
        keep = lidarops.nms_bev(b, s, 0.1)
        assert_equal_report(keep.cpu(), torch.cat([plain, torch.nonzero(nan).squeeze(1)]), "NaN last")
        keep, count = lidarops.nms_bev(b, s, 0.1, score_threshold=-math.inf, padded=True)
        assert_equal_report(keep[:int(count)].cpu(), plain, "NaN never a candidate")
        assert keep.shape == (80,) and (keep[int(count):] == -1).all()
        keep = torch.ops.lidarops.nms_bev(b, s, None, 0.1)
        assert_equal_report(keep.cpu(), torch.cat([plain, torch.nonzero(nan).squeeze(1)]), "the op: NaN last")


def test_nms_padded_empty_shapes(device):
    z = torch.zeros(0, 7, device=device)
    keep, count = lidarops.nms_bev(z, torch.zeros(0, device=device), 0.5, padded=True)
    assert keep.shape == (0,) and int(count) == 0
    boxes = lidar_boxes(10, seed=1).to(device)
    for pre, post, size in ((0, None, 0), (None, 0, 0), (3, 7, 3), (20, 4, 4)):
        keep, count = lidarops.nms_bev(boxes, torch.rand(10, device=device), 0.5, pre_max=pre, post_max=post,
                                       padded=True)
        assert keep.shape == (size,) and int(count) <= size


@pytest.mark.skipif(not LIDAROPS_CUDA, reason="needs a GPU and lidarops built with CUDA kernels")
@pytest.mark.parametrize("n", [1, 63, 64, 65, 4096, 5000])
def test_nms_cuda_equals_cpu(n):
    boxes = lidar_boxes(n, seed=n)
    scores = torch.rand(n, generator=torch.Generator().manual_seed(n))
    scores[::7] = 0.5  # ties
    for thr, pre, post in ((0.01, None, None), (0.3, 4096, 500), (0.6, None, 100)):
        cpu = lidarops.nms_bev(boxes, scores, thr, pre_max=pre, post_max=post)
        cuda = lidarops.nms_bev(boxes.cuda(), scores.cuda(), thr, pre_max=pre, post_max=post)
        assert_equal_report(cuda.cpu(), cpu, f"n={n} thr={thr}")
    idxs = torch.randint(0, 3, (n,), generator=torch.Generator().manual_seed(1))
    assert_equal_report(lidarops.batched_nms_bev(boxes.cuda(), scores.cuda(), idxs.cuda(), 0.1).cpu(),
                        lidarops.batched_nms_bev(boxes, scores, idxs, 0.1), f"batched n={n}")


@pytest.mark.skipif(not LIDAROPS_CUDA, reason="needs a GPU and lidarops built with CUDA kernels")
@pytest.mark.parametrize("n", [130, 2500, 4096, 4097])
def test_nms_cuda_keeps_many_boxes_and_stops_at_post_max(n):
    """Spread boxes: most are kept, so the reduction ORs many rows per step and post_max stops it inside
    a block of 64 (4,096 boxes and fewer take the shared-memory ring, 4,097 the one-warp kernel)."""
    boxes = random_boxes(n, seed=n, extent=float(n) ** 0.5 * 4).float()
    scores = torch.rand(n, generator=torch.Generator().manual_seed(n))
    full = lidarops.nms_bev(boxes, scores, 0.05)
    assert full.numel() > n // 2  # the case tests what it says: many kept boxes
    for post in (1, 37, 64, 65, n // 2 + 3, None):
        for st in (None, 0.25):
            cpu = lidarops.nms_bev(boxes, scores, 0.05, post_max=post, score_threshold=st)
            cuda = lidarops.nms_bev(boxes.cuda(), scores.cuda(), 0.05, post_max=post, score_threshold=st)
            assert_equal_report(cuda.cpu(), cpu, f"n={n} post={post} st={st}")


def _frames(B, n, seed, dtype=torch.float64):
    """B frames of n detector-like boxes with scores: ties, some exactly at the thresholds, and in the last
    frame a block of equal boxes (all suppressed by the first)."""
    boxes = torch.stack([lidar_boxes(n, seed=seed + b) for b in range(B)]).to(dtype)
    g = torch.Generator().manual_seed(seed)
    scores = (torch.rand(B, n, generator=g) * 20).round() / 20
    if n >= 8:
        boxes[-1, 1:6] = boxes[-1, 0]
    return boxes, scores.to(dtype)


@pytest.mark.parametrize("st,pre,post", [(None, None, None), (0.5, None, None), (0.5, 40, 6), (0.3, 70, None),
                                         (0.99, None, 10), (2.0, 50, 50), (0.0, 0, 5), (-math.inf, 200, 3)])
def test_nms_frames_is_each_frames_padded_nms(device, st, pre, post):
    """nms_bev_frames, row by row, is nms_bev(..., padded=True) of each frame (itself checked against the
    float64 reference above), which is the threshold-first reference NMS of each frame."""
    B, n = 5, 120
    boxes, scores = _frames(B, n, seed=21)
    keep, count = lidarops.nms_bev_frames(boxes.to(device), scores.to(device), 0.1, pre_max=pre, post_max=post,
                                          score_threshold=st)
    size = min(n, n if pre is None else pre, n if post is None else post)
    assert keep.shape == (B, size) and count.shape == (B,) and keep.dtype == count.dtype == torch.int64
    for b in range(B):
        want = _padded_expected(boxes[b], scores[b], 0.1, -math.inf if st is None else st, pre, post)
        assert int(count[b]) == want.numel(), f"frame {b}"
        assert_equal_report(keep[b, :int(count[b])].cpu(), want, f"frame {b} st={st} pre={pre} post={post}")
        assert (keep[b, int(count[b]):] == -1).all()


def test_nms_frames_empty_shapes_and_checks(device):
    z = torch.zeros(3, 0, 7, device=device)
    keep, count = lidarops.nms_bev_frames(z, torch.zeros(3, 0, device=device), 0.5)
    assert keep.shape == (3, 0) and count.tolist() == [0, 0, 0]
    keep, count = lidarops.nms_bev_frames(torch.zeros(0, 9, 7, device=device), torch.zeros(0, 9, device=device), 0.5)
    assert keep.shape == (0, 9) and count.shape == (0,)
    boxes, scores = _frames(2, 10, seed=3)
    b, s = boxes.to(device), scores.to(device)
    for pre, post, size in ((0, None, 0), (None, 0, 0), (3, 7, 3), (20, 4, 4)):
        keep, count = lidarops.nms_bev_frames(b, s, 0.5, pre_max=pre, post_max=post)
        assert keep.shape == (2, size) and (count <= size).all()
    with pytest.raises(ValueError, match=r"boxes must be a floating \(B, N, 7\)"):
        lidarops.nms_bev_frames(b[0], s, 0.5)
    with pytest.raises(ValueError, match=r"scores must be a floating \(B, N\) tensor with \(B, N\) = \(2, 10\)"):
        lidarops.nms_bev_frames(b, s[:, :9], 0.5)
    with pytest.raises(ValueError, match="iou_threshold must be a finite number >= 0"):
        lidarops.nms_bev_frames(b, s, -0.1)
    bad = b.clone()
    bad[1, 4, 3] = math.nan
    with pytest.raises(ValueError, match=r"boxes \(as \(B \* N, 7\)\) contains NaN"):
        lidarops.nms_bev_frames(bad, s, 0.5)
    bad = s.clone()
    bad[0, 2] = math.inf
    with pytest.raises(ValueError, match="scores contains NaN or infinite"):
        lidarops.nms_bev_frames(b, bad, 0.5)
    with pytest.raises(ValueError, match="score_threshold must be None or a number"):
        lidarops.nms_bev_frames(b, s, 0.5, score_threshold=math.nan)


@pytest.mark.skipif(not LIDAROPS_CUDA, reason="needs a GPU and lidarops built with CUDA kernels")
@pytest.mark.parametrize("B,n", [(1, 1), (3, 64), (4, 65), (2, 4096), (3, 4097), (16, 5000)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_nms_frames_cuda_equals_cpu_and_replays_in_a_graph(B, n, dtype):
    """Frames of up to 4,096 boxes take the block sort (a block per frame), more the segmented sort, float64
    scores always the latter; the mask kernel and the reduction run a grid slice and a block per frame."""
    boxes, scores = _frames(B, n, seed=n)
    boxes, scores = boxes.to(dtype), torch.rand(B, n, generator=torch.Generator().manual_seed(n)).to(dtype)
    scores[:, ::7] = 0.5
    for st, pre, post in ((0.1, 4096, 500), (0.5, -1, 100), (None, 100, -1), (0.95, 4096, 500)):
        cpu = torch.ops.lidarops.nms_bev_padded_batched(boxes, scores, 0.01, st, pre, post)
        cuda = torch.ops.lidarops.nms_bev_padded_batched(boxes.cuda(), scores.cuda(), 0.01, st, pre, post)
        assert_equal_report(cuda[0].cpu(), cpu[0], f"B={B} n={n} st={st}")
        assert_equal_report(cuda[1].cpu(), cpu[1], f"B={B} n={n} st={st} counts")
        for b in range(B):  # and each frame's own padded NMS on the GPU
            one = torch.ops.lidarops.nms_bev_padded(boxes[b].cuda(), scores[b].cuda(), None, 0.01, st, pre, post)
            assert_equal_report(cuda[0][b].cpu(), one[0].cpu(), f"frame {b}")
    sb, ss = boxes.cuda(), scores.cuda()
    torch.ops.lidarops.nms_bev_padded_batched(sb, ss, 0.01, 0.3, 4096, 500)  # warm-up outside the capture
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = torch.ops.lidarops.nms_bev_padded_batched(sb, ss, 0.01, 0.3, 4096, 500)
    for seed in (1, 2):
        new = (torch.rand(B, n, generator=torch.Generator().manual_seed(seed)) ** (seed + 1)).to(dtype)
        ss.copy_(new)
        graph.replay()
        ref = torch.ops.lidarops.nms_bev_padded_batched(boxes, new, 0.01, 0.3, 4096, 500)
        assert_equal_report(out[0].cpu(), ref[0], f"graph replay seed={seed}")
        assert_equal_report(out[1].cpu(), ref[1], f"graph replay seed={seed} counts")


def test_nms_checked_status_is_count_and_value_flags(device):
    boxes = lidar_boxes(50, seed=3).float().to(device)
    scores = torch.rand(50, device=device)
    keep, count = torch.ops.lidarops.nms_bev_padded(boxes, scores, None, 0.1, 0.2, 40, 30)
    keep2, status = torch.ops.lidarops.nms_bev_checked(boxes, scores, None, 0.1, 0.2, 40, 30)
    assert_equal_report(keep2, keep, "checked keep")
    assert status.tolist() == [int(count), 0, 0, 0]
    # [non-finite box value, non-finite score, a value outside the supported range (a negative size, a centre
    # beyond 1e6 m, ...; an infinity is both)]; post_max=0 keeps nothing but still checks
    for col, value, expected in ((0, math.nan, [1, 0, 0]), (6, math.inf, [1, 0, 1]), (4, -0.5, [0, 0, 1]),
                                 (3, -math.inf, [1, 0, 1]), (5, math.nan, [1, 0, 0]), (1, -2e6, [0, 0, 1]),
                                 (6, 1.5e6, [0, 0, 1]), (4, 1e-7, [0, 0, 1]), (5, 0.0, [0, 0, 0])):
        bad = boxes.clone()
        bad[17, col] = value
        flags = torch.ops.lidarops.nms_bev_checked(bad, scores, None, 0.1, None, -1, 0)[1].tolist()[1:]
        assert flags == expected, (col, value, flags)
    bad_scores = scores.clone()
    bad_scores[49] = math.nan
    assert torch.ops.lidarops.nms_bev_checked(boxes, bad_scores, None, 0.1, None, -1, -1)[1].tolist()[1:] == [0, 1, 0]
    assert torch.ops.lidarops.nms_bev_checked(boxes[:0], scores[:0], None, 0.1, None, -1, -1)[1].tolist() == [0] * 4
    # -0.0 is not negative
    zero = boxes.clone()
    zero[5, 3:6] = -0.0
    assert torch.ops.lidarops.nms_bev_checked(zero, scores, None, 0.1, None, -1, -1)[1].tolist()[1:] == [0, 0, 0]
    # values are checked in their own dtype: 1e300 is finite in float64 (but beyond the supported centres),
    # float16 boxes and scores widen exactly
    huge, big_scores = boxes.double(), scores.double()
    huge[3, 0], big_scores[7] = 1e300, -1e300
    assert torch.ops.lidarops.nms_bev_checked(huge, big_scores, None, 0.1, None, -1, -1)[1].tolist()[1:] == [0, 0, 1]
    half = boxes.half()
    half[2, 1] = math.inf
    assert torch.ops.lidarops.nms_bev_checked(half, scores.half(), None, 0.1, None, -1, -1)[1].tolist()[1:] == [1, 0, 1]
    half[2, 1] = 65504.0  # float16's largest value: within the supported centres
    assert torch.ops.lidarops.nms_bev_checked(half, scores.half(), None, 0.1, None, -1, -1)[1].tolist()[1:] == [0, 0, 0]


@pytest.mark.skipif(not LIDAROPS_CUDA, reason="needs a GPU and lidarops built with CUDA kernels")
@pytest.mark.parametrize("n", [1, 64, 65, 4096, 5000])
def test_nms_padded_cuda_equals_cpu_and_replays_in_a_graph(n):
    boxes = lidar_boxes(n, seed=n)
    scores = torch.rand(n, generator=torch.Generator().manual_seed(n))
    scores[::7] = 0.5
    for st, pre, post in ((0.1, 4096, 500), (0.5, -1, 100), (-math.inf, 100, -1), (0.95, 4096, 500)):
        cpu = torch.ops.lidarops.nms_bev_padded(boxes, scores, None, 0.01, st, pre, post)
        cuda = torch.ops.lidarops.nms_bev_padded(boxes.cuda(), scores.cuda(), None, 0.01, st, pre, post)
        assert_equal_report(cuda[0].cpu(), cpu[0], f"n={n} st={st}")
        assert int(cuda[1]) == int(cpu[1])
    # captured once, replayed on other scores: the candidates and the kept count change inside the graph
    sb, ss = boxes.cuda(), scores.cuda()
    torch.ops.lidarops.nms_bev_padded(sb, ss, None, 0.01, 0.3, 4096, 500)  # warm-up outside the capture
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = torch.ops.lidarops.nms_bev_padded(sb, ss, None, 0.01, 0.3, 4096, 500)
    for seed in (1, 2, 3):
        new = torch.rand(n, generator=torch.Generator().manual_seed(seed)) ** (seed + 1)
        ss.copy_(new)
        graph.replay()
        ref = torch.ops.lidarops.nms_bev_padded(boxes, new, None, 0.01, 0.3, 4096, 500)
        assert_equal_report(out[0].cpu(), ref[0], f"graph replay seed={seed}")
        assert int(out[1]) == int(ref[1])


@pytest.mark.skipif(not LIDAROPS_CUDA, reason="needs a GPU and lidarops built with CUDA kernels")
def test_pairwise_cuda_equals_cpu_bitwise():
    a, b = lidar_boxes(257, seed=1), random_boxes(99, seed=2)
    for fn, _ in PAIR_OPS.values():
        for dtype in (torch.float32, torch.float64):
            assert_equal_report(fn(a.to("cuda", dtype), b.to("cuda", dtype)).cpu(), fn(a.to(dtype), b.to(dtype)),
                                f"{fn.__name__} {dtype}")


# ---------------------------------------------------------------------------------------------
# points in boxes
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dt", ["f32", "f64"])
def test_points_in_boxes_matches_reference(device, dt):
    boxes = random_boxes(15, seed=13).to(DTYPES[dt])
    g = torch.Generator().manual_seed(13)
    points = ((torch.rand(2000, 4, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([8.0, 8.0, 3.0, 1.0]))
    points = points.to(DTYPES[dt])
    got = lidarops.points_in_boxes(points.to(device), boxes.to(device)).cpu()
    expected = _points_in_boxes_reference(points, boxes)
    assert (expected >= 0).float().mean() > 0.2
    assert_equal_report(got, expected, "points_in_boxes")


def test_points_in_boxes_boundaries_and_overlaps(device):
    boxes = torch.tensor([[0.0, 0.0, 0.0, 2.0, 4.0, 2.0, 0.0], [1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]],
                         dtype=torch.float64)
    points = torch.tensor([
        [1.0, 0.0, 0.0],    # on box 0's face and inside box 1: the lower index
        [-1.0, 2.0, 1.0],   # box 0's corner (closed box)
        [1.5, 0.0, 0.0],    # box 1 only
        [-1.0 - 1e-9, 0.0, 0.0],  # just outside
        [0.0, 0.0, 1.0 + 1e-9],   # just above
        [float("nan"), 0.0, 0.0],  # NaN point: in no box
    ], dtype=torch.float64)
    got = lidarops.points_in_boxes(points.to(device), boxes.to(device)).tolist()
    assert got == [0, 0, 1, -1, -1, -1]


def test_points_in_boxes_empty_and_extra_columns(device):
    boxes = random_boxes(3, seed=1).to(device)
    assert lidarops.points_in_boxes(torch.zeros(0, 4, device=device), boxes).shape == (0,)
    pts = torch.rand(10, 5, device=device)
    assert lidarops.points_in_boxes(pts, boxes[:0]).tolist() == [-1] * 10
    assert torch.equal(lidarops.points_in_boxes(pts[:, 1:], boxes), lidarops.points_in_boxes(pts[:, 1:4].clone(), boxes))


def test_points_in_boxes_agrees_with_the_simulator_labels(device):
    """The simulator's counts (lidarops.data.geometry, NumPy) on a driving frame."""
    from lidarops.data.geometry import box_index_of_points
    from lidarops.data.synthetic import Simulator

    frame = Simulator("driving_city", seed=2).sweep(0)
    pts = torch.from_numpy(frame.points)
    got = lidarops.points_in_boxes(pts.to(device), torch.from_numpy(frame.boxes).to(device)).cpu().numpy()
    expected = box_index_of_points(frame.points, frame.boxes)
    assert (expected >= 0).sum() > 100
    assert (got != expected).sum() <= 2  # float64 sin/cos of NumPy vs ours: boundary points only


# ---------------------------------------------------------------------------------------------
# errors, dispatcher, compile
# ---------------------------------------------------------------------------------------------
def _bad_cases():
    good = random_boxes(4, seed=0).float()
    nan = good.clone()
    nan[1, 6] = float("nan")
    neg = good.clone()
    neg[2, 4] = -1.0
    scores = torch.rand(4)
    return [
        (lambda: lidarops.box_iou_bev(good[:, :6], good), "a must be \\(N, 7\\)"),
        (lambda: lidarops.box_iou_bev(good, good.long()), "b must be floating"),
        (lambda: lidarops.box_iou_bev(good, good.double()), "same dtype"),
        (lambda: lidarops.box_iou_3d(good, nan), "b contains NaN"),
        (lambda: lidarops.box_overlap_bev(neg, good), "a must hold .*sizes dx, dy, dz of 0 or in .*rows \\[2\\] are not; row 2 has d[xyz] = -[0-9.]+ \\(a negative size\\)"),
        (lambda: lidarops.nms_bev(good, scores[:3], 0.5), "scores must be a floating \\(N,\\) tensor with N = 4"),
        (lambda: lidarops.nms_bev(nan, scores, 0.5), "boxes contains NaN"),
        (lambda: lidarops.nms_bev(good, torch.tensor([0.1, float("nan"), 0, 0]), 0.5), "scores contains NaN"),
        (lambda: lidarops.nms_bev(neg, scores, 0.5, post_max=0), "boxes must hold .*rows \\[2\\] are not; row 2 has d[xyz] = -[0-9.]+ \\(a negative size\\)"),
        (lambda: lidarops.nms_bev(nan, scores, 0.5, padded=True), "boxes contains NaN"),
        (lambda: lidarops.nms_bev(good, scores, float("nan")), "iou_threshold must be a finite number"),
        (lambda: lidarops.nms_bev(good, scores, -0.5), "iou_threshold must be a finite number >= 0"),
        (lambda: torch.ops.lidarops.nms_bev(good, scores, None, -0.5), "iou_threshold must be a finite number >= 0"),
        (lambda: lidarops.nms_bev(good, scores, 0.5, pre_max=-3), "pre_max must be None or an int >= 0"),
        (lambda: lidarops.nms_bev(good, scores, 0.5, post_max=2.5), "post_max must be None or an int >= 0"),
        (lambda: lidarops.batched_nms_bev(good, scores, scores, 0.5), "idxs must be an integer \\(N,\\) tensor"),
        (lambda: lidarops.nms_bev(good, scores, 0.5, score_threshold=float("nan")), "score_threshold must be"),
        (lambda: lidarops.nms_bev(good, scores, 0.5, score_threshold=True), "score_threshold must be"),
        (lambda: torch.ops.lidarops.nms_bev_padded(good, scores, None, 0.5, float("nan")),
         "score_threshold must be a number or None"),
        (lambda: torch.ops.lidarops.nms_bev_padded(good, scores[:2], None, 0.5, 0.0), "scores must be \\(N,\\)"),
        (lambda: lidarops.points_in_boxes(good[:, :2], good), "points must be a floating \\(P, C >= 3\\)"),
        (lambda: lidarops.points_in_boxes(good[:, :3], nan), "boxes contains NaN"),
        (lambda: lidarops.box_iou_bev([1, 2], good), "a must be a torch.Tensor"),
    ]


@pytest.mark.parametrize("case", range(len(_bad_cases())))
def test_bad_input_raises_value_error_naming_argument(case):
    fn, pattern = _bad_cases()[case]
    with pytest.raises(ValueError, match=pattern):
        fn()


@pytest.mark.skipif(not CUDA_VISIBLE, reason="needs a GPU")
def test_device_mismatch_errors():
    good = random_boxes(4, seed=0).float()
    with pytest.raises(ValueError, match="b is on cpu but a is on cuda"):
        lidarops.box_iou_bev(good.cuda(), good)
    with pytest.raises(ValueError, match="scores is on cpu"):
        lidarops.nms_bev(good.cuda(), torch.rand(4), 0.5)


def _op_samples(device):
    a, b = lidar_boxes(9, seed=1).to(device), random_boxes(5, seed=2).float().to(device)
    yield "box_overlap_bev", (a, a)
    yield "box_iou_bev", (b, b)
    yield "box_iou_3d", (a.float(), b)
    yield "points_in_boxes", (torch.rand(30, 4, device=device) * 6 - 3, b)
    yield "nms_bev", (a, torch.rand(9, device=device), None, 0.1, -1, 3)
    yield "nms_bev", (b, torch.rand(5, device=device), torch.tensor([0, 1, 0, 1, 1], device=device), 0.1, 4, -1)
    yield "nms_bev_padded", (a, torch.rand(9, device=device), None, 0.1, 0.3, 6, 4)
    yield "nms_bev_padded", (b, torch.rand(5, device=device), torch.tensor([0, 1, 0, 1, 1], device=device), 0.1,
                             -math.inf, -1, -1)
    yield "nms_bev_checked", (a, torch.rand(9, device=device), None, 0.1, 0.3, 6, 4)
    yield "nms_bev_checked", (b, torch.rand(5, device=device), torch.tensor([0, 1, 0, 1, 1], device=device), 0.1,
                              None, -1, -1)


def test_opcheck(device):
    for op, args in _op_samples(device):
        utils = ("test_schema", "test_autograd_registration", "test_faketensor")
        if op != "nms_bev":  # a data-dependent output size: no AOT dispatch with dynamic shapes
            utils += ("test_aot_dispatch_dynamic",)
        result = torch.library.opcheck(getattr(torch.ops.lidarops, op).default, args, test_utils=utils,
                                       raise_exception=False)
        bad = {k: v for k, v in result.items() if v != "SUCCESS"}
        assert not bad, f"opcheck {op}: {bad}"


def test_compile_fullgraph(device):
    def post(boxes, scores, points):
        iou = lidarops.box_iou_bev(boxes, boxes)
        owner = lidarops.points_in_boxes(points, boxes)
        return iou.sum(1), owner, lidarops.box_iou_3d(boxes, boxes).amax(1)

    boxes = lidar_boxes(40, seed=2).float().to(device)
    scores = torch.rand(40, device=device)
    points = torch.rand(200, 3, device=device) * 60
    torch._dynamo.reset()
    compiled = torch.compile(post, fullgraph=True, backend="aot_eager")
    for a, b in zip(compiled(boxes, scores, points), post(boxes, scores, points)):
        assert_equal_report(a, b, "compiled")


def test_compile_nms_with_dynamic_output(device):
    import torch._dynamo.config as dconfig

    def nms(boxes, scores):
        return lidarops.nms_bev(boxes, scores, 0.1, post_max=10) * 2

    boxes = lidar_boxes(40, seed=2).float().to(device)
    scores = torch.rand(40, device=device)
    torch._dynamo.reset()
    with dconfig.patch(capture_dynamic_output_shape_ops=True):
        compiled = torch.compile(nms, fullgraph=True, backend="aot_eager")
        assert_equal_report(compiled(boxes, scores), nms(boxes, scores), "compiled nms")


def test_compile_padded_nms_needs_no_dynamic_sizes(device):
    def post(boxes, scores):
        keep, count = lidarops.nms_bev(boxes, scores, 0.1, pre_max=30, post_max=10, score_threshold=0.2, padded=True)
        valid = torch.arange(keep.shape[0], device=keep.device) < count
        return torch.where(valid[:, None], boxes[keep.clamp(min=0)], 0), count

    boxes = lidar_boxes(40, seed=2).float().to(device)
    scores = torch.rand(40, device=device)
    torch._dynamo.reset()
    compiled = torch.compile(post, fullgraph=True, backend="aot_eager")
    for a, b in zip(compiled(boxes, scores), post(boxes, scores)):
        assert_equal_report(a, b, "compiled padded nms")

    def frames(boxes, scores):
        keep, count = lidarops.nms_bev_frames(boxes, scores, 0.1, pre_max=30, post_max=10, score_threshold=0.2)
        valid = torch.arange(keep.shape[1], device=keep.device) < count[:, None]
        return torch.where(valid[..., None], boxes.gather(1, keep.clamp(min=0)[..., None].expand(-1, -1, 7)), 0), count

    many = torch.stack([boxes, boxes.flip(0)])
    manys = torch.stack([scores, torch.rand(40, device=device)])
    with lidarops.validation(False):  # the value checks read back: a graph break under fullgraph
        compiled = torch.compile(frames, fullgraph=True, backend="aot_eager")
        for a, b in zip(compiled(many, manys), frames(many, manys)):
            assert_equal_report(a, b, "compiled nms_bev_frames")


def test_meta_tensors_give_shapes():
    a = torch.empty(6, 7, device="meta")
    b = torch.empty(4, 7, device="meta", dtype=torch.float64)
    assert torch.ops.lidarops.box_iou_bev(a, a).shape == (6, 6)
    assert torch.ops.lidarops.box_iou_3d(b, b).dtype == torch.float64
    assert torch.ops.lidarops.points_in_boxes(torch.empty(9, 4, device="meta"), a).shape == (9,)
    keep, count = torch.ops.lidarops.nms_bev_padded(a, torch.empty(6, device="meta"), None, 0.1, 0.0, 4, 9)
    assert keep.shape == (4,) and count.shape == ()
    keep, status = torch.ops.lidarops.nms_bev_checked(a, torch.empty(6, device="meta"), None, 0.1, None, 5, -1)
    assert keep.shape == (5,) and status.shape == (4,)
    keep, count = torch.ops.lidarops.nms_bev_padded_batched(a.expand(3, 6, 7), torch.empty(3, 6, device="meta"), 0.1,
                                                            None, -1, 4)
    assert keep.shape == (3, 4) and count.shape == (3,)


def test_ops_are_registered_with_their_kernels():
    from lidarops import extension

    has = torch._C._dispatch_has_kernel_for_dispatch_key
    for op in ("box_overlap_bev", "box_iou_bev", "box_iou_3d", "nms_bev", "nms_bev_padded", "nms_bev_checked",
               "nms_bev_padded_batched", "points_in_boxes", "kitti_match"):
        name = f"lidarops::{op}"
        assert has(name, "CPU") and has(name, "Meta"), name
        if extension.cuda_available() and op != "kitti_match":  # the evaluator's matching is CPU-only
            assert has(name, "CUDA"), name


@pytest.mark.parametrize("threshold", [0.001, 0.01, 0.05, 0.2])
def test_nms_pair_decisions_equal_the_clipped_iou(device, threshold):
    """NMS decides most overlapping pairs from a disk inside both boxes (a lower bound of the IoU) and
    clips only the rest: every pair decision must be the one the clipped IoU gives, near the threshold too."""
    g = torch.Generator().manual_seed(int(threshold * 1000))
    a = lidar_boxes(400, seed=7)[:, :7]
    b = a.clone()
    b[:, :2] += (torch.rand(400, 2, generator=g, dtype=torch.float64) - 0.5) * 6  # from far apart to on top
    b[:, 3:5] *= 0.3 + torch.rand(400, 2, generator=g, dtype=torch.float64) * 2
    b[:, 6] += torch.rand(400, generator=g, dtype=torch.float64) * 3
    iou = torch.stack([lidarops.box_iou_bev(a[i:i + 1], b[i:i + 1])[0, 0] for i in range(400)])
    assert ((iou > threshold) & (iou < threshold + 0.05)).sum() >= 3  # pairs near the threshold exist
    for i in range(400):
        pair = torch.stack([a[i], b[i]]).to(device)
        keep = lidarops.nms_bev(pair, torch.tensor([0.9, 0.8], dtype=torch.float64, device=device), threshold)
        assert keep.tolist() == ([0] if iou[i] > threshold else [0, 1]), (i, float(iou[i]))
