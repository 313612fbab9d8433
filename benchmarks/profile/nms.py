"""Where the time of one rotated-NMS call goes on CUDA: torch.profiler's kernel and host times for
``lidarops.nms_bev`` on bm_boxes' PointPillars case (4,096 boxes around 40 objects).

    python benchmarks/profile/nms.py
"""
from __future__ import annotations

import os
import sys

import torch

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path[:0] = [ROOT, os.path.join(ROOT, "tests")]

import lidarops  # noqa: E402
from helpers.boxes import lidar_boxes  # noqa: E402


def main() -> int:
    boxes = lidar_boxes(4096, seed=1, objects=40).float().cuda()
    scores = torch.rand(4096, generator=torch.Generator().manual_seed(1)).cuda()
    for checks in (True, False):
        with lidarops.validation(checks):
            for _ in range(20):
                keep = lidarops.nms_bev(boxes, scores, 0.01, pre_max=4096, post_max=500)
            torch.cuda.synchronize()
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                                    torch.profiler.ProfilerActivity.CUDA]) as prof:
                for _ in range(20):
                    lidarops.nms_bev(boxes, scores, 0.01, pre_max=4096, post_max=500)
                torch.cuda.synchronize()
        print(f"value checks {'on' if checks else 'off'}; kept {keep.numel()} of 4096")
        print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=14))
    return 0


if __name__ == "__main__":
    sys.exit(main())
