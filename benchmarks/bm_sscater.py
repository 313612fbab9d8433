"""Benchmark of SSCATeR (lidarops.sscater) against the full sparse and the dense PointPillars front.

    python benchmarks/bm_sscater.py                       # CUDA when available, else CPU
    python benchmarks/bm_sscater.py --device cpu --json   # write benchmarks/results/<device>.json
    python benchmarks/bm_sscater.py --quick               # smoke test

Sections (``--only``):

* ``stream``: per 10 ms step of a simulated stream (``drone_bridge`` Avia on a hovering drone, 512 x 512
  pillars; ``driving_city`` HDL-64, 320 x 320 pillars ahead of the car), the default PointPillars sizes
  (PFN 64, blocks 3/5/5 with 64/128/256 channels, upsampling to 3 x 128): active and changed sites per
  layer, PFN points saved, and the time of one step for SSCATeR (stream push + PFN on the changed
  pillars + recycling backbone) against the full sparse recomputation (pillarize + PFN + sparse
  backbone) and the dense backbone (pillarize + PFN + scatter + cuDNN), with the identity of SSCATeR
  and the full recomputation checked on every timed step.
* ``detector`` (``--only detector``; ``--checkpoint``, default the shipped detector): the trained PointPillars
  streamed on the scene it was trained on (``--detector-scenario``, ``--realism``) with its boxes every 10 ms
  (``SSCATeRPointPillars.from_detector``), against the detector on the same window, stage by stage; the boxes
  compared every ``--every`` steps, and SSCATeR's detection AP against the detector's on the windows that are whole
  frames of the simulator (their labels; untimed).
* ``layer``: one 3x3 submanifold layer on the stream's 512 x 512 pillar map (the paper's Tables IV/V):
  Cin in {16, 32, 64, 128} x Cout in {8, 16, 32, 64, 128}; SSCATeR's update for one step's changed
  sites against the full sparse layer (kernel map cached) and the dense layer (cuDNN).

The ``stream`` and ``layer`` sections use seeded random weights (``lidarops.models.sscater_calibration``, as
in ``lidarops stream``) whose BatchNorms are calibrated on the first window so that each layer's
pre-activations have unit spread and a chosen share of them is negative (``--relu-zeros``, default
0.5): a trained network's ReLU sparsity, which is what stops changes from spreading through the layers.
The share actually reached is reported.

Step times are reported as median, mean and p95 over the steps: many steps of a spinning sensor's
stream change nothing and cost little, so the median alone overstates the saving.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch
import torch.nn.functional as F

from benchmarks.common import env_meta, fmt_ms, fmt_ratio, print_table, time_call, write_results
from lidarops.models.sscater_calibration import calibrate_on_window

_SCENARIOS = ("drone_bridge", "driving_city")


def _grid(scenario: str):
    from lidarops.stream import PillarGrid
    if scenario.startswith("drone"):
        return PillarGrid.drone(), 100
    return PillarGrid.driving_ahead(), 256


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _model(scenario: str, device, zeros: float, seed: int = 0):
    """The default-size PointPillars front of :func:`lidarops.models.sscater_calibration.build_model` (seeded random
    weights) in an :class:`~lidarops.models.SSCATeRPointPillars` on ``scenario``'s grid, and its pillar
    capacity. Calibrate it with :func:`lidarops.models.sscater_calibration.calibrate_on_window` once its window is full."""
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    from lidarops.models.sscater_calibration import build_model
    pfn, bb = build_model(False, seed, torch.float32, device)
    grid, N = _grid(scenario)
    return SSCATeRPointPillars(pfn, bb, grid, max_points_per_pillar=N, refresh_every=0, device=device), N



def _quantile(xs: list, q: float) -> float:
    """Linear interpolation between the closest ranks (numpy's default)."""
    v = sorted(xs)
    pos = q * (len(v) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(v) - 1)
    return v[lo] + (v[hi] - v[lo]) * (pos - lo)


def bench_stream(device, steps: int, every: int, zeros: float, rows: list, traces: dict, scenarios=_SCENARIOS):
    from lidarops.data.synthetic import Simulator
    from lidarops.models.map_to_bev import scatter_to_bev
    from lidarops.sparse import SparseConvTensor
    from lidarops.stream import pillarize
    for scenario in scenarios:
        model, N = _model(scenario, device, zeros)
        sim = Simulator(scenario, seed=0)
        slices = list(sim.slices(0.0, 0.01 * steps, 0.01))
        # calibrate on the first full window
        for i, (p, t) in enumerate(slices[:10]):
            model.step(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device), now=0.01 * (i + 1))
        shares = calibrate_on_window(model, zeros)
        pushed_p, pushed_t = [], []
        ss, full, full_bb, dense, rel, stats = [], [], [], [], [], []
        for i, (p, t) in enumerate(slices):
            pt, tt = torch.from_numpy(p).to(device), torch.from_numpy(t).to(device)
            pushed_p.append(pt)
            pushed_t.append(tt)
            _sync(device)
            t0 = time.perf_counter()
            out = model.step(pt, tt, now=0.01 * (i + 1))
            _sync(device)
            ss.append((time.perf_counter() - t0) * 1e3)
            stats.append(model.stats)
            if i < 10 or i % every:
                continue
            allp, allt = torch.cat(pushed_p), torch.cat(pushed_t)
            keep = allt > model.stats.t - model.window
            pushed_p, pushed_t = [allp[keep]], [allt[keep]]
            win = allp[keep]
            out = out.clone()
            _sync(device)
            t0 = time.perf_counter()
            with torch.no_grad():  # what model.recompute does, with the backbone timed on its own
                pil = pillarize(win, model.grid, N, model.stream.max_pillars)
                f = model.pfn(pil).to(model.dtype)
                _sync(device)
                t1 = time.perf_counter()
                ref = model.backbone(SparseConvTensor(f, pil.coords, list(model.grid.shape), 1), mode="sparse")
            _sync(device)
            full.append((time.perf_counter() - t0) * 1e3)
            full_bb.append((time.perf_counter() - t1) * 1e3)
            scale = float(ref.abs().max())
            rel.append(float((out - ref).abs().max()) / scale if scale else 0.0)
            _sync(device)
            t0 = time.perf_counter()
            with torch.no_grad():
                pil = pillarize(win, model.grid, N, 12000)
                img = scatter_to_bev(model.pfn(pil), pil.coords, model.grid.shape)
                model.backbone(img, mode="dense")
            _sync(device)
            dense.append((time.perf_counter() - t0) * 1e3)
        run = stats[10:]
        ss_run = ss[10:]
        med = statistics.median
        layer_names = [l.name for l in run[0].layers]
        reached = [shares.get(n, 0.0) for n in layer_names]
        active = [med([s.layers[j].active for s in run]) for j in range(len(layer_names))]
        changed = [med([s.layers[j].changed for s in run]) for j in range(len(layer_names))]
        share = [c / a if a else 0.0 for c, a in zip(changed, active)]
        row = {
            "op": "sscater_stream", "scenario": scenario, "device": str(device), "steps": len(run),
            "relu_zeros_target": zeros, "relu_zeros_reached": reached, "relu_zeros_reached_pfn": shares.get("pfn"),
            "ms_sscater": med(ss_run), "ms_full_sparse": med(full) if full else None,
            # the step time's spread: medians over steps of which many change nothing flatter SSCATeR
            "ms_sscater_mean": statistics.fmean(ss_run), "ms_sscater_p95": _quantile(ss_run, 0.95),
            "ms_full_sparse_mean": statistics.fmean(full) if full else None,
            "ms_full_sparse_p95": _quantile(full, 0.95) if full else None,
            "ms_dense_mean": statistics.fmean(dense) if dense else None,
            "ms_dense_p95": _quantile(dense, 0.95) if dense else None,
            "ms_dense": med(dense) if dense else None,
            "speedup_vs_full": med(full) / med(ss_run) if full else None,
            "speedup_vs_dense": med(dense) / med(ss_run) if dense else None,
            "ms_sscater_stages": {k: med([getattr(s, k) for s in run]) for k in ("ms_stream", "ms_pfn", "ms_backbone")},
            # the backbones alone: the recycling update against backbone(mode="sparse") with its maps built
            "ms_full_backbone": med(full_bb) if full_bb else None,
            "under_10ms": sum(v < 10.0 for v in ss_run) / len(ss_run),
            "pillars_active": med([s.pillars_active for s in run]), "pillars_changed": med([s.pillars_changed for s in run]),
            "pfn_saved": statistics.mean([s.pfn_saved for s in run]),
            "layers": layer_names, "active": active, "changed": changed, "changed_share": share,
            "changed_share_mean": statistics.mean(share), "max_rel_diff": max(rel) if rel else None,
            "checks": len(rel),
        }
        row["speedup_vs_full_mean"] = row["ms_full_sparse_mean"] / row["ms_sscater_mean"] if full else None
        row["speedup_vs_dense_mean"] = row["ms_dense_mean"] / row["ms_sscater_mean"] if dense else None
        row["backbone_speedup_vs_full"] = (row["ms_full_backbone"] / row["ms_sscater_stages"]["ms_backbone"]
                                           if full_bb else None)
        rows.append(row)
        traces[scenario] = {"ms_sscater": ss, "ms_full_sparse_every": every, "ms_full_sparse": full, "ms_dense": dense,
                            "changed_share": [s.pillars_changed / max(s.pillars_active, 1) for s in stats]}
        print_table(f"\nSSCATeR stream {scenario} on {device}: {len(run)} steps, ReLU zeros {zeros:.0%} targeted",
                    ["stage", "SSCATeR ms", "full sparse ms", "dense ms", "vs full", "vs dense"],
                    [["step (median)", fmt_ms(row["ms_sscater"]), fmt_ms(row["ms_full_sparse"]), fmt_ms(row["ms_dense"]),
                      fmt_ratio(row["speedup_vs_full"]), fmt_ratio(row["speedup_vs_dense"])],
                     ["step (mean)", fmt_ms(row["ms_sscater_mean"]), fmt_ms(row["ms_full_sparse_mean"]),
                      fmt_ms(row["ms_dense_mean"]), fmt_ratio(row["speedup_vs_full_mean"]),
                      fmt_ratio(row["speedup_vs_dense_mean"])],
                     ["step (p95)", fmt_ms(row["ms_sscater_p95"]), fmt_ms(row["ms_full_sparse_p95"]),
                      fmt_ms(row["ms_dense_p95"]), "", ""]]
                    + [[f"  {k[3:]}", fmt_ms(v), "", "", "", ""] for k, v in row["ms_sscater_stages"].items()
                       if k != "ms_backbone"]
                    + [["  backbone", fmt_ms(row["ms_sscater_stages"]["ms_backbone"]), fmt_ms(row["ms_full_backbone"]),
                        "", fmt_ratio(row["backbone_speedup_vs_full"]), ""]],
                    right=(1, 2, 3, 4, 5))
        print_table("", ["layer", "active", "changed", "changed %", "zeros %"],
                    [[n, f"{a:.0f}", f"{c:.0f}", f"{100 * s:.1f}", f"{100 * z:.0f}"]
                     for n, a, c, s, z in zip(layer_names, active, changed, share, reached)], right=(1, 2, 3, 4))
        print(f"pillars changed {row['pillars_changed']:.0f} of {row['pillars_active']:.0f}; PFN points saved "
              f"{100 * row['pfn_saved']:.1f}%; mean changed share over layers {100 * row['changed_share_mean']:.1f}%; "
              f"steps under 10 ms {100 * row['under_10ms']:.0f}%; identity max rel diff {row['max_rel_diff']:.2e} "
              f"over {row['checks']} checks")


def bench_layers(device, quick: bool, rows: list):
    """One submanifold 3x3 layer on the drone stream's pillar map: SSCATeR update vs full sparse vs dense."""
    from lidarops.data.synthetic import Simulator
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs
    from lidarops.stream import PillarGrid, PillarStream
    grid = PillarGrid.drone()
    stream = PillarStream(grid, 0.1, 100, 12000, device=device)
    for i, (p, t) in enumerate(Simulator("drone_bridge", seed=0).slices(0.0, 0.5, 0.01)):
        upd = stream.push(torch.from_numpy(p).to(device), torch.from_numpy(t).to(device), now=0.01 * (i + 1))
    H, W = grid.shape
    active = upd.active[:, 1:].contiguous()
    changed = upd.changed[:, 1:].contiguous()
    ops = torch.ops.lidarops
    cins = (16, 64) if quick else (16, 32, 64, 128)
    couts = (16, 64) if quick else (8, 16, 32, 64, 128)
    out_rows = []
    for cin in cins:
        for cout in couts:
            g = torch.Generator(device="cpu").manual_seed(cin * 1000 + cout)
            x = torch.randn(active.shape[0], cin, generator=g).to(device)
            w = torch.randn(cout, 3, 3, cin, generator=g).to(device) * 0.1
            w_taps = w.permute(1, 2, 0, 3).contiguous().permute(2, 0, 1, 3)
            scale, shift = torch.ones(cout, device=device), torch.zeros(cout, device=device)
            acc = torch.zeros(H, W, cout, device=device)
            feats = torch.zeros(H, W, cout, device=device)
            act = torch.zeros(H, W, dtype=torch.bool, device=device)
            act[active[:, 0].long(), active[:, 1].long()] = True
            delta = torch.randn(changed.shape[0], cin, generator=g).to(device)

            stamp = torch.zeros(H, W, dtype=torch.int32, device=device)
            none = torch.zeros(0, 2, dtype=torch.int32, device=device)
            step = [0]

            def sscater_layer():  # what DeltaBackbone._layer_step does for a submanifold layer
                step[0] += 4
                reached = ops.sscater_scatter_(acc, changed, delta, w_taps, 1, 1, False, act)
                cand, count = ops.sscater_touch_(stamp, acc, step[0] + 2, reached, none, none)
                sites, d, counts = ops.sscater_finalize_compact_(acc, feats, act, cand, count, stamp, step[0] + 3,
                                                                 scale, shift)
                if device.type == "cuda":  # sync-free: the next layer reads the count on the device
                    return sites, d, counts[:1]
                n = int(counts[0])  # CPU: the list is trimmed
                return sites[:n], d[:n]

            xs = SparseConvTensor(x, torch.cat([torch.zeros_like(active[:, :1]), active], 1), [H, W], 1)
            km = Fs.build_kernel_map(xs, "subm", 3)
            wk = w.reshape(cout, 9, cin)

            def full_layer():
                return torch.relu(ops.sparse_conv(x, wk, km.neighbors, km.order) * scale + shift)

            dense_x = xs.dense()
            wd = w.permute(0, 3, 1, 2).contiguous()

            def dense_layer():
                return torch.relu(F.conv2d(dense_x, wd, None, 1, 1))

            with torch.no_grad():
                t_ss = time_call(sscater_layer, (), device).median
                t_full = time_call(full_layer, (), device).median
                t_dense = time_call(dense_layer, (), device).median
            r = {"op": "sscater_layer", "device": str(device), "cin": cin, "cout": cout, "active": int(active.shape[0]),
                 "changed": int(changed.shape[0]), "ms_sscater": t_ss, "ms_full_sparse": t_full, "ms_dense": t_dense,
                 "speedup_vs_full": t_full / t_ss, "speedup_vs_dense": t_dense / t_ss}
            rows.append(r)
            out_rows.append(r)
    print_table(f"\nOne SubM 3x3 layer on the drone_bridge pillar map ({H}x{W}), {out_rows[0]['active']} active, "
                f"{out_rows[0]['changed']} changed sites, {device}",
                ["Cin", "Cout", "SSCATeR ms", "full sparse ms", "dense ms", "vs full", "vs dense"],
                [[r["cin"], r["cout"], fmt_ms(r["ms_sscater"]), fmt_ms(r["ms_full_sparse"]), fmt_ms(r["ms_dense"]),
                  fmt_ratio(r["speedup_vs_full"]), fmt_ratio(r["speedup_vs_dense"])] for r in out_rows],
                right=(0, 1, 2, 3, 4, 5, 6))


def plot(traces: dict, rows: list, device: str, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(traces), figsize=(6.5 * len(traces), 4), squeeze=False)
    for ax, (scenario, tr) in zip(axes[0], traces.items()):
        ss = tr["ms_sscater"]
        ax.plot(range(len(ss)), ss, lw=0.8, label="SSCATeR step")
        every = tr["ms_full_sparse_every"]
        xs = [i for i in range(10, len(ss)) if i % every == 0][:len(tr["ms_full_sparse"])]
        ax.plot(xs, tr["ms_full_sparse"], "o", ms=3, label="full sparse recomputation")
        ax.plot(xs, tr["ms_dense"], "x", ms=3, label="dense (cuDNN/ATen)")
        ax.axhline(10.0, color="k", ls="--", lw=0.8, label="10 ms budget")
        ax.set_yscale("log")
        ax.set_xlabel("step (10 ms)")
        ax.set_ylabel("ms per step")
        ax.set_title(f"{scenario} ({device})")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def _graphs_recorded(model) -> int:
    """CUDA graphs the stream has recorded so far (each new input capacity of a step or a refresh records one, once)."""
    return model.delta.cuda_graphs + (model._detect_graph is not None)


def _refresh_graph(model) -> bool:
    """Whether the stream's refreshes replayed a CUDA graph."""
    return bool(model.delta._refresh_graphs)


def _p95(xs: list) -> float:
    return sorted(xs)[min(len(xs) - 1, int(round(0.95 * (len(xs) - 1))))]


def bench_channel_sparse(device, rows: list, quick: bool = False) -> None:
    """The two scatter kernels on one delta layer (3x3, the detector's block widths, changed sites as on the
    drone stream): each row's nonzero channels alone (``channel_sparse=0``) against one GEMM per tap over the
    whole delta (``channel_sparse=2``), as the share of exactly-zero delta values grows. The op's default picks
    the sparse kernel from the share where it starts to win (on CUDA the choice is made on the device, so the
    default's time, with its count of the zeros, is shown too)."""
    from lidarops import extension

    extension.load()
    scatter = torch.ops.lidarops.sscater_scatter_
    g = torch.Generator().manual_seed(0)
    table = []
    shapes = [(252, 4000, 64, 1), (126, 3000, 128, 1), (63, 1500, 256, 1), (252, 4000, 64, 2)]
    for H, n, C, stride in shapes[:2] if quick else shapes:
        keys = torch.randperm(H * H, generator=g)[:n]
        sites = torch.stack([keys // H, keys % H], 1).int().to(device)
        weight = torch.randn(C, 3, 3, C, generator=g).to(device)
        Ho = (H + 2 - 3) // stride + 1
        for zeros in ((0.5, 0.9) if quick else (0.0, 0.5, 0.7, 0.8, 0.85, 0.9, 0.95)):
            delta = torch.randn(n, C, generator=g)
            delta[torch.rand(n, C, generator=g) < zeros] = 0.0
            delta = delta.to(device)
            acc = torch.zeros(Ho, Ho, C, device=device)
            ms = {}
            for name, arg in (("sparse", 0.0), ("gemm", 2.0), ("default", 0.85)):
                if name == "default" and device.type == "cpu":
                    continue  # the CPU counts the zeros on the host: the default is one of the two
                ms[name] = time_call(lambda a=arg: scatter(acc, sites, delta, weight, stride, 1, False, None, None, a),
                                     (), device, min_runs=5 if device.type == "cpu" else 20,
                                     budget_s=1.0 if device.type == "cpu" else 0.3).median
            row = {"op": f"sscater_channel_sparse/{C}ch_s{stride}_z{zeros:g}", "channels": C, "stride": stride,
                   "rows": n, "zero_share": zeros, "sparse_ms": ms["sparse"], "gemm_ms": ms["gemm"],
                   "default_ms": ms.get("default"), "sparse_speedup": ms["gemm"] / ms["sparse"]}
            rows.append(row)
            table.append([f"{C} -> {C}, stride {stride}", f"{100 * zeros:.0f} %", fmt_ms(ms["sparse"]),
                          fmt_ms(ms["gemm"]), fmt_ms(ms["default"]) if "default" in ms else "",
                          fmt_ratio(row["sparse_speedup"])])
    print_table(f"channel-sparse scatter against the per-tap GEMM ({device}, one 3x3 delta layer)",
                ["layer", "zero deltas", "sparse ms", "GEMM ms", "default (0.85) ms", "sparse speed-up"], table,
                right=(1, 2, 3, 4, 5))


def bench_detector(device, steps: int, every: int, checkpoint: str, rows: list, scenario: str = "driving_city",
                   warm: int = 12, channel_sparse: Optional[float] = None,
                   sparse_refresh: bool = False, refresh_format: Optional[str] = None,
                   realism: Optional[str] = None, warm_up: Optional[int] = 0, eager_push: bool = False) -> dict:
    """A trained PointPillars streamed (``SSCATeRPointPillars.from_detector``): each 10 ms step's boxes by
    SSCATeR (stream push, the detector's pillar net on the changed pillars, the recycled backbone, the head at
    the changed output sites, NMS) against the detector on the same window, stage by stage (pillarize + pillar
    net + scatter, backbone, head + NMS) and as ``predict`` (on CUDA replayed as one CUDA graph, and eager inside
    ``eager_predict()``); every ``every`` steps, with the boxes compared. ``realism``: the simulator's realism
    profile of the scene (None: ray-cast). ``warm_up``: the stream's CUDA graphs recorded before the first step
    (:meth:`SSCATeRPointPillars.warm_up`) for up to that many pillars (0: the stream's ``max_pillars``; None: not
    at all, each is recorded by the first step of its size). ``eager_push``: the stream pushes eagerly
    (``PillarStream.cuda_graph = False``)."""
    from lidarops.data.synthetic import Simulator
    from lidarops.models import load_model, weights
    from lidarops.models.pointpillars import eager_predict
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    path = _checkpoint_path(checkpoint)
    det = load_model(path, map_location=device).eval()
    model = SSCATeRPointPillars.from_detector(det, device=device)
    if channel_sparse is not None:  # before the first update: a CUDA graph keeps the value it was captured with
        model.delta.channel_sparse = float(channel_sparse)
    sim = Simulator(scenario, seed=0, realism=realism)
    model.stream.cuda_graph = not eager_push
    warmed = {}
    if warm_up is not None:
        _sync(device)
        mem = torch.cuda.memory_reserved(device) if device.type == "cuda" else 0
        t0 = time.perf_counter()
        recorded = model.warm_up(warm_up or None)
        _sync(device)
        warmed = {"warm_up_ms": 1e3 * (time.perf_counter() - t0), "warm_up_graphs": recorded,
                  "warm_up_pillars": warm_up or model.stream.max_pillars,
                  "warm_up_memory_mb": ((torch.cuda.memory_reserved(device) - mem) / 2 ** 20
                                        if device.type == "cuda" else 0.0)}
    ours, full, same, pfn, pfn_full = [], [], [], 0, 0
    # detection AP: the windows that are whole frames of the simulator (their labels), SSCATeR's boxes and the
    # detector's on each
    per_frame = max(1, round(sim.frame_period / 0.01))
    ap_frames, ap_ours, ap_full = [], [], []
    for k in range(warm + steps):
        pts, t = sim.stream(k * 0.01, (k + 1) * 0.01)
        _sync(device)
        graphs = _graphs_recorded(model)
        t0 = time.perf_counter()
        model.step(torch.from_numpy(pts).to(device), torch.from_numpy(t).to(device), now=(k + 1) * 0.01)
        boxes = model.detect()
        _sync(device)
        ms = 1e3 * (time.perf_counter() - t0)
        if k < warm:  # the window fills: 10 steps
            continue
        st = model.stats
        pfn, pfn_full = pfn + st.pfn_points, pfn_full + st.pfn_points_full
        ours.append({"k": k - warm, "step": ms, "stream": st.ms_stream, "pfn": st.ms_pfn, "backbone": st.ms_backbone,
                     "head_nms": ms - st.ms_stream - st.ms_pfn - st.ms_backbone, "refreshed": st.refreshed,
                     "changed": st.pillars_changed, "active": st.pillars_active,
                     "recorded": _graphs_recorded(model) - graphs})
        checked, whole_frame = not (k - warm) % every, (k + 1) % per_frame == 0
        if not (checked or whole_frame):
            continue
        batch = {"points": F.pad(model.window_points(), (1, 0)), "batch_size": 1}
        if whole_frame:  # untimed: the frame's labels and, off the checks, the detector's boxes
            ap_frames.append(sim.sweep((k + 1) // per_frame - 1))
            ap_ours.append({key: v.cpu() for key, v in boxes.items()})
            if not checked:
                with torch.no_grad():
                    ap_full.append({key: v.cpu() for key, v in det.predict(batch)[0].items()})
                continue
        with torch.no_grad():
            _sync(device)
            t0 = time.perf_counter()
            want = det.predict(batch)[0]  # on CUDA from the second check a replayed CUDA graph, as users get it
            _sync(device)
            t_predict = 1e3 * (time.perf_counter() - t0)
            with eager_predict():
                det.predict(batch)
            _sync(device)
            t1 = time.perf_counter()
            t_eager = 1e3 * (t1 - t0) - t_predict
            vox = det.voxelize(batch["points"], 1)
            bev_in = det.map_to_bev(det.vfe(*vox), vox[2], 1)
            _sync(device)
            t2 = time.perf_counter()
            bev = det.backbone_2d(bev_in)
            _sync(device)
            t3 = time.perf_counter()
            det.postprocess(det.dense_head(bev))
            _sync(device)
            t4 = time.perf_counter()
        if whole_frame:
            ap_full.append({key: v.cpu() for key, v in want.items()})
        full.append({"predict": t_predict, "predict_eager": t_eager,
                     "pillars_pfn": 1e3 * (t2 - t1), "backbone": 1e3 * (t3 - t2),
                     "head_nms": 1e3 * (t4 - t3)})
        same.append(boxes["labels"].tolist() == want["labels"].tolist()
                    and bool(torch.allclose(boxes["scores"], want["scores"], rtol=1e-4, atol=1e-4)))
    summary = {"scenario": scenario, "checkpoint": path.name, "steps": steps, "checked": len(full),
               "same_boxes": sum(same), "pfn_saved": 1 - pfn / max(pfn_full, 1),
               "refreshes": sum(r["refreshed"] for r in ours),
               "pillars_changed_share": statistics.mean(r["changed"] / max(r["active"], 1) for r in ours),
               "channel_sparse": model.delta.channel_sparse, "sparse_refresh": sparse_refresh,
               "refresh_format": refresh_format or "default", "refresh_graph": _refresh_graph(model),
               "tiling": os.environ.get("LIDAROPS_SSCATER_TILING", "default"), **warmed}
    if ap_frames:
        summary["ap_frames"] = len(ap_frames)
        summary["ap_sscater"], summary["ap_detector"] = stream_ap(ap_frames, ap_ours, ap_full, det.config.class_names,
                                                                  path, list(det.config.point_cloud_range))
        summary["ap_identical"] = summary["ap_sscater"] == summary["ap_detector"]
    for name, xs in (("sscater_step", [r["step"] for r in ours]), ("sscater_backbone", [r["backbone"] for r in ours]),
                     ("sscater_pfn", [r["pfn"] for r in ours]), ("sscater_head_nms", [r["head_nms"] for r in ours]),
                     ("detector_predict", [r["predict"] for r in full]),
                     ("detector_predict_eager", [r["predict_eager"] for r in full]),
                     ("detector_backbone", [r["backbone"] for r in full]),
                     ("detector_pillars_pfn", [r["pillars_pfn"] for r in full]),
                     ("detector_head_nms", [r["head_nms"] for r in full])):
        summary[name] = {"mean_ms": statistics.mean(xs), "median_ms": statistics.median(xs), "p95_ms": _p95(xs),
                         "max_ms": max(xs)}
    for name, refreshed in (("sscater_backbone_refresh", True), ("sscater_backbone_recycled", False)):
        xs = [r["backbone"] for r in ours if r["refreshed"] == refreshed]
        if xs:
            summary[name] = {"mean_ms": statistics.mean(xs), "median_ms": statistics.median(xs), "p95_ms": _p95(xs),
                             "max_ms": max(xs)}
    # what the slowest steps spent their time on (a refresh, the first replay of a new graph capacity...)
    summary["slowest_steps"] = [{key: (round(v, 3) if isinstance(v, float) else v) for key, v in r.items()
                                 if key in ("k", "step", "stream", "pfn", "backbone", "head_nms", "refreshed",
                                            "changed", "recorded")} for r in sorted(ours, key=lambda r: -r["step"])[:5]]
    # a step that records a CUDA graph (a new input capacity) pays for it once; the others only replay
    replayed = [r["step"] for r in ours if not r["recorded"]]
    summary["steps_recording_graphs"] = len(ours) - len(replayed)
    if replayed:
        summary["max_step_replayed_ms"] = max(replayed)
    for what in ("mean_ms", "median_ms"):
        summary[f"step_speedup_{what[:-3]}"] = summary["detector_predict"][what] / summary["sscater_step"][what]
        summary[f"step_speedup_eager_{what[:-3]}"] = \
            summary["detector_predict_eager"][what] / summary["sscater_step"][what]
        summary[f"backbone_speedup_{what[:-3]}"] = summary["detector_backbone"][what] / summary["sscater_backbone"][what]
    tag = "" if channel_sparse is None else f"/channel_sparse_{channel_sparse:g}"
    tag += "/sparse_refresh" if sparse_refresh else ""
    tag += f"/{refresh_format}" if refresh_format else ""
    tag += "/eager_refresh" if model.delta.cuda_graph and not _refresh_graph(model) else ""
    tag += "/no_warm_up" if warm_up is None and device.type == "cuda" else ""
    tag += "/eager_push" if eager_push and device.type == "cuda" else ""
    tag += f"/tiling_{os.environ['LIDAROPS_SSCATER_TILING']}" if os.environ.get("LIDAROPS_SSCATER_TILING") else ""
    scene = f"{scenario}+{realism}" if realism else scenario
    rows.append({"op": f"detector_stream/{scene}/{path.stem}{tag}", **summary})
    print_table(f"trained detector streamed: {path.name} on {scene}, {steps} steps of 10 ms ({device}); "
                f"{summary['refreshes']} refreshes, {100 * summary['pillars_changed_share']:.1f} % of pillars changed "
                f"per step, PFN work saved {100 * summary['pfn_saved']:.1f} %, same boxes {sum(same)} of {len(full)}",
                ["", "mean ms", "median ms", "p95 ms", "max ms"],
                [[name.replace("_", " "), fmt_ms(summary[name]["mean_ms"]), fmt_ms(summary[name]["median_ms"]),
                  fmt_ms(summary[name]["p95_ms"]), fmt_ms(summary[name]["max_ms"])] for name in
                 ("sscater_step", "detector_predict", "detector_predict_eager", "sscater_backbone", "detector_backbone",
                  "sscater_pfn",
                  "detector_pillars_pfn", "sscater_head_nms", "detector_head_nms", "sscater_backbone_refresh",
                  "sscater_backbone_recycled") if name in summary], right=(1, 2, 3, 4))
    print(f"speed-up by the mean step {summary['step_speedup_mean']:.2f}x (median {summary['step_speedup_median']:.2f}x); "
          f"backbone {summary['backbone_speedup_mean']:.2f}x (median {summary['backbone_speedup_median']:.2f}x)")
    if ap_frames:
        names = list(det.config.class_names)
        print_table(f"detection on the {len(ap_frames)} windows that are whole frames of the simulator (moderate AP "
                    f"R40, %): {'identical' if summary['ap_identical'] else 'DIFFERENT'}",
                    ["", *(f"{c} {m}" for c in names for m in ("3D", "BEV"))],
                    [[who, *(f"{summary[key][f'{c}_{m}_moderate_R40']:.2f}" for c in names for m in ("3d", "bev"))]
                     for who, key in (("SSCATeR", "ap_sscater"), ("the detector", "ap_detector"))]
                    + [["objects", *(str(summary["ap_sscater"][f"{c}_moderate_objects"]) for c in names
                                     for _ in range(2))]],
                    right=tuple(range(1, 1 + 2 * len(names))))
    print("slowest steps: " + "; ".join(
        f"#{r['k']} {r['step']:.2f} ms (stream {r['stream']:.2f}, pillar net {r['pfn']:.2f}, backbone "
        f"{r['backbone']:.2f}, head and NMS {r['head_nms']:.2f}{', refresh' if r['refreshed'] else ''}"
        f"{', recorded a CUDA graph' if r['recorded'] else ''})" for r in summary["slowest_steps"]))
    if warmed.get("warm_up_graphs"):
        print(f"warm_up() recorded {warmed['warm_up_graphs']} CUDA graphs for up to {warmed['warm_up_pillars']} pillars "
              f"in {warmed['warm_up_ms']:.0f} ms, holding {warmed['warm_up_memory_mb']:.0f} MB more of the device's memory")
    if summary["steps_recording_graphs"] and "max_step_replayed_ms" in summary:
        print(f"{summary['steps_recording_graphs']} step(s) recorded a CUDA graph (once per new input capacity); the "
              f"slowest of the others took {summary['max_step_replayed_ms']:.2f} ms")
    return summary


def stream_ap(frames: list, ours: list[dict], full: list[dict], class_names, checkpoint: Path,
              point_cloud_range: list) -> tuple[dict, dict]:
    """Moderate AP R40 (3D and BEV, per class, with the number of objects it counts: below 41, R40 cannot reach
    100) of SSCATeR's boxes and of the detector's on the same windows, scored as ``lidarops detect`` scores the
    simulator's frames: labels and detections of the camera's view, or of the sensor's whole view for a model
    trained on whole-view labels (the drone scenes). ``frames``: the windows' labelled frames; ``ours`` / ``full``:
    per window ``{"boxes", "scores", "labels"}``."""
    from lidarops.checkpoint import read_checkpoint
    from lidarops.cli.detect import _sees_whole_view
    from lidarops.data.formats.kitti import KittiCalib
    from lidarops.eval import kitti as kitti_eval

    whole = _sees_whole_view(read_checkpoint(checkpoint))
    calib = KittiCalib.default()
    gt = [kitti_eval.frame_annos(f, calib, camera_fov_only=not whole) for f in frames]
    if whole:
        gt = [kitti_eval.whole_view_annos(g, calib, point_cloud_range) for g in gt]
    counts = kitti_eval.count_difficulties(gt, list(class_names))
    out = []
    for dets in (ours, full):
        dt = [kitti_eval.detection_annos(d, calib, class_names=list(class_names), index=i, camera_fov_only=not whole)
              for i, d in enumerate(dets)]
        _, results = kitti_eval.evaluate(gt, dt, list(class_names), metrics=("bev", "3d"))
        out.append({key: round(v, 4) for key, v in results.items()
                    if key.endswith("_moderate_R40") and key.split("_")[1] in ("3d", "bev")})
        out[-1].update({f"{c}_moderate_objects": counts[c]["moderate"] for c in class_names})
    return out[0], out[1]


def _checkpoint_path(checkpoint: str) -> Path:
    """A checkpoint file, or a shipped one by name ("shipped": the default detector)."""
    from lidarops.models import weights

    if checkpoint == "shipped":
        return weights.path()
    return Path(checkpoint) if Path(checkpoint).exists() else weights.path(checkpoint)


def stream_realism(checkpoint: str, scenario: str, realism: Optional[str]) -> Optional[str]:
    """The realism profile a detector's stream is made with: ``realism`` as given (``"none"``: ray-cast), else the
    one the checkpoint's first training frames of ``scenario`` were made with (``lidarops stream``'s default)."""
    from lidarops.models import weights

    if realism == "none":
        return None
    return realism or weights.trained_realism(_checkpoint_path(checkpoint), scenario)


def _first_scenario(checkpoint: str) -> str:
    """The first scene a checkpoint was trained on (its data recipe), else driving_city."""
    from lidarops.models import weights

    return next(iter(weights.trained_scenarios(_checkpoint_path(checkpoint))), "driving_city")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", default="stream,layer",
                    help="comma-separated: stream, layer, detector, channel_sparse (the two scatter kernels)")
    ap.add_argument("--steps", type=int, default=None, help="10 ms steps per scenario (default 1000 on CUDA, 60 on CPU)")
    ap.add_argument("--every", type=int, default=None, help="time the full recomputation every N steps")
    ap.add_argument("--relu-zeros", type=float, default=0.5)
    ap.add_argument("--scenarios", default=",".join(_SCENARIOS))
    ap.add_argument("--plot", default=None, help="PNG of the per-step runtime trace (default docs/img/sscater_trace_<device>.png)")
    ap.add_argument("--checkpoint", default="shipped",
                    help="--only detector: the trained PointPillars streamed (a file or a shipped name; shipped: the "
                         "default detector)")
    ap.add_argument("--detector-scenario", default=None,
                    help="--only detector: the stream (default: the first scene the checkpoint was trained on)")
    ap.add_argument("--realism", default=None,
                    help="--only detector: the scene's realism profile (default: the one the checkpoint's first "
                         "frames of that scene were made with; none: ray-cast)")
    ap.add_argument("--channel-sparse", type=float, default=None,
                    help="--only detector: the streamed backbone's channel_sparse (default: the device's, "
                         "lidarops.sscater.delta.CHANNEL_SPARSE)")
    ap.add_argument("--sparse-refresh", action="store_true",
                    help="--only detector: refresh with the sparse ops only (not lidarops.sscater.delta.DENSE_REFRESH)")
    ap.add_argument("--refresh-format", choices=("nchw", "channels_last"), default=None,
                    help="--only detector: the dense refresh's memory format (default: the device's, "
                         "lidarops.sscater.delta.DENSE_CHANNELS_LAST)")
    ap.add_argument("--eager-refresh", action="store_true",
                    help="--only detector: no CUDA graph of the refresh (lidarops.sscater.delta.REFRESH_CUDA_GRAPH)")
    ap.add_argument("--warm-up", type=int, default=0, metavar="PILLARS",
                    help="--only detector: record the stream's CUDA graphs before the first step for up to PILLARS "
                         "pillars (SSCATeRPointPillars.warm_up; default 0: the stream's max_pillars)")
    ap.add_argument("--eager-push", action="store_true",
                    help="--only detector: the stream pushes eagerly, not as a CUDA graph (PillarStream.cuda_graph)")
    ap.add_argument("--no-warm-up", action="store_true",
                    help="--only detector: no warm_up(): each CUDA graph is recorded by the first step of its size")
    a = ap.parse_args(argv)
    import lidarops.extension as ext
    ext.load()
    device = torch.device(a.device or ("cuda" if torch.cuda.is_available() and ext.cuda_available() else "cpu"))
    if device.type == "cuda":
        torch.backends.cudnn.allow_tf32 = False
        torch.backends.cuda.matmul.allow_tf32 = False
    steps = a.steps or (30 if a.quick else (1000 if device.type == "cuda" else 60))
    every = a.every or (5 if a.quick else (10 if device.type == "cuda" else 5))
    rows, traces = [], {}
    only = set(a.only.split(","))
    if "stream" in only:
        bench_stream(device, steps, every, a.relu_zeros, rows, traces, a.scenarios.split(","))
    if "layer" in only:
        bench_layers(device, a.quick, rows)
    if "channel_sparse" in only:
        bench_channel_sparse(device, rows, a.quick)
    if a.sparse_refresh:
        from lidarops.sscater import delta
        delta.DENSE_REFRESH[device.type] = 2.0
    if a.refresh_format:
        from lidarops.sscater import delta
        delta.DENSE_CHANNELS_LAST[device.type] = a.refresh_format == "channels_last"
    if a.eager_refresh:
        from lidarops.sscater import delta
        delta.REFRESH_CUDA_GRAPH = False
    if "detector" in only:
        scenario = a.detector_scenario or _first_scenario(a.checkpoint)
        realism = stream_realism(a.checkpoint, scenario, a.realism)
        bench_detector(device, a.steps or (20 if a.quick else (1000 if device.type == "cuda" else 120)),
                       a.every or (5 if a.quick else (10 if device.type == "cuda" else 3)), a.checkpoint, rows,
                       scenario, channel_sparse=a.channel_sparse, sparse_refresh=a.sparse_refresh,
                       refresh_format=a.refresh_format, realism=realism,
                       warm_up=None if a.no_warm_up else a.warm_up, eager_push=a.eager_push)
    if traces and not a.quick:
        from benchmarks.common import device_slug
        plot(traces, rows, str(device), Path(a.plot) if a.plot else
             Path(__file__).resolve().parents[1] / "docs" / "img" / f"sscater_trace_{device_slug(device)}.png")
    if a.json:
        meta = env_meta(device)
        stream_rows = [r for r in rows if not r["op"].startswith(("detector_stream/", "sscater_channel_sparse/"))]
        if stream_rows:
            meta["traces"] = traces
            print(f"results: {write_results('sscater', device, stream_rows, meta, replace_by='op')}")
        sparse_rows = [r for r in rows if r["op"].startswith("sscater_channel_sparse/")]
        if sparse_rows:
            path = write_results('sscater_channel_sparse', device, sparse_rows, env_meta(device), replace_by='op')
            print(f"results: {path}")
        detector_rows = [r for r in rows if r["op"].startswith("detector_stream/")]
        if detector_rows:  # a section of its own: the stream section's meta holds that run's traces
            print(f"results: {write_results('sscater_detector', device, detector_rows, env_meta(device), replace_by='op')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
