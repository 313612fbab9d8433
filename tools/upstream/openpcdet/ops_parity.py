"""lidarops.compat.pcdet against OpenPCDet's own compiled ops (built by build_ops.py), on CUDA.

    python tools/upstream/openpcdet/ops_parity.py .peers/OpenPCDet [--out report.json]

Each face is called beside the OpenPCDet function it replaces, on the same random and LiDAR-like
inputs (float32, as OpenPCDet's kernels take), and the outputs are compared: indices exactly, values
to rounding. Gradients of the differentiable ops too. Prints one line per op; exit status 1 when any
op differs beyond its tolerance.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT / "tests"))


def lidar_cloud(n: int, rng) -> np.ndarray:
    from helpers.compat import lidar_like

    return lidar_like(n, rng)


def boxes(n: int, rng, spread: float = 20.0) -> torch.Tensor:
    b = np.zeros((n, 7), np.float32)
    b[:, :2] = rng.uniform(-spread, spread, (n, 2))
    b[:, 2] = rng.uniform(-1, 1, n)
    b[:, 3:6] = rng.uniform(0.5, 4.5, (n, 3))
    b[:, 6] = rng.uniform(-math.pi, math.pi, n)
    return torch.from_numpy(b)


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("openpcdet", type=Path)
    p.add_argument("--out", type=Path)
    p.add_argument("--device", default="cuda")
    args = p.parse_args()
    sys.path.insert(0, str(args.openpcdet.resolve()))
    from pcdet.ops.iou3d_nms import iou3d_nms_utils as T_iou
    from pcdet.ops.pointnet2.pointnet2_batch import pointnet2_utils as T_pb
    from pcdet.ops.pointnet2.pointnet2_stack import pointnet2_utils as T_ps
    from pcdet.ops.roiaware_pool3d import roiaware_pool3d_utils as T_pib

    from lidarops.compat.pcdet import iou3d_nms_utils as L_iou
    from lidarops.compat.pcdet import pointnet2_batch as L_pb
    from lidarops.compat.pcdet import pointnet2_stack as L_ps
    from lidarops.compat.pcdet import roiaware_pool3d_utils as L_pib

    dev = args.device
    rng = np.random.default_rng(0)
    results = []

    def record(op, ok, detail):
        results.append({"op": op, "same": bool(ok), "detail": detail})
        print(f"  {op:48s} {'same' if ok else 'DIFFERENT'}  {detail}", flush=True)
        if args.out:  # after every op: a crash in a later one keeps these
            args.out.write_text(json.dumps(results, indent=1))

    def close(a, b, tol, rel=0.0):
        """Within ``tol + rel * |b|`` everywhere (``rel`` for sums of many terms whose order differs)."""
        a, b = a.detach().double(), b.detach().double()
        if not a.numel():
            return True, "max diff 0"
        d = (a - b).abs()
        return bool((d <= tol + rel * b.abs()).all()), f"max diff {float(d.max()):.2e} (|values| up to {float(b.abs().max()):.1f})"

    def fps_divergence(xyz, ours, theirs):
        """Where two farthest-point samplings of one cloud part: the first differing pick, and which of the two
        candidates is farther from the picks before it in float64 (a rounding or tie decision, or a wrong pick)."""
        ours, theirs = ours.long().cpu(), theirs.long().cpu()
        diff = (ours != theirs).nonzero()
        if not len(diff):
            return "identical"
        j = int(diff[0])
        pts = xyz.double().cpu()
        dist = torch.cdist(pts, pts[ours[:j]]).min(1).values if j else torch.full((len(pts),), float("inf"))
        d_o, d_t = float(dist[ours[j]]), float(dist[theirs[j]])
        f32 = "equal" if np.float32(d_o) == np.float32(d_t) else "different"
        return (f"first differs at pick {j}: lidarops {int(ours[j])} at {d_o:.9f} m, OpenPCDet {int(theirs[j])} at "
                f"{d_t:.9f} m (float64; float32 {f32}); farthest: {'lidarops' if d_o > d_t else 'OpenPCDet' if d_t > d_o else 'tie'}")

    def section_boxes():
        from lidarops.ops.boxes import _box_iou_bev_reference
        for n, m in ((200, 300), (1000, 1000)):
            a, b = boxes(n, rng).to(dev), boxes(m, rng).to(dev)
            b[: n // 4] = a[: n // 4]
            ours, theirs = L_iou.boxes_iou_bev(a, b), T_iou.boxes_iou_bev(a, b)
            record(f"boxes_iou_bev {n}x{m}", *close(ours, theirs, 1e-5))
            if n * m <= 60_000:  # which side is right: the float64 polygon-clipping reference
                ref = _box_iou_bev_reference(a.cpu().double(), b.cpu().double())
                for side, got in (("lidarops", ours), ("OpenPCDet", theirs)):
                    err = (got.cpu().double() - ref).abs()
                    worst = np.unravel_index(int(err.argmax()), tuple(err.shape))
                    record(f"  {side} boxes_iou_bev vs float64", float(err.max()) <= 1e-5,
                           f"max error {float(err.max()):.2e} at pair {tuple(int(i) for i in worst)} "
                           f"(reference {float(ref[worst]):.6f}); {int((err > 1e-5).sum())} pairs off by > 1e-5")
            record(f"boxes_iou3d_gpu {n}x{m}", *close(L_iou.boxes_iou3d_gpu(a, b), T_iou.boxes_iou3d_gpu(a, b), 1e-5))
            bb = b[:n] + torch.randn_like(a) * torch.tensor([0.5, 0.5, 0.2, 0.1, 0.1, 0.1, 0.3], device=dev)
            bb[:, 3:6] = bb[:, 3:6].abs() + 0.1
            record(f"boxes_aligned_iou3d_gpu {n}",
                   *close(L_iou.boxes_aligned_iou3d_gpu(a, bb), T_iou.boxes_aligned_iou3d_gpu(a, bb), 1e-5))
            record(f"paired_boxes_iou3d_gpu {n}",
                   *close(L_iou.paired_boxes_iou3d_gpu(a, bb), T_iou.paired_boxes_iou3d_gpu(a, bb), 1e-5))
        for n, spread in ((500, 20.0), (4096, 40.0)):
            bx = boxes(n, rng, spread).to(dev)
            sc = torch.from_numpy(rng.permutation(n).astype(np.float32) / n).to(dev)  # distinct scores
            for thr in (0.01, 0.1, 0.7):
                for pre in (None, 1000):
                    ours, _ = L_iou.nms_gpu(bx, sc, thr, pre_maxsize=pre)
                    theirs, _ = T_iou.nms_gpu(bx, sc, thr, pre_maxsize=pre)
                    record(f"nms_gpu n={n} thresh={thr} pre={pre}", torch.equal(ours.cpu(), theirs.cpu()),
                           f"kept {len(ours)}/{len(theirs)}")
                ours, _ = L_iou.nms_normal_gpu(bx, sc, thr)
                theirs, _ = T_iou.nms_normal_gpu(bx, sc, thr)
                record(f"nms_normal_gpu n={n} thresh={thr}", torch.equal(ours.cpu(), theirs.cpu()),
                       f"kept {len(ours)}/{len(theirs)}")

    def section_points_in_boxes():
        bxs = torch.stack([boxes(30, rng, 25.0) for _ in range(3)]).to(dev)
        ptss = torch.from_numpy(np.stack([lidar_cloud(50000, rng) for _ in range(3)])).to(dev)
        ours, theirs = L_pib.points_in_boxes_gpu(ptss, bxs), T_pib.points_in_boxes_gpu(ptss, bxs)
        record("points_in_boxes_gpu 3 x (30 boxes, 50000 points)", torch.equal(ours, theirs),
               f"{int((ours != theirs).sum())} differ, {int((theirs >= 0).sum())} inside")

    def section_pointnet2_batch():
        xyz = torch.from_numpy(np.stack([lidar_cloud(16384, rng) for _ in range(2)])).to(dev).contiguous()
        idx_o, idx_t = L_pb.farthest_point_sample(xyz, 4096), T_pb.farthest_point_sample(xyz, 4096)
        record("pointnet2_batch farthest_point_sample 2x16384 -> 4096", torch.equal(idx_o, idx_t),
               f"{int((idx_o != idx_t).sum())} differ; " + "; ".join(
                   fps_divergence(xyz[b], idx_o[b], idx_t[b]) for b in range(xyz.shape[0])))
        new_xyz = L_pb.gather_operation(xyz.transpose(1, 2).contiguous(), idx_t).transpose(1, 2).contiguous()
        new_t = T_pb.gather_operation(xyz.transpose(1, 2).contiguous(), idx_t).transpose(1, 2).contiguous()
        record("pointnet2_batch gather_operation", torch.equal(new_xyz, new_t), "")
        for r, ns in ((0.8, 16), (2.4, 32)):
            bo, bt = L_pb.ball_query(r, ns, xyz, new_xyz), T_pb.ball_query(r, ns, xyz, new_xyz)
            record(f"pointnet2_batch ball_query r={r} nsample={ns}", torch.equal(bo, bt), f"{int((bo != bt).sum())} differ")
        feats = torch.randn(2, 16, 16384, device=dev, requires_grad=True)
        go = L_pb.grouping_operation(feats, bt)
        gt = T_pb.grouping_operation(feats, bt)
        record("pointnet2_batch grouping_operation", torch.equal(go, gt), "")
        gradient = torch.randn_like(go)
        (g_o,) = torch.autograd.grad(go, feats, gradient)
        (g_t,) = torch.autograd.grad(gt, feats, gradient)
        record("pointnet2_batch grouping_operation backward", *close(g_o, g_t, 1e-5, rel=1e-5))
        do, no = L_pb.three_nn(new_xyz, xyz[:, ::4].contiguous())
        dt, nt = T_pb.three_nn(new_xyz, xyz[:, ::4].contiguous())
        ok, det = close(do, dt, 1e-5)
        known = xyz[:, ::4].double()
        where = (no != nt).nonzero()
        gap = max((abs(float((new_xyz[b, i].double() - known[b, no[b, i, k]]).norm())
                           - float((new_xyz[b, i].double() - known[b, nt[b, i, k]]).norm())) for b, i, k in where.tolist()),
                  default=0.0)
        record("pointnet2_batch three_nn", ok and torch.equal(no, nt), f"{len(where)} indices differ, {det}; where they "
               f"differ, the two picks' float64 distances differ by at most {gap:.2e} m (a near tie)")
        w = torch.rand(2, 4096, 3, device=dev)
        f2 = torch.randn(2, 16, 4096, device=dev, requires_grad=True)
        io, it = L_pb.three_interpolate(f2, nt, w), T_pb.three_interpolate(f2, nt, w)
        record("pointnet2_batch three_interpolate", *close(io, it, 1e-5))
        gradient = torch.randn_like(io)
        record("pointnet2_batch three_interpolate backward",
               *close(torch.autograd.grad(io, f2, gradient)[0], torch.autograd.grad(it, f2, gradient)[0], 1e-4))
        q_o = L_pb.QueryAndGroup(1.6, 16)(xyz, new_xyz, feats.detach())
        q_t = T_pb.QueryAndGroup(1.6, 16)(xyz, new_xyz, feats.detach())
        record("pointnet2_batch QueryAndGroup", *close(q_o, q_t, 1e-6))

    def section_pointnet2_stack():
        counts = [20000, 37, 9000]
        parts = [lidar_cloud(c, rng) for c in counts]
        sxyz = torch.from_numpy(np.concatenate(parts)).to(dev).contiguous()
        cnt = torch.tensor(counts, dtype=torch.int32, device=dev)
        so = L_ps.stack_farthest_point_sample(sxyz, cnt, [2048, 30, 1024])
        st = T_ps.stack_farthest_point_sample(sxyz, cnt, [2048, 30, 1024])
        starts = np.cumsum([0] + counts)
        picks = np.cumsum([0, 2048, 30, 1024])
        record("pointnet2_stack stack_farthest_point_sample", torch.equal(so, st), f"{int((so != st).sum())} differ; " +
               "; ".join(fps_divergence(sxyz[starts[i]:starts[i + 1]], so[picks[i]:picks[i + 1]] - starts[i],
                                        st[picks[i]:picks[i + 1]] - starts[i]) for i in range(3)))
        centers = sxyz[st.long()].contiguous()
        ccnt = torch.tensor([2048, 30, 1024], dtype=torch.int32, device=dev)
        far = centers.clone()
        far[::7] += 500.0  # empty balls
        io_, eo = L_ps.ball_query(1.2, 16, sxyz, cnt, far, ccnt)
        it_, et = T_ps.ball_query(1.2, 16, sxyz, cnt, far, ccnt)
        record("pointnet2_stack ball_query (with empty balls)", torch.equal(io_, it_) and torch.equal(eo, et),
               f"{int((io_ != it_).sum())} differ, {int(et.sum())} empty")
        sf = torch.randn(sxyz.shape[0], 8, device=dev, requires_grad=True)
        go, gt = L_ps.grouping_operation(sf, cnt, it_, ccnt), T_ps.grouping_operation(sf, cnt, it_, ccnt)
        record("pointnet2_stack grouping_operation", torch.equal(go, gt), "")
        gradient = torch.randn_like(go)
        record("pointnet2_stack grouping_operation backward",
               *close(torch.autograd.grad(go, sf, gradient)[0], torch.autograd.grad(gt, sf, gradient)[0], 1e-5, rel=1e-5))
        qo, qio = L_ps.QueryAndGroup(1.2, 16)(sxyz, cnt, far, ccnt, sf.detach())
        qt, qit = T_ps.QueryAndGroup(1.2, 16)(sxyz, cnt, far, ccnt, sf.detach())
        ok, det = close(qo, qt, 1e-6)
        record("pointnet2_stack QueryAndGroup", ok and torch.equal(qio, qit), det)
        do, no = L_ps.three_nn(sxyz, cnt, centers, ccnt)
        dt, nt = T_ps.three_nn(sxyz, cnt, centers, ccnt)
        ok, det = close(do, dt, 1e-5)
        record("pointnet2_stack three_nn", ok and torch.equal(no, nt), f"{int((no != nt).sum())} indices differ, {det}")
        cf = torch.randn(centers.shape[0], 8, device=dev, requires_grad=True)
        w = torch.rand(sxyz.shape[0], 3, device=dev)
        io, it = L_ps.three_interpolate(cf, nt, w), T_ps.three_interpolate(cf, nt, w)
        record("pointnet2_stack three_interpolate", *close(io, it, 1e-5))
        gradient = torch.randn_like(io)
        record("pointnet2_stack three_interpolate backward",
               *close(torch.autograd.grad(io, cf, gradient)[0], torch.autograd.grad(it, cf, gradient)[0], 1e-4))

    def section_cpu_ops():
        # last: OpenPCDet's own CPU ops have ended the process here (no traceback), and what ran before is kept
        a, b = boxes(200, rng).cpu(), boxes(300, rng).cpu()
        record("boxes_bev_iou_cpu 200x300 (distinct boxes)",
               *close(L_iou.boxes_bev_iou_cpu(a, b), T_iou.boxes_bev_iou_cpu(a, b), 1e-5))
        bx = boxes(40, rng, 25.0)
        pts = torch.from_numpy(lidar_cloud(60000, rng))
        ours, theirs = L_pib.points_in_boxes_cpu(pts, bx), T_pib.points_in_boxes_cpu(pts, bx)
        record("points_in_boxes_cpu 40 boxes x 60000 points", torch.equal(ours, theirs),
               f"{int((ours != theirs).sum())} of {ours.numel()} entries differ, {int(theirs.sum())} inside")

    for section in (section_boxes, section_points_in_boxes, section_pointnet2_batch, section_pointnet2_stack,
                    section_cpu_ops):
        try:
            section()
        except Exception as e:  # noqa: BLE001  (report it and go on with the other ops)
            import traceback
            traceback.print_exc()
            record(section.__name__, False, f"raised {type(e).__name__}: {e}")

    bad = [r["op"] for r in results if not r["same"]]
    print(f"{len(results) - len(bad)} of {len(results)} comparisons the same" + (f"; different: {bad}" if bad else ""))
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
