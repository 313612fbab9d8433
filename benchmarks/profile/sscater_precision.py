"""How close a trained detector's float32 stream stays to the exact answer: every ``--every`` steps the head
outputs of ``SSCATeRPointPillars.from_detector`` (float32) are compared with the detector's float32 forward on
the same window and with its float64 forward (the exact answer, to float32's eyes), relative to each output's
largest value. So the stream's own error is told apart from the float32 detector's.

    python benchmarks/profile/sscater_precision.py [--device cuda] [--checkpoint shipped] [--steps 300]
"""
from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from benchmarks.bm_sscater import _checkpoint_path, _first_scenario  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--checkpoint", default="shipped")
    ap.add_argument("--scenario", default="")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--refresh-every", type=int, default=25)
    a = ap.parse_args()
    from lidarops.data.synthetic import Simulator
    from lidarops.models import load_model
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    dev = torch.device(a.device)
    det = load_model(_checkpoint_path(a.checkpoint), map_location=dev).eval()
    exact = copy.deepcopy(det).double()
    scenario = a.scenario or _first_scenario(a.checkpoint)
    stream = SSCATeRPointPillars.from_detector(det, device=dev, refresh_every=a.refresh_every)
    sim = Simulator(scenario, seed=5)
    worst = {"stream vs detector": 0.0, "stream vs exact": 0.0, "detector vs exact": 0.0}
    by_age: dict = {}
    for k in range(12 + a.steps):
        pts, t = sim.stream(0.01 * k, 0.01 * (k + 1))
        stream.step(torch.from_numpy(pts).to(dev), torch.from_numpy(t).to(dev), now=0.01 * (k + 1))
        if k < 12 or k % a.every:
            continue
        points = F.pad(stream.window_points(), (1, 0))
        with torch.no_grad():
            f32 = det({"points": points, "batch_size": 1})
            vox = det.voxelize(points, 1)  # the same pillars: float64 points could fall into other cells
            vox64 = [v.double() if v.is_floating_point() else v for v in vox]
            f64 = exact.dense_head(exact.backbone_2d(exact.map_to_bev(exact.vfe(*vox64), vox[2], 1)))
            got = det.dense_head(stream.delta.out)
        errs = {"stream vs detector": 0.0, "stream vs exact": 0.0, "detector vs exact": 0.0}
        for key in ("cls_preds", "box_preds", "dir_cls_preds"):
            if key not in f64:
                continue
            scale = f64[key].abs().max().item() or 1.0
            for name, (x, y) in (("stream vs detector", (got[key], f32[key])),
                                 ("stream vs exact", (got[key].double(), f64[key])),
                                 ("detector vs exact", (f32[key].double(), f64[key]))):
                errs[name] = max(errs[name], (x.double() - y.double()).abs().max().item() / scale)
        age = stream._since_refresh
        for name, e in errs.items():
            worst[name] = max(worst[name], e)
            by_age.setdefault(age, {}).setdefault(name, []).append(e)
        print(f"step {k:4d} since refresh {age:2d}: " + ", ".join(f"{n} {e:.2e}" for n, e in errs.items()), flush=True)
    print("== worst relative error of the head outputs: " + ", ".join(f"{n} {e:.2e}" for n, e in worst.items()))
    for age in sorted(by_age):
        print(f"   {age:2d} steps after a refresh: " + ", ".join(f"{n} {max(v):.2e}" for n, v in by_age[age].items()))


if __name__ == "__main__":
    main()
