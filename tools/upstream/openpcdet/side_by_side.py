"""OpenPCDet's own PointPillar beside lidarops' PointPillars: same weights, same points, stage by stage.

    python tools/upstream/openpcdet/side_by_side.py --openpcdet .peers/OpenPCDet --frames DIR [options]

``--openpcdet``: a checkout of open-mmlab/OpenPCDet (not part of lidarops; see README.md here) whose ops
were built by ``build_ops.py``, or, with ``--faces``, none built: lidarops.compat.pcdet serves them.
``--frames``: KITTI ``velodyne/*.bin`` scans (``lidarops data synth --format kitti`` writes them).

Directions:

- default: a lidarops checkpoint (``--checkpoint``, the shipped model by default) loaded into OpenPCDet's
  ``PointPillar`` (built by ``pcdet.models.build_network`` from ``--cfg``, OpenPCDet's own
  ``pointpillar.yaml`` by default) with ``strict=True``;
- ``--pcdet-checkpoint F``: a checkpoint written by OpenPCDet's ``train.py`` loaded into both (lidarops
  through ``PointPillars.from_checkpoint(F, config=--cfg)``).

OpenPCDet's data pipeline (its point feature encoder, range mask and spconv's voxel generator, test
mode) prepares each frame; both models then get the same points. Compared per frame: the pillars (set
and order), the PFN output, the head outputs (class logits, box residuals, direction logits) and the
final boxes (count, order, labels, values). Writes a JSON report (``--out``) and prints a summary; exit
status 1 when the final boxes differ.

Its helpers (:func:`import_openpcdet`, :func:`read_config`, :func:`scan_dataset`, :func:`load_strict`) build
OpenPCDet's side for other scripts too: ``benchmarks/openpcdet_peer.py`` times what they build.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[3]


def parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--openpcdet", required=True, type=Path, help="OpenPCDet checkout")
    p.add_argument("--frames", required=True, type=Path, help="folder of velodyne .bin scans (or a KITTI split folder)")
    p.add_argument("--max-frames", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=2)
    p.add_argument("--cfg", type=Path, default=None,
                   help="OpenPCDet model config (default: its tools/cfgs/kitti_models/pointpillar.yaml)")
    p.add_argument("--checkpoint", type=Path, default=None, help="lidarops checkpoint (default: the shipped model)")
    p.add_argument("--pcdet-checkpoint", type=Path, default=None, help="an OpenPCDet-written checkpoint instead")
    p.add_argument("--faces", action="store_true", help="lidarops.compat.pcdet in place of OpenPCDet's compiled ops")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--score-thresh", type=float, default=None,
                   help="both models' SCORE_THRESH (default: the config's); lower compares more boxes")
    p.add_argument("--tf32", action="store_true",
                   help="leave TF32 convolutions on (torch's default for cuDNN): both sides then round differently")
    p.add_argument("--box-tol", type=float, default=1e-4, help="largest box value difference counted as the same")
    p.add_argument("--dump", type=Path, default=None, help="also save OpenPCDet's outputs per frame (.pt)")
    p.add_argument("--out", type=Path, default=None, help="JSON report")
    return p.parse_args()


def import_openpcdet(src: Path, faces: bool):
    """OpenPCDet's modules from the checkout ``src``: ``pcdet``, its ``cfg`` and ``cfg_from_yaml_file``,
    ``DatasetTemplate``, ``build_network`` and ``iou3d_nms_utils``. ``faces``: lidarops.compat.pcdet serves
    its compiled ops (installed before ``pcdet`` is imported)."""
    if str(src) not in sys.path:
        sys.path.insert(0, str(src))
    if faces:
        import lidarops.compat.pcdet as pcdet_faces

        pcdet_faces.install()
    import pcdet
    from pcdet.config import cfg, cfg_from_yaml_file
    from pcdet.datasets import DatasetTemplate
    from pcdet.models import build_network
    from pcdet.ops.iou3d_nms import iou3d_nms_utils

    return pcdet, cfg, cfg_from_yaml_file, DatasetTemplate, build_network, iou3d_nms_utils


def read_config(src: Path, cfg, cfg_from_yaml_file, cfg_path: Path | None = None,
                score_thresh: float | None = None) -> Path:
    """Reads ``cfg_path`` (default: OpenPCDet's own ``tools/cfgs/kitti_models/pointpillar.yaml``) into OpenPCDet's
    global ``cfg``, optionally with another ``SCORE_THRESH``; returns the resolved path."""
    cfg_path = (cfg_path or src / "tools/cfgs/kitti_models/pointpillar.yaml").resolve()
    cwd = os.getcwd()
    os.chdir(src / "tools")  # its configs name their base configs relative to tools/
    try:
        cfg_from_yaml_file(str(cfg_path), cfg)
    finally:
        os.chdir(cwd)
    if score_thresh is not None:
        cfg.MODEL.POST_PROCESSING.SCORE_THRESH = score_thresh
    return cfg_path


def scan_dataset(DatasetTemplate, cfg, scans: list, root_path: Path | None = None, logger=None):
    """OpenPCDet's test-mode dataset over ``scans`` (the shape of its ``tools/demo.py`` dataset): item ``i`` is
    scan ``i`` (a KITTI ``.bin`` path, or an (N, 4) float32 array) through its ``prepare_data``: the point
    feature encoder, the range mask and spconv's voxel generator."""

    class Scans(DatasetTemplate):
        def __init__(self):
            super().__init__(dataset_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES, training=False,
                             root_path=root_path, logger=logger)

        def __len__(self):
            return len(scans)

        def __getitem__(self, i):
            scan = scans[i]
            points = scan if isinstance(scan, np.ndarray) else np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
            return self.prepare_data(data_dict={"points": points, "frame_id": i})

    return Scans()


def load_strict(model: torch.nn.Module, ckpt_path: Path) -> dict:
    """Loads a checkpoint's ``model_state`` (lidarops' or OpenPCDet's) into OpenPCDet's model with
    ``strict=True``: every tensor, or an error naming the keys. Returns the state."""
    state = torch.load(ckpt_path, map_location="cpu", weights_only=False)["model_state"]
    model.load_state_dict(state, strict=True)
    return state


def scan_files(frames: Path, limit: int) -> list[Path]:
    folder = frames / "velodyne" if (frames / "velodyne").is_dir() else frames
    files = sorted(folder.glob("*.bin"))[:limit]
    if not files:
        raise SystemExit(f"no .bin scans in {folder}")
    return files


def to_device(batch: dict, device: str) -> dict:
    """OpenPCDet's ``load_data_to_gpu`` for any device."""
    out = {}
    for k, v in batch.items():
        if isinstance(v, np.ndarray) and k not in ("frame_id", "metadata", "calib"):
            out[k] = torch.from_numpy(v).float().to(device) if k != "image_shape" else torch.from_numpy(v).int().to(device)
        else:
            out[k] = v
    return out


def max_abs(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).abs().max()) if a.numel() else 0.0


def compare_boxes(ours: dict, theirs: dict, tol: float) -> dict:
    """Same boxes: every box of one list has a box of the other with the same label within ``tol`` (matched
    greedily, closest first); same order: index by index as well (equal scores may come in either order)."""
    ob, tb = ours["boxes"].double().cpu(), theirs["pred_boxes"].double().cpu()
    ol, tl = ours["labels"].cpu().long(), theirs["pred_labels"].cpu().long()
    res = {"lidarops": int(ob.shape[0]), "openpcdet": int(tb.shape[0])}
    if ob.shape[0] != tb.shape[0]:
        res.update(same=False, same_order=False)
        return res
    if not ob.shape[0]:
        res.update(same=True, same_order=True, max_box_diff=0.0)
        return res
    d = (ob[:, None] - tb[None]).abs()
    d[..., 6] = (torch.remainder(d[..., 6] + np.pi, 2 * np.pi) - np.pi).abs()
    d = d.amax(-1) + (ol[:, None] != tl[None]) * 1e9
    matched, worst = set(), 0.0
    for i in d.min(1).values.argsort().tolist():
        row = d[i].clone()
        row[list(matched)] = float("inf")
        j = int(row.argmin())
        matched.add(j)
        worst = max(worst, float(row[j]))
    in_order = (ob - tb).abs()
    in_order[:, 6] = (torch.remainder(in_order[:, 6] + np.pi, 2 * np.pi) - np.pi).abs()
    res["max_box_diff"] = worst
    res["same"] = worst <= tol
    res["same_order"] = bool(float(in_order.max()) <= tol and torch.equal(ol, tl))
    res["max_score_diff_in_order"] = max_abs(ours["scores"].cpu(), theirs["pred_scores"].cpu())
    return res


def main() -> int:
    args = parse()
    for name in ("checkpoint", "pcdet_checkpoint", "cfg", "out", "dump"):
        if getattr(args, name) is not None:
            setattr(args, name, getattr(args, name).resolve())
    src = args.openpcdet.resolve()
    if not args.tf32:  # float32 arithmetic on both sides, so that the comparison measures the code, not TF32
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_tf32 = False
    pcdet, cfg, cfg_from_yaml_file, DatasetTemplate, build_network, iou3d_nms_utils = import_openpcdet(src, args.faces)
    frames = scan_files(args.frames.resolve(), args.max_frames)
    cfg_path = read_config(src, cfg, cfg_from_yaml_file, args.cfg, args.score_thresh)
    logger = logging.getLogger("side_by_side")
    logging.basicConfig(level=logging.WARNING)
    dataset = scan_dataset(DatasetTemplate, cfg, frames, frames[0].parent, logger)
    model = build_network(model_cfg=cfg.MODEL, num_class=len(cfg.CLASS_NAMES), dataset=dataset)

    from lidarops.models import PointPillars

    if args.pcdet_checkpoint is not None:
        ckpt_path = args.pcdet_checkpoint.resolve()
        ours = PointPillars.from_checkpoint(ckpt_path, config=cfg_path)
    else:
        from lidarops.models import weights

        ckpt_path = (args.checkpoint or weights.path()).resolve()
        ours = PointPillars.from_checkpoint(ckpt_path)
    state = load_strict(model, ckpt_path)
    n_params = sum(p.numel() for p in model.parameters())
    if args.score_thresh is not None:
        ours.config.score_thresh = args.score_thresh
    model.to(args.device).eval()
    ours.to(args.device).eval()

    report = {"openpcdet_version": pcdet.__version__, "faces": args.faces, "device": args.device, "tf32": args.tf32,
              "checkpoint": str(ckpt_path), "direction": "openpcdet->lidarops" if args.pcdet_checkpoint else
              "lidarops->openpcdet", "cfg": str(cfg_path), "tensors": len(state), "parameters": n_params,
              "frames": [], "anchors": {}}
    # anchors: OpenPCDet builds them in float32 arithmetic, lidarops in float64 rounded once
    theirs_a = torch.cat([a.reshape(-1, 7) for a in model.dense_head.anchors]).cpu()
    ours_a = torch.cat([a.reshape(-1, 7) for a in ours.dense_head.anchors]).cpu()
    if ours_a.shape == theirs_a.shape:
        diff = (ours_a.double() - theirs_a.double()).abs()
        report["anchors"] = {"count": int(theirs_a.shape[0]), "differing": int((diff > 0).any(1).sum()),
                             "max_diff_m": float(diff.max())}

    dumps = []
    all_same = True
    t_theirs = t_ours = 0.0
    for start in range(0, len(dataset), args.batch_size):
        items = [dataset[i] for i in range(start, min(start + args.batch_size, len(dataset)))]
        batch = to_device(dataset.collate_batch(items), args.device)
        B = len(items)
        with torch.no_grad():
            sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
            sync(); t0 = time.perf_counter()
            preds, _ = model(batch)
            sync(); t_theirs += time.perf_counter() - t0
            points = batch["points"]
            t0 = time.perf_counter()
            voxels, nums, coords = ours.voxelize(points, B)
            feats = ours.vfe(voxels, nums, coords)
            raw = ours.network(voxels, nums, coords, B)
            mine = ours.postprocess(raw)
            sync(); t_ours += time.perf_counter() - t0
        head = model.dense_head.forward_ret_dict
        theirs_coords = batch["voxel_coords"].long()
        same_set = same_order = False
        if theirs_coords.shape == coords.shape:
            same_order = bool(torch.equal(theirs_coords, coords.long()))
            key = lambda c: (c[:, 0] * 1_000_000_007 + c[:, 2] * 100_003 + c[:, 3]).sort().values
            same_set = bool(torch.equal(key(theirs_coords), key(coords.long())))
        pfn = max_abs(feats, batch["pillar_features"]) if same_order else None
        stage = {"pillars_lidarops": int(coords.shape[0]), "pillars_openpcdet": int(theirs_coords.shape[0]),
                 "same_pillar_set": same_set, "same_pillar_order": same_order, "pfn_max_diff": pfn,
                 "cls_max_diff": max_abs(raw["cls_preds"], head["cls_preds"]),
                 "box_max_diff": max_abs(raw["box_preds"], head["box_preds"]),
                 "dir_max_diff": max_abs(raw["dir_cls_preds"], head["dir_cls_preds"])
                 if "dir_cls_preds" in raw else None}
        for b in range(B):
            boxes = compare_boxes(mine[b], preds[b], args.box_tol)
            all_same &= boxes["same"]
            report["frames"].append({"scan": frames[start + b].name, "batch": stage, "boxes": boxes})
            if args.dump:
                dumps.append({k: v.cpu() for k, v in preds[b].items()})
    report["seconds"] = {"openpcdet": t_theirs, "lidarops": t_ours}
    report["same_boxes"] = all_same
    if args.dump:
        torch.save(dumps, args.dump)
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    print(f"OpenPCDet {pcdet.__version__} ({'lidarops faces' if args.faces else 'its own ops'}, {args.device}), "
          f"{report['direction']}: {report['tensors']} tensors loaded strictly, {n_params:,} parameters")
    if report["anchors"]:
        a = report["anchors"]
        print(f"anchors: {a['differing']} of {a['count']} differ, at most {a['max_diff_m']:.2e} m")
    for f in report["frames"]:
        s, bx = f["batch"], f["boxes"]
        print(f"  {f['scan']}: pillars {s['pillars_lidarops']}/{s['pillars_openpcdet']} set={s['same_pillar_set']} "
              f"order={s['same_pillar_order']} pfn={s['pfn_max_diff']} cls={s['cls_max_diff']:.1e} "
              f"box={s['box_max_diff']:.1e} | boxes {bx['lidarops']}/{bx['openpcdet']} "
              f"max diff {bx.get('max_box_diff', float('nan')):.1e} same={bx['same']} same order={bx['same_order']}")
    print(f"same boxes on every frame: {all_same}")
    return 0 if all_same else 1


if __name__ == "__main__":
    sys.exit(main())
