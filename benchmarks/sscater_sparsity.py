"""How sparse a trained detector's streamed activations and their changes are, layer by layer (issue 39): what
SSCATeR's recycling and a channel-sparse delta convolution could exploit.

    python benchmarks/sscater_sparsity.py --device cuda --steps 1000 --json
    python benchmarks/sscater_sparsity.py --device cpu --steps 50          # a short look on the CPU

The stream: ``--steps`` slices of 10 ms of the simulated ``--scenario`` (seed 0), a 100 ms window, through
``SSCATeRPointPillars.from_detector`` of a shipped PointPillars (``--checkpoint``: ``pointpillars_synth`` on
``driving_city`` by default, ``aerial_pointpillars`` on ``drone_bridge``; float32; the backbone is
recycled over every site, as the dense detector computes it). After each step, for the pillar net's map (the
backbone's input) and for every convolution's output (after BatchNorm and ReLU), over every site of its map:

* ``zeros``: the share of (site, channel) values that are exactly 0 (ReLU's zeros; the input map's empty sites);
* ``changed``: the share of sites whose value changed since the last step (any channel): what the next layer
  must recompute around;
* ``zero_delta_channels``: at those changed sites, the share of channels whose change is exactly 0 (zero before
  and after): the input channels a channel-sparse delta convolution of the next layer could skip.

Each figure is averaged over the steps after the first (the window fills during the first 100 ms). Also the share
of pillars that changed per step (``pillars_changed / pillars_active``, the seed's 27.2 % on its drone data).
``--json`` writes the rows as section ``"sscater_sparsity"`` of ``benchmarks/results/<device>.json``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from benchmarks.common import bench_device, device_name, env_meta, print_table, write_results

SECTION = "sscater_sparsity"


def _nodes(model) -> list[tuple[str, torch.Tensor]]:
    """(name, (H, W, C) map) of the backbone's input and of every convolution's output, in execution order."""
    delta = model.delta
    return [("input (pillar net)", delta.in_feats)] + [(layer.name, layer.feats)
                                                        for layer in delta.layers + delta.up_layers]


def figures(feats: torch.Tensor, prev: torch.Tensor) -> torch.Tensor:
    """``[zeros, changed, zero_delta_channels, any site changed]`` of one (H, W, C) map against its previous value
    (see the module docstring); one tensor, read with the step's others."""
    d = feats - prev
    changed = (d != 0).any(-1)
    n_changed = changed.sum()
    zero_delta = ((d == 0) & changed[..., None]).sum() / (n_changed * feats.shape[-1]).clamp(min=1)
    return torch.stack([(feats == 0).float().mean(), changed.float().mean(), zero_delta.float(),
                        (n_changed > 0).float()])


def measure(device: torch.device, steps: int, scenario: str = "driving_city", seed: int = 0,
            checkpoint: str = "pointpillars_synth", realism: str | None = None) -> tuple[list[dict], dict]:
    from lidarops.data.synthetic import Simulator
    from lidarops.models import weights
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    detector = weights.load(checkpoint, map_location=device).float().to(device).eval()
    model = SSCATeRPointPillars.from_detector(detector, dtype=torch.float32, device=device)
    sim = Simulator(scenario, seed=seed, realism=realism)
    sums: dict[str, list[float]] = {}
    prev: dict[str, torch.Tensor] = {}
    pillar_share, counted, refreshed = [], 0, 0
    t0 = time.perf_counter()
    for k in range(steps):
        a, b = k * 0.01, (k + 1) * 0.01
        pts, t = sim.stream(a, b)
        model.step(torch.from_numpy(pts).to(device), torch.from_numpy(t).to(device), now=b)
        st = model.stats
        nodes = _nodes(model)
        if k >= 10:  # the window has filled
            step_figures = torch.stack([figures(feats, prev[name]) for name, feats in nodes]).tolist()
            for (name, _), (zeros, ch, zd, any_change) in zip(nodes, step_figures):
                s = sums.setdefault(name, [0.0, 0.0, 0.0, 0.0])
                s[0] += zeros
                s[1] += ch
                s[2] += zd * any_change
                s[3] += any_change
            counted += 1
            refreshed += bool(st.refreshed)
            if st.pillars_active:
                pillar_share.append(st.pillars_changed / st.pillars_active)
        prev = {name: feats.clone() for name, feats in nodes}
        if (k + 1) % 100 == 0:
            print(f"  step {k + 1} of {steps} ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = []
    for name, (zeros, ch, zd, n_any) in sums.items():
        scene = f"{scenario}+{realism}" if realism else scenario
        rows.append(dict(section=SECTION, op=f"{SECTION}/{scene}/{name}", scenario=scenario, checkpoint=checkpoint,
                         realism=realism, node=name,
                         zeros=round(zeros / counted, 4), changed=round(ch / counted, 4),
                         zero_delta_channels=round(zd / n_any, 4) if n_any else None, steps=counted))
    info = dict(scenario=scenario, checkpoint=checkpoint, realism=realism, seed=seed, steps=steps, steps_measured=counted,
                refresh_steps=refreshed,
                pillars_changed_share=round(sum(pillar_share) / max(1, len(pillar_share)), 4),
                seconds=round(time.perf_counter() - t0, 1))
    return rows, info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="auto", help="auto (default), cpu or cuda")
    ap.add_argument("--steps", type=int, default=1000, help="10 ms steps (default 1000)")
    ap.add_argument("--checkpoint", default="pointpillars_synth",
                    help="shipped detector streamed (default pointpillars_synth; aerial_pointpillars on the drone "
                         "scenes)")
    ap.add_argument("--scenario", default=None,
                    help="the stream (default: the first scene the checkpoint was trained on)")
    ap.add_argument("--realism", default=None,
                    help="the scene's realism profile (default: the one the checkpoint's first frames of that scene "
                         "were made with; none: ray-cast)")
    ap.add_argument("--json", action="store_true", help="write benchmarks/results/<device>.json")
    a = ap.parse_args(argv)
    if a.steps < 12:
        ap.error("--steps must be at least 12 (the first 10 fill the window)")
    dev = bench_device(a.device)
    if dev is None:
        return 2
    from benchmarks.bm_sscater import _first_scenario, stream_realism

    scenario = a.scenario or _first_scenario(a.checkpoint)
    realism = stream_realism(a.checkpoint, scenario, a.realism)
    rows, info = measure(dev, a.steps, scenario, checkpoint=a.checkpoint, realism=realism)
    scene = f"{scenario} ({realism} profile)" if realism else scenario
    print_table(f"== {a.checkpoint} streaming {scene} ({device_name(dev)}), {info['steps_measured']} "
                f"steps measured; pillars changed per step: {100 * info['pillars_changed_share']:.1f} % of the active",
                ["node", "zeros", "changed sites", "zero delta channels at changed sites"],
                [[r["node"], f"{100 * r['zeros']:.1f} %", f"{100 * r['changed']:.1f} %",
                  "" if r["zero_delta_channels"] is None else f"{100 * r['zero_delta_channels']:.1f} %"] for r in rows],
                right=(1, 2, 3))
    if a.json:
        meta = env_meta(dev)
        meta.update(benchmark=f"benchmarks/sscater_sparsity.py --device {dev.type} --steps {a.steps} "
                              f"--checkpoint {a.checkpoint} --scenario {scenario} --realism {realism or 'none'}",
                    **info)
        print("wrote", write_results(SECTION, dev, rows, meta, replace_by="op"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
