"""lidarops.compat.pcdet against float64 / NumPy re-implementations of OpenPCDet's kernels.

The references follow open-mmlab/OpenPCDet ``pcdet/ops``: ``iou3d_nms/src/iou3d_nms_kernel.cu`` (rotated
BEV overlap; NMS suppresses when IoU > thresh; ``nms_normal`` on the axis-aligned rectangles),
``iou3d_nms_utils.boxes_iou3d_gpu`` (overlap over the union clamped at 1e-6),
``roiaware_pool3d/src/roiaware_pool3d{.cpp,_kernel.cu}`` (``|z - cz| <= dz/2`` and ``|local| < d/2 +
margin``, margin 1e-2 on the CPU, 1e-5 on CUDA; the first box wins), ``pointnet2_stack/src`` (local ball
indices with -1 for an empty ball, global three_nn and FPS indices). Box overlaps come from the
world-frame polygon clipping in ``lidarops.ops.boxes`` (another route than the kernels').
"""
from __future__ import annotations

import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from lidarops.compat.pcdet import iou3d_nms_utils, pointnet2_batch, pointnet2_stack, roiaware_pool3d_utils
from lidarops.ops.boxes import _box_iou_bev_reference, _box_overlap_bev_reference, _nms_bev_reference
from helpers.compat import lidar_like, sqdist, to_t


def random_boxes(n, rng, spread=10.0):
    b = np.zeros((n, 7))
    b[:, :2] = rng.uniform(-spread, spread, (n, 2))
    b[:, 2] = rng.uniform(-1, 1, n)
    b[:, 3:6] = rng.uniform(0.5, 4.0, (n, 3))
    b[:, 6] = rng.uniform(-math.pi, math.pi, n)
    return b


# ---------------------------------------------------------------------------------------------
# iou3d_nms_utils
# ---------------------------------------------------------------------------------------------

def ref_iou3d(a, b, paired=False):
    a64, b64 = torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64)
    if paired:
        ov = torch.stack([_box_overlap_bev_reference(a64[i:i + 1], b64[i:i + 1])[0, 0] for i in range(len(a64))])
        bb = b64
        h = (torch.minimum(a64[:, 2] + a64[:, 5] / 2, bb[:, 2] + bb[:, 5] / 2)
             - torch.maximum(a64[:, 2] - a64[:, 5] / 2, bb[:, 2] - bb[:, 5] / 2)).clamp_min(0)
        inter = ov * h
        return (inter / (a64[:, 3:6].prod(1) + bb[:, 3:6].prod(1) - inter).clamp_min(1e-6)).numpy()
    ov = _box_overlap_bev_reference(a64, b64)
    h = (torch.minimum(a64[:, None, 2] + a64[:, None, 5] / 2, b64[None, :, 2] + b64[None, :, 5] / 2)
         - torch.maximum(a64[:, None, 2] - a64[:, None, 5] / 2, b64[None, :, 2] - b64[None, :, 5] / 2)).clamp_min(0)
    inter = ov * h
    union = a64[:, 3:6].prod(1)[:, None] + b64[:, 3:6].prod(1)[None] - inter
    return (inter / union.clamp_min(1e-6)).numpy()


@pytest.mark.parametrize("n,m", [(0, 3), (5, 0), (17, 23)])
def test_iou_faces_match_references(device, n, m):
    rng = np.random.default_rng(n * 100 + m)
    a, b = random_boxes(n, rng, 4.0), random_boxes(m, rng, 4.0)
    b[: min(n, m) // 2] = a[: min(n, m) // 2]  # identical pairs: IoU 1
    ta, tb = to_t(a, device), to_t(b, device)
    want_bev = _box_iou_bev_reference(torch.as_tensor(a), torch.as_tensor(b)).numpy() if n and m else np.zeros((n, m))
    for got in (iou3d_nms_utils.boxes_iou_bev(ta, tb), iou3d_nms_utils.boxes_bev_iou_cpu(ta, tb)):
        assert got.shape == (n, m) and got.dtype == torch.float32 and got.device == ta.device
        np.testing.assert_allclose(got.cpu().numpy(), want_bev, atol=2e-5)
    got3 = iou3d_nms_utils.boxes_iou3d_gpu(ta, tb)
    np.testing.assert_allclose(got3.cpu().numpy(), ref_iou3d(a, b) if n and m else np.zeros((n, m)), atol=2e-5)


def test_bev_iou_cpu_takes_numpy_and_float64():
    rng = np.random.default_rng(1)
    a, b = random_boxes(6, rng, 3.0), random_boxes(4, rng, 3.0)
    got = iou3d_nms_utils.boxes_bev_iou_cpu(a, b)  # float64 arrays: float64 out (OpenPCDet: float32 only)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64
    np.testing.assert_allclose(got, _box_iou_bev_reference(torch.as_tensor(a), torch.as_tensor(b)).numpy(), atol=1e-9)


def test_paired_iou3d(device):
    rng = np.random.default_rng(2)
    n = iou3d_nms_utils.PAIR_BLOCK + 37  # more than one block
    a = random_boxes(n, rng, 2.0)
    b = a + rng.normal(0, 0.3, a.shape) * np.array([1, 1, 1, 0.2, 0.2, 0.2, 1])
    want = ref_iou3d(a, b, paired=True)
    got = iou3d_nms_utils.boxes_aligned_iou3d_gpu(to_t(a, device), to_t(b, device))
    assert got.shape == (n, 1)
    np.testing.assert_allclose(got[:, 0].cpu().numpy(), want, atol=2e-5)
    np.testing.assert_allclose(iou3d_nms_utils.paired_boxes_iou3d_gpu(to_t(a, device), to_t(b, device)).cpu().numpy(),
                               want, atol=2e-5)
    with pytest.raises(ValueError, match="same number of boxes"):
        iou3d_nms_utils.paired_boxes_iou3d_gpu(to_t(a, device), to_t(b[:-1], device))


def ref_nms_normal(boxes, scores, thresh):
    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    keep = []
    for i in order:
        ok = True
        for j in keep:
            w = min(boxes[i, 0] + boxes[i, 3] / 2, boxes[j, 0] + boxes[j, 3] / 2) - max(boxes[i, 0] - boxes[i, 3] / 2,
                                                                                      boxes[j, 0] - boxes[j, 3] / 2)
            h = min(boxes[i, 1] + boxes[i, 4] / 2, boxes[j, 1] + boxes[j, 4] / 2) - max(boxes[i, 1] - boxes[i, 4] / 2,
                                                                                      boxes[j, 1] - boxes[j, 4] / 2)
            inter = max(w, 0) * max(h, 0)
            if inter / max(boxes[i, 3] * boxes[i, 4] + boxes[j, 3] * boxes[j, 4] - inter, 1e-8) > thresh:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


@pytest.mark.parametrize("pre_maxsize", [None, 20])
def test_nms_faces(device, pre_maxsize):
    rng = np.random.default_rng(3)
    boxes = random_boxes(60, rng, 6.0)
    scores = rng.permutation(60).astype(np.float64) / 60  # distinct: OpenPCDet's order is then defined
    tb, ts = to_t(boxes, device), to_t(scores, device)
    keep, other = iou3d_nms_utils.nms_gpu(tb, ts, 0.1, pre_maxsize=pre_maxsize, unused_option=1)
    assert other is None and keep.dtype == torch.int64 and keep.device == tb.device
    want = _nms_bev_reference(torch.as_tensor(boxes), torch.as_tensor(scores), 0.1, pre_max=pre_maxsize)
    assert keep.cpu().tolist() == want.tolist()
    keep_n, _ = iou3d_nms_utils.nms_normal_gpu(tb, ts, 0.1)
    assert keep_n.cpu().tolist() == ref_nms_normal(boxes, scores, 0.1)
    assert keep_n.cpu().tolist() != keep.cpu().tolist() or pre_maxsize  # the heading matters in these boxes


def test_nms_bad_input_names_argument():
    boxes = torch.zeros(4, 7)
    with pytest.raises(ValueError, match=r"scores must be a \(N,\) tensor with N = 4"):
        iou3d_nms_utils.nms_gpu(boxes, torch.zeros(3), 0.1)
    with pytest.raises(ValueError, match=r"boxes must be a floating \(N, 7\)"):
        iou3d_nms_utils.nms_gpu(torch.zeros(4, 6), torch.zeros(4), 0.1)
    with pytest.raises(ValueError, match="boxes_b"):
        iou3d_nms_utils.boxes_iou_bev(torch.zeros(2, 7), torch.zeros(2, 8))


# ---------------------------------------------------------------------------------------------
# roiaware_pool3d_utils
# ---------------------------------------------------------------------------------------------

def ref_in_boxes(points, boxes, margin):
    """(N, P) bool, float64, and (N, P) bool of points within 1e-4 of a face (either answer is right)."""
    p, b = points.astype(np.float64), boxes.astype(np.float64)
    sx, sy = p[None, :, 0] - b[:, None, 0], p[None, :, 1] - b[:, None, 1]
    c, s = np.cos(-b[:, 6:7]), np.sin(-b[:, 6:7])
    lx, ly = sx * c - sy * s, sx * s + sy * c
    dz = np.abs(p[None, :, 2] - b[:, None, 2]) - b[:, None, 5] / 2
    ex, ey = np.abs(lx) - b[:, None, 3] / 2 - margin, np.abs(ly) - b[:, None, 4] / 2 - margin
    inside = (dz <= 0) & (ex < 0) & (ey < 0)
    near = (np.abs(dz) < 1e-4) | (np.abs(ex) < 1e-4) | (np.abs(ey) < 1e-4)
    return inside, near


def scene(rng, n_boxes=8, n_points=3000):
    boxes = random_boxes(n_boxes, rng, 8.0)
    pts = np.concatenate([rng.uniform(-12, 12, (n_points, 3)) * [1, 1, 0.2],
                          (boxes[:, None, :3] + rng.uniform(-1, 1, (n_boxes, 100, 3)) * boxes[:, None, 3:6] / 1.9).reshape(-1, 3)])
    return pts.reshape(-1, 3).astype(np.float32), boxes.astype(np.float32)


def test_points_in_boxes_cpu_mask_with_margin(device):
    rng = np.random.default_rng(4)
    pts, boxes = scene(rng)
    boxes[1] = boxes[0]  # overlapping boxes: a point is in both (a mask, not a label)
    got = roiaware_pool3d_utils.points_in_boxes_cpu(to_t(pts, device), to_t(boxes, device))
    assert got.dtype == torch.int32 and got.shape == (8, len(pts))
    want, near = ref_in_boxes(pts, boxes, roiaware_pool3d_utils.CPU_MARGIN)
    g = got.cpu().numpy().astype(bool)
    assert ((g == want) | near).all() and want.sum() > 300
    assert (g[0] == g[1]).all() and g[0].any()
    # the 1 cm margin: a point 5 mm outside a face is in
    b = np.array([[0, 0, 0, 2, 2, 2, 0]], np.float32)
    p = np.array([[1.005, 0, 0], [1.02, 0, 0], [0, 0, 1.005]], np.float32)
    assert roiaware_pool3d_utils.points_in_boxes_cpu(p, b).tolist() == [[1, 0, 0]]  # numpy in, numpy out


def test_points_in_boxes_gpu_first_box(device):
    rng = np.random.default_rng(5)
    pts, boxes = zip(*(scene(rng, 6, 500) for _ in range(2)))
    n = min(len(p) for p in pts)
    pts = np.stack([p[:n] for p in pts])
    boxes = np.stack(boxes)
    boxes[1, 3] = boxes[1, 2]  # overlapping: the first index wins
    got = roiaware_pool3d_utils.points_in_boxes_gpu(to_t(pts, device), to_t(boxes, device))
    assert got.dtype == torch.int32 and got.shape == (2, n)
    for bi in range(2):
        inside, near = ref_in_boxes(pts[bi], boxes[bi], roiaware_pool3d_utils.GPU_MARGIN)
        want = np.where(inside.any(0), inside.argmax(0), -1)
        ok = (got[bi].cpu().numpy() == want) | near.any(0)
        assert ok.all() and (want >= 0).sum() > 50
    with pytest.raises(ValueError, match="same batch size"):
        roiaware_pool3d_utils.points_in_boxes_gpu(to_t(pts, device), to_t(boxes[:1], device))


def test_points_in_boxes_bad_boxes_named():
    with pytest.raises(ValueError, match="boxes"):
        roiaware_pool3d_utils.points_in_boxes_cpu(np.zeros((3, 3), np.float32), np.array([[0, 0, 0, -1, 1, 1, 0]], np.float32))
    with pytest.raises(ValueError, match=r"points must be a floating \(num_points, 3\)"):
        roiaware_pool3d_utils.points_in_boxes_cpu(np.zeros((3, 4), np.float32), np.zeros((1, 7), np.float32))


# ---------------------------------------------------------------------------------------------
# pointnet2 (batch)
# ---------------------------------------------------------------------------------------------

def ref_fps(x, m):
    temp, old, out = np.full(len(x), 1e10), 0, [0]
    for _ in range(1, m):
        temp = np.minimum(temp, sqdist(x[old:old + 1], x)[0])
        old = int(np.argmax(temp))
        out.append(old)
    return out


def ref_ball(xyz, centers, r, nsample):
    out = np.zeros((len(centers), nsample), np.int64)
    d = sqdist(centers, xyz)
    for i in range(len(centers)):
        hits = np.flatnonzero(d[i] < np.float32(r) * np.float32(r))[:nsample]
        if len(hits):
            out[i] = hits[0]
            out[i, :len(hits)] = hits
    return out, np.array([len(np.flatnonzero(d[i] < np.float32(r) * np.float32(r))) == 0 for i in range(len(centers))])


def ref_three_nn(q, p):
    d = sqdist(q, p)
    idx = np.argsort(d, axis=1, kind="stable")[:, :3]
    return np.sqrt(np.take_along_axis(d, idx, 1)), idx


def test_pointnet2_batch(device):
    rng = np.random.default_rng(6)
    x = np.stack([lidar_like(400, rng) for _ in range(2)])
    tx = to_t(x, device)
    idx = pointnet2_batch.farthest_point_sample(tx, 32)
    assert idx.dtype == torch.int32 and [ref_fps(x[b], 32) for b in range(2)] == idx.cpu().tolist()
    centers = x[:, :40]
    ball = pointnet2_batch.ball_query(1.5, 8, tx, to_t(centers, device))
    for b in range(2):
        np.testing.assert_array_equal(ball[b].cpu().numpy(), ref_ball(x[b], centers[b], 1.5, 8)[0])
    dist, nn = pointnet2_batch.three_nn(to_t(centers, device), tx)
    for b in range(2):
        d_ref, i_ref = ref_three_nn(centers[b], x[b])
        np.testing.assert_array_equal(nn[b].cpu().numpy(), i_ref)
        np.testing.assert_allclose(dist[b].cpu().numpy(), d_ref, rtol=1e-6)
    feats = torch.randn(2, 5, 400, dtype=torch.float64, device=device, requires_grad=True)
    w = torch.rand(2, 40, 3, dtype=torch.float64, device=device)
    out = pointnet2_batch.three_interpolate(feats, nn, w)
    want = (feats.detach().cpu().numpy()[np.arange(2)[:, None, None, None], np.arange(5)[None, :, None, None],
                                         nn.cpu().numpy()[:, None].astype(np.int64)] * w.cpu().numpy()[:, None]).sum(-1)
    np.testing.assert_allclose(out.detach().cpu().numpy(), want, rtol=1e-12)
    small = feats[:, :2, :50].detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda f: pointnet2_batch.three_interpolate(f, nn % 50, w), (small,))
    grouped = pointnet2_batch.QueryAndGroup(1.5, 8)(tx, to_t(centers, device), feats.detach().float())
    assert grouped.shape == (2, 3 + 5, 40, 8)
    rel = x[0][ref_ball(x[0], centers[0], 1.5, 8)[0]] - centers[0][:, None]
    np.testing.assert_allclose(grouped[0, :3].permute(1, 2, 0).cpu().numpy(), rel, atol=1e-6)
    np.testing.assert_allclose(grouped[0, 3:].cpu().numpy(), feats.detach().float().cpu().numpy()[0][:, ref_ball(
        x[0], centers[0], 1.5, 8)[0]])
    assert pointnet2_batch.GroupAll()(tx, None, feats.detach().float()).shape == (2, 8, 1, 400)
    g = pointnet2_batch.gather_operation(feats, idx)
    np.testing.assert_array_equal(g[1, 2].detach().cpu().numpy(), feats[1, 2].detach().cpu().numpy()[idx[1].cpu().numpy()])


# ---------------------------------------------------------------------------------------------
# pointnet2 (stack)
# ---------------------------------------------------------------------------------------------

def test_pointnet2_stack(device):
    rng = np.random.default_rng(7)
    counts = [300, 0, 150]
    parts = [lidar_like(c, rng) if c else np.zeros((0, 3), np.float32) for c in counts]
    xyz = np.concatenate(parts)
    starts = np.cumsum([0] + counts[:-1])
    cnt = torch.tensor(counts, dtype=torch.int32, device=device)
    tx = to_t(xyz, device)
    # FPS: global indices; an example without points repeats its start index (the kernel's writes)
    got = pointnet2_stack.stack_farthest_point_sample(tx, cnt, [10, 3, 12])
    want = ref_fps(parts[0], 10) + [int(starts[1])] * 3 + [int(starts[2]) + i for i in ref_fps(parts[2], 12)]
    assert got.dtype == torch.int32 and got.cpu().tolist() == want
    # ball query: local indices, empty mask
    centers = [parts[0][:20], rng.uniform(-5, 5, (4, 3)).astype(np.float32), parts[2][:7] + 100.0]
    ccnt = torch.tensor([len(c) for c in centers], dtype=torch.int32, device=device)
    idx, empty = pointnet2_stack.ball_query(2.0, 6, tx, cnt, to_t(np.concatenate(centers), device), ccnt)
    want_idx, want_empty = [], []
    for part, c in zip(parts, centers):
        if len(part):
            i, e = ref_ball(part, c, 2.0, 6)
        else:
            i, e = np.zeros((len(c), 6), np.int64), np.ones(len(c), bool)
        want_idx.append(np.where(e[:, None], 0, i))
        want_empty.append(e)
    np.testing.assert_array_equal(idx.cpu().numpy(), np.concatenate(want_idx))
    np.testing.assert_array_equal(empty.cpu().numpy(), np.concatenate(want_empty))
    assert empty.cpu().numpy()[20:].all() and not empty.cpu().numpy()[:20].any()
    feats = torch.randn(len(xyz), 4, device=device)
    new, idx2 = pointnet2_stack.QueryAndGroup(2.0, 6)(tx, cnt, to_t(np.concatenate(centers), device), ccnt, feats)
    assert new.shape == (31, 7, 6) and torch.equal(idx2, idx)
    assert (new[20:] == 0).all()  # empty balls
    np.testing.assert_allclose(new[:20, 3:].cpu().numpy(), feats.cpu().numpy()[idx[:20].cpu().numpy()].transpose(0, 2, 1))
    # three_nn: indices into the whole stacked array
    q = [parts[0][::7], np.zeros((0, 3), np.float32), parts[2][::5]]
    qcnt = torch.tensor([len(v) for v in q], dtype=torch.int32, device=device)
    dist, nn = pointnet2_stack.three_nn(to_t(np.concatenate(q), device), qcnt, tx, cnt)
    refs = [ref_three_nn(q[0], parts[0]), ref_three_nn(q[2], parts[2])]
    np.testing.assert_array_equal(nn.cpu().numpy(), np.concatenate([refs[0][1], refs[1][1] + starts[2]]))
    np.testing.assert_allclose(dist.cpu().numpy(), np.concatenate([refs[0][0], refs[1][0]]), rtol=1e-6)
    w = torch.rand(nn.shape[0], 3, device=device)
    out = pointnet2_stack.three_interpolate(feats, nn, w)
    want = (feats.cpu().numpy()[nn.cpu().numpy().astype(np.int64)] * w.cpu().numpy()[..., None]).sum(1)
    np.testing.assert_allclose(out.cpu().numpy(), want, rtol=1e-5, atol=1e-6)


def test_stack_grouping_gradient():
    f = torch.randn(12, 3, dtype=torch.float64, requires_grad=True)
    cnt, icnt = torch.tensor([5, 7]), torch.tensor([2, 1])
    idx = torch.tensor([[0, 4], [1, 1], [6, 0]], dtype=torch.int32)
    assert torch.autograd.gradcheck(lambda t: pointnet2_stack.grouping_operation(t, cnt, idx, icnt), (f,))
    out = pointnet2_stack.grouping_operation(f, cnt, idx, icnt)
    assert torch.equal(out[2, :, 0], f[5 + 6])  # local index 6 of the second example


# ---------------------------------------------------------------------------------------------
# install(): OpenPCDet's own imports get the faces
# ---------------------------------------------------------------------------------------------

def test_install_serves_openpcdet_imports(tmp_path):
    """A stand-in ``pcdet`` checkout (never installed: no version.py) whose model code imports the ops
    the way OpenPCDet's does; after install() it runs on the faces, and an op lidarops does not serve
    raises NotImplementedError naming it."""
    pkg = tmp_path / "pcdet"
    for d in ("ops/iou3d_nms", "ops/roiaware_pool3d", "ops/roipoint_pool3d", "models"):
        (pkg / d).mkdir(parents=True)
        (pkg / d / "__init__.py").write_text("")
    (pkg / "ops" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("from .version import __version__\n")
    (pkg / "ops/roipoint_pool3d/roipoint_pool3d_utils.py").write_text("from . import roipoint_pool3d_cuda\n")
    (pkg / "models/nms.py").write_text(textwrap.dedent("""
        from ..ops.iou3d_nms import iou3d_nms_utils
        from ..ops.roiaware_pool3d import roiaware_pool3d_utils
        from ..ops.roipoint_pool3d import roipoint_pool3d_utils
        def run(boxes, scores):
            return iou3d_nms_utils.nms_gpu(boxes, scores, 0.1)[0]
    """))
    code = textwrap.dedent("""
        import torch, lidarops.compat.pcdet as P
        names = P.install()
        import pcdet
        from pcdet.models import nms
        boxes = torch.tensor([[0, 0, 0, 4, 2, 1.5, 0.3], [0.2, 0, 0, 4, 2, 1.5, 0.3], [9, 9, 0, 4, 2, 1.5, 0]])
        print(pcdet.__version__, nms.run(boxes, torch.tensor([0.5, 0.9, 0.1])).tolist())
        print(nms.roiaware_pool3d_utils.points_in_boxes_cpu(torch.zeros(1, 3), boxes).tolist())
        try:
            nms.roipoint_pool3d_utils.roipoint_pool3d_cuda.forward
        except NotImplementedError as e:
            print("raised:", e)
        print(sorted(n for n in names if "roipoint" in n or "version" in n))
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "0.0.0+lidarops [1, 2]"
    assert lines[1] == "[[1], [1], [0]]"
    assert lines[2].startswith("raised: pcdet.ops.roipoint_pool3d.roipoint_pool3d_cuda.forward") and "RoIPointPool3d" in lines[2]
    assert lines[3] == "['pcdet.ops.roipoint_pool3d.roipoint_pool3d_cuda', 'pcdet.version']"
