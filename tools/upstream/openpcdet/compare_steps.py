"""Compare two train_steps.py records (OpenPCDet's own ops vs lidarops.compat.pcdet): the batches the
data pipeline produced must be identical, the losses equal to the run-to-run spread of CUDA training.

    python tools/upstream/openpcdet/compare_steps.py OWN.json FACES.json
"""
from __future__ import annotations

import json
import sys


def main(a_path: str, b_path: str) -> int:
    a, b = json.load(open(a_path))["steps"], json.load(open(b_path))["steps"]
    same_batches = all(x[k] == y[k] for x, y in zip(a, b) for k in ("points", "n_points", "gt_boxes", "n_gt"))
    loss_diff = max(abs(x["loss"] - y["loss"]) for x, y in zip(a, b))
    print(f"{len(a)} training steps: identical batches {same_batches}; largest loss difference {loss_diff:.2e} "
          f"(losses {[round(x['loss'], 4) for x in a]} / {[round(y['loss'], 4) for y in b]})")
    return 0 if same_batches and len(a) == len(b) else 1


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:3]))
