"""``lidarops stream``: the simulator streamed through pillarization, the PFN and the SSCATeR backbone.

Each step pushes one slice of points (10 ms by default) into
:class:`~lidarops.models.sscater_pointpillars.SSCATeRPointPillars`,
which updates the pillars, the pillar features and the backbone's output by recomputing only what
changed. Every ``--check-every`` steps the output is compared with a full recomputation of the window
(``pillarize`` + PFN + ``backbone(mode="sparse")``, timed stage by stage), which is also the "full" column
of the printed table. The run says what it demonstrates, then prints a table (time per stage, active and
changed sites per layer, PFN work saved), what the run shows (identity, what was saved and why), a PNG
(runtime trace, change map, pseudo-image, changed share per layer) and, with ``--json``, the per-step figures.

The network has seeded random weights (the shipped detector's weights are for OpenPCDet's 10-feature
pillar net, not this 9-feature one), and BatchNorm's statistics are calibrated on the first window so that
a chosen share of each layer's pre-activations is negative (``--relu-zeros``), like the ReLU sparsity of a
trained network. Which sites change, and so the work SSCATeR saves, depends on that share; identity with
the full recomputation does not.

Exit codes: 0 when every identity check held, 1 when one failed; errors (bad arguments, ``--device cuda``
without CUDA, unwritable ``--out`` / ``--json``, a stream capacity too small) are one line on stderr and exit
code 2 (:mod:`lidarops.cli.errors`).

Examples::

    lidarops stream --scenario driving_city --seconds 1
    lidarops stream --scenario drone_bridge --seconds 1.5 --relu-zeros 0.9
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
from typing import Optional

import torch
from torch import Tensor

from lidarops._progress import progress_bar
from lidarops.cli._device import resolve_device
from lidarops.cli.data import _realism_or_none_arg
from lidarops.cli.errors import CliError, guarded
from lidarops.models.sscater_calibration import build_model, calibrate_relu_zeros, layer_labels, relu_zero_shares

__all__ = ["register", "run", "SCENARIO_SETUP", "SCENARIO_NOTES"]

# scenario -> pillar grid preset. Drones look ahead along x from the sensor; the driving scenes' HDL-64
# sits at the origin with x forward, so the KITTI grid (x in [0, 69.12)) holds the half ahead of the car.
SCENARIO_SETUP = {"drone_bridge": "drone", "drone_lock": "drone", "driving_city": "kitti", "driving_highway": "kitti"}
# what changes from one slice to the next in each scene (the sensors of lidarops.data.sensors)
_ROSETTE = "its rosette scan spreads every slice over the whole field of view, so the changed pillars are scattered"
_SPIN = ("the grid holds the 69 m ahead of the car, which the beam sweeps during half of each 100 ms turn: "
         "a slice changes one sector of it, or nothing")
SCENARIO_NOTES = {
    "drone_bridge": f"a Livox Avia on a hovering drone, a bridge 48-62 m ahead; {_ROSETTE}",
    "drone_lock": f"a Livox Avia on a hovering drone inside a canal lock; {_ROSETTE}",
    "driving_city": f"an HDL-64 spinning at 10 Hz on a car in a city street; {_SPIN}",
    "driving_highway": f"an HDL-64 spinning at 10 Hz on a car on a highway; {_SPIN}",
}

_TOL = {torch.float32: 1e-5, torch.float64: 1e-12}
_BUDGET_MS = 10.0  # one 10 ms slice: a step must keep up with the sensor


# ---- the run -----------------------------------------------------------------------------------------

def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def _full_recompute(model, points: Tensor) -> tuple[Tensor, tuple[float, float, float]]:
    """``model.recompute(points)``, the same calls, timed per stage: (output, (ms pillarize, ms PFN,
    ms backbone))."""
    from lidarops.ops.pillars import pillarize
    from lidarops.sparse import SparseConvTensor
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
        threads: Optional[int] = None, realism: Optional[str] = None) -> int:
    """Streams ``seconds`` of ``scenario`` through SSCATeR PointPillars; prints the table, writes the PNG
    (and the JSON). Returns 0 when every identity check is within tolerance, 1 otherwise.

    ``threads``: CPU threads of torch during the run (default 1 on CPU, see ``--threads``; restored after).
    ``realism``: the simulator's realism profile of the scene (:mod:`lidarops.data.realism`; None or "none": ray-cast).

    Raises:
        ValueError: a bad argument, ``device="cuda"`` without CUDA torch or lidarops' CUDA kernels, an
            ``out`` / ``json_path`` that cannot be written (all checked before anything runs), or a stream
            capacity (``max_points_per_pillar`` / ``max_pillars``) too small for the scene.
        lidarops.extension.LidaropsBuildError: the compiled library cannot be loaded.
    """
    _check_arguments(scenario, seconds, slice_s, window, dtype, check_every, refresh_every, relu_zeros, seed,
                     max_points_per_pillar, max_pillars, threads)
    realism = _check_realism(realism)
    dev = resolve_device(device)
    out = _check_output(Path(out or f"lidarops_stream_{scenario}.png"), "--out", image=True)
    if json_path:
        json_path = _check_output(Path(json_path), "--json")
        if json_path.resolve() == out.resolve():
            raise ValueError(f"--out and --json are the same file ({out})")
    if threads is None and dev.type == "cpu":
        threads = 1
    saved = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        return _run(scenario, seconds, slice_s, window, dev, dtype, check_every, refresh_every, relu_zeros, seed,
                    small, out, json_path, max_points_per_pillar, max_pillars, profile, progress, realism)
    finally:
        torch.set_num_threads(saved)


def _check_arguments(scenario, seconds, slice_s, window, dtype, check_every, refresh_every, relu_zeros, seed,
                     max_points_per_pillar, max_pillars, threads) -> None:
    """ValueError naming the flag, before anything is simulated."""
    if scenario not in SCENARIO_SETUP:
        raise ValueError(f"--scenario must be one of {', '.join(sorted(SCENARIO_SETUP))}, got {scenario!r}")
    for name, v in (("seconds", seconds), ("slice", slice_s), ("window", window)):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (v > 0 and math.isfinite(v)):
            raise ValueError(f"--{name} must be a positive number of seconds, got {v}")
    if dtype not in _TOL:
        raise ValueError(f"--dtype must be float32 or float64, got {dtype}")
    for name, v, low in (("check-every", check_every, 0), ("refresh-every", refresh_every, 0),
                         ("max-points-per-pillar", max_points_per_pillar, 1), ("max-pillars", max_pillars, 1),
                         ("threads", threads, 1)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < low):
            raise ValueError(f"--{name} must be an integer >= {low}, got {v}")
    # torch.manual_seed's range
    if isinstance(seed, bool) or not isinstance(seed, int) or not -2 ** 63 <= seed < 2 ** 64:
        raise ValueError(f"--seed must be an integer that fits in 64 bits, got {seed}")
    if not (isinstance(relu_zeros, (int, float)) and 0.0 <= relu_zeros < 1.0):
        raise ValueError(f"--relu-zeros must be a share in [0, 1), e.g. 0.5, got {relu_zeros}")


def _check_output(path: Path, flag: str, image: bool = False) -> Path:
    """``path``, once it is known to be writable (its folders are created; a file that did not exist is
    removed again), so that a bad path fails before the run rather than after it."""
    if path.is_dir():
        raise ValueError(f"{flag} {path} is a directory; give a file name")
    if image and path.suffix:
        try:
            from matplotlib.figure import Figure
            formats = Figure().canvas.get_supported_filetypes()
        except ImportError:  # no picture then (said at the end); the path is still checked
            formats = None
        if formats is not None and path.suffix[1:].lower() not in formats:
            raise ValueError(f"{flag} {path}: matplotlib cannot write .{path.suffix[1:]} files; use one of "
                             f"{', '.join('.' + f for f in sorted(formats))}")
    existed = path.exists()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "ab"):
            pass
    except OSError as e:
        raise ValueError(f"{flag} {path} cannot be written: {e.strerror or e}") from None
    if not existed:
        path.unlink()
    return path


def _check_realism(realism) -> "str | None":
    """``realism`` checked before anything runs: None or ``"none"`` (ray-cast: None), or a profile that
    :func:`lidarops.data.realism.make_realism` accepts (returned as given)."""
    from lidarops.data.realism import make_realism

    if realism is not None and not isinstance(realism, str):
        raise ValueError(f"--realism must be a profile name such as 'avia', got {realism!r}")
    if realism == "none":
        return None
    try:
        make_realism(realism)
    except ValueError as e:
        raise ValueError(f"--realism: {e}") from None
    return realism


def _run(scenario, seconds, slice_s, window, device, dtype, check_every, refresh_every, relu_zeros, seed, small,
         out, json_path, max_points_per_pillar, max_pillars, profile, progress, realism=None) -> int:
    import lidarops
    from lidarops.data.synthetic import Simulator
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars
    from lidarops.ops.pillars import PillarGrid, pillarize

    if small is None:
        small = device.type == "cpu"
    if profile is None:
        profile = device.type == "cpu"  # per-layer times cost nothing on CPU; on CUDA they synchronise
    grid_name = SCENARIO_SETUP[scenario]
    grid = getattr(PillarGrid, grid_name)()
    steps = max(1, int(math.ceil(seconds / slice_s - 1e-9)))
    tol = _TOL[dtype]
    print(_intro(scenario, seconds, steps, slice_s, window, check_every, realism))

    sim = Simulator(scenario, seed=seed, realism=realism)
    # simulate first: the steps then time only the model, and the stream's capacity can be measured
    sim0 = time.perf_counter()
    bounds = [(i * slice_s, min((i + 1) * slice_s, seconds)) for i in range(steps)]
    slices = [(torch.from_numpy(p), torch.from_numpy(t)) for p, t in (sim.stream(a, b) for a, b in bounds)]
    # BatchNorm is calibrated on the first full window (what the stream holds once it has filled), which
    # outlasts a run shorter than the window (the simulator's output does not depend on how spans are requested)
    p0, _ = sim.stream(0.0, window)
    if max_points_per_pillar is None or max_pillars is None:
        need_n, need_m = _window_capacity(slices, bounds, grid, window, p0)
        # margin for points on pillar borders, where float32 rounding may place them differently
        N = max_points_per_pillar or max(8, -(-int(need_n * 1.1 + 2) // 8) * 8)
        M = max_pillars or max(64, int(need_m * 1.1) + 64)
    else:
        N, M = max_points_per_pillar, max_pillars
    sim_s = time.perf_counter() - sim0
    pfn, backbone = build_model(small, seed, dtype, device)
    pillars0 = pillarize(torch.from_numpy(p0).to(device), grid, N, M)
    calibrate_relu_zeros(pfn, backbone, pillars0, grid.shape, relu_zeros)
    zeros_first = relu_zero_shares(pfn, backbone, pillars0, grid.shape)

    if refresh_every is None:  # the model's default, chosen from the measured float32 drift
        import inspect
        refresh_every = inspect.signature(SSCATeRPointPillars).parameters["refresh_every"].default
    model = SSCATeRPointPillars(pfn, backbone, grid, window=window, max_points_per_pillar=N, max_pillars=M,
                                refresh_every=refresh_every, dtype=dtype, device=device, profile=profile)
    # the stream's pushes, for the change map (SSCATeRPointPillars keeps only its counts)
    last_push, shown_change = {}, {}
    push = model.stream.push

    def recording_push(*a, **k):
        last_push["update"] = upd = push(*a, **k)
        return upd

    model.stream.push = recording_push

    dev_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    size = ("small (PFN 16, backbone 16/32/64, upsampling 3 x 32; --full-size for PointPillars' sizes)" if small
            else "PointPillars' sizes (PFN 64, backbone 64/128/256, upsampling 3 x 128)")
    n_threads = torch.get_num_threads()
    threads = f" ({n_threads} thread{'s' if n_threads > 1 else ''})" if device.type == "cpu" else ""
    print(_wrap(f"setup: lidarops {lidarops.__version__}, torch {torch.__version__}, {dev_name}{threads}, "
                f"{str(dtype).replace('torch.', '')}; grid {grid_name} {grid.shape[0]} x {grid.shape[1]} pillars of "
                f"{grid.pillar_size[0]:g} m, capacity {N} points x {M} pillars"
                f"{' (measured on the stream)' if max_points_per_pillar is None or max_pillars is None else ''}; "
                f"scene seed {seed}"))
    print(_wrap(f"network {size}, random weights (seed {seed}), BatchNorm calibrated on the first window for "
                f"~{relu_zeros:.0%} ReLU zeros (--relu-zeros; measured {_mean(zeros_first.values()):.0%} over "
                f"{len(zeros_first)} layers); SSCATeR recomputes everything every {model.refresh_every or 'never'} "
                f"steps (--refresh-every: bounds float drift); identity check every {check_every or 'never'} steps "
                "(--check-every)", "  "))

    pushed: deque = deque()  # (points, t) of the slices that may still hold points of the window
    records, checks = [], []
    bar = progress_bar(steps, scenario, progress, unit="step", dynamic_ncols=True, leave=True)
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
            # the change map shown: the step that changed the most pillars once the window is full (before,
            # every pillar is new), or the last step with changes in a run shorter than the window
            full_window = st.t > model.window + 1e-9
            if not shown_change or not shown_change["full_window"]:
                better = st.pillars_changed > 0
            else:
                better = full_window and st.pillars_changed > shown_change["changed"].shape[0]
            if better:
                upd = last_push["update"]  # copies: the stream reuses its buffers
                shown_change.update(step=i, t=st.t, full_window=full_window, changed=upd.changed.clone(),
                                    removed=upd.removed.clone(), active=upd.active.clone())
            bar.set_postfix_str(f"active {st.pillars_active}, changed "
                                f"{st.pillars_changed / max(st.pillars_active, 1):.0%}, {rec['ms_total']:.1f} ms",
                                refresh=False)
            bar.update(1)
    finally:
        bar.close()
    wall = time.perf_counter() - wall0

    # the last window's pseudo-image and ReLU zeros
    last_pillars = model.stream.pillars()
    zeros_last = relu_zero_shares(pfn, backbone, last_pillars, grid.shape) if last_pillars.coords.shape[0] else {}

    summary = _summarize(records, checks, tol, model.window)
    labels = layer_labels(backbone)
    for L in summary["layers"]:
        L["label"] = labels.get(L["name"], L["name"])
    print()
    print(_report(summary, model))
    print(_wrap(f"ReLU zeros: {_mean(zeros_first.values()):.0%} on the calibration window, "
                f"{_mean(zeros_last.values()):.0%} on the last window (mean over layers). Wall time {wall:.1f} s for "
                f"{steps} steps (identity checks included), after {sim_s:.1f} s simulating the stream."))
    print()
    print(_takeaway(summary, tol, relu_zeros, device))

    worst = summary["max_rel_diff"]
    try:
        _plot(out, scenario, records, shown_change, model, last_pillars, summary)
        print(f"wrote {out}")
    except ImportError as e:
        print(f"no picture written: {e}", file=sys.stderr)
    if json_path:
        doc = {"scenario": scenario, "realism": realism, "seed": seed, "seconds": seconds, "slice": slice_s,
               "window": window, "device": str(device), "device_name": dev_name,
               "dtype": str(dtype).replace("torch.", ""),
               "small": small, "grid": {"preset": grid_name, "shape": list(grid.shape)},
               "max_points_per_pillar": N, "max_pillars": M, "refresh_every": model.refresh_every,
               "check_every": check_every, "relu_zeros_target": relu_zeros,
               "relu_zeros_first": zeros_first, "relu_zeros_last": zeros_last, "tolerance": tol,
               "summary": summary, "steps": records}
        json_path.write_text(json.dumps(doc, indent=1, allow_nan=True))
        print(f"wrote {json_path}")
    return 0 if (not checks or worst <= tol) else 1


def _window_capacity(slices: list, bounds: list, grid, window: float, first_window) -> tuple[int, int]:
    """(most points in one pillar, most occupied pillars) over the windows of the run and the calibration
    window [0, window), whose points are ``first_window`` (array[n, 4])."""
    import numpy as np
    x0, y0, z0, x1, y1, z1 = grid.point_cloud_range
    vx, vy = grid.pillar_size
    H, W = grid.shape
    most_points, most_pillars = 0, 0
    recent: deque = deque()
    ends = [window] + [b for _, b in bounds]
    for i, end in enumerate(ends):
        if i == 0:
            pts = np.asarray(first_window).reshape(-1, 4)
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
    s["full_under_budget"] = (sum(c["ms_total"] < _BUDGET_MS for c in checks) / len(checks)) if checks else float("nan")
    # the whole run's compute, refresh steps included, against a full recomputation at every step
    s["sscater_s_all"] = sum(r["ms_total"] for r in records) / 1e3
    s["full_s_all_estimate"] = len(records) * s["full_ms_total"] / 1e3
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


def _ratio(s: dict, k: str) -> float:
    a, b = s[f"sscater_{k}"], s[f"full_{k}"]
    return b / a if a > 0 and math.isfinite(a) and math.isfinite(b) else float("nan")


def _wrap(text: str, first: str = "", rest: str = "  ") -> str:
    import textwrap
    return textwrap.fill(text, width=110, initial_indent=first, subsequent_indent=rest, break_on_hyphens=False)


def _intro(scenario: str, seconds: float, steps: int, slice_s: float, window: float, check_every: int,
           realism: Optional[str] = None) -> str:
    """What the run demonstrates, printed before anything runs."""
    sl, win = f"{slice_s * 1e3:g} ms", f"{window * 1e3:g} ms"
    checked = f"checked every {check_every} steps" if check_every else "not checked here: --check-every 0"
    what = (f"At each step a {sl} slice of points arrives; the network's input is the last {win}. A full "
            "recomputation redoes pillarization, the pillar feature net (PFN) and the backbone on the whole window. "
            "SSCATeR updates the previous result where the input changed: the PFN on the pillars that gained or "
            "lost points, each convolution by O += (I_curr - I_prev) * W at the sites the changes reach. The output "
            f"must be the same ({checked}); the cost follows the share of sites that change.")
    scene = f"{scenario}, realism profile {realism}" if realism else scenario
    title = f"lidarops stream: SSCATeR on {seconds:g} s of simulated LiDAR ({scene}), {steps} steps of {sl}"
    return "\n".join([title, _wrap(what, "  "), _wrap(f"Scene: {SCENARIO_NOTES[scenario]}.", "  ")])


def _report(s: dict, model) -> str:
    rows = []
    for label, k in (("pillars: stream push / pillarize", "ms_stream"), ("PFN", "ms_pfn"),
                     ("backbone", "ms_backbone"), ("total", "ms_total")):
        r = _ratio(s, k)
        rows.append([label, _fmt_ms(s[f"sscater_{k}"]), _fmt_ms(s[f"full_{k}"]),
                     f"{r:.1f}x" if math.isfinite(r) else "-"])
    t1 = _table(["stage", "SSCATeR ms", "full ms", "speed-up"], rows, "lrrr")
    rows = [["pillars (PFN)", f"{s['pillars_active']:.0f}", f"{s['pillars_changed']:.0f}", f"{s['changed_share']:.1%}",
             "-"]]
    rows += [[L.get("label", L["name"]), f"{L['active']:.0f}", f"{L['changed']:.0f}", f"{L['changed_share']:.1%}",
              _fmt_ms(L["ms"]) if model.profile else "-"] for L in s["layers"]]
    t2 = _table(["layer", "active sites", "changed sites", "changed %", "ms"], rows, "lrrrr")
    refresh = f"{s['refresh_steps']} full refresh step{'s' if s['refresh_steps'] != 1 else ''} left out"
    under_full = f"{s['full_under_budget']:.1%} of {s['checks']}" if s["checks"] else "not measured"
    full_all = ""
    if s["checks"] and s["sscater_s_all"] > 0:
        full_all = (f"; a full recomputation at every step would take about {s['full_s_all_estimate']:.1f} s "
                    f"({s['full_s_all_estimate'] / s['sscater_s_all']:.1f}x)")
    lines = [_wrap(f"time per step: SSCATeR = median of the {s['median_steps']} steps once the window is full "
                   f"({refresh}); full = median of the {s['checks']} full recomputations of the same window "
                   "(pillarize + PFN + sparse backbone)"), t1, "",
             _wrap("sites per step (medians over the same steps): active = non-empty sites of the layer; changed = "
                   "sites whose output changed in any channel, which the next layer must update"), t2, "",
             f"PFN points saved: {s['pfn_saved']:.1%} (SSCATeR runs the PFN on the changed pillars' points only)",
             _wrap(f"steps under {_BUDGET_MS:g} ms (one slice: keeping up with the sensor): SSCATeR "
                   f"{s['under_budget']:.1%} of {s['steps']} steps, full recomputation {under_full}"),
             _wrap(f"compute over all {s['steps']} steps: SSCATeR {s['sscater_s_all']:.1f} s (refresh steps "
                   f"included){full_all}")]
    return "\n".join(lines)


def _takeaway(s: dict, tol: float, relu_zeros: float, device: torch.device) -> str:
    """What the run shows, in words, from its figures."""
    lines = ["What this run shows:"]
    if s["checks"]:
        ok = s["identity_ok"]
        lines.append(_wrap(
            f"identity {'OK' if ok else 'FAILED'}: at {s['checks']} checks against pillarize + PFN + backbone on the "
            f"same window, the largest difference was {s['max_rel_diff']:.1e} of max|output| (tolerance {tol:g}).",
            "- "))
    else:
        lines.append("- identity: not checked (--check-every 0).")
    rb, rt, rp = _ratio(s, "ms_backbone"), _ratio(s, "ms_total"), _ratio(s, "ms_pfn")
    p = s["changed_share"]
    deep = max((L["changed_share"] for L in s["layers"]), default=float("nan"))
    run_ratio = s["full_s_all_estimate"] / s["sscater_s_all"] if s["sscater_s_all"] > 0 else float("nan")
    ratios = (f"against the full recomputation, backbone {rb:.1f}x, PFN {rp:.1f}x, whole step {rt:.1f}x (median "
              f"step; {run_ratio:.1f}x over the whole run, refresh steps included)")
    rs = _ratio(s, "ms_stream")
    stream_note = (f" The stream's own bookkeeping (per-pillar queues) cost more than a one-off pillarize ({rs:.1f}x)."
                   if rs < 1 else "")
    if not math.isfinite(rb):
        lines.append("- saving: not measured (no full recomputation to compare with: --check-every 0).")
    elif rb >= 1.5:
        lines.append(_wrap(
            f"saving: {ratios}. {p:.0%} of the pillars changed per step and "
            f"at most {deep:.0%} of any layer's sites, so most of the work was recycled.{stream_note}", "- "))
    else:
        lines.append(_wrap(
            f"saving: little in the backbone; {ratios}. {p:.0%} of the pillars "
            f"changed per step, and each 3x3 convolution widens the changed region by one site, up to {deep:.0%} "
            "of a layer's sites, so the update redid nearly a full pass; on CPU the time follows the work "
            f"(docs/sscater.md, \"The work bound\").{stream_note}", "- "))
    hint = " (compare --relu-zeros 0.9)" if relu_zeros < 0.85 else ""
    lines.append(_wrap(
        f"weights: random, with ~{relu_zeros:.0%} ReLU zeros per layer (--relu-zeros). A site whose output stays "
        f"zero passes no change on, so sparser activations save more{hint}; a trained network's sparsity is not "
        "known here.", "- "))
    rt_line = (f"real time: a step must take under {_BUDGET_MS:g} ms (one slice) to keep up with the sensor: "
               f"SSCATeR {s['under_budget']:.0%} of the steps")
    if s["checks"]:
        rt_line += f", full recomputation {s['full_under_budget']:.0%}"
    if device.type == "cpu":
        rt_line += " (CPU; docs/sscater.md gives GPU figures)"
    lines.append(_wrap(rt_line + ".", "- "))
    return "\n".join(lines)


def _plot(path: Path, scenario: str, records: list[dict], change: dict, model, pillars, s: dict) -> None:
    """The run's picture: time per step with the changed share, the change map of the step with the most
    changes, the pseudo-image of the last window, the changed share per layer."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from matplotlib.patches import Patch

    from lidarops.models.map_to_bev import scatter_to_bev

    grid = model.grid
    x0, y0, _, x1, y1, _ = grid.point_cloud_range
    extent = (x0, x1, y0, y1)
    H, W = grid.shape
    fig = plt.figure(figsize=(16, 11), constrained_layout=True)
    gs = fig.add_gridspec(2, 3, height_ratios=(1, 1.35))

    # ---- time per step, with the share of pillars that changed behind it
    ax = fig.add_subplot(gs[0, :])
    t = np.array([r["t"] for r in records])
    share = np.array([100.0 * r["pillars_changed"] / max(r["pillars_active"], 1) for r in records])
    axs = ax.twinx()
    axs.fill_between(t, share, step="mid", color="tab:orange", alpha=0.25, lw=0)
    axs.set_ylim(0, 100)
    axs.set_ylabel("changed pillars (% of active)", color="tab:orange")
    ax.set_zorder(axs.get_zorder() + 1)  # the times in front of the shaded share
    ax.patch.set_visible(False)
    handles = [ax.plot(t, [r["ms_total"] for r in records], lw=0.8, color="tab:blue",
                       label="SSCATeR step (stream push + PFN + backbone)")[0]]
    ref = [r for r in records if r["refreshed"]]
    if ref:
        handles += ax.plot([r["t"] for r in ref], [r["ms_total"] for r in ref], "v", color="tab:purple", ms=5,
                           label=f"SSCATeR refresh step (full recomputation every {model.refresh_every} steps)")
    chk = [r for r in records if r["check"]]
    if chk:
        handles += ax.plot([r["t"] for r in chk], [r["check"]["ms_total"] for r in chk], "o", color="tab:red", ms=3,
                           label="full recomputation (pillarize + PFN + sparse backbone), also the identity check")
    handles.append(ax.axhline(_BUDGET_MS, color="k", ls="--", lw=0.8,
                              label=f"{_BUDGET_MS:g} ms: one slice (real time)"))
    handles.append(Patch(color="tab:orange", alpha=0.25, label="changed pillars, % of active (right axis)"))
    ax.set_yscale("log")
    ax.set_xlabel("stream time (s)")
    ax.set_ylabel("time per step (ms, log scale)")
    where = "CPU" if model.device.type == "cpu" else torch.cuda.get_device_name(model.device)
    rb, rt = _ratio(s, "ms_backbone"), _ratio(s, "ms_total")
    ax.set_title(f"{scenario} on {where}: median step SSCATeR {_fmt_ms(s['sscater_ms_total'])} ms vs full "
                 f"recomputation {_fmt_ms(s['full_ms_total'])} ms (whole step {rt:.1f}x, backbone {rb:.1f}x)")
    # below the axes, where it covers no data
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3, fontsize=8, frameon=False)

    # ---- change map of the last step that changed pillars
    ax = fig.add_subplot(gs[1, 0])
    img = np.ones((H, W, 3), dtype=np.float32)
    if change:
        act = np.zeros((H, W), dtype=bool)
        a = change["active"].long().cpu().numpy()
        act[a[:, 1], a[:, 2]] = True
        # pillars are drawn 3 x 3 so that single ones stay visible once the 512-pillar grid is scaled down
        img[_dilate(act)] = 0.75
        c = change["changed"].long().cpu().numpy()
        gone = change["removed"].cpu().numpy()
        for sel, colour in ((gone, (0.1, 0.3, 0.9)), (~gone, (0.85, 0.1, 0.1))):
            m = np.zeros((H, W), dtype=bool)
            m[c[sel, 1], c[sel, 2]] = True
            img[_dilate(m)] = colour
        # the window's first steps are left out: every pillar is new then
        which = ("the step with the most changed pillars" if change["full_window"]
                 else "the last step with changes (the window never filled)")
        title = (f"change map of step {change['step']} (t = {change['t']:.2f} s),\n{which}:\n"
                 f"{c.shape[0]} changed ({int(gone.sum())} emptied) of {int(act.sum())} active; "
                 f"median step {s['pillars_changed']:.0f}")
    else:
        title = "change map: no pillar changed in this run"
    ax.imshow(img, origin="lower", extent=extent, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(handles=[Patch(color=(0.85, 0.1, 0.1), label="gained or lost points"),
                       Patch(color=(0.1, 0.3, 0.9), label="emptied"),
                       Patch(color=(0.75, 0.75, 0.75), label="unchanged")],
              loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3, fontsize=8, frameon=False,
              title="pillars (drawn 3 x 3 to stay visible)", title_fontsize=8)

    # ---- pseudo-image of the last window
    ax = fig.add_subplot(gs[1, 1])
    occ = np.zeros((H, W), dtype=bool)
    if pillars.coords.shape[0]:
        cc = pillars.coords.long().cpu().numpy()
        occ[cc[:, 1], cc[:, 2]] = True
        with torch.no_grad():
            f = model.pfn(pillars)
        bev = scatter_to_bev(f.float(), pillars.coords, grid.shape)[0].amax(0).cpu().numpy()
    else:
        bev = np.zeros((H, W), dtype=np.float32)
    vmax = float(np.percentile(bev[bev > 0], 99)) if (bev > 0).any() else 1.0
    # 3 x 3 too, as the change map; empty pillars black, active ones with all-zero features dark purple
    shown = np.ma.masked_where(~_dilate(occ), _max3(np.where(occ, bev, -1.0)).clip(min=0))
    im = ax.imshow(shown, origin="lower", extent=extent, interpolation="nearest", cmap="viridis", vmin=0, vmax=vmax)
    ax.set_facecolor("black")
    cb = fig.colorbar(im, ax=ax, shrink=0.8, extend="max")
    cb.set_label(f"pillar feature, max over its {model.pfn.out_channels} channels (after ReLU; dimensionless)",
                 fontsize=8)
    ax.set_title(f"pseudo-image of the last window (t = {records[-1]['t']:.2f} s):\n"
                 f"the PFN's output at {int(occ.sum())} pillars (black: empty)", fontsize=9)
    ax.set_xlabel("x (m)")

    # ---- changed share per layer
    ax = fig.add_subplot(gs[1, 2])
    names = ["pillars (PFN)"] + [L.get("label", L["name"]) for L in s["layers"]]
    shares = [100 * s["changed_share"]] + [100 * L["changed_share"] for L in s["layers"]]
    ax.barh(range(len(names)), shares, color="tab:orange")
    for y, v in enumerate(shares):
        ax.text(min(v, 100) + 1, y, f"{v:.0f}", va="center", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.set_xlim(0, 110)
    ax.invert_yaxis()
    ax.set_xlabel("changed sites per step (% of active, median)")
    ax.set_title("how far the change spreads through the network\n(the update's work follows these shares)",
                 fontsize=9)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, format=None if path.suffix else "png")
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

def _trained_scenario(path: Path) -> str:
    """The first simulated scenario of a checkpoint's data recipe that the stream can run, else driving_city."""
    from lidarops.models.weights import trained_scenarios

    return next((n for n in trained_scenarios(path) if n in SCENARIO_SETUP), "driving_city")


#: the pillars `lidarops stream --checkpoint` warms a CUDA stream up to (the simulator's streams hold up to about 12,000)
WARM_UP_PILLARS = 16384


def run_detector(checkpoint: str, scenario: Optional[str] = None, seconds: float = 0.3, slice_s: float = 0.01,
                 window: float = 0.1, device: Optional[str] = None, dtype: torch.dtype = torch.float32,
                 check_every: int = 5, refresh_every: Optional[int] = None, seed: int = 0,
                 json_path: Optional[str] = None, threads: Optional[int] = None, print_every: int = 1,
                 realism: Optional[str] = None) -> int:
    """Streaming detection (``lidarops stream --checkpoint``): ``seconds`` of ``scenario`` through
    :meth:`SSCATeRPointPillars.from_detector` of a trained PointPillars; each step's boxes printed, and every
    ``check_every`` steps compared with the detector's own eager call on the points the stream holds (the same
    labels, scores within 1e-5 / 1e-12 relative in float32 / float64). Returns 0 when every check held, 1 otherwise.
    ``checkpoint``: a file, or the name of shipped weights ("shipped": the default detector); ``scenario``: default
    the first one the detector was trained on (its data recipe), else driving_city; ``realism``: the simulator's
    realism profile of the scene, default (None) the one the detector's first frames of that scenario were made
    with (its data recipe), ``"none"``: ray-cast."""
    import json as json_module

    from torch.nn import functional as F

    from lidarops.data.synthetic import Simulator
    from lidarops.models import load_model, weights
    from lidarops.models.cuda_graph import precision_mode
    from lidarops.models.sscater_pointpillars import SSCATeRPointPillars

    if scenario is not None and scenario not in SCENARIO_SETUP:
        raise ValueError(f"scenario must be one of {sorted(SCENARIO_SETUP)}, got {scenario!r}")
    for name, v in (("seconds", seconds), ("slice", slice_s), ("window", window)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"--{name} must be a positive number, got {v!r}")
    if isinstance(check_every, bool) or not isinstance(check_every, int) or check_every < 0:
        raise ValueError(f"--check-every must be an int >= 0, got {check_every!r}")
    ray_cast = realism == "none"
    realism = _check_realism(realism)
    dev = resolve_device(device)
    if json_path:
        json_path = _check_output(Path(json_path), "--json")
    path = weights.path() if checkpoint == "shipped" else \
        (Path(checkpoint) if Path(checkpoint).is_file() or checkpoint not in weights.available() else weights.path(checkpoint))
    detector = load_model(path, map_location=dev).to(dtype).eval()
    if scenario is None:
        scenario = _trained_scenario(path)
    if realism is None and not ray_cast:
        realism = weights.trained_realism(path, scenario)
    if type(detector).__name__ != "PointPillars":
        raise ValueError(f"--checkpoint {checkpoint} holds a {type(detector).__name__}; streaming detection needs a "
                         "PointPillars")
    kwargs = {} if refresh_every is None else {"refresh_every": refresh_every}
    model = SSCATeRPointPillars.from_detector(detector, window=window, dtype=dtype, device=dev, **kwargs)
    names = list(detector.config.class_names)
    steps = max(1, int(math.ceil(seconds / slice_s - 1e-9)))
    saved = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    sim = Simulator(scenario, seed=seed, realism=realism)
    tol = _TOL[dtype]
    scene = f"{scenario}, realism profile {realism}" if realism else f"{scenario}, ray-cast"
    print(_wrap(f"lidarops stream --checkpoint: SSCATeR with the detector {path.name} on {seconds:g} s of simulated "
                f"{scene} ({steps} steps of {slice_s * 1e3:g} ms, a {window * 1e3:g} ms window, {dev.type}, "
                f"{str(dtype).replace('torch.', '')}). Each step recomputes the pillars that gained or lost points "
                f"and the sites their change reaches, then runs the detector's head and NMS on the recycled map; every "
                f"{check_every or 'no'} step(s) the boxes are compared with the detector run on the same points.", ""))
    records, failed = [], 0
    if dev.type == "cuda":  # the CUDA graphs recorded now, so that the steps' times are those of replays
        t0 = time.perf_counter()
        with precision_mode("fp32"):
            recorded = model.warm_up(min(model.stream.max_pillars, WARM_UP_PILLARS))
        print(f"recorded {recorded} CUDA graphs in {time.perf_counter() - t0:.1f} s (SSCATeRPointPillars.warm_up): "
              "no step records one below that size")
    # float32 without TF32 for the whole run on CUDA: the recycled backbone sums in float32 whatever the flags, the
    # pillar net and the head follow them, and the check runs the detector so (cuDNN's TF32 is on by default)
    try:
        with precision_mode("fp32" if dev.type == "cuda" else None):
            for k in range(steps):
                a, b = k * slice_s, min((k + 1) * slice_s, seconds)
                pts, t = sim.stream(a, b)
                t0 = time.perf_counter()
                model.step(torch.from_numpy(pts).to(dev), torch.from_numpy(t).to(dev), now=b)
                det = model.detect()
                _sync(dev)
                ms = (time.perf_counter() - t0) * 1e3
                labels = det["labels"].tolist()
                rec = {"step": k, "t": b, "ms": ms, "refreshed": model.stats.refreshed,
                       "pillars_active": model.stats.pillars_active, "pillars_changed": model.stats.pillars_changed,
                       "boxes": {c: labels.count(i + 1) for i, c in enumerate(names)}}
                if check_every and (k + 1) % check_every == 0:
                    t1 = time.perf_counter()
                    window_pts = model.window_points().to(dtype)
                    with torch.no_grad():
                        want = detector.predict({"points": F.pad(window_pts, (1, 0)), "batch_size": 1})[0]
                    _sync(dev)
                    rec["ms_detector"] = (time.perf_counter() - t1) * 1e3
                    same = labels == want["labels"].tolist() and torch.allclose(
                        det["scores"], want["scores"], rtol=tol * 10, atol=tol * 10)
                    rec["same_as_detector"] = bool(same)
                    failed += not same
                records.append(rec)
                if print_every and (k % print_every == 0 or k == steps - 1 or "same_as_detector" in rec):
                    found = ", ".join(f"{c} {n}" for c, n in rec["boxes"].items() if n) or "no boxes"
                    check = "" if "same_as_detector" not in rec else \
                        (f"; detector on the window {rec['ms_detector']:.0f} ms: " +
                         ("same boxes" if rec["same_as_detector"] else "DIFFERENT boxes"))
                    print(f"  t {b * 1e3:6.0f} ms  {'refresh' if rec['refreshed'] else 'recycle'}  changed "
                          f"{rec['pillars_changed']:5d} of {rec['pillars_active']:5d} pillars  {ms:7.1f} ms  "
                          f"{found}{check}")
    finally:
        torch.set_num_threads(saved)
    checks = [r for r in records if "same_as_detector" in r]
    recycled = [r["ms"] for r in records if not r["refreshed"]]
    print(_wrap(f"{len(checks)} check(s) against the detector: " + ("all the same boxes" if not failed else
                f"{failed} DIFFERED") + (f"; recycled steps: median {_median(recycled):.1f} ms" if recycled else "") +
                (f", the detector on a window: median {_median([r['ms_detector'] for r in checks]):.1f} ms" if checks
                 else "") + "."))
    if json_path:
        json_path.write_text(json_module.dumps({"checkpoint": str(path), "scenario": scenario, "realism": realism,
                                                "steps": records}, indent=1))
    return 1 if failed else 0


def _main(args: argparse.Namespace) -> int:
    from lidarops.ops.pillars import PillarOverflowError

    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    detecting = args.checkpoint is not None
    # the defaults of each mode: random weights on a drone scene; a detector on the scenes it was trained on
    scenario = args.scenario or (None if detecting else "drone_bridge")
    seconds = args.seconds if args.seconds is not None else (0.3 if detecting else 5.0)
    check_every = args.check_every if args.check_every is not None else (5 if detecting else 10)
    if detecting:
        return run_detector(args.checkpoint, scenario, seconds, args.slice, args.window, args.device, dtype,
                            check_every, args.refresh_every, args.seed, args.json, args.threads,
                            realism=args.realism)
    args.scenario, args.seconds, args.check_every = scenario, seconds, check_every
    small = True if args.small else (False if args.full_size else None)
    try:
        return run(args.scenario, args.seconds, args.slice, args.window, args.device, dtype, args.check_every,
                   args.refresh_every, args.relu_zeros, args.seed, small, args.out, args.json,
                   args.max_points_per_pillar, args.max_pillars, args.profile or None, not args.no_progress,
                   args.threads, args.realism)
    except PillarOverflowError as e:  # the stream never drops points: name the flags that give it room
        raise CliError(f"{e} (--max-points-per-pillar / --max-pillars)") from None


def register(subparsers) -> None:
    """Adds ``stream`` to the ``lidarops`` parser."""
    p = subparsers.add_parser(
        "stream", help="stream the simulator through SSCATeR PointPillars, checked against full recomputation",
        description="Streams a simulated LiDAR scene in slices through streaming pillarization, the pillar "
                    "feature net and the SSCATeR (temporal data recycling) backbone; checks the output against a "
                    "full recomputation as it goes; prints time per stage, active/changed sites per layer and what "
                    "the run shows; writes a PNG (time per step, change map, pseudo-image, changed share per "
                    "layer). Exit code 0: identity held; 1: an identity check failed; 2: an error (one line on "
                    "stderr).")
    p.add_argument("--checkpoint", default=None, metavar="PATH|NAME",
                   help="streaming detection with a trained PointPillars (a file, a shipped name, or 'shipped' for "
                        "the shipped detector): its boxes at every step, checked against the detector run on the "
                        "same points; without it, the random-weights benchmark of the recycling backbone")
    p.add_argument("--scenario", choices=sorted(SCENARIO_SETUP), default=None,
                   help="simulated scene (default drone_bridge; with --checkpoint, the first scene the detector was "
                        "trained on: driving_city for the shipped one, drone_bridge for aerial_pointpillars); drone "
                        "scenes use the 512 x 512 drone grid (a detector: its own grid), driving scenes the KITTI "
                        "grid (x forward)")
    p.add_argument("--seconds", type=float, default=None, help="stream length in seconds (default 5; 0.3 with "
                                                               "--checkpoint)")
    p.add_argument("--slice", type=float, default=0.01, help="seconds per step (default 0.01)")
    p.add_argument("--window", type=float, default=0.1, help="sliding window in seconds (default 0.1)")
    p.add_argument("--device", choices=("cpu", "cuda"), default=None,
                   help="default: cuda when available and lidarops has its CUDA kernels, else cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--check-every", type=int, default=None,
                   help="compare with a full recomputation every N steps (default 10, 5 with --checkpoint; 0: never); "
                        "exit code 1 when a relative difference exceeds 1e-5 (float32) or 1e-12 (float64)")
    p.add_argument("--refresh-every", type=int, default=None,
                   help="full recomputation inside SSCATeR every N steps (0: never; default: SSCATeRPointPillars' "
                        "default, 25, chosen from the float32 drift of the recycled sums, ~1e-7 of max|output| "
                        "per step)")
    p.add_argument("--relu-zeros", type=float, default=0.5,
                   help="share of negative pre-activations BatchNorm is calibrated for on the first window "
                        "(default 0.5; random weights stand in for a trained network)")
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and of the weights")
    p.add_argument("--realism", default=None, type=_realism_or_none_arg, metavar="PROFILE",
                   help="the simulator's realism profile of the scene (as lidarops data synth --realism): avia for "
                        "the drone scenes (a Livox Avia's reflectivity, quadcopter drones), kitti for the driving "
                        "scenes, none: ray-cast; default: with --checkpoint the profile the detector was trained on "
                        "for the scene (its data recipe), else ray-cast")
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
    p.add_argument("--out", default=None,
                   help="picture path (default lidarops_stream_<scenario>.png; .pdf, .svg ... also work)")
    p.add_argument("--json", default=None, metavar="PATH", help="write the per-step figures as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=guarded("stream", _main))
