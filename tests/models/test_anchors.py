"""lidarops.models.anchors: the residual coder, anchors, nearest-BEV IoU, the axis-aligned target assigner
and the direction bins, against values derived by hand and float64 references written here with plain
Python loops (OpenPCDet's semantics as described in the module docstring)."""
from __future__ import annotations

import math

import pytest
import torch

from lidarops.models.anchors import (AnchorGenerator, AxisAlignedTargetAssigner, ResidualCoder,
                                     boxes3d_nearest_bev_iou, decode_direction, flatten_anchors,
                                     get_direction_target, limit_period)

PI = math.pi
SQRT20 = math.sqrt(20.0)  # diagonal of a 4 x 2 anchor


def kitti_config(align_center: bool = False) -> list[dict]:
    """OpenPCDet's pointpillar.yaml ANCHOR_GENERATOR_CONFIG."""
    def one(name, size, bottom, matched, unmatched):
        return dict(class_name=name, anchor_sizes=[size], anchor_rotations=[0, 1.57], anchor_bottom_heights=[bottom],
                    align_center=align_center, feature_map_stride=2, matched_threshold=matched,
                    unmatched_threshold=unmatched)
    return [one("Car", [3.9, 1.6, 1.56], -1.78, 0.6, 0.45), one("Pedestrian", [0.8, 0.6, 1.73], -0.6, 0.5, 0.35),
            one("Cyclist", [1.76, 0.6, 1.73], -0.6, 0.5, 0.35)]


KITTI_RANGE = [0, -39.68, -3, 69.12, 39.68, 1]
KITTI_GRID = [432, 496, 1]
KITTI_CLASSES = ["Car", "Pedestrian", "Cyclist"]


# ---- float64 references (plain Python) ----

def ref_limit(v: float, offset: float, period: float) -> float:
    return v - math.floor(v / period + offset) * period


def ref_rect(b) -> tuple[float, float, float, float]:
    x, y, dx, dy, r = float(b[0]), float(b[1]), float(b[3]), float(b[4]), float(b[6])
    if abs(ref_limit(r, 0.5, PI)) >= PI / 4:
        dx, dy = dy, dx
    return x - dx / 2, y - dy / 2, x + dx / 2, y + dy / 2


def ref_iou(a, b) -> float:
    a, b = ref_rect(a), ref_rect(b)
    w = max(min(a[2], b[2]) - max(a[0], b[0]), 0.0)
    h = max(min(a[3], b[3]) - max(a[1], b[1]), 0.0)
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / max(union, 1e-6)


def ref_encode(g, a, sincos: bool = False) -> list[float]:
    g, a = [float(v) for v in g], [float(v) for v in a] + [0.0] * (len(g) - len(a))
    dxa, dya, dza = (max(v, 1e-5) for v in a[3:6])
    dxg, dyg, dzg = (max(v, 1e-5) for v in g[3:6])
    d = math.sqrt(dxa * dxa + dya * dya)
    out = [(g[0] - a[0]) / d, (g[1] - a[1]) / d, (g[2] - a[2]) / dza,
           math.log(dxg / dxa), math.log(dyg / dya), math.log(dzg / dza)]
    out += [math.cos(g[6]) - math.cos(a[6]), math.sin(g[6]) - math.sin(a[6])] if sincos else [g[6] - a[6]]
    return out + [gv - av for gv, av in zip(g[7:], a[7:])]


def ref_iou3d(a, b) -> float:
    """Rotated 3D IoU restated with shapely's polygons (the oracle): bird's-eye intersection x z overlap / union."""
    from shapely.geometry import Polygon

    def bev(x):
        c, s = math.cos(x[6]), math.sin(x[6])
        return Polygon([(x[0] + c * u * x[3] / 2 - s * v * x[4] / 2, x[1] + s * u * x[3] / 2 + c * v * x[4] / 2)
                        for u, v in ((1, 1), (-1, 1), (-1, -1), (1, -1))])

    dz = min(a[2] + a[5] / 2, b[2] + b[5] / 2) - max(a[2] - a[5] / 2, b[2] - b[5] / 2)
    inter = bev(a).intersection(bev(b)).area * max(dz, 0.0)
    union = a[3] * a[4] * a[5] + b[3] * b[4] * b[5] - inter
    return inter / union if union > 0 else 0.0


def ref_assign(anchors_list, gt, class_names, cfgs, norm=False, iou=None):
    """Per-anchor loops: labels (B, A), targets (B, A, 7), weights (B, A) in the flattened order; ``iou``: the
    overlap (default nearest-BEV, ``ref_iou``)."""
    iou = ref_iou if iou is None else iou
    nz, ny, nx = anchors_list[0].shape[:3]
    B = gt.shape[0]
    per_class = []  # per frame, per class: (labels, targets, weights) lists over the class's anchors
    for b in range(B):
        rows = [r.tolist() for r in gt[b] if r[-1] != 0]
        frame = []
        for cfg, anchors in zip(cfgs, anchors_list):
            anc = anchors.reshape(-1, 7).tolist()
            gts = [r for r in rows if class_names[int(r[-1]) - 1] == cfg["class_name"]]
            labels, targets, weights = [0] * len(anc), [[0.0] * 7 for _ in anc], [0.0] * len(anc)
            if gts:
                ious = [[iou(a, g) for g in gts] for a in anc]
                gt_max = [max(ious[i][j] for i in range(len(anc))) for j in range(len(gts))]
                gt_max = [-1.0 if m == 0 else m for m in gt_max]
                for i, a in enumerate(anc):
                    best = max(range(len(gts)), key=lambda j: (ious[i][j], -j))  # first on ties
                    amax = ious[i][best]
                    force = any(ious[i][j] == gt_max[j] for j in range(len(gts)))
                    fg = force or amax >= cfg["matched_threshold"]
                    label = int(gts[best][-1]) if fg else -1
                    if amax < cfg["unmatched_threshold"]:
                        label = 0
                    if force:
                        label = int(gts[best][-1])
                    labels[i] = label
                    if fg:
                        targets[i] = ref_encode(gts[best][:7], a)
                n_examples = max(sum(1 for v in labels if v >= 0), 1)
                weights = [(1.0 / n_examples if norm else 1.0) if v > 0 else 0.0 for v in labels]
            frame.append((labels, targets, weights))
        per_class.append(frame)
    # (y, x, class, z, per-class anchors per height): the head's channels at a location hold every height
    per_loc = [a.shape[3] * a.shape[4] for a in anchors_list]
    out_l, out_t, out_w = [], [], []
    for b in range(B):
        lab, tgt, wts = [], [], []
        for loc in range(ny * nx):
            for c, k in enumerate(per_loc):
                labels, targets, weights = per_class[b][c]
                for z in range(nz):
                    at = (z * ny * nx + loc) * k  # the class's own anchors are (z, y, x, size, rotation)
                    lab += labels[at:at + k]
                    tgt += targets[at:at + k]
                    wts += weights[at:at + k]
        out_l.append(lab), out_t.append(tgt), out_w.append(wts)
    return (torch.tensor(out_l, dtype=torch.int64), torch.tensor(out_t, dtype=torch.float64),
            torch.tensor(out_w, dtype=torch.float64))


# ---- limit_period ----

def test_limit_period_ranges():
    v = torch.tensor([-7.0, -PI, -0.1, 0.0, PI, 3.5, 7.0], dtype=torch.float64)
    half = limit_period(v)
    assert ((half >= -PI) & (half < PI)).all()
    assert torch.allclose(half, torch.tensor([-7 + 2 * PI, -PI, -0.1, 0, -PI, 3.5 - 2 * PI, 7 - 2 * PI],
                                             dtype=torch.float64))
    assert torch.allclose(limit_period(v, 0, 2 * PI), torch.tensor(
        [-7 + 4 * PI, PI, 2 * PI - 0.1, 0, PI, 3.5, 7 - 2 * PI], dtype=torch.float64))
    assert limit_period(3 * PI / 4, 0.5, PI) == pytest.approx(-PI / 4)


# ---- ResidualCoder ----

def random_boxes(n, extra, seed, dtype):
    g = torch.Generator().manual_seed(seed)
    b = torch.cat([torch.rand(n, 3, generator=g, dtype=torch.float64) * 40 - 20,
                   torch.rand(n, 3, generator=g, dtype=torch.float64) * 4 + 0.3,
                   torch.rand(n, 1, generator=g, dtype=torch.float64) * 2 * PI - PI,
                   torch.randn(n, extra, generator=g, dtype=torch.float64)], 1)
    return b.to(dtype)


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-4), (torch.float64, 1e-10)], ids=["f32", "f64"])
@pytest.mark.parametrize("sincos", [False, True], ids=["angle", "sincos"])
@pytest.mark.parametrize("extra", [0, 2])
def test_coder_round_trip(device, dtype, tol, sincos, extra):
    coder = ResidualCoder(7 + extra, encode_angle_by_sincos=sincos)
    assert coder.code_size == 7 + extra + sincos and coder.box_size == 7 + extra
    boxes = random_boxes(300, extra, 1, dtype).to(device)
    anchors = random_boxes(300, extra, 2, dtype).to(device)
    deltas = coder.encode(boxes, anchors)
    assert deltas.shape == (300, coder.code_size) and deltas.dtype == dtype
    back = coder.decode(deltas, anchors)
    assert back.shape == boxes.shape
    err = (back - boxes).abs()
    err[:, 6] = limit_period(back[:, 6] - boxes[:, 6]).abs()  # atan2 gives (-pi, pi]
    assert err.max() <= tol, f"max error {err.max():.3g} at {divmod(int(err.argmax()), err.shape[1])}"
    # the encoding matches the float64 formula row by row
    ref = torch.tensor([ref_encode(g, a, sincos) for g, a in zip(boxes.double().tolist(), anchors.double().tolist())],
                       dtype=torch.float64)
    assert (deltas.double().cpu() - ref).abs().max() <= tol


@pytest.mark.parametrize("sincos", [False, True], ids=["angle", "sincos"])
@pytest.mark.parametrize("extra", [0, 2])
def test_coder_decode_without_autograd_is_the_autograd_paths_result(device, sincos, extra):
    """decode writes its columns in place unless autograd needs the result: both paths give the same bits, with
    anchors broadcast over a batch, anchors without their extras, one box, and the gradient reaches the deltas."""
    coder = ResidualCoder(7 + extra, encode_angle_by_sincos=sincos)
    boxes = random_boxes(120, extra, 4, torch.float32).to(device)
    anchors = random_boxes(120, extra, 5, torch.float32).to(device)
    deltas = coder.encode(boxes, anchors)
    deltas = torch.stack([deltas, deltas.flip(0) * 0.5])  # (2, 120, code): the anchors broadcast
    for d, a in ((deltas, anchors), (deltas.double(), anchors.double()), (deltas, anchors[:, :7]),
                 (deltas[0, 3], anchors[3])):
        with torch.no_grad():
            fast = coder.decode(d, a)
        slow = coder.decode(d.clone().requires_grad_(), a)
        assert slow.requires_grad and fast.dtype == slow.dtype == d.dtype
        assert fast.shape == slow.shape and torch.equal(fast, slow.detach())
    d = deltas.clone().requires_grad_()
    coder.decode(d, anchors)[..., 3].sum().backward()
    assert d.grad is not None and bool((d.grad[..., 3] != 0).all())


def test_coder_encode_by_hand():
    g = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.5, 0.5, -1.0]], dtype=torch.float64)
    a = torch.tensor([[0.0, 0.0, 1.0, 2.0, 2.0, 3.0, 0.2, 0.1, 0.2]], dtype=torch.float64)
    d = math.sqrt(8.0)
    want = [1 / d, 2 / d, 2 / 3, math.log(2.0), math.log(2.5), math.log(2.0)]
    got = ResidualCoder().encode(g[:, :7], a[:, :7])[0].tolist()
    assert got == pytest.approx(want + [0.3], abs=1e-14)
    got = ResidualCoder(encode_angle_by_sincos=True).encode(g[:, :7], a[:, :7])[0].tolist()
    assert got == pytest.approx(want + [math.cos(0.5) - math.cos(0.2), math.sin(0.5) - math.sin(0.2)], abs=1e-14)
    got = ResidualCoder(9).encode(g, a)[0].tolist()
    assert got == pytest.approx(want + [0.3, 0.4, -1.2], abs=1e-14)
    # anchors without the extra columns: their extras count as zero (OpenPCDet's zero padding)
    got = ResidualCoder(9).encode(g, a[:, :7])[0].tolist()
    assert got == pytest.approx(want + [0.3, 0.5, -1.0], abs=1e-14)
    # dims clamped to 1e-5 (no -inf), inputs untouched
    g0 = g[:, :7].clone()
    g0[0, 3] = 0.0
    got = ResidualCoder().encode(g0, a[:, :7])
    assert got[0, 3].item() == pytest.approx(math.log(1e-5 / 2.0)) and g0[0, 3] == 0


def test_coder_broadcasts_anchors_over_batch():
    coder = ResidualCoder()
    anchors = random_boxes(50, 0, 3, torch.float64)
    deltas = torch.randn(4, 50, 7, dtype=torch.float64) * 0.1
    boxes = coder.decode(deltas, anchors)
    assert boxes.shape == (4, 50, 7)
    assert torch.allclose(boxes[2], coder.decode(deltas[2], anchors))
    assert torch.allclose(coder.encode(boxes, anchors), deltas, atol=1e-12)


# ---- anchors ----

def test_kitti_anchors_count_shape_and_order():
    gen = AnchorGenerator(KITTI_RANGE, kitti_config())
    assert gen.feature_map_sizes(KITTI_GRID) == [(216, 248)] * 3
    anchors, per_loc = gen.generate_anchors(gen.feature_map_sizes(KITTI_GRID))
    assert per_loc == [2, 2, 2]
    assert [tuple(a.shape) for a in anchors] == [(1, 248, 216, 1, 2, 7)] * 3
    flat, cls = gen.flat_anchors(KITTI_GRID)
    assert flat.shape == (321408, 7) == (216 * 248 * 6, 7) and flat.dtype == torch.float32
    car_z, small_z = -1.78 + 1.56 / 2, -0.6 + 1.73 / 2  # bottom + dz / 2
    first_location = [[0, -39.68, car_z, 3.9, 1.6, 1.56, 0], [0, -39.68, car_z, 3.9, 1.6, 1.56, 1.57],
                      [0, -39.68, small_z, 0.8, 0.6, 1.73, 0], [0, -39.68, small_z, 0.8, 0.6, 1.73, 1.57],
                      [0, -39.68, small_z, 1.76, 0.6, 1.73, 0], [0, -39.68, small_z, 1.76, 0.6, 1.73, 1.57]]
    assert torch.allclose(flat[:6], torch.tensor(first_location), atol=1e-5)
    assert cls[:12].tolist() == [0, 0, 1, 1, 2, 2] * 2
    # the next location steps along x (69.12 / 215), then y after 216 of them
    assert flat[6, 0].item() == pytest.approx(69.12 / 215, abs=1e-6) and flat[6, 1].item() == pytest.approx(-39.68)
    assert flat[216 * 6, 0].item() == 0 and flat[216 * 6, 1].item() == pytest.approx(-39.68 + 79.36 / 247, abs=1e-5)
    assert torch.allclose(flat[-1], torch.tensor([69.12, 39.68, small_z, 1.76, 0.6, 1.73, 1.57]), atol=1e-5)
    # flat order == per class (z, y, x, size, rotation) interleaved per location
    grid = flat.view(1, 248, 216, 3, 2, 7)
    for c in range(3):
        assert torch.equal(grid[:, :, :, c], anchors[c][:, :, :, 0])
    # the centres are OpenPCDet's torch.arange(start, stop + 1e-5, step) ones (to a float32 ulp)
    xs = torch.arange(0, 69.12 + 1e-5, 69.12 / 215, dtype=torch.float32)
    ys = torch.arange(-39.68, 39.68 + 1e-5, 79.36 / 247, dtype=torch.float32)
    assert (anchors[0][0, 0, :, 0, 0, 0] - xs).abs().max() <= 1e-5
    assert (anchors[0][0, :, 0, 0, 0, 1] - ys).abs().max() <= 1e-5


def test_kitti_anchors_align_center():
    gen = AnchorGenerator(KITTI_RANGE, kitti_config(align_center=True))
    anchors, _ = gen.generate_anchors(gen.feature_map_sizes(KITTI_GRID), dtype=torch.float64)
    a = anchors[0]
    # cells of 69.12 / 216 = 0.32 by 79.36 / 248 = 0.32: centres half a cell (0.16) in from the corners
    assert a[0, 0, 0, 0, 0, :2].tolist() == pytest.approx([0.16, -39.52], abs=1e-9)
    assert a[0, -1, -1, 0, 0, :2].tolist() == pytest.approx([68.96, 39.52], abs=1e-9)
    assert a[0, 0, 1, 0, 0, 0].item() == pytest.approx(0.48, abs=1e-9)
    assert a.dtype == torch.float64


def test_anchor_counts_exact_where_arange_is_not():
    cfg = [dict(class_name="A", anchor_sizes=[[1, 1, 1], [2, 1, 1]], anchor_rotations=[0, 0.5, 1.0],
                anchor_bottom_heights=[-1, 0], align_center=False)]
    gen = AnchorGenerator([0, 0, -1, 2e-5, 1, 1], cfg)
    # a step below arange's 1e-5 tolerance: OpenPCDet's construction gives 6 centres for 5 cells
    assert torch.arange(0, 2e-5 + 1e-5, 2e-5 / 4).numel() == 6
    anchors, per_loc = gen.generate_anchors([(5, 3)])
    assert anchors[0].shape == (2, 3, 5, 2, 3, 7) and per_loc == [12]
    # (z, ..., size, rotation): z is bottom + dz / 2 per height, sizes and rotations in config order
    a = anchors[0]
    assert a[:, 0, 0, 0, 0, 2].tolist() == pytest.approx([-0.5, 0.5])
    assert a[0, 0, 0, :, 0, 3].tolist() == [1, 2] and a[0, 0, 0, 0, :, 6].tolist() == pytest.approx([0, 0.5, 1])
    assert a[0, 0, -1, 0, 0, 0].item() == pytest.approx(2e-5) and a[0, -1, 0, 0, 0, 1].item() == 1
    for n in (2, 3, 7, 100, 215, 1001):
        for align in (False, True):
            g = AnchorGenerator([-3.3, 0.1, -1, 7.7, 9.9, 1], [dict(cfg[0], align_center=align)])
            assert g.generate_anchors([(n, n + 1)])[0][0].shape[1:3] == (n + 1, n)


# ---- nearest-BEV IoU ----

def iou_boxes(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    eps = 1e-7
    headings = [0, PI / 4, PI / 4 - eps, PI / 4 + eps, 3 * PI / 4, 3 * PI / 4 - eps, 3 * PI / 4 + eps, -PI, PI,
                -PI + eps, PI / 2, -PI / 4, -PI / 4 + eps, 5 * PI / 4, 2.0, -2.5]

    def make(n):
        b = random_boxes(n, 0, int(torch.randint(0, 10**6, (1,), generator=g)), torch.float64)
        b[:, :2] = torch.rand(n, 2, generator=g, dtype=torch.float64) * 6  # crowded, so many overlap
        b[:, 6] = torch.tensor(headings, dtype=torch.float64)[torch.randint(0, len(headings), (n,), generator=g)]
        b[:3, 3:5] = torch.tensor([[0.0, 0.0], [0.0, 1.5], [2.0, 0.0]], dtype=torch.float64)  # zero area
        return b
    return make(40), make(30)


def test_nearest_bev_iou_matches_reference(device):
    a, b = iou_boxes(0)
    got = boxes3d_nearest_bev_iou(a.to(device), b.to(device)).cpu()
    ref = torch.tensor([[ref_iou(x, y) for y in b.tolist()] for x in a.tolist()], dtype=torch.float64)
    assert got.shape == (40, 30) and not got.isnan().any()
    err = (got - ref).abs()
    assert err.max() <= 1e-12, f"max error {err.max():.3g} at {divmod(int(err.argmax()), 30)}"
    assert (ref > 0.05).sum() > 30  # the case exercises overlaps
    assert (got[:3] == 0).all() and (got[:, :3] == 0).all()
    # batched leading dims broadcast
    batched = boxes3d_nearest_bev_iou(torch.stack([a, a.flip(0)]), b)
    assert torch.equal(batched[0], got) and torch.equal(batched[1], got.flip(0))


def test_nearest_bev_iou_by_hand():
    box = lambda x, y, dx, dy, r: [x, y, 0.0, dx, dy, 1.0, r]  # noqa: E731
    a = torch.tensor([box(0, 0, 2, 2, 0), box(0, 0, 4, 2, 0), box(0, 0, 0, 0, 0)], dtype=torch.float64)
    b = torch.tensor([box(1, 0, 2, 2, 0), box(0, 0, 4, 2, PI / 2), box(0, 0, 4, 2, PI), box(0, 0, 4, 2, PI / 4),
                      box(0, 0, 4, 2, PI / 4 - 1e-3), box(0, 0, 0, 0, 0)], dtype=torch.float64)
    got = boxes3d_nearest_bev_iou(a, b)
    want = [[2 / 6, 4 / 8, 4 / 8, 4 / 8, 4 / 8, 0],  # 2x2 in a 4x2 or 2x4: 4 / 8
            [4 / 8, 4 / 12, 1, 4 / 12, 1, 0],  # heading pi/2 or exactly pi/4 turns the 4x2 to 2x4: 2x2 / 12
            [0, 0, 0, 0, 0, 0]]  # zero area against anything (even zero area): 0, no NaN
    assert (got - torch.tensor(want, dtype=torch.float64)).abs().max() <= 1e-12


# ---- assigner ----

def box(x, cls=1.0, y=0.0, z=0.0, dx=4.0, dy=2.0, dz=1.5, r=0.0):
    return [x, y, z, dx, dy, dz, r, cls]


def hand_case():
    """Car anchors 4 x 2 x 1.5 and Pedestrian anchors 0.8 x 0.6 x 1.7 at the same 10 x positions."""
    xs = [0.0, 0.5, 1.2, 20.0, 40.0, 60.0, 100.0, 104.0, 150.0, 200.0]
    car = torch.tensor([[x, 0, 0, 4, 2, 1.5, 0] for x in xs], dtype=torch.float64).view(1, 1, 10, 1, 1, 7)
    ped = torch.tensor([[x, 0, 0, 0.8, 0.6, 1.7, 0] for x in xs], dtype=torch.float64).view(1, 1, 10, 1, 1, 7)
    cfgs = [dict(class_name="Car", matched_threshold=0.6, unmatched_threshold=0.45),
            dict(class_name="Pedestrian", matched_threshold=0.5, unmatched_threshold=0.35)]
    zero = [0.0] * 8
    gt = torch.tensor([
        [box(0.0),  # A: on anchor 0 (IoU 1); anchor 0.5: 3.5 / 4.5 = 0.78 (positive); 1.2: 2.8 / 5.2 = 0.54 (ignored)
         box(42.5, z=0.3, dx=4.4, dy=2.2, dz=1.8, r=0.1),  # B: best anchor (40) only 3.4 / 14.28 = 0.24: forced
         box(60.4),  # C: anchor 60 at 3.6 / 4.4 = 0.82
         box(59.2),  # D: competes for anchor 60 (3.2 / 4.8 = 0.67), loses to C
         box(102.0, r=PI / 2),  # E: turned to 2 x 4, 1/7 with anchors 100 and 104 alike: both forced
         box(18.5), box(21.5),  # F, G: 2.5 / 5.5 = 0.455 with anchor 20 alike: forced, F (the first) its gt
         zero],
        [zero] * 8,  # an empty frame
        [box(150.0, cls=2, dx=0.8, dy=0.6, dz=1.7),  # a pedestrian on a pedestrian anchor
         box(300.0),  # a car far from every anchor: forces nothing
         box(0.0, cls=3),  # a Van (no anchors of its class): ignored, though it sits on car anchor 0
         zero, zero, zero, zero, zero]], dtype=torch.float64)
    return [car, ped], cfgs, gt


def test_assigner_hand_case():
    anchors, cfgs, gt = hand_case()
    assigner = AxisAlignedTargetAssigner(cfgs, ["Car", "Pedestrian", "Van"], ResidualCoder())
    out = assigner.assign_targets(anchors, gt)
    labels, targets, weights = out["box_cls_labels"], out["box_reg_targets"], out["reg_weights"]
    assert labels.shape == (3, 20) and labels.dtype == torch.int64
    assert targets.shape == (3, 20, 7) and weights.shape == (3, 20) and weights.dtype == torch.float64
    # flattened order (x, class): car anchors are the even entries, pedestrian anchors the odd ones
    car, ped = labels.view(3, 10, 2).unbind(2)
    assert car[0].tolist() == [1, 1, -1, 1, 1, 1, 1, 1, 0, 0]
    assert ped[0].tolist() == [0] * 10  # a class with no gt in the frame
    assert labels[1].tolist() == [0] * 20  # an empty frame
    assert car[2].tolist() == [0] * 10 and ped[2].tolist() == [0] * 8 + [2, 0]
    assert torch.equal(weights, (labels > 0).double())
    t = targets.view(3, 10, 2, 7)[:, :, 0]
    want = torch.zeros(10, 7, dtype=torch.float64)
    want[1, 0] = -0.5 / SQRT20
    want[3, 0] = -1.5 / SQRT20  # F, the first of the tied gts
    want[4] = torch.tensor([2.5 / SQRT20, 0, 0.3 / 1.5, math.log(1.1), math.log(1.1), math.log(1.2), 0.1],
                           dtype=torch.float64)
    want[5, 0] = 0.4 / SQRT20  # the argmax gt C, not D
    want[6, 0], want[6, 6] = 2 / SQRT20, PI / 2
    want[7, 0], want[7, 6] = -2 / SQRT20, PI / 2
    assert (t[0] - want).abs().max() <= 1e-12
    assert (targets[1] == 0).all() and (targets[2] == 0).all()  # the pedestrian's anchor is exact: zeros
    # norm_by_num_examples: positives weigh 1 / (anchors not ignored of the class in the frame)
    normed = AxisAlignedTargetAssigner(cfgs, ["Car", "Pedestrian", "Van"], ResidualCoder(),
                                       norm_by_num_examples=True).assign_targets(anchors, gt)
    assert torch.equal(normed["box_cls_labels"], labels)
    w = normed["reg_weights"].view(3, 10, 2)
    assert torch.allclose(w[0, :, 0], (car[0] > 0).double() / 9) and (w[0, :, 1] == 0).all()
    assert torch.allclose(w[2, :, 1], (ped[2] > 0).double() / 10)


def test_assigner_matches_loop_reference(device):
    cfgs = [dict(class_name="Car", anchor_sizes=[[4.0, 1.8, 1.5], [3.2, 1.6, 1.4]], anchor_rotations=[0, PI / 2],
                 anchor_bottom_heights=[-1.7], align_center=False, matched_threshold=0.6, unmatched_threshold=0.45),
            dict(class_name="Pedestrian", anchor_sizes=[[0.8, 0.6, 1.7]], anchor_rotations=[0, 0.7854, 1.57],
                 anchor_bottom_heights=[-0.6], align_center=True, matched_threshold=0.5, unmatched_threshold=0.35)]
    names = ["Car", "Pedestrian", "Van"]
    gen = AnchorGenerator([0, 0, -3, 12, 8, 1], cfgs)
    anchors, _ = gen.generate_anchors([(7, 5), (7, 5)], dtype=torch.float64)
    flat, _ = flatten_anchors(anchors)
    g = torch.Generator().manual_seed(0)
    kinds = torch.zeros(3, dtype=torch.int64)  # ignored, background, positive labels seen
    for trial in range(4):
        B, M = 4, 7
        gt = torch.zeros(B, M, 8, dtype=torch.float64)
        for b in range(B):
            n = [5, 0, 7, int(torch.randint(1, M + 1, (1,), generator=g))][b]
            for j in range(n):
                cls = int(torch.randint(1, 4, (1,), generator=g))
                size = [[4.0, 1.8, 1.5], [0.8, 0.6, 1.7], [5.0, 2.0, 2.0]][cls - 1]
                k = int(torch.randint(0, flat.shape[0], (1,), generator=g))
                centre = flat[k, :3] + torch.randn(3, generator=g, dtype=torch.float64) * 0.4
                dims = torch.tensor(size, dtype=torch.float64) * (0.7 + 0.6 * torch.rand(3, generator=g,
                                                                                         dtype=torch.float64))
                heading = float(torch.rand(1, generator=g, dtype=torch.float64)) * 2 * PI - PI
                gt[b, j] = torch.tensor([*centre.tolist(), *dims.tolist(), heading, cls], dtype=torch.float64)
            if n >= 2 and b == 2:
                gt[b, 1] = gt[b, 0]  # two identical gts: the first wins every argmax tie
        for norm in (False, True):
            assigner = AxisAlignedTargetAssigner(cfgs, names, ResidualCoder(), norm_by_num_examples=norm)
            out = assigner.assign_targets([a.to(device) for a in anchors], gt.to(device))
            ref_l, ref_t, ref_w = ref_assign(anchors, gt, names, cfgs, norm)
            got_l = out["box_cls_labels"].cpu()
            assert torch.equal(got_l, ref_l), f"trial {trial}: labels differ at {(got_l != ref_l).nonzero()[:5]}"
            err = (out["box_reg_targets"].cpu() - ref_t).abs()
            assert err.max() <= 1e-12, f"trial {trial}: max target error {err.max():.3g}"
            assert torch.allclose(out["reg_weights"].cpu(), ref_w, rtol=0, atol=1e-15)
        kinds += torch.stack([(ref_l < 0).sum(), (ref_l == 0).sum(), (ref_l > 0).sum()])
    print("ignored, background, positive:", kinds.tolist())
    assert (kinds >= 5).all()  # the case exercises every kind of label


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a GPU"))])
def test_assigner_match_height_matches_loop_reference(device):
    """MATCH_HEIGHT: anchors stacked 1 m apart in height (an aerial detector's drones) matched by rotated 3D IoU
    (shapely's polygons in the reference), beside rotated car anchors; the nearest-BEV assigner cannot tell the
    layers apart, this one gives each layer its own label."""
    pytest.importorskip("shapely")
    cfgs = [dict(class_name="Drone", anchor_sizes=[[0.7, 0.7, 0.3]], anchor_rotations=[0],
                 anchor_bottom_heights=[-1.0, 0.0, 1.0, 2.0], align_center=False, matched_threshold=0.5,
                 unmatched_threshold=0.35),
            dict(class_name="Car", anchor_sizes=[[4.0, 1.8, 1.5]], anchor_rotations=[0, PI / 2],
                 anchor_bottom_heights=[-1.7, -1.2, -0.7, -0.2], align_center=False, matched_threshold=0.6,
                 unmatched_threshold=0.45)]  # the classes share one grid: as many heights each
    names = ["Drone", "Car"]
    gen = AnchorGenerator([0, 0, -3, 6, 4, 4], cfgs)
    anchors, _ = gen.generate_anchors([(8, 6), (8, 6)], dtype=torch.float64)
    flat, _ = flatten_anchors(anchors)
    g = torch.Generator().manual_seed(1)
    B, M = 3, 5
    gt = torch.zeros(B, M, 8, dtype=torch.float64)
    for b in range(B):
        for j in range([5, 3, 4][b]):
            cls = 1 if j % 3 else 2
            size = [[0.7, 0.7, 0.3], [4.0, 1.8, 1.5]][cls - 1]
            k = int(torch.randint(0, flat.shape[0], (1,), generator=g))
            centre = flat[k, :3] + torch.randn(3, generator=g, dtype=torch.float64) * torch.tensor([0.1, 0.1, 0.25])
            dims = torch.tensor(size, dtype=torch.float64) * (0.8 + 0.4 * torch.rand(3, generator=g, dtype=torch.float64))
            heading = float(torch.rand(1, generator=g, dtype=torch.float64)) * 2 * PI - PI
            gt[b, j] = torch.tensor([*centre.tolist(), *dims.tolist(), heading, cls], dtype=torch.float64)
    assigner = AxisAlignedTargetAssigner(cfgs, names, ResidualCoder(), match_height=True)
    out = assigner.assign_targets([a.to(device) for a in anchors], gt.to(device))
    ref_l, ref_t, ref_w = ref_assign(anchors, gt, names, cfgs, iou=ref_iou3d)
    got_l = out["box_cls_labels"].cpu()
    assert torch.equal(got_l, ref_l), f"labels differ at {(got_l != ref_l).nonzero()[:5]}"
    assert (out["box_reg_targets"].cpu() - ref_t).abs().max() <= 1e-9
    assert torch.equal(out["reg_weights"].cpu(), ref_w)
    assert (ref_l == 1).sum() >= 5 and (ref_l == 2).sum() >= 3
    # the drone layers at a location: 3D matching tells them apart, nearest-BEV matching cannot
    drone = got_l.view(B, 6, 8, 12)[..., :4]  # (B, y, x, layer): per location the 4 drone anchors come first
    layered = (drone > 0).any(-1) & ~(drone > 0).all(-1)
    bev = AxisAlignedTargetAssigner(cfgs, names, ResidualCoder()).assign_targets(anchors, gt)["box_cls_labels"]
    bev_drone = bev.view(B, 6, 8, 12)[..., :4]
    assert layered.any() and ((bev_drone > 0).any(-1) == (bev_drone > 0).all(-1)).all()


def test_stacked_anchors_follow_the_head_channels():
    """Several bottom heights: a location's heights are its channels (conv_cls's output, permuted to (B, H, W, A)
    and flattened), so the flat anchors and the assigner's labels must step through the heights fastest after the
    class, and x, y outside. OpenPCDet's own flattening puts z outermost, which pairs an anchor with the output
    of another location and height: a model trained that way learns nothing."""
    cfgs = [dict(class_name="Drone", anchor_sizes=[[0.7, 0.7, 1.0]], anchor_rotations=[0, PI / 2],
                 anchor_bottom_heights=[-1.0, 0.0, 1.0], align_center=False, matched_threshold=0.2,
                 unmatched_threshold=0.1)]
    gen = AnchorGenerator([0, 0, -3, 7, 5, 3], cfgs)
    anchors, per_loc = gen.generate_anchors([(8, 6)])
    assert per_loc == [6] and anchors[0].shape == (3, 6, 8, 1, 2, 7)
    flat, _ = flatten_anchors(anchors)
    head = flat.view(6, 8, 3, 2, 7)  # (y, x, channel = (z, rotation)) as the head's outputs read
    for y, x, z, r in [(0, 0, 0, 0), (0, 0, 2, 1), (3, 5, 1, 0), (5, 7, 2, 1)]:
        assert torch.equal(head[y, x, z, r], anchors[0][z, y, x, 0, r])
    assert torch.equal(head[..., 2].unique(), torch.tensor([-0.5, 0.5, 1.5]))  # bottom + dz / 2
    # a drone at one location and height: its positive anchors are at that location's channel of its layer
    gt = torch.tensor([[[3.0, 2.0, 0.6, 0.7, 0.7, 0.3, 0.0, 1]]])
    labels = AxisAlignedTargetAssigner(cfgs, ["Drone"], ResidualCoder(), match_height=True).assign_targets(
        anchors, gt)["box_cls_labels"][0].view(6, 8, 3, 2)
    pos = (labels > 0).nonzero().tolist()
    assert pos and all(abs(head[y, x, z, r, 0] - 3.0) < 0.6 and abs(head[y, x, z, r, 1] - 2.0) < 0.6 and z == 1
                       for y, x, z, r in pos)


def test_assigner_kitti_anchors_consistent_with_flat_order():
    gen = AnchorGenerator(KITTI_RANGE, kitti_config())
    anchors, _ = gen.generate_anchors(gen.feature_map_sizes(KITTI_GRID))
    flat, cls = flatten_anchors(anchors)
    gt = torch.tensor([[[20.0, 5.0, -1.0, 3.9, 1.6, 1.56, 0.2, 1], [30.0, -8.0, -0.5, 0.8, 0.6, 1.7, 1.5, 2],
                        [45.0, 10.0, -0.5, 1.7, 0.6, 1.7, 3.0, 3], [0] * 8]])
    out = AxisAlignedTargetAssigner(kitti_config(), KITTI_CLASSES, ResidualCoder()).assign_targets(anchors, gt)
    labels = out["box_cls_labels"][0]
    assert labels.shape == (321408,)
    pos = labels > 0
    assert set(labels[pos].tolist()) == {1, 2, 3}
    assert torch.equal(cls[pos] + 1, labels[pos])  # a positive anchor belongs to its label's class
    # and lies near its gt, which decoding its target recovers
    decoded = ResidualCoder().decode(out["box_reg_targets"][0][pos], flat[pos])
    assert torch.allclose(decoded, gt[0, labels[pos] - 1, :7], atol=1e-4)


# ---- direction bins ----

@pytest.mark.parametrize("heading,want", [(0.0, 1), (0.79, 0), (0.78, 1), (3.92, 0), (3.93, 1), (-2.36, 0),
                                          (-2.35, 1), (PI / 2, 0), (-PI / 2, 1), (7.0, 1), (-7.0, 1), (-4.0, 0)])
def test_direction_target_by_hand(heading, want):
    # dir_offset 0.78539: bin 0 holds headings in [0.78539, 0.78539 + pi) modulo 2 pi
    anchors = torch.tensor([[0.0, 0, 0, 1, 1, 1, 1.0]], dtype=torch.float64)
    reg = torch.tensor([[0.0, 0, 0, 0, 0, 0, heading - 1.0]], dtype=torch.float64)  # rot_gt = anchor + target
    assert get_direction_target(anchors, reg, one_hot=False).tolist() == [want]
    hot = get_direction_target(anchors, reg)
    assert hot.dtype == torch.float64 and hot.tolist() == [[1.0 - want, float(want)]]


def test_direction_target_four_bins():
    off = 0.78539
    rel = torch.tensor([0.1, PI / 2 + 0.1, PI + 0.1, -0.1, 2 * PI + 0.1], dtype=torch.float64)
    reg = torch.zeros(5, 7, dtype=torch.float64)
    reg[:, 6] = rel + off
    bins = get_direction_target(torch.zeros(5, 7, dtype=torch.float64), reg, one_hot=False, num_bins=4)
    assert bins.tolist() == [0, 1, 2, 3, 0]


@pytest.mark.parametrize("num_bins", [2, 3])
def test_decode_direction_recovers_heading(device, num_bins):
    g = torch.Generator().manual_seed(num_bins)
    heading = (torch.rand(2, 500, generator=g, dtype=torch.float64) * 4 * PI - 2 * PI).to(device)
    reg = torch.zeros(2, 500, 7, dtype=torch.float64, device=device)
    reg[..., 6] = heading
    anchors = torch.zeros(500, 7, dtype=torch.float64, device=device)  # broadcast over the batch
    bins = get_direction_target(anchors, reg, one_hot=False, num_bins=num_bins)
    assert bins.shape == (2, 500) and bins.min() >= 0 and bins.max() == num_bins - 1
    period = 2 * PI / num_bins
    # the regressed heading is known modulo the bin period only: any multiple of it must decode back
    for m in (-2, -1, 0, 1, 3):
        decoded = decode_direction(heading + m * period, bins, num_bins=num_bins)
        diff = limit_period(decoded - heading, 0.5, 2 * PI).abs()
        assert diff.max() <= 1e-9
    assert decode_direction(torch.tensor([0.5]), torch.tensor([1]), dir_offset=0.0).item() == pytest.approx(0.5 + PI)


# ---- errors ----

def test_errors_name_the_argument():
    f64 = torch.float64
    coder = ResidualCoder()
    cases = [
        (lambda: coder.encode(torch.zeros(5, 6), torch.zeros(5, 7)), "boxes"),
        (lambda: coder.encode(torch.zeros(5, 7), torch.zeros(5, 7, dtype=torch.int64)), "anchors"),
        (lambda: coder.encode(torch.zeros(5, 7), torch.zeros(5, 7, dtype=f64)), "anchors has dtype"),
        (lambda: coder.encode(torch.zeros(5, 7), torch.zeros(4, 7)), "do not broadcast"),
        (lambda: ResidualCoder(encode_angle_by_sincos=True).decode(torch.zeros(5, 7), torch.zeros(5, 7)), "deltas"),
        (lambda: ResidualCoder(6), "code_size"),
        (lambda: boxes3d_nearest_bev_iou(torch.zeros(7), torch.zeros(3, 7)), "boxes_a"),
        (lambda: boxes3d_nearest_bev_iou(torch.zeros(2, 7), torch.zeros(3, 5)), "boxes_b"),
        (lambda: AnchorGenerator([0, 0, 0, 1, 1], kitti_config()), "anchor_range"),
        (lambda: AnchorGenerator(KITTI_RANGE, [{"class_name": "Car"}]), "anchor_sizes"),
        (lambda: AnchorGenerator(KITTI_RANGE, kitti_config()).generate_anchors([(4, 4)]), "grid_sizes"),
        (lambda: AnchorGenerator(KITTI_RANGE, kitti_config()[:1]).generate_anchors([(1, 4)]), "grid_sizes[0][0]"),
        (lambda: AxisAlignedTargetAssigner([{"class_name": "Car"}], ["Car"], coder), "matched_threshold"),
        (lambda: get_direction_target(torch.zeros(3, 7), torch.zeros(3, 7), num_bins=0), "num_bins"),
        (lambda: decode_direction(torch.zeros(3), torch.zeros(3)), "dir_labels"),
    ]
    for call, word in cases:
        with pytest.raises(ValueError, match=word.replace("[", r"\[").replace("]", r"\]")):
            call()


def test_assigner_errors():
    anchors, cfgs, gt = hand_case()
    assigner = AxisAlignedTargetAssigner(cfgs, ["Car", "Pedestrian", "Van"], ResidualCoder())
    with pytest.raises(ValueError, match="gt_boxes_with_classes must be"):
        assigner.assign_targets(anchors, gt[..., :7])
    with pytest.raises(ValueError, match="gt_boxes_with_classes has dtype"):
        assigner.assign_targets(anchors, gt.float())
    for bad in (4.0, 1.5, -1.0):
        g = gt.clone()
        g[0, 5, 7] = bad
        with pytest.raises(ValueError, match="class ids"):
            assigner.assign_targets(anchors, g)
    with pytest.raises(ValueError, match=r"all_anchors\[1\]"):
        assigner.assign_targets([anchors[0], anchors[1][:, :, :5]], gt)
    with pytest.raises(ValueError, match="one tensor per class"):
        assigner.assign_targets(anchors[:1], gt)

