"""CounterNet end to end on one device, small enough for compute-sanitizer (issue 38's device session):

    python tools/counternet/cuda_smoke.py                 # cuda when available, else cpu
    compute-sanitizer --tool memcheck --error-exitcode 9 python tools/counternet/cuda_smoke.py

tests/models/test_counternet.py runs on the CPU only; this runs the whole model where the GPU kernels are used
(voxelization and the scatter of lidarops, the convolutions, targets, focal loss, soft count, Otsu, peaks, the
merge): two simulated dense city frames, a reduced backbone (one layer per block), pt 1 and pt 4 with delta 0.2.
Per model: one training step (loss and every gradient finite) and ``predict`` on the device; on CUDA the same
weights also on the CPU, the heatmaps compared (max difference printed) and the counts compared (equal, or the
frames that differ named: a peak at the threshold can fall either side). Exit status 1 on a failed check.
"""
from __future__ import annotations

import sys
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import copy

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]


def batch_of(frames, classes) -> dict:
    pts, boxes = [], []
    for b, f in enumerate(frames):
        p = torch.from_numpy(np.ascontiguousarray(f.points[:, :4], np.float32))
        pts.append(torch.cat([torch.full((len(p), 1), float(b)), p], 1))
        names = [f.class_names[i] for i in f.labels]
        keep = [k for k, n in enumerate(names) if n in classes]
        cls = torch.tensor([classes.index(names[k]) + 1 for k in keep], dtype=torch.float32)
        boxes.append(torch.cat([torch.from_numpy(np.asarray(f.boxes, np.float32)[keep, :7]), cls[:, None]], 1))
    m = max(len(x) for x in boxes)
    gt = torch.zeros(len(frames), m, 8)
    for b, x in enumerate(boxes):
        gt[b, :len(x)] = x
    return {"points": torch.cat(pts), "gt_boxes": gt, "batch_size": len(frames)}


def main() -> int:
    from lidarops.config import load_config
    from lidarops.data.synthetic import SyntheticFrames
    from lidarops.models.counternet import CounterNet

    device = torch.device(sys.argv[1] if len(sys.argv) > 1 else ("cuda" if torch.cuda.is_available() else "cpu"))
    src = SyntheticFrames("driving_city", num_frames=2, seed=7, object_counts="dense", fov_deg=90)
    ok = True
    for pt, delta in ((1, 0.0), (4, 0.2)):
        cfg = load_config(str(ROOT / "configs" / "counternet" / "counternet_synth.yaml"))
        cfg["MODEL"]["BACKBONE_2D"]["LAYER_NUMS"] = [1, 1, 1]
        cfg["MODEL"]["COUNT_HEAD"].update(PARTITIONS=pt, OVERLAP=delta, SHARED_CHANNELS=16, HEAD_CHANNELS=16)
        torch.manual_seed(0)
        model = CounterNet(cfg)
        classes = list(model.config.class_names)
        batch = batch_of([src[0], src[1]], classes)
        on = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        cpu_model = copy.deepcopy(model).eval()
        model = model.to(device).train()
        out = model(on)
        out["loss"].backward()
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        finite = bool(torch.isfinite(out["loss"])) and all(bool(torch.isfinite(g).all()) for g in grads)
        ok &= finite
        print(f"pt {pt} delta {delta} on {device}: training step loss {out['loss'].item():.3f} (heatmap "
              f"{float(out['loss_heatmap']):.3f}, count {float(out['loss_count']):.3f}); {len(grads)} gradients, "
              f"all finite: {finite}")
        model.zero_grad(set_to_none=True)
        model.eval()
        frames = model.predict(on)
        counts = torch.stack([f["counts"] for f in frames]).cpu()
        true = torch.stack([f["true_counts"] for f in frames]).cpu()
        print(f"  predict: counts {counts.tolist()}, true {true.tolist()}, centres "
              f"{[tuple(f['centres'].shape) for f in frames]}")
        # an untrained map has no peak above t = 0.5: with t = 0.05 (and Otsu) it has hundreds, whose positions and
        # merging are then compared too
        model.config.threshold = cpu_model.config.threshold = 0.05
        low = torch.stack([f["counts"] for f in model.predict(on)]).cpu()
        print(f"  predict with t = 0.05: counts {low.tolist()}")
        if device.type == "cuda":
            torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False  # compare float32 with float32
            cpu_model.load_state_dict({k: v.cpu() for k, v in model.state_dict().items()})
            with torch.no_grad():
                hd = [h.float().cpu() for h in model(on)["heatmaps"]]
                hc = cpu_model(batch)["heatmaps"]
            diff = max(float((a - b).abs().max()) for a, b in zip(hd, hc))
            gpu = torch.stack([f["counts"] for f in model.predict(on)]).cpu()
            cc = torch.stack([f["counts"] for f in cpu_model.predict(batch)])
            ok &= diff < 1e-3
            print(f"  cuda vs cpu, same weights, float32: heatmaps max |diff| {diff:.2e}; counts at t = 0.05 equal: "
                  f"{torch.equal(cc, gpu)}, largest difference {int((cc - gpu).abs().max())} of "
                  f"{int(cc.max())} (two near-equal neighbours can swap which is the peak)")
            torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = True
    print("cuda_smoke:", "ok" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
