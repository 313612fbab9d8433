"""Does OpenPCDet's own CPU box IoU (``iou3d_nms_utils.boxes_bev_iou_cpu``, which its gt sampling calls)
survive identical boxes? Each case runs in a child process, so a crash is reported rather than fatal.

    python tools/upstream/openpcdet/cpu_op_probe.py OPENPCDET
"""
from __future__ import annotations

import subprocess
import sys

CASE = """
import sys, torch
sys.path.insert(0, {src!r})
from pcdet.ops.iou3d_nms import iou3d_nms_utils as T
g = torch.Generator().manual_seed(0)
a = torch.rand(50, 7, generator=g) * torch.tensor([40., 40., 2., 4., 2., 2., 6.28]) + torch.tensor([0., 0., 0., .5, .5, .5, 0.])
b = {b}
if "index_fill_" in {b!r}:
    a = b.clone()
print(float(T.boxes_bev_iou_cpu(a, b).max()))
"""


def main(src: str) -> int:
    crashed = False
    for name, b in (("distinct boxes", "a.flip(0) + 0.37"), ("identical boxes", "a.clone()"),
                    ("identical upright boxes", "a.clone().index_fill_(1, torch.tensor([6]), 0.)")):
        code = CASE.format(src=src, b=b)
        p = subprocess.run([sys.executable, "-X", "faulthandler", "-c", code], capture_output=True, text=True)
        tail = (p.stdout + p.stderr).strip().splitlines()[-1:] or [""]
        print(f"OpenPCDet boxes_bev_iou_cpu, {name}: exit {p.returncode} {tail[0][:160]}")
        crashed |= p.returncode != 0
    return 3 if crashed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
