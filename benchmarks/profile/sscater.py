"""Where an SSCATeR step spends its time: torch.profiler over steps of the drone_bridge stream.

    python benchmarks/profile/sscater.py [--device cuda] [--steps 20] [--scenario drone_bridge]
    python benchmarks/profile/sscater.py --checkpoint shipped|aerial_pointpillars [--scenario driving_city]

Prints the top ops by self device time and by self CPU time, the host-device synchronisations, and
the per-layer times of one profiled step (``SSCATeRPointPillars(profile=True)``). With ``--checkpoint`` it
profiles a trained detector's stream (``from_detector``, steps with their boxes) instead of the random-weights
model, the refresh steps apart from the recycled ones.
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch  # noqa: E402

from benchmarks.bm_sscater import _checkpoint_path, _first_scenario, _model  # noqa: E402
from lidarops.models.sscater_calibration import calibrate_on_window  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--scenario", default=None,
                    help="default: drone_bridge; with --checkpoint, the first scene it was trained on")
    ap.add_argument("--per-call", default="", help="comma-separated kernel name parts: print each launch's "
                    "device time in the first profiled step, in launch order")
    ap.add_argument("--checkpoint", default="", help="profile a trained detector's stream (with its boxes)")
    a = ap.parse_args()
    from lidarops.data.synthetic import Simulator
    dev = torch.device(a.device)
    if a.checkpoint:
        return profile_detector(a, dev)
    a.scenario = a.scenario or "drone_bridge"
    model, _ = _model(a.scenario, dev, 0.5)
    slices = list(Simulator(a.scenario, seed=0).slices(0.0, 0.01 * (40 + a.steps), 0.01))
    feed = [(torch.from_numpy(p).to(dev), torch.from_numpy(t).to(dev)) for p, t in slices]
    for i, (p, t) in enumerate(feed[:10]):
        model.step(p, t, now=0.01 * (i + 1))
    calibrate_on_window(model, 0.5)
    for i in range(10, 40):
        model.step(*feed[i], now=0.01 * (i + 1))
    acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with torch.profiler.profile(activities=acts) as prof:
        for i in range(40, 40 + a.steps):
            model.step(*feed[i], now=0.01 * (i + 1))
        if dev.type == "cuda":
            torch.cuda.synchronize()
    ka = prof.key_averages()
    _top(prof, a.steps, dev, 25)
    print("== top ops by self CPU time (ms per step)")
    for e in sorted(ka, key=lambda e: e.self_cpu_time_total, reverse=True)[:25]:
        print(f"{e.key[:60]:60s} calls/step {e.count / a.steps:8.1f}  cpu {e.self_cpu_time_total / 1e3 / a.steps:8.3f}")
    if a.per_call and dev.type == "cuda":
        parts = a.per_call.split(",")
        events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
        events.sort(key=lambda e: e.time_range.start)
        per_step = len(events) // a.steps
        for part in parts:
            times = [e.time_range.elapsed_us() for e in events[:per_step] if part in e.name]
            print(f"== {part}: {len(times)} launches in one step, µs: " + " ".join(f"{t:.0f}" for t in times))
    syncs = [e for e in ka if any(s in e.key for s in ("Synchronize", "cudaMemcpy", "item", "nonzero", "unique"))]
    print("== syncing calls per step:", {e.key: round(e.count / a.steps, 1) for e in syncs})
    model.profile = True
    ms = []
    for i in range(40, 40 + min(a.steps, 10)):
        model.step(*feed[i], now=0.01 * (i + 1))
        ms.append([l.ms for l in model.stats.layers])
    names = [l.name for l in model.stats.layers]
    print("== per-layer ms (median of profiled steps, synchronised per layer)")
    for j, n in enumerate(names):
        print(f"{n:16s} {statistics.median(r[j] for r in ms):7.3f}  active {model.stats.layers[j].active:6d}"
              f"  changed {model.stats.layers[j].changed:6d}")


def _top(prof, steps: int, dev, n: int = 30) -> None:
    ka = prof.key_averages()
    dkey = "self_device_time_total" if dev.type == "cuda" else "self_cpu_time_total"
    total = sum(getattr(e, dkey, 0) for e in ka) / 1e3 / steps
    print(f"== top ops by {dkey} (ms per step; all ops {total:.3f})")
    for e in sorted(ka, key=lambda e: getattr(e, dkey, 0), reverse=True)[:n]:
        print(f"{e.key[:70]:70s} calls/step {e.count / steps:7.1f}  dev {getattr(e, dkey, 0) / 1e3 / steps:7.3f}"
              f"  cpu {e.self_cpu_time_total / 1e3 / steps:7.3f}")


def profile_detector(a, dev) -> None:
    """The trained detector's stream: stage times per step, then torch.profiler over recycled steps and over
    refresh steps apart."""
    from lidarops.data.synthetic import Simulator
    from lidarops.models import load_model
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    det = load_model(_checkpoint_path(a.checkpoint), map_location=dev).eval()
    model = SSCATeRPointPillars.from_detector(det, device=dev)
    scenario = a.scenario or _first_scenario(a.checkpoint)
    sim = Simulator(scenario, seed=0)
    feed = []
    for k in range(60 + 2 * a.steps):
        p, t = sim.stream(k * 0.01, (k + 1) * 0.01)
        feed.append((torch.from_numpy(p).to(dev), torch.from_numpy(t).to(dev), (k + 1) * 0.01))
    stages = []
    for k, (p, t, now) in enumerate(feed[:60]):
        model.step(p, t, now=now)
        model.detect()
        if dev.type == "cuda":
            torch.cuda.synchronize()
        st = model.stats
        if k >= 12:
            stages.append((st.refreshed, st.ms_stream, st.ms_pfn, st.ms_backbone))
    for refreshed in (False, True):
        rows = [r[1:] for r in stages if r[0] == refreshed]
        if rows:
            med = [statistics.median(c) for c in zip(*rows)]
            print(f"== {scenario} {'refresh' if refreshed else 'recycled'} steps ({len(rows)}): stream "
                  f"{med[0]:.3f} ms, pillar net {med[1]:.3f}, backbone {med[2]:.3f} (medians)")
    acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    recycled = refresh = 0
    with torch.profiler.profile(activities=acts) as prof:
        for p, t, now in feed[60:]:
            if model._since_refresh is not None and model._since_refresh + 1 >= model.refresh_every:
                model._since_refresh = 0  # keep this profile to recycled steps
            model.step(p, t, now=now)
            model.detect()
            recycled += 1
        if dev.type == "cuda":
            torch.cuda.synchronize()
    print(f"== recycled steps with their boxes ({recycled})")
    _top(prof, recycled, dev)
    with torch.profiler.profile(activities=acts) as prof:
        for p, t, now in feed[-3:]:
            model._since_refresh = None  # every step a refresh
            model.step(p, t, now=now + 0.02)
            model.detect()
            refresh += 1
        if dev.type == "cuda":
            torch.cuda.synchronize()
    print(f"== refresh steps with their boxes ({refresh})")
    _top(prof, refresh, dev, 20)


if __name__ == "__main__":
    main()
