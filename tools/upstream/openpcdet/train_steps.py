"""A few steps of OpenPCDet's own PointPillar training (its KittiDataset with gt sampling and the world
augmentations, its model, losses and optimizer), recorded so that two runs can be compared: OpenPCDet's
compiled ops against lidarops.compat.pcdet in their place.

    python tools/upstream/openpcdet/train_steps.py .peers/OpenPCDet DATA --out run.json [--faces] [--steps 8]

DATA: a root prepared by prepare_kitti.py. Every seed is fixed (numpy, random, torch) and the loader
runs in the main process, so two runs draw the same augmentations when the ops answer the same; cuDNN
is set deterministic. Recorded per step: a checksum of the batch the pipeline produced (points,
ground-truth boxes: what gt sampling, which calls ``points_in_boxes_cpu`` and ``boxes_bev_iou_cpu``,
inserted) and the loss.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import random
import sys
from pathlib import Path

import numpy as np
import torch


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("openpcdet", type=Path)
    p.add_argument("data", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--faces", action="store_true")
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=4)
    args = p.parse_args()
    src, data = args.openpcdet.resolve(), args.data.resolve()
    sys.path.insert(0, str(src))
    if args.faces:
        import lidarops.compat.pcdet

        lidarops.compat.pcdet.install()
    from pcdet.config import cfg, cfg_from_yaml_file
    from pcdet.datasets import build_dataloader
    from pcdet.models import build_network, model_fn_decorator

    sys.path.insert(0, str(src / "tools"))
    from train_utils.optimization import build_optimizer

    os.chdir(src / "tools")
    cfg_from_yaml_file("cfgs/kitti_models/pointpillar.yaml", cfg)
    cfg.DATA_CONFIG.DATA_PATH = str(data)
    cfg.DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST[0].USE_ROAD_PLANE = False  # the simulator writes no planes
    seed = 0
    np.random.seed(seed); random.seed(seed); torch.manual_seed(seed); torch.cuda.manual_seed_all(seed)
    torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    logger = logging.getLogger("train_steps")
    dataset, loader, _ = build_dataloader(dataset_cfg=cfg.DATA_CONFIG, class_names=cfg.CLASS_NAMES,
                                          batch_size=args.batch_size, dist=False, workers=0, logger=logger,
                                          training=True)
    model = build_network(model_cfg=cfg.MODEL, num_class=len(cfg.CLASS_NAMES), dataset=dataset).cuda().train()
    optimizer = build_optimizer(model, cfg.OPTIMIZATION)
    model_func = model_fn_decorator()
    steps = []
    it = iter(loader)
    for step in range(args.steps):
        batch = next(it)
        check = {"points": float(np.float64(batch["points"]).sum()), "n_points": int(batch["points"].shape[0]),
                 "gt_boxes": float(np.float64(batch["gt_boxes"]).sum()), "n_gt": int((batch["gt_boxes"][..., 7] > 0).sum())}
        optimizer.zero_grad()
        loss, tb, _ = model_func(model, batch)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.OPTIMIZATION.GRAD_NORM_CLIP)
        optimizer.step()
        steps.append({**check, "loss": float(loss), "loss_rpn": float(tb.get("loss_rpn", float("nan")))})
        print(f"step {step}: {steps[-1]}")
    args.out.write_text(json.dumps({"faces": args.faces, "steps": steps}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
