"""Where do the host synchronisations of a step happen? (CUDA only.)

    python benchmarks/profile/sync_audit.py       # SSCATeR step on drone_bridge + sparse PointPillars (maps cached)
    python benchmarks/profile/sync_audit.py --steps 20

Runs the calls under ``torch.cuda.set_sync_debug_mode("warn")`` and prints, per Python source line,
how many synchronising CUDA calls it made per step (``.item()``, ``.tolist()``, ``nonzero``, blocking
copies...). Synchronisations made inside lidarops' C++ code without going through ATen are not seen.
"""
from __future__ import annotations

import argparse
import collections
import sys
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch


def audit(fn, calls: int, title: str) -> None:
    seen: collections.Counter = collections.Counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            for i in range(calls):
                fn(i)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    root = str(Path(__file__).resolve().parents[2]) + "/"
    for w in caught:
        if "synchroniz" in str(w.message):
            seen[f"{w.filename.replace(root, '')}:{w.lineno}"] += 1
    total = sum(seen.values())
    print(f"\n{title}: {total / calls:.1f} synchronising calls per call")
    for where, n in seen.most_common():
        print(f"  {n / calls:5.1f}  {where}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=10)
    args = ap.parse_args(argv)
    if not torch.cuda.is_available():
        print("sync_audit: needs a GPU")
        return 0
    from benchmarks.bm_sparse import pillars_input
    from benchmarks.bm_sscater import _model
    from lidarops.models.sscater_calibration import calibrate_on_window
    from lidarops.data.synthetic import Simulator

    dev = torch.device("cuda")
    model, _ = _model("drone_bridge", dev, 0.5)
    slices = [(torch.from_numpy(p).to(dev), torch.from_numpy(t).to(dev))
              for p, t in Simulator("drone_bridge", seed=0).slices(0.0, 0.05 + 0.01 * (args.steps + 20), 0.01)]
    for i, (p, t) in enumerate(slices[:10]):
        model.step(p, t, now=0.01 * (i + 1))
    calibrate_on_window(model, 0.5)
    for i, (p, t) in enumerate(slices[:20]):  # warm-up: graphs captured, refresh done
        model.step(p, t, now=0.01 * (i + 1))

    def step(i):
        p, t = slices[20 + i]
        model.step(p, t, now=0.01 * (21 + i))
    audit(step, args.steps, "SSCATeR step (drone_bridge; stream push, PFN, backbone)")

    with torch.no_grad():
        net, _, cached = pillars_input(dev, torch.float32)
        net(cached)
        audit(lambda i: net(cached), args.steps, "Sparse-PointPillars forward, KITTI grid, maps cached")
    return 0


if __name__ == "__main__":
    sys.exit(main())
