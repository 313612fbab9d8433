"""Benchmark the rotated-box ops: pairwise BEV IoU and rotated NMS, against torchvision's rotated
``box_iou(fmt="cxcywhr")`` (torchvision >= 0.27; skipped, with the reason, where it is older), a
vectorised pure-PyTorch rotated IoU (what one writes without a custom op) and a Python greedy NMS
over each, measured in the same run.

    python benchmarks/bm_boxes.py                 # CPU, and CUDA when available
    python benchmarks/bm_boxes.py --device cuda --json

Cases: IoU of 500 x 500 and 4096 x 4096 KITTI-like boxes; NMS of 4,096 pre-NMS boxes (PointPillars'
post-processing: NMS_PRE_MAXSIZE 4096, IoU threshold 0.01, NMS_POST_MAXSIZE 500) clustered around 40
objects. Times are medians of the eager call as a user writes it (validation, sort, kernels, the
read-back of the number kept), CUDA events on GPU. ``--json`` merges the rows into
``benchmarks/results/<device>.json`` under ``"boxes"``.
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

import lidarops  # noqa: E402
from lidarops import extension  # noqa: E402
from benchmarks.common import (  # noqa: E402
    Skip, env_meta, fmt_ms, fmt_ratio, print_table, time_call, write_results)
from helpers.boxes import lidar_boxes  # noqa: E402


def _torchvision_iou():
    try:
        import torchvision
        torchvision.ops.box_iou(torch.zeros(1, 5), torch.zeros(1, 5), fmt="cxcywhr")
    except Exception as e:  # noqa: BLE001  (missing, or too old for rotated boxes)
        raise Skip(f"torchvision rotated box_iou unavailable: {e}") from None

    def iou(a, b):
        def cxcywhr(x):
            return torch.stack([x[:, 0], x[:, 1], x[:, 3], x[:, 4], torch.rad2deg(x[:, 6])], 1)
        return torchvision.ops.box_iou(cxcywhr(a), cxcywhr(b), fmt="cxcywhr")
    return iou


def _corners(b: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    u = torch.tensor([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=b.dtype, device=b.device) / 2
    lx, ly = u[None, :, 0] * b[:, 3:4], u[None, :, 1] * b[:, 4:5]
    return torch.stack([b[:, None, 0] + c[:, None] * lx - s[:, None] * ly,
                        b[:, None, 1] + s[:, None] * lx + c[:, None] * ly], -1)  # (N, 4, 2) counter-clockwise


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def torch_rotated_iou(a: torch.Tensor, b: torch.Tensor, chunk_pairs: int = 1 << 20) -> torch.Tensor:
    """Vectorised rotated BEV IoU in plain PyTorch: the usual construction (corners of each box inside
    the other, the 16 edge crossings, sorted by angle around their centroid, shoelace), in row chunks."""
    ca, cb = _corners(a), _corners(b)
    area_a, area_b = a[:, 3] * a[:, 4], b[:, 3] * b[:, 4]
    rows = max(1, chunk_pairs // max(b.shape[0], 1))
    out = []
    for i0 in range(0, a.shape[0], rows):
        A, B = ca[i0:i0 + rows, None], cb[None]  # (n, 1, 4, 2), (1, M, 4, 2)

        def inside(p, poly):  # points p (n, M, 4, 2) inside the convex polygons poly (n|1, M|1, 4, 2)
            e0, e1 = poly, poly.roll(-1, dims=-2)
            return (_cross((e1 - e0)[..., None, :, :], p[..., :, None, :] - e0[..., None, :, :]) >= 0).all(-1)

        pa, pb = A.expand(-1, B.shape[1], -1, -1), B.expand(A.shape[0], -1, -1, -1)
        in_a, in_b = inside(pa, B), inside(pb, A)
        p, r = pa[..., :, None, :], (pa.roll(-1, dims=-2) - pa)[..., :, None, :]
        q, s = pb[..., None, :, :], (pb.roll(-1, dims=-2) - pb)[..., None, :, :]
        den = _cross(r, s)
        safe = torch.where(den != 0, den, torch.ones_like(den))  # parallel edges do not cross
        t, u = _cross(q - p, s) / safe, _cross(q - p, r) / safe
        hit = (den != 0) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
        cross_pts = (p + t[..., None] * r).flatten(-3, -2)
        pts = torch.cat([pa, pb, cross_pts], -2)  # (n, M, 24, 2)
        valid = torch.cat([in_a, in_b, hit.flatten(-2)], -1)
        count = valid.sum(-1, keepdim=True).clamp_min(1)
        centre = torch.where(valid[..., None], pts, torch.zeros_like(pts)).sum(-2) / count
        ang = torch.atan2(pts[..., 1] - centre[..., None, 1], pts[..., 0] - centre[..., None, 0])
        ang = torch.where(valid, ang, torch.full_like(ang, 10.0))
        order = ang.argsort(-1)
        pts = torch.gather(pts, -2, order[..., None].expand(-1, -1, -1, 2))
        valid = torch.gather(valid, -1, order)
        pts = torch.where(valid[..., None], pts, pts[..., :1, :])  # padding repeats the first vertex
        inter = 0.5 * _cross(pts, pts.roll(-1, dims=-2)).sum(-1).abs()
        inter = torch.where(valid.sum(-1) >= 3, inter, torch.zeros_like(inter))
        out.append(inter / (area_a[i0:i0 + rows, None] + area_b[None] - inter).clamp_min(1e-9))
    return torch.cat(out) if out else a.new_zeros(0, b.shape[0])


def python_greedy_nms(iou_fn, boxes, scores, threshold, pre_max, post_max):
    """The baseline without a rotated NMS op: sort, one IoU matrix, a host loop over the boxes."""
    order = torch.sort(scores, stable=True, descending=True).indices[:pre_max]
    over = (iou_fn(boxes[order], boxes[order]) > threshold).cpu()
    removed = torch.zeros(order.numel(), dtype=torch.bool)
    keep = []
    for i in range(order.numel()):
        if removed[i]:
            continue
        keep.append(i)
        if len(keep) == post_max:
            break
        removed |= over[i]
    return order[torch.tensor(keep, dtype=torch.int64, device=order.device)]


def run(device: str) -> list[dict]:
    dev = torch.device(device)
    rows = []

    def measure(op, case, impl, fn, args):
        try:
            t = time_call(fn, args, dev, budget_s=1.0)
            rows.append({"op": op, "case": case, "impl": impl, "status": "ok", **t.as_dict()})
        except Skip as e:
            rows.append({"op": op, "case": case, "impl": impl, "status": f"skipped ({e})"})
        except Exception as e:  # noqa: BLE001  (reported, not blanked)
            rows.append({"op": op, "case": case, "impl": impl, "status": f"error: {type(e).__name__}: {e}"})

    try:
        tv_iou = _torchvision_iou()
    except Skip as e:
        tv_iou, tv_reason = None, str(e)
    for n in (500, 4096):
        boxes = lidar_boxes(n, seed=n).float().to(dev)
        case = f"{n} x {n}"
        measure("box_iou_bev", case, "lidarops", lidarops.box_iou_bev, (boxes, boxes))
        if tv_iou is None:
            rows.append({"op": "box_iou_bev", "case": case, "impl": "torchvision", "status": f"skipped ({tv_reason})"})
        else:
            measure("box_iou_bev", case, "torchvision", tv_iou, (boxes, boxes))
        measure("box_iou_bev", case, "pure PyTorch", torch_rotated_iou, (boxes, boxes))
    boxes = lidar_boxes(4096, seed=1, objects=40).float().to(dev)
    scores = torch.rand(4096, generator=torch.Generator().manual_seed(1)).to(dev)
    case = "4096 boxes, thr 0.01, keep <= 500"
    measure("nms_bev", case, "lidarops", lambda b, s: lidarops.nms_bev(b, s, 0.01, pre_max=4096, post_max=500),
            (boxes, scores))
    if tv_iou is None:
        rows.append({"op": "nms_bev", "case": case, "impl": "python greedy over torchvision IoU",
                     "status": f"skipped ({tv_reason})"})
    else:
        measure("nms_bev", case, "python greedy over torchvision IoU",
                lambda b, s: python_greedy_nms(tv_iou, b, s, 0.01, 4096, 500), (boxes, scores))
    measure("nms_bev", case, "python greedy over pure-PyTorch IoU",
            lambda b, s: python_greedy_nms(torch_rotated_iou, b, s, 0.01, 4096, 500), (boxes, scores))
    measure("nms_bev", case, "python greedy over lidarops IoU",
            lambda b, s: python_greedy_nms(lidarops.box_iou_bev, b, s, 0.01, 4096, 500), (boxes, scores))
    kept = lidarops.nms_bev(boxes, scores, 0.01, pre_max=4096, post_max=500).numel()
    for r in rows:
        r["device"] = device
        if r["op"] == "nms_bev":
            r["kept"] = kept
    return rows


def print_rows(rows: list[dict], title: str) -> None:
    base = {(r["op"], r["case"]): r["median_ms"] for r in rows if r["impl"] == "lidarops" and r["status"] == "ok"}
    table = []
    for r in rows:
        ms = r.get("median_ms")
        ratio = ms / base[(r["op"], r["case"])] if ms is not None and (r["op"], r["case"]) in base else None
        table.append([r["op"], r["case"], r["impl"], fmt_ms(ms), fmt_ratio(ratio) if r["impl"] != "lidarops" else "",
                      r["status"] if r["status"] != "ok" else ""])
    print_table(title, ["op", "case", "impl", "median ms", "vs lidarops", "status"], table, right=(3, 4))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=("cpu", "cuda", "all"), default="all")
    ap.add_argument("--json", action="store_true", help="merge results into benchmarks/results/<device>.json")
    args = ap.parse_args(argv)
    devices = ["cpu", "cuda"] if args.device == "all" else [args.device]
    devices = [d for d in devices if d == "cpu" or (torch.cuda.is_available() and extension.cuda_available())]
    for device in devices:
        rows = run(device)
        print_rows(rows, f"rotated boxes on {device} ({env_meta(device).get('device', device)})")
        if args.json:
            path = write_results("boxes", device, rows, env_meta(device), replace_by=None)
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
