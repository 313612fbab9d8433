"""``lidarops stream``: the simulator streamed through pillarization, the PFN and the SSCATeR backbone.

Each step pushes one slice of points (10 ms by default) into :class:`~lidarops.sscater.SSCATeRPointPillars`,
which updates the pillars, the pillar features and the backbone's output by recomputing only what
changed. Every ``--check-every`` steps the output is compared with a full recomputation of the window
(``pillarize`` + PFN + ``backbone(mode="sparse")``, timed stage by stage), which is also the "full" column
of the printed table. The run ends with a table (time per stage, active and changed sites per layer,
PFN work saved, identity), a PNG (runtime trace, change map, pseudo-image, changed share per layer) and,
with ``--json``, the per-step figures.

No trained checkpoint ships with lidarops: the network has seeded random weights, and BatchNorm's
statistics are calibrated on the first window so that a chosen share of each layer's pre-activations is
negative (``--relu-zeros``), like the ReLU sparsity of a trained network. Which sites change, and so the
work SSCATeR saves, depends on that share; identity with the full recomputation does not.

Examples::

    lidarops stream --scenario drone_bridge --seconds 5
    lidarops stream --scenario driving_city --seconds 2 --device cuda --full-size --json city.json
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections import deque
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import torch
from torch import Tensor
from torch.nn import functional as F

__all__ = ["register", "run", "build_model", "calibrate_relu_zeros", "relu_zero_shares", "SCENARIO_SETUP"]

# scenario -> pillar grid preset. Drones look ahead along x from the sensor; the driving scenes' HDL-64
# sits at the origin with x forward, so the KITTI grid (x in [0, 69.12)) holds the half ahead of the car.
SCENARIO_SETUP = {"drone_bridge": "drone", "drone_lock": "drone", "driving_city": "kitti", "driving_highway": "kitti"}

_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
_BUDGET_MS = 10.0  # one 10 ms slice: a step must keep up with the sensor


# ---- the model ---------------------------------------------------------------------------------------

def build_model(small: bool, seed: int, dtype: torch.dtype, device) -> tuple:
    """Seeded random PointPillars front: (pfn, backbone), in eval mode, on ``device`` in ``dtype``.

    Args:
        small (bool): PFN 16 channels and backbone channels (16, 32, 64) with 32 channels per upsampling
            branch (output 96 channels), for quick CPU runs; otherwise PointPillars' sizes (64; (64, 128,
            256); 3 x 128 = 384 output channels). The layout (3/5/5 convolutions, strides 2/2/2,
            upsampling 1/2/4) is PointPillars' in both cases.
    """
    from lidarops.models.pointpillars import PillarFeatureNet, PointPillarsBackbone
    torch.manual_seed(seed)
    if small:
        pfn = PillarFeatureNet(9, 16)
        backbone = PointPillarsBackbone(16, (3, 5, 5), (2, 2, 2), (16, 32, 64), (1, 2, 4), (32, 32, 32))
    else:
        pfn = PillarFeatureNet(9, 64)
        backbone = PointPillarsBackbone()
    return pfn.eval().to(device, dtype), backbone.eval().to(device, dtype)


def _sparse_pass(pfn, backbone, pillars, shape,
                 on_preactivation: Callable[[str, torch.nn.Module, Tensor], None]) -> None:
    """The sparse network (PFN + ``backbone(mode="sparse")``) on ``pillars``, calling
    ``on_preactivation(name, norm, x)`` with each BatchNorm's input features ``x (Tensor[n, C])`` (active
    sites or points only) before the BatchNorm and ReLU are applied; the callback may change the norm."""
    from lidarops.models.pointpillars import _norm_relu, backbone_layers
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs

    feats, num = pillars.features.to(pfn.linear.weight.dtype), pillars.num_points.long()
    mask = torch.arange(feats.shape[1], device=feats.device) < num[:, None]
    on_preactivation("pfn", pfn.norm, pfn.linear(feats[mask]))
    x = SparseConvTensor(pfn(pillars), pillars.coords, list(shape), 1)
    block_out, n_conv = {}, 0
    for layer in backbone_layers(backbone):
        if layer.kind == "down":
            y = Fs.conv(x, layer.sparse_weight(), None, "conv", stride=layer.stride, padding=1)
        elif layer.kind == "subm":
            y = Fs.conv(x, layer.sparse_weight(), None, "subm", indice_key=f"subm{layer.block}")
        else:
            y = Fs.conv(block_out[layer.block], layer.sparse_weight(), None, "transposed", stride=layer.stride)
        # DeltaBackbone's layer names
        name = f"up{layer.block}" if layer.kind == "up" else f"block{layer.block}.{layer.kind}{n_conv}"
        n_conv += layer.kind != "up"
        on_preactivation(name, layer.norm, y.features)
        y = _norm_relu(y, layer)
        if layer.kind != "up":
            x = block_out[layer.block] = y


@torch.no_grad()
def calibrate_relu_zeros(pfn, backbone, pillars, shape, share: float) -> None:
    """Sets every BatchNorm (running statistics, weight 1, bias 0) so that, on ``pillars``, each channel's
    pre-activation is standardised and its ``share`` quantile sits at 0: about ``share`` of the ReLU
    outputs are zero. Layers are calibrated in order, each on the output of the calibrated layers before it.

    Args:
        pillars (Pillars): e.g. ``pillarize`` of the first window.
        shape ((H, W)): the pillar grid.
        share (float): in [0, 1).
    """
    if not 0.0 <= share < 1.0:
        raise ValueError(f"share must be in [0, 1), got {share}")

    def set_norm(name, norm, x):
        if x.shape[0] == 0:
            return
        k = min(x.shape[0] - 1, max(0, round(share * (x.shape[0] - 1))))
        q = x.sort(dim=0).values[k]
        var = x.var(dim=0, unbiased=False) if x.shape[0] > 1 else torch.ones_like(q)
        norm.running_mean.copy_(q)
        norm.running_var.copy_(torch.where(var > 1e-12, var, torch.ones_like(var)))
        norm.weight.fill_(1.0)
        norm.bias.fill_(0.0)

    _sparse_pass(pfn, backbone, pillars, shape, set_norm)


@torch.no_grad()
def relu_zero_shares(pfn, backbone, pillars, shape) -> dict[str, float]:
    """Share of zero ReLU outputs per layer (PFN: over the real points; backbone: over active sites)."""
    shares = {}

    def measure(name, norm, x):
        if x.shape[0]:
            y = F.batch_norm(x, norm.running_mean, norm.running_var, norm.weight, norm.bias, False, 0.0, norm.eps)
            shares[name] = float((y <= 0).double().mean())

    _sparse_pass(pfn, backbone, pillars, shape, measure)
    return shares


# ---- the run -----------------------------------------------------------------------------------------

def _default_device() -> str:
    from lidarops import extension
    return "cuda" if torch.cuda.is_available() and extension.cuda_available() else "cpu"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def _full_recompute(model, points: Tensor) -> tuple[Tensor, tuple[float, float, float]]:
    """``model.recompute(points)``, the same calls, timed per stage: (output, (ms pillarize, ms PFN,
    ms backbone))."""
    from lidarops.sparse import SparseConvTensor
    from lidarops.stream import pillarize
    dev = model.device
    _sync(dev)
    t0 = time.perf_counter()
    p = pillarize(points.to(dev), model.grid, model.stream.max_points_per_pillar, model.stream.max_pillars)
    _sync(dev)
    t1 = time.perf_counter()
    f = model.pfn(p)
    _sync(dev)
    t2 = time.perf_counter()
    out = model.backbone(SparseConvTensor(f, p.coords, list(model.grid.shape), 1), mode="sparse")
    _sync(dev)
    t3 = time.perf_counter()
    return out, ((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3)


def _progress(total: int, desc: str, enabled: bool):
    if not enabled:
        return None
    try:
        from tqdm import tqdm
    except ImportError:  # tqdm is optional
        return None
    return tqdm(total=total, desc=desc, unit="step", dynamic_ncols=True, leave=True)


def _median(xs) -> float:
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def _fmt_ms(v: float) -> str:
    return "-" if not math.isfinite(v) else (f"{v:.2f}" if v < 100 else f"{v:.0f}")


def _table(header: list[str], rows: list[list[str]], align: str) -> str:
    widths = [max(len(str(c)) for c in col) for col in zip(header, *rows)]
    fmt = "  ".join(("{:<%d}" if a == "l" else "{:>%d}") % w for a, w in zip(align, widths))
    lines = [fmt.format(*header).rstrip(), "  ".join("-" * w for w in widths)]
    lines += [fmt.format(*r).rstrip() for r in rows]
    return "\n".join(lines)


def run(scenario: str = "drone_bridge", seconds: float = 5.0, slice_s: float = 0.01, window: float = 0.1,
        device: Optional[str] = None, dtype: torch.dtype = torch.float32, check_every: int = 10,
        refresh_every: Optional[int] = None, relu_zeros: float = 0.5, seed: int = 0, small: Optional[bool] = None,
        out: Optional[str] = None, json_path: Optional[str] = None, max_points_per_pillar: Optional[int] = None,
        max_pillars: Optional[int] = None, profile: Optional[bool] = None, progress: bool = True,
        threads: Optional[int] = None) -> int:
    """Streams ``seconds`` of ``scenario`` through SSCATeR PointPillars; prints the table, writes the PNG
    (and the JSON). Returns 0 when every identity check is within tolerance, 1 otherwise.

    ``threads``: CPU threads of torch during the run (default 1 on CPU, see ``--threads``; restored after)."""
    if threads is not None and threads < 1:
        raise ValueError(f"--threads must be >= 1, got {threads}")
    dev = torch.device(device or _default_device())
    if threads is None and dev.type == "cpu":
        threads = 1
    saved = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        return _run(scenario, seconds, slice_s, window, dev, dtype, check_every, refresh_every, relu_zeros, seed,
                    small, out, json_path, max_points_per_pillar, max_pillars, profile, progress)
    finally:
        torch.set_num_threads(saved)


def _run(scenario, seconds, slice_s, window, device, dtype, check_every, refresh_every, relu_zeros, seed, small,
         out, json_path, max_points_per_pillar, max_pillars, profile, progress) -> int:
    import lidarops
    from lidarops.data.synthetic import Simulator
    from lidarops.sscater import SSCATeRPointPillars
    from lidarops.stream import PillarGrid, pillarize

    if scenario not in SCENARIO_SETUP:
        raise ValueError(f"scenario must be one of {sorted(SCENARIO_SETUP)}, got {scenario!r}")
    for name, v in (("seconds", seconds), ("slice", slice_s), ("window", window)):
        if not (v > 0 and math.isfinite(v)):
            raise ValueError(f"--{name} must be a positive number, got {v}")
    if check_every < 0:
        raise ValueError(f"--check-every must be >= 0, got {check_every}")
    if small is None:
        small = device.type == "cpu"
    if profile is None:
        profile = device.type == "cpu"  # per-layer times cost nothing on CPU; on CUDA they synchronise
    grid_name = SCENARIO_SETUP[scenario]
    grid = getattr(PillarGrid, grid_name)()
    out = Path(out or f"lidarops_stream_{scenario}.png")
    steps = max(1, int(math.ceil(seconds / slice_s - 1e-9)))
    tol = _TOL[dtype]

    sim = Simulator(scenario, seed=seed)
    # simulate first: the steps then time only the model, and the stream's capacity can be measured
    sim0 = time.perf_counter()
    bounds = [(i * slice_s, min((i + 1) * slice_s, seconds)) for i in range(steps)]
    slices = [(torch.from_numpy(p), torch.from_numpy(t)) for p, t in (sim.stream(a, b) for a, b in bounds)]
    if max_points_per_pillar is None or max_pillars is None:
        need_n, need_m = _window_capacity(slices, bounds, grid, window)
        # margin for points on pillar borders, where float32 rounding may place them differently
        N = max_points_per_pillar or max(8, -(-int(need_n * 1.1 + 2) // 8) * 8)
        M = max_pillars or max(64, int(need_m * 1.1) + 64)
    else:
        N, M = max_points_per_pillar, max_pillars
    sim_s = time.perf_counter() - sim0
    pfn, backbone = build_model(small, seed, dtype, device)
    # calibrate BatchNorm on the first full window (what the stream holds once it has filled)
    p0, _ = sim.stream(0.0, window)  # (the simulator's output does not depend on how spans are requested)
    pillars0 = pillarize(torch.from_numpy(p0).to(device), grid, N, M)
    calibrate_relu_zeros(pfn, backbone, pillars0, grid.shape, relu_zeros)
    zeros_first = relu_zero_shares(pfn, backbone, pillars0, grid.shape)

    if refresh_every is None:  # the model's default, chosen from the measured float32 drift
        import inspect
        refresh_every = inspect.signature(SSCATeRPointPillars).parameters["refresh_every"].default
    model = SSCATeRPointPillars(pfn, backbone, grid, window=window, max_points_per_pillar=N, max_pillars=M,
                                refresh_every=refresh_every, dtype=dtype, device=device, profile=profile)
    # the change map of the last push, for the picture (SSCATeRPointPillars keeps only its counts)
    last_update = {}
    push = model.stream.push

    def recording_push(*a, **k):
        upd = push(*a, **k)
        last_update["update"] = upd
        return upd

    model.stream.push = recording_push

    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    size = ("small (PFN 16, backbone 16/32/64, upsampling 3 x 32)" if small
            else "PointPillars (PFN 64, backbone 64/128/256, upsampling 3 x 128)")
    n_threads = torch.get_num_threads()
    threads = f", {n_threads} CPU thread{'s' if n_threads > 1 else ''}" if device.type == "cpu" else ""
    print(f"lidarops {lidarops.__version__} stream: torch {torch.__version__}, {dev_name}{threads}, "
          f"{str(dtype).replace('torch.', '')}")
    print(f"scenario {scenario} (seed {seed}), {seconds:g} s in {steps} slices of {slice_s * 1e3:g} ms, window "
          f"{window * 1e3:g} ms; grid {grid_name} {grid.shape[0]} x {grid.shape[1]} pillars of "
          f"{grid.pillar_size[0]:g} m, capacity {N} points x {M} pillars"
          f"{' (measured on the stream)' if max_points_per_pillar is None or max_pillars is None else ''}")
    print(f"model: {size}, random weights (seed {seed}); no trained checkpoint: BatchNorm calibrated on the first "
          f"window for ~{relu_zeros:.0%} ReLU zeros (--relu-zeros; measured {_mean(zeros_first.values()):.0%} over "
          f"{len(zeros_first)} layers); full recomputation every {model.refresh_every or 'never'} steps "
          f"(--refresh-every), identity check every {check_every or 'never'} steps (--check-every)")

    pushed: deque = deque()  # (points, t) of the slices that may still hold points of the window
    records, checks = [], []
    bar = _progress(steps, scenario, progress)
    wall0 = time.perf_counter()
    try:
        for i, ((a, b), (p, t)) in enumerate(zip(bounds, slices)):
            result = model.step(p.to(device), t.to(device), now=b)
            st = model.stats
            pushed.append((p, t))
            # the window: pushed points with t > stats.t - window (the stream's rule)
            cutoff = st.t - model.window
            while pushed and (pushed[0][1].numel() == 0 or float(pushed[0][1].max()) <= cutoff) and len(pushed) > 1:
                pushed.popleft()
            rec = {"step": i, "t": st.t, "refreshed": st.refreshed, "points_in": st.points_in,
                   "points_out": st.points_out, "pillars_active": st.pillars_active,
                   "pillars_changed": st.pillars_changed, "pfn_points": st.pfn_points,
                   "pfn_points_full": st.pfn_points_full, "ms_stream": st.ms_stream, "ms_pfn": st.ms_pfn,
                   "ms_backbone": st.ms_backbone, "ms_total": st.ms_stream + st.ms_pfn + st.ms_backbone,
                   "layers": [asdict(s) for s in st.layers], "check": None}
            if check_every and (i % check_every == check_every - 1 or i == steps - 1):
                allp, allt = torch.cat([q[0] for q in pushed]), torch.cat([q[1] for q in pushed])
                win = allp[allt > cutoff]
                ref, ms = _full_recompute(model, win)
                scale = float(ref.abs().max()) if ref.numel() else 0.0
                diff = float((result - ref).abs().max()) if ref.numel() else 0.0
                rel = diff / scale if scale > 0 else (0.0 if diff == 0 else math.inf)
                rec["check"] = {"rel_diff": rel, "points": int(win.shape[0]), "ms_stream": ms[0], "ms_pfn": ms[1],
                                "ms_backbone": ms[2], "ms_total": sum(ms)}
                checks.append(rec["check"])
            records.append(rec)
            if bar is not None:
                bar.set_postfix_str(f"active {st.pillars_active}, changed "
                                    f"{st.pillars_changed / max(st.pillars_active, 1):.0%}, {rec['ms_total']:.1f} ms",
                                    refresh=False)
                bar.update(1)
    except ValueError as e:  # e.g. PillarOverflowError: the stream never drops points
        if bar is not None:
            bar.close()
        print(f"error: {e}\n(raise --max-points-per-pillar / --max-pillars)", file=sys.stderr)
        return 2
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - wall0

    # the last window's pseudo-image and ReLU zeros
    last_pillars = model.stream.pillars()
    zeros_last = relu_zero_shares(pfn, backbone, last_pillars, grid.shape) if last_pillars.coords.shape[0] else {}

    summary = _summarize(records, checks, tol, model.window)
    print()
    print(_report(records, summary, model))
    print(f"\nReLU zeros: {_mean(zeros_first.values()):.0%} on the calibration window, "
          f"{_mean(zeros_last.values()):.0%} "
          f"on the last window (mean over layers). Wall time {wall:.1f} s for {steps} steps (identity checks "
          f"included), after {sim_s:.1f} s simulating the stream.")
    worst = summary["max_rel_diff"]
    if checks:
        status = "OK" if worst <= tol else "FAIL"
        print(f"identity: {status}: max relative difference {worst:.2e} over {len(checks)} full recomputations "
              f"(tolerance {tol:g} of max|output|)")
    else:
        print("identity: not checked (--check-every 0)")

    try:
        _plot(out, scenario, records, last_update.get("update"), model, last_pillars, summary)
        print(f"wrote {out}")
    except ImportError as e:
        print(f"no PNG written: {e}", file=sys.stderr)
    if json_path:
        doc = {"scenario": scenario, "seed": seed, "seconds": seconds, "slice": slice_s, "window": window,
               "device": str(device), "device_name": dev_name, "dtype": str(dtype).replace("torch.", ""),
               "small": small, "grid": {"preset": grid_name, "shape": list(grid.shape)},
               "max_points_per_pillar": N, "max_pillars": M, "refresh_every": model.refresh_every,
               "check_every": check_every, "relu_zeros_target": relu_zeros,
               "relu_zeros_first": zeros_first, "relu_zeros_last": zeros_last, "tolerance": tol,
               "summary": summary, "steps": records}
        Path(json_path).write_text(json.dumps(doc, indent=1, allow_nan=True))
        print(f"wrote {json_path}")
    return 0 if (not checks or worst <= tol) else 1


def _window_capacity(slices: list, bounds: list, grid, window: float) -> tuple[int, int]:
    """(most points in one pillar, most occupied pillars) over the windows of the run (the calibration
    window [0, window) included)."""
    import numpy as np
    x0, y0, z0, x1, y1, z1 = grid.point_range
    vx, vy = grid.pillar_size
    H, W = grid.shape
    most_points, most_pillars = 0, 0
    recent: deque = deque()
    ends = [window] + [b for _, b in bounds]
    for i, end in enumerate(ends):
        if i == 0:
            p = torch.cat([q[0] for q, (a, _) in zip(slices, bounds) if a < window] or [torch.zeros(0, 4)])
            pts = p.numpy()
        else:
            recent.append(slices[i - 1])
            while len(recent) > 1 and (recent[0][1].numel() == 0 or float(recent[0][1].max()) <= end - window):
                recent.popleft()
            p, t = torch.cat([q[0] for q in recent]), torch.cat([q[1] for q in recent])
            pts = p[t > end - window].numpy()
        x, y, z = pts[:, 0], pts[:, 1], pts[:, 2]
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1) & (z >= z0) & (z < z1)
        ix = np.clip(np.floor((x[inside] - x0) / vx).astype(np.int64), 0, W - 1)
        iy = np.clip(np.floor((y[inside] - y0) / vy).astype(np.int64), 0, H - 1)
        counts = np.bincount(iy * W + ix)
        if counts.size:
            most_points, most_pillars = max(most_points, int(counts.max())), max(most_pillars, int((counts > 0).sum()))
    return most_points, most_pillars


def _mean(xs) -> float:
    xs = list(xs)
    return sum(xs) / len(xs) if xs else float("nan")


def _summarize(records: list[dict], checks: list[dict], tol: float, window: float) -> dict:
    # medians over the steady state: recycling steps once the window has filled
    recyc = [r for r in records if not r["refreshed"] and r["t"] > window + 1e-9] \
        or [r for r in records if not r["refreshed"]] or records
    s = {"steps": len(records), "refresh_steps": sum(r["refreshed"] for r in records), "median_steps": len(recyc)}
    for k in ("ms_stream", "ms_pfn", "ms_backbone", "ms_total"):
        s[f"sscater_{k}"] = _median(r[k] for r in recyc)
        s[f"full_{k}"] = _median(c[k] for c in checks)
    s["under_budget"] = sum(r["ms_total"] < _BUDGET_MS for r in records) / len(records)
    s["pfn_saved"] = 1.0 - sum(r["pfn_points"] for r in recyc) / max(1, sum(r["pfn_points_full"] for r in recyc))
    s["pillars_active"] = _median(r["pillars_active"] for r in recyc)
    s["pillars_changed"] = _median(r["pillars_changed"] for r in recyc)
    s["changed_share"] = _median(r["pillars_changed"] / max(r["pillars_active"], 1) for r in recyc)
    layers = {}
    for r in recyc:
        for L in r["layers"]:
            layers.setdefault(L["name"], []).append(L)
    s["layers"] = [{"name": n, "active": _median(x["active"] for x in Ls), "changed": _median(x["changed"] for x in Ls),
                    "changed_share": _median(x["changed"] / max(x["active"], 1) for x in Ls),
                    "ms": _median(x["ms"] for x in Ls)} for n, Ls in layers.items()]
    s["checks"] = len(checks)
    s["max_rel_diff"] = max((c["rel_diff"] for c in checks), default=0.0)
    s["identity_ok"] = s["max_rel_diff"] <= tol
    return s


def _report(records: list[dict], s: dict, model) -> str:
    rows = []
    for label, k in (("stream (SSCATeR) / pillarize (full)", "ms_stream"), ("PFN", "ms_pfn"),
                     ("backbone", "ms_backbone"), ("total", "ms_total")):
        a, b = s[f"sscater_{k}"], s[f"full_{k}"]
        rows.append([label, _fmt_ms(a), _fmt_ms(b), f"{b / a:.1f}x" if a > 0 and math.isfinite(b) else "-"])
    t1 = _table(["stage", "SSCATeR ms", "full ms", "speed-up"], rows, "lrrr")
    rows = [["pillars", f"{s['pillars_active']:.0f}", f"{s['pillars_changed']:.0f}", f"{s['changed_share']:.1%}", "-"]]
    rows += [[L["name"], f"{L['active']:.0f}", f"{L['changed']:.0f}", f"{L['changed_share']:.1%}",
              _fmt_ms(L["ms"]) if model.profile else "-"] for L in s["layers"]]
    t2 = _table(["layer", "active sites", "changed sites", "changed %", "ms"], rows, "lrrrr")
    lines = [f"time per step: median over {s['median_steps']} recycling steps once the window is full (SSCATeR; "
             f"{s['refresh_steps']} refresh step{'s' if s['refresh_steps'] != 1 else ''} left out) and over "
             f"{s['checks']} full recomputations of the window", t1, "",
             "sites per step (same steps; changed = sites whose value changed)", t2, "",
             f"PFN points saved: {s['pfn_saved']:.1%} (points run through the PFN vs a full recomputation)",
             f"steps under {_BUDGET_MS:g} ms (SSCATeR, all steps): {s['under_budget']:.1%} of {s['steps']}"]
    return "\n".join(lines)


def _plot(path: Path, scenario: str, records: list[dict], update, model, pillars, s: dict) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from lidarops.models.pointpillars import scatter_to_bev

    grid = model.grid
    x0, y0, _, x1, y1, _ = grid.point_range
    extent = (x0, x1, y0, y1)
    fig = plt.figure(figsize=(16, 10), constrained_layout=True)
    gs = fig.add_gridspec(2, 3, height_ratios=(1, 1.3))

    ax = fig.add_subplot(gs[0, :])
    t = np.array([r["t"] for r in records])
    ms = np.array([r["ms_total"] for r in records])
    ax.plot(t, ms, lw=0.8, color="tab:blue", label="SSCATeR step (stream + PFN + backbone)")
    ref = [r for r in records if r["refreshed"]]
    if ref:
        ax.plot([r["t"] for r in ref], [r["ms_total"] for r in ref], "v", color="tab:purple", ms=5,
                label="refresh step (full recomputation inside SSCATeR)")
    chk = [r for r in records if r["check"]]
    if chk:
        ax.plot([r["t"] for r in chk], [r["check"]["ms_total"] for r in chk], "o", color="tab:red", ms=3,
                label="full recomputation (pillarize + PFN + sparse backbone)")
    ax.axhline(_BUDGET_MS, color="k", ls="--", lw=0.8, label=f"{_BUDGET_MS:g} ms (one slice)")
    ax.set_yscale("log")
    ax.set_xlabel("stream time (s)")
    ax.set_ylabel("ms per step")
    ax.set_title(f"{scenario}: runtime per step, {str(model.device)}; median SSCATeR "
                 f"{_fmt_ms(s['sscater_ms_total'])} ms"
                 f" vs full {_fmt_ms(s['full_ms_total'])} ms")
    ax.legend(loc="best", fontsize=8, framealpha=0.6)

    H, W = grid.shape
    occ = np.zeros((H, W), dtype=np.float32)
    if pillars.coords.shape[0]:
        c = pillars.coords.long().cpu().numpy()
        occ[c[:, 1], c[:, 2]] = 1.0
    # pillars are drawn 3 x 3 so that single ones stay visible once the 512-pillar grid is scaled down
    img = np.ones((H, W, 3), dtype=np.float32)
    img[_dilate(occ > 0)] = 0.7  # active pillars grey on white
    n_changed = 0
    if update is not None and update.changed.shape[0]:
        c = update.changed.long().cpu().numpy()
        gone = update.removed.cpu().numpy()
        for sel, colour in ((gone, (0.1, 0.3, 0.9)), (~gone, (0.85, 0.1, 0.1))):  # emptied; points in or out
            m = np.zeros((H, W), dtype=bool)
            m[c[sel, 1], c[sel, 2]] = True
            img[_dilate(m)] = colour
        n_changed = c.shape[0]
    ax = fig.add_subplot(gs[1, 0])
    ax.imshow(img, origin="lower", extent=extent, interpolation="nearest")
    ax.set_title(f"change map, last step: {n_changed} of {int(occ.sum())} pillars changed\n"
                 "(red: points in/out, blue: emptied, grey: unchanged; drawn 3 x 3)", fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")

    ax = fig.add_subplot(gs[1, 1])
    if pillars.coords.shape[0]:
        with torch.no_grad():
            f = model.pfn(pillars)
        bev = scatter_to_bev(f.float(), pillars.coords, grid.shape)[0].amax(0).cpu().numpy()
    else:
        bev = np.zeros((H, W), dtype=np.float32)
    vmax = float(np.percentile(bev[bev > 0], 99)) if (bev > 0).any() else 1.0
    # 3 x 3 too, as the change map; empty pillars black, active ones with all-zero features dark purple
    shown = np.ma.masked_where(~_dilate(occ > 0), _max3(np.where(occ > 0, bev, -1.0)).clip(min=0))
    im = ax.imshow(shown, origin="lower", extent=extent, interpolation="nearest",
                   cmap="viridis", vmin=0, vmax=vmax)
    ax.set_facecolor("black")
    fig.colorbar(im, ax=ax, shrink=0.7)
    ax.set_title("pseudo-image of the last window\n(max over channels of the pillar features)", fontsize=9)
    ax.set_xlabel("x (m)")

    ax = fig.add_subplot(gs[1, 2])
    names = ["pillars"] + [L["name"] for L in s["layers"]]
    shares = [s["changed_share"]] + [L["changed_share"] for L in s["layers"]]
    ax.barh(range(len(names)), [100 * v for v in shares], color="tab:orange")
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("changed sites per step (% of active, median)")
    ax.set_title("changed share per layer", fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _dilate(mask):
    """3 x 3 binary dilation of an (H, W) bool array (NumPy only)."""
    import numpy as np
    p = np.pad(mask, 1)
    H, W = mask.shape
    return np.logical_or.reduce([p[dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)])


def _max3(a):
    """3 x 3 maximum filter of an (H, W) float array (NumPy only)."""
    import numpy as np
    p = np.pad(a, 1)
    H, W = a.shape
    return np.maximum.reduce([p[dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)])


# ---- argparse ----------------------------------------------------------------------------------------

def _main(args: argparse.Namespace) -> int:
    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    small = True if args.small else (False if args.full_size else None)
    try:
        return run(args.scenario, args.seconds, args.slice, args.window, args.device, dtype, args.check_every,
                   args.refresh_every, args.relu_zeros, args.seed, small, args.out, args.json,
                   args.max_points_per_pillar, args.max_pillars, args.profile or None, not args.no_progress,
                   args.threads)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def register(subparsers) -> None:
    """Adds ``stream`` to the ``lidarops`` parser."""
    p = subparsers.add_parser(
        "stream", help="stream the simulator through SSCATeR PointPillars, checked against full recomputation",
        description="Streams a simulated LiDAR scene in slices through streaming pillarization, the pillar "
                    "feature net and the SSCATeR (temporal data recycling) backbone; checks the output against a "
                    "full recomputation as it goes; prints time per stage and active/changed sites per layer; "
                    "writes a PNG (runtime trace, change map, pseudo-image).")
    p.add_argument("--scenario", choices=sorted(SCENARIO_SETUP), default="drone_bridge",
                   help="simulated scene (default drone_bridge); drone scenes use the 512 x 512 drone grid, driving "
                        "scenes the KITTI grid (x forward)")
    p.add_argument("--seconds", type=float, default=5.0, help="stream length in seconds (default 5)")
    p.add_argument("--slice", type=float, default=0.01, help="seconds per step (default 0.01)")
    p.add_argument("--window", type=float, default=0.1, help="sliding window in seconds (default 0.1)")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="default: cuda when available and lidarops has its CUDA kernels, else cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--check-every", type=int, default=10,
                   help="compare with a full recomputation every N steps (default 10; 0: never); exit code 1 when a "
                        "relative difference exceeds 1e-5 (float32) or 1e-12 (float64)")
    p.add_argument("--refresh-every", type=int, default=None,
                   help="full recomputation inside SSCATeR every N steps (0: never; default: SSCATeRPointPillars' "
                        "default, 25, chosen from the float32 drift of the recycled sums, ~1e-7 of max|output| "
                        "per step)")
    p.add_argument("--relu-zeros", type=float, default=0.5,
                   help="share of negative pre-activations BatchNorm is calibrated for on the first window "
                        "(default 0.5; random weights stand in for a trained network)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and of the weights")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--small", action="store_true",
                      help="narrow network (PFN 16, backbone 16/32/64, upsampling 32 each); the default on CPU")
    size.add_argument("--full-size", action="store_true",
                      help="PointPillars' sizes (PFN 64, backbone 64/128/256, upsampling 128 each); "
                           "the default on CUDA")
    p.add_argument("--max-points-per-pillar", type=int, default=None,
                   help="stream capacity (default: the most points in one pillar over the run's windows, +10%%)")
    p.add_argument("--max-pillars", type=int, default=None,
                   help="stream capacity (default: the most occupied pillars over the run's windows, +10%%)")
    p.add_argument("--profile", action="store_true",
                   help="time each backbone layer (on by default on CPU; on CUDA it synchronises after each layer)")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads of torch (default on CPU: 1; a step is thousands of small sites, where intra-op "
                        "threads cost more than they save and slow down ~10x when the cores are shared)")
    p.add_argument("--out", default=None, help="PNG path (default lidarops_stream_<scenario>.png)")
    p.add_argument("--json", default=None, metavar="PATH", help="write the per-step figures as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_main)
