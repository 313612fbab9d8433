"""Benchmark of CAS-Net sampling (lidarops.models.casnet) beside the baseline samplers, CUDA graphs, and the
whole-cloud (chunked offset-attention) path against the paper's segments.

    python benchmarks/bm_casnet.py                          # CUDA when available, else CPU
    python benchmarks/bm_casnet.py --device cuda --json     # write benchmarks/results/<device>.json
    python benchmarks/bm_casnet.py --device cuda --checkpoint runs/casnet/last.pt   # a trained CAS-Net too
    python benchmarks/bm_casnet.py --device cpu --quick     # smoke test: tiny clouds and models (seconds)
    python benchmarks/bm_casnet.py --device cpu --threads 1 # CPU, about 2 minutes (see "CPU sizing")
    python benchmarks/bm_casnet.py --device cpu --full      # CPU with the CUDA sizes (long)

The cloud: sweep 0 of ``lidarops.data.synthetic.Simulator("driving_city", seed=0)`` (x, y, z, intensity),
cropped to KITTI's camera field of view (``x > 0`` and ``|atan2(y, x)| <= 45`` degrees; 31,274 points), then an
order-preserving random subset (seed 0) of exactly N = 20,000 points, about what a KITTI frame keeps in that
field of view. The 65,536-point cloud: the field-of-view crops of sweeps 0, 1, 2 concatenated (the sensor
moves between them: an accumulated cloud) and cut the same way. Sampling ratio D = 8: ``m = N // 8``.

1. ``sampling``: time per cloud as users see it (eager calls as written, host work included), ``m = N // 8``:
   ``RandomSampler(seed=0)``, ``FPSSampler()``, ``ChunkedFPSSampler()`` (chunks of 8,192) and
   ``CASNetSampler`` (dedup on, its default) around an untrained CAS-Net in eval mode, the full variant
   ``CASNet(num_out=1024, k=32, radius=2.0)`` (segments of 8,192 = 1,024 x 8 points, as the paper) and
   ``CASNet.fast(num_out=1024)``, each also with ``chunk="fused"`` (the offset attention through torch's fused
   attention kernels; on CUDA also under float16 autocast, the flash kernels); for each also ``segment_and_sample(model, points, 8, dedup=False)``, the
   paper's raw picks (``segments x 1,024`` rows, repeats included: ``m`` is then that count). ``--checkpoint``
   adds the same two rows for ``load_casnet(PATH, device)`` (a name of ``lidarops/weights`` too), and the
   whole-cloud rows below when its head is anchored. Columns: ``distinct`` = distinct points picked;
   ``x FPS`` = median / FPSSampler's median.
2. ``cuda_graph`` (CUDA only): the CAS-Net forward (hard mode, no dedup, no grad) on one fixed padded segment
   batch (the 20,000-point cloud's 3 segments, padded to 8,192 rows, with their lengths) eagerly, with the
   value checks on (as called) and off, and captured in a ``torch.cuda.CUDAGraph`` (static input). A capture
   that fails is reported as skipped with its reason, the first error and the lidarops line it came from
   (expected: the forward reads the lengths on the host and indexes with boolean masks, host syncs that a
   capture refuses). Also: the stages after the embedding (the offset-attention layers, the head and the
   argmax, called as the forward calls them) on 3 full segments (8,192 real points each, no mask), eager and
   graph-captured: what a capture saves where one is possible. This section runs last, so that a failed
   capture cannot disturb the others.
3. ``whole_cloud``: a CAS-Net with ``num_out = N // 8`` (k = 32, r = 2 m, ``chunk="auto"``: blocks of query
   rows, never an N x N matrix; and the same weights with ``chunk="fused"``: torch's fused attention) on the
   whole cloud, beside the segmented path (the full variant, segments of
   8,192, ``segment_and_sample(..., num_samples=N // 8, dedup=False)``: the same number of points kept), for
   N = 20,000 and 65,536: inference (eval, no grad) and one training step (train mode, hard forward,
   ``casnet_loss`` = Chamfer + cosine with a zero task loss, backward; no optimiser step; the segmented step
   runs the cloud's padded segments as one batch). On CUDA also the peak memory of the call.

Times are medians in ms with the timers of ``benchmarks/common.py``: on CUDA CUDA events (one cold call, warm-up,
then as many calls as fit in the budget; a warm call over 2 s counts alone), on CPU ``time.perf_counter`` with
the implementations of one table's cases interleaved (:func:`~benchmarks.common.time_cpu_interleaved`).
``peak MB`` (CUDA) = ``torch.cuda.max_memory_allocated`` over one call (reset just before) minus what was
allocated before it: the memory the call itself needs (the JSON keeps the absolute peak as
``peak_allocated_mb``). The dedup rows' time depends on the weights (the greedy assignment runs on the host;
rows of an untrained model agree more than trained ones), the others' does not.

CPU sizing: on this project's 2-core machines one full-variant CAS-Net call on 20,000 points takes 10-30 s, so
a CPU run without ``--full`` keeps section 1 at 20,000 points (each CAS-Net row: one cold call and one timed warm
call), skips section 2 (CUDA only) and runs section 3 on a 4,096-point cloud only, without the segmented training
step (one 8,192-row segment however small the cloud: about 20 s a call); it takes 80-130 s (240 s with that step,
under load). ``--full`` runs the CUDA sizes on CPU (tens of minutes; cases estimated beyond half the free memory,
such as the 65,536-point whole-cloud training step, are skipped). On a loaded machine ``--threads 1`` gives
steadier CPU times: two threads contending with other work made small calls up to 25 times slower here.

``--quick`` (the smoke test): a 2,048-point cloud, the variants with ``num_out = 64`` (segments of 512) and
section 3 on 1,024 points.

Every case is guarded: one that runs out of memory, is estimated not to fit, or fails is reported with its
reason (``skipped (...)`` or ``error: ...``) and the others go on. ``--json`` writes the rows (``op`` =
``section/case/implementation``) as section ``"casnet"`` of ``benchmarks/results/<device>.json``, replacing that
section whole (the other sections are kept).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from benchmarks.common import (
    Skip,
    add_common_args,
    bench_device,
    load_average_warning,
    run_with_threads,
    available_memory,
    device_name,
    env_meta,
    fmt_ms,
    fmt_ratio,
    print_table,
    short_status,
    time_cpu_interleaved,
    time_cuda,
    write_results,
)

import lidarops
from lidarops.models.casnet import CASNet, CASNetSampler, casnet_loss, segment_and_sample
from lidarops.models.offset_attention import _rows_per_chunk
from lidarops.models.samplers import ChunkedFPSSampler, FPSSampler, RandomSampler, spatial_segments
from lidarops.ops.validation import validation

SECTION = "casnet"
RATIO = 8  # the sampling ratio D
FOV_DEG = 45.0  # KITTI's camera field of view: |azimuth| <= 45 degrees, x > 0
SCENARIO, SEED = "driving_city", 0
GRAPH_SEGMENTS = 3


@dataclass
class Sizes:
    cloud: int  # points of section 1's cloud (and of section 2's padded batch)
    segment: int  # points per segment: the full/fast variants' num_out * RATIO
    whole: tuple  # clouds of section 3
    seg_train_skip: str | None = None  # why section 3's segmented training step is not run


def sizes_for(device: torch.device, quick: bool, full: bool) -> Sizes:
    if quick:
        return Sizes(cloud=2048, segment=512, whole=(1024,))
    if device.type == "cuda" or full:
        return Sizes(cloud=20_000, segment=8192, whole=(20_000, 65_536))
    return Sizes(cloud=20_000, segment=8192, whole=(4096,),
                 seg_train_skip="skipped (time: about 20 s a call on 2 CPU cores; run with --full)")


# ------------------------------------------------------------------ clouds

class FovClouds:
    """Field-of-view crops of the simulator's sweeps 0, 1, ... (x, y, z, intensity), cut to a given size."""

    def __init__(self, scenario: str = SCENARIO, seed: int = SEED):
        self.scenario, self.seed = scenario, seed
        self._sim = None
        self.crops: list[np.ndarray] = []  # per sweep: its field-of-view points (P, 4) float32

    def _crop(self, i: int) -> np.ndarray:
        while len(self.crops) <= i:
            if self._sim is None:
                from lidarops.data.synthetic import Simulator
                self._sim = Simulator(self.scenario, seed=self.seed)
            p = self._sim.sweep(len(self.crops)).points
            keep = (p[:, 0] > 0) & (np.abs(np.degrees(np.arctan2(p[:, 1], p[:, 0]))) <= FOV_DEG)
            self.crops.append(np.ascontiguousarray(p[keep, :4], dtype=np.float32))
        return self.crops[i]

    def cloud(self, n: int) -> tuple[torch.Tensor, dict]:
        """(n, 4) float32 points: the crops of sweeps 0, 1, ... concatenated until there are n, then an
        order-preserving random subset of n (seed 0); and a description of where they come from."""
        parts, total = [], 0
        while total < n:
            parts.append(self._crop(len(parts)))
            total += parts[-1].shape[0]
        pts = torch.from_numpy(np.concatenate(parts))
        g = torch.Generator().manual_seed(0)
        keep = torch.randperm(pts.shape[0], generator=g)[:n].sort().values
        info = dict(points=n, sweeps=len(parts), fov_points=total,
                    source=f'lidarops.data.synthetic.Simulator("{self.scenario}", seed={self.seed}), sweeps 0..'
                           f'{len(parts) - 1}, x > 0 and |azimuth| <= {FOV_DEG:g} deg, random subset of {n}')
        return pts[keep].contiguous(), info


def padded_segments(points: torch.Tensor, segment: int, count: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The cloud's segments (:func:`spatial_segments`, as :func:`segment_and_sample` cuts them), the first
    ``count``, as one zero-padded batch (S, segment, C) and their lengths (S,) int64, on the cloud's device."""
    segs = spatial_segments(points, segment)[:count]
    batch = points.new_zeros(len(segs), segment, points.shape[1])
    for i, s in enumerate(segs):
        batch[i, :s.numel()] = points[s]
    lengths = torch.tensor([s.numel() for s in segs], dtype=torch.int64, device=points.device)
    return batch, lengths


# ------------------------------------------------------------------ measurement plumbing

@dataclass
class Case:
    row: dict
    fn: Callable[[], Any] | None
    skip: str | None = None
    mem: int = 0  # estimated bytes the call needs
    peak: bool = True  # measure the CUDA peak memory
    result: dict = field(default_factory=dict)  # the last call's return value, under "out"

    def call(self) -> None:
        self.result["out"] = self.fn()


def _error(e: BaseException) -> str:
    msg = str(e).strip().splitlines()[0][:200] if str(e).strip() else ""
    return f"error: {type(e).__name__}: {msg}"


def _is_oom(e: BaseException) -> bool:
    return isinstance(e, (torch.OutOfMemoryError, MemoryError)) or "out of memory" in str(e).lower()


@dataclass
class Runner:
    device: torch.device
    quick: bool = False
    rows: list[dict] = field(default_factory=list)

    def __post_init__(self):
        cuda = self.device.type == "cuda"
        self.budget_s = (0.1 if self.quick else 0.5) if cuda else (0.2 if self.quick else 1.0)
        self.mem_budget = int((0.85 if cuda else 0.5) * available_memory(self.device))

    def sync(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _failed(self, case: Case, e: BaseException) -> None:
        if _is_oom(e):
            case.row.update(status="skipped (memory: out of memory)", median_ms=None)
        else:
            case.row.update(status=_error(e), median_ms=None)
            print(f"  {case.row['op']}: {case.row['status']}", file=sys.stderr)
        case.result.clear()
        if self.device.type == "cuda":
            torch.cuda.empty_cache()

    def run(self, cases: list[Case]) -> list[Case]:
        """Times the cases (interleaved on CPU; one after the other on CUDA, each with its peak memory)."""
        todo = []
        for c in cases:
            c.row.setdefault("device", self.device.type)
            try:
                if c.skip:
                    raise Skip(c.skip)
                if c.mem > self.mem_budget:
                    raise Skip(f"skipped (memory: needs about {c.mem / 2**30:.1f} GiB, budget "
                               f"{self.mem_budget / 2**30:.1f} GiB)")
                todo.append(c)
            except Skip as e:
                c.row.update(status=str(e), median_ms=None)
        if self.device.type == "cuda":
            for c in todo:
                try:
                    t = time_cuda(c.call, (), warmup=2, min_runs=5, max_runs=100, budget_s=self.budget_s,
                                  slow_single_s=2.0, rotate=False)
                    c.row.update(status="ok", **t.as_dict())
                    if c.peak:
                        c.row.update(self.peak_memory(c))
                except Exception as e:  # noqa: BLE001  (reported in the row)
                    self._failed(c, e)
                torch.cuda.empty_cache()
        else:
            timings = time_cpu_interleaved([(c.call, ()) for c in todo], budget_s=self.budget_s, slow_single_s=2.0,
                                           max_runs=30)
            for c, t in zip(todo, timings):
                if isinstance(t, BaseException):
                    self._failed(c, t)
                else:
                    c.row.update(status="ok", **t.as_dict())
        self.rows += [c.row for c in cases]
        return cases

    def peak_memory(self, case: Case) -> dict:
        """One more call: the peak of CUDA memory allocated during it, beyond what was allocated before."""
        self.sync()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(self.device)
        before = torch.cuda.memory_allocated(self.device)
        case.call()
        self.sync()
        peak = torch.cuda.max_memory_allocated(self.device)
        return dict(peak_mb=round((peak - before) / 2**20, 1), peak_allocated_mb=round(peak / 2**20, 1))


def _row(section: str, case: str, impl: str, **extra) -> dict:
    return dict(op=f"{section}/{case}/{impl}", section=section, case=case, impl=impl, **extra)


def _picks(case: Case) -> None:
    """Adds the distinct points of the last call's indices (any shape, -1 padding ignored) to the row."""
    out = case.result.get("out")
    if isinstance(out, torch.Tensor):
        idx = out.reshape(-1)
        idx = idx[idx >= 0]
        case.row.update(picks=int(idx.numel()), distinct=int(torch.unique(idx).numel()))


# ------------------------------------------------------------------ models

def paper_models(segment: int, device: torch.device) -> dict[str, CASNet]:
    """The untrained full and fast variants (m = segment // RATIO), eval mode, seeded weights."""
    num_out = segment // RATIO
    torch.manual_seed(0)
    full = CASNet(num_out=num_out, k=32, radius=2.0).eval().to(device)
    torch.manual_seed(0)
    fast = CASNet.fast(num_out=num_out).eval().to(device)
    torch.manual_seed(0)
    full_fused = CASNet(num_out=num_out, k=32, radius=2.0, chunk="fused").eval().to(device)
    torch.manual_seed(0)
    fast_fused = CASNet.fast(num_out=num_out, chunk="fused").eval().to(device)
    return {f"full CASNet(num_out={num_out}, k=32, radius=2.0)": full, f"fast CASNet.fast(num_out={num_out})": fast,
            f"full CASNet(num_out={num_out}, k=32, radius=2.0, chunk='fused')": full_fused,
            f"fast CASNet.fast(num_out={num_out}, chunk='fused')": fast_fused}


def anchored_models(dev: torch.device) -> dict[str, CASNet]:
    """The anchored head (ours), full and fast, fused attention, untrained (seeded): the row count is set per call."""
    torch.manual_seed(0)
    full = CASNet(num_out=1, k=32, radius=2.0, chunk="fused", head="anchored").eval().to(dev)
    torch.manual_seed(0)
    fast = CASNet.fast(num_out=1, chunk="fused", head="anchored").eval().to(dev)
    return {"full CASNet(k=32, radius=2.0, chunk='fused', head='anchored')": full,
            "fast CASNet.fast(chunk='fused', head='anchored')": fast}


# ------------------------------------------------------------------ 1. sampling

def bench_sampling(run: Runner, points: torch.Tensor, sizes: Sizes, models: dict[str, Any]) -> list[dict]:
    N = points.shape[0]
    m = N // RATIO
    batch = points.unsqueeze(0)  # (1, N, 4): the samplers' interface
    segs = math.ceil(N / sizes.segment)
    samplers = [("RandomSampler(seed=0)", RandomSampler(seed=0)), ("FPSSampler()", FPSSampler()),
                (f"ChunkedFPSSampler(chunk={sizes.segment})", ChunkedFPSSampler(chunk=sizes.segment))]
    cases = [Case(_row("sampling", "sampler", name, N=N, m=m), lambda s=s: s(batch, m)) for name, s in samplers]
    for name, model in models.items():
        kind = name.split(" ")[0]
        try:
            if isinstance(model, str):  # a checkpoint that did not load: the reason
                raise Skip(model)
            sampler = CASNetSampler(model, max_points=sizes.segment)
            skip = None
        except Exception as e:  # noqa: BLE001  (reported in its rows)
            sampler, skip = None, str(e) if isinstance(e, Skip) else _error(e)
        cases.append(Case(_row("sampling", "CASNetSampler", name, N=N, m=m, variant=kind, dedup=True),
                          lambda s=sampler: s(batch, m), skip=skip))
        raw_m = None if isinstance(model, str) else segs * model.num_out
        cases.append(Case(_row("sampling", "segment_and_sample", name, N=N, m=raw_m, variant=kind, dedup=False,
                               ratio=RATIO, segments=segs),
                          lambda mod=model: segment_and_sample(mod, points, RATIO, max_points=sizes.segment,
                                                               dedup=False),
                          skip=skip if isinstance(model, str) else None))
        if points.device.type == "cuda" and "fused" in name:  # float16 autocast: the flash kernels
            def half(mod=model):
                with torch.autocast("cuda", dtype=torch.float16):
                    return segment_and_sample(mod, points, RATIO, max_points=sizes.segment, dedup=False)

            cases.append(Case(_row("sampling", "segment_and_sample, fp16 autocast", name, N=N, m=raw_m, variant=kind,
                                   dedup=False, ratio=RATIO, segments=segs), half))
    whole = {**anchored_models(dev=points.device),  # ours: the whole cloud, m free per call; and anchored checkpoints
             **{n: mod for n, mod in models.items() if isinstance(mod, CASNet) and mod.head_kind == "anchored"}}
    for name, model in whole.items():
        kind = name.split(" ")[0]
        for dedup in (True, False):
            sampler = CASNetSampler(model, dedup=dedup, whole=True)
            tag = "" if dedup else ", raw"
            cases.append(Case(_row("sampling", f"CASNetSampler(whole=True{tag})", name, N=N, m=m, variant=kind,
                                   dedup=dedup, head="anchored"), lambda s=sampler: s(batch, m)))
            if points.device.type == "cuda":
                def half(s=sampler):
                    with torch.autocast("cuda", dtype=torch.float16):
                        return s(batch, m)

                cases.append(Case(_row("sampling", f"CASNetSampler(whole=True{tag}), fp16 autocast", name, N=N, m=m,
                                       variant=kind, dedup=dedup, head="anchored"), half))
    run.run(cases)
    for c in cases:
        _picks(c)
    fps = next((c.row["median_ms"] for c in cases if c.row["impl"] == "FPSSampler()"), None)
    for c in cases:
        if fps and c.row.get("median_ms"):
            c.row["vs_fps"] = c.row["median_ms"] / fps
    return [c.row for c in cases]


def print_sampling(rows: list[dict], cloud: dict, device: torch.device) -> None:
    cuda = device.type == "cuda"
    table = []
    for r in rows:
        impl = r["impl"] if r["case"] == "sampler" else f"{r['case']}: {r['impl']}"
        if r["case"] == "segment_and_sample":
            impl += " (raw, no dedup)"
        table.append([impl, r["N"], r["m"] if r["m"] is not None else "-", r.get("distinct", ""), *_time_cells(r),
                      fmt_ratio(r.get("vs_fps"))] + ([r.get("peak_mb", "")] if cuda else []))
    headers = ["sampler", "N", "m", "distinct", "ms", "IQR", "runs", "x FPS"] + (["peak MB"] if cuda else [])
    print_table(f"== 1. sampling one cloud, D = {RATIO} ({device_name(device)}); cloud: {cloud['source']} "
                f"({cloud['fov_points']:,} points in the field of view)", headers, table,
                right=(1, 2, 3, 4, 5, 6, 7, 8))
    _print_reasons(rows)


def _time_cells(r: dict) -> list:
    """The ms, IQR and runs cells of a row (its short status in place of a time)."""
    if r.get("median_ms") is None:
        return [short_status(r["status"]), "", ""]
    return [fmt_ms(r["median_ms"]), fmt_ms(r["iqr_ms"]) if r["runs"] > 1 else "", r["runs"]]


def _print_reasons(rows: list[dict]) -> None:
    """The whole status of each row that was not measured, once per distinct status."""
    by_status: dict[str, list[str]] = {}
    for r in rows:
        if r["status"] != "ok":
            by_status.setdefault(r["status"], []).append(r["op"])
    for status, ops in by_status.items():
        print(f"  {ops[0]}: {status}" if len(ops) == 1 else f"  {len(ops)} rows: {status}")


# ------------------------------------------------------------------ 2. CUDA graphs

def _capture(fn: Callable[[], Any]) -> tuple[torch.cuda.CUDAGraph, Any]:
    """A CUDA graph of ``fn`` (warmed up on a side stream, as torch.cuda.graphs asks) and its static output."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = fn()
    torch.cuda.synchronize()
    return graph, out


def _capture_failure(e: BaseException) -> str:
    """Why a capture failed: the first error of the chain (``torch.cuda.graph``'s exit raises its own error on
    top of the one that broke the capture) and the deepest lidarops line it came from."""
    root = e
    while root.__context__ is not None and root.__context__ is not root:
        root = root.__context__
    msg = str(root).strip().splitlines()[0][:160] if str(root).strip() else ""
    where = ""
    tb = root.__traceback__
    while tb is not None:
        code = tb.tb_frame.f_code
        if f"{os.sep}lidarops{os.sep}" in code.co_filename:
            where = f" (at {Path(code.co_filename).name}:{tb.tb_lineno} in {code.co_name})"
        tb = tb.tb_next
    return f"{type(root).__name__}: {msg}{where}"


def _graph_case(row: dict, fn: Callable[[], Any]) -> Case:
    """A case that replays a graph of ``fn``; a capture that fails makes it a skip naming why."""
    stream = torch.cuda.current_stream()
    try:
        graph, out = _capture(fn)
    except Exception as e:  # noqa: BLE001  (reported in the row)
        # torch.cuda.graph's exit raised before restoring the stream it captured on
        torch.cuda.set_stream(stream)
        try:
            torch.cuda.synchronize()
        except Exception:  # noqa: BLE001
            pass
        torch.cuda.empty_cache()
        return Case(row, None, skip=f"skipped (capture failed: {_capture_failure(e)})")
    case = Case(row, graph.replay)
    case.result["graph"] = (graph, out)  # keeps the graph and its static output alive while it is timed
    return case


def bench_cuda_graphs(run: Runner, points: torch.Tensor, full_cloud: torch.Tensor, sizes: Sizes,
                      model: CASNet) -> list[dict]:
    """The forward on a padded segment batch, eager and captured; the stages after the embedding on full
    segments, eager and captured."""
    dev = run.device
    batch, lengths = padded_segments(points, sizes.segment, GRAPH_SEGMENTS)
    base = dict(N=sizes.segment, segments=batch.shape[0], lengths=lengths.tolist())
    fwd = "forward (padded segments)"
    name = "attention + head + argmax (full segments)"

    def forward(checks: bool):
        def f():
            with torch.no_grad(), validation(checks):
                return model(batch, lengths, mode="hard", dedup=False).indices
        return f

    if dev.type != "cuda":  # CPU --full: the eager forward alone
        why = "skipped (CUDA only: CUDA graphs)"
        cases = [Case(_row("cuda_graph", fwd, "eager, value checks on", **base), forward(True)),
                 Case(_row("cuda_graph", fwd, "eager, value checks off", **base), forward(False)),
                 Case(_row("cuda_graph", fwd, "CUDA graph", **base), None, skip=why),
                 Case(_row("cuda_graph", name, "eager", **base), None, skip=why),
                 Case(_row("cuda_graph", name, "CUDA graph", **base), None, skip=why)]
        run.run(cases)
        for c in cases:
            c.result.clear()
        return [c.row for c in cases]

    cases = [Case(_row("cuda_graph", fwd, "eager, value checks on", **base), forward(True)),
             Case(_row("cuda_graph", fwd, "eager, value checks off", **base), forward(False))]
    run.run(cases)
    cases.append(_graph_case(_row("cuda_graph", fwd, "CUDA graph", **base), forward(False)))
    run.run(cases[-1:])

    # the stages after the embedding, on full segments (no padding, no mask): offset attention, head, argmax
    full_batch, full_lengths = padded_segments(full_cloud, sizes.segment, GRAPH_SEGMENTS)
    with torch.no_grad(), validation(False):
        xyz = full_batch[..., :3].contiguous()
        embedded = model.embedding(xyz, full_lengths)
    xyz_t = xyz.transpose(1, 2).contiguous()

    def stages():
        with torch.no_grad():
            x, feats = embedded, []
            for layer in model.attention:
                x = layer(x)
                feats.append(x)
            logits = model.head(torch.cat(feats + [xyz_t], dim=1)) / model.temperature
            return logits.argmax(dim=-1)

    rows_per_block = _rows_per_chunk(model.attention[0].chunk, full_batch.shape[0], sizes.segment)
    sbase = dict(N=sizes.segment, segments=full_batch.shape[0], lengths=full_lengths.tolist(),
                 attention_rows=rows_per_block)
    tail = [Case(_row("cuda_graph", name, "eager", **sbase), stages)]
    run.run(tail)
    tail.append(_graph_case(_row("cuda_graph", name, "CUDA graph", **sbase), stages))
    run.run(tail[-1:])
    cases += tail
    for a, b in ((cases[1], cases[2]), (tail[0], tail[1])):
        if a.row.get("median_ms") and b.row.get("median_ms"):
            b.row["speedup_vs_eager"] = a.row["median_ms"] / b.row["median_ms"]
    for c in cases:
        c.result.clear()
    return [c.row for c in cases]


def print_cuda_graphs(rows: list[dict], device: torch.device) -> None:
    cuda = device.type == "cuda"
    table = [[r["case"], f"{r['segments']} x {r['N']}", r["impl"], *_time_cells(r),
              fmt_ratio(r.get("speedup_vs_eager"))] + ([r.get("peak_mb", "")] if cuda else []) for r in rows]
    print_table(f"== 2. CUDA graphs, eval mode, no grad ({device_name(device)}); speedup = eager (checks off) / graph",
                ["case", "batch", "implementation", "ms", "IQR", "runs", "speedup"] + (["peak MB"] if cuda else []),
                table, right=(3, 4, 5, 6, 7))
    _print_reasons(rows)


# ------------------------------------------------------------------ 3. whole cloud

def _train_step(model: CASNet, points: torch.Tensor, lengths: torch.Tensor | None, zero: torch.Tensor):
    model.train()
    model.zero_grad(set_to_none=True)
    out = model(points, lengths, mode="hard", dedup=False)
    loss = casnet_loss(out, points, zero)["loss"]
    loss.backward()
    return loss.detach()


def _autocast_cuda(fn: Callable, *args):
    with torch.autocast("cuda", dtype=torch.float16):
        return fn(*args)


def bench_whole_cloud(run: Runner, clouds: FovClouds, sizes: Sizes) -> tuple[list[dict], list[dict]]:
    dev = run.device
    rows, infos = [], []
    seg_num_out = sizes.segment // RATIO
    torch.manual_seed(0)
    seg_model = CASNet(num_out=seg_num_out, k=32, radius=2.0).to(dev)
    zero = torch.zeros((), device=dev)
    for n in sizes.whole:
        cloud, info = clouds.cloud(n)
        infos.append(info)
        cloud = cloud.to(dev)
        m = n // RATIO
        torch.manual_seed(0)
        whole = CASNet(num_out=m, k=32, radius=2.0, chunk="auto").to(dev)
        torch.manual_seed(0)
        fused = CASNet(num_out=m, k=32, radius=2.0, chunk="fused").to(dev)
        fused_name = f"whole cloud: CASNet(num_out={m}, k=32, radius=2.0, chunk='fused')"
        seg_batch, seg_lengths = padded_segments(cloud, sizes.segment)
        S = seg_batch.shape[0]
        attn_rows = _rows_per_chunk("auto", 1, n)
        seg_rows = _rows_per_chunk("auto", S, sizes.segment)
        whole_name = f"whole cloud: CASNet(num_out={m}, k=32, radius=2.0, chunk='auto')"
        seg_name = f"segmented: {S} x {sizes.segment}, CASNet(num_out={seg_num_out}, k=32, radius=2.0)"
        # bytes: float32 (m, N) matrices (head output, logits, S~, ...) and (m, segment) per segment
        mn, sm = 4 * m * n, 4 * S * seg_num_out * sizes.segment

        def infer_whole(model=whole, x=cloud.unsqueeze(0)):
            model.eval()
            with torch.no_grad():
                return model(x, mode="hard", dedup=False).indices

        def infer_seg(x=cloud, k=m):
            seg_model.eval()
            return segment_and_sample(seg_model, x, RATIO, max_points=sizes.segment, num_samples=k, dedup=False)

        base = dict(N=n, m=m, sweeps=info["sweeps"])
        cases = [Case(_row("whole_cloud", f"N={n} inference", whole_name, path="whole", step="inference",
                           attention_rows=attn_rows, **base), infer_whole, mem=5 * mn),
                 Case(_row("whole_cloud", f"N={n} inference", fused_name, path="whole, fused", step="inference",
                           attention_rows="fused", **base), lambda model=fused: infer_whole(model), mem=5 * mn),
                 Case(_row("whole_cloud", f"N={n} inference", fused_name + ", fp16 autocast", path="whole, fused, fp16",
                           step="inference", attention_rows="fused", **base),
                      lambda model=fused: _autocast_cuda(infer_whole, model), mem=5 * mn,
                      skip=None if dev.type == "cuda" else "skipped (CUDA only: float16 autocast)"),
                 Case(_row("whole_cloud", f"N={n} inference", seg_name, path="segmented", step="inference",
                           segments=S, attention_rows=seg_rows, **base), infer_seg, mem=5 * sm)]
        run.run(cases)
        for c in cases:
            _picks(c)
            c.result.clear()
        rows += [c.row for c in cases]
        cases = [Case(_row("whole_cloud", f"N={n} training step", whole_name, path="whole", step="training",
                           attention_rows=attn_rows, **base),
                      lambda model=whole, x=cloud.unsqueeze(0): _train_step(model, x, None, zero), mem=16 * mn),
                 Case(_row("whole_cloud", f"N={n} training step", fused_name, path="whole, fused", step="training",
                           attention_rows="fused", **base),
                      lambda model=fused, x=cloud.unsqueeze(0): _train_step(model, x, None, zero), mem=16 * mn),
                 Case(_row("whole_cloud", f"N={n} training step", seg_name, path="segmented", step="training",
                           segments=S, attention_rows=seg_rows, **base),
                      lambda b=seg_batch, lens=seg_lengths: _train_step(seg_model, b, lens, zero), mem=16 * sm,
                      skip=sizes.seg_train_skip)]
        run.run(cases)
        for c in cases:
            c.result.clear()
        rows += [c.row for c in cases]
        del whole, fused, cloud, seg_batch, seg_lengths, cases
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    return rows, infos


def print_whole_cloud(rows: list[dict], device: torch.device) -> None:
    cuda = device.type == "cuda"
    table = [[r["N"], r["m"], r["step"], r["impl"], r.get("attention_rows") or "plain", *_time_cells(r)]
             + ([r.get("peak_mb", "")] if cuda else []) for r in rows]
    print_table(f"== 3. whole cloud (chunked offset attention) vs segments, m = N // {RATIO} ({device_name(device)}); "
                "attention rows = query rows per block ('plain': N x N)",
                ["N", "m", "step", "path", "attention rows", "ms", "IQR", "runs"] + (["peak MB"] if cuda else []),
                table, right=(0, 1, 4, 5, 6, 7, 8))
    _print_reasons(rows)


# ------------------------------------------------------------------ main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--quick", action="store_true", help="tiny clouds and models, for smoke tests")
    ap.add_argument("--full", action="store_true", help="on CPU: the CUDA sizes (section 3 at 20,000 and 65,536 "
                                                        "points, section 2's eager rows); long")
    ap.add_argument("--checkpoint", default=None, metavar="PATH",
                    help="also time this CAS-Net (lidarops.models.casnet.load_casnet: a file or a shipped name)")
    return run_with_threads(_main, ap.parse_args(argv))


def _main(a: argparse.Namespace) -> int:
    dev = bench_device(a.device)
    if dev is None:
        return 2
    sizes = sizes_for(dev, a.quick, a.full)
    t0 = time.perf_counter()
    load0 = load_average_warning(dev)
    run = Runner(dev, quick=a.quick)
    print(f"# {device_name(dev)}: torch {torch.__version__}, lidarops {lidarops.__version__}", flush=True)

    clouds = FovClouds()
    cloud, cloud_info = clouds.cloud(sizes.cloud)
    cloud = cloud.to(dev)
    models: dict[str, Any] = paper_models(sizes.segment, dev)
    if a.checkpoint:
        name = f"checkpoint {a.checkpoint}"
        try:
            from lidarops.models.casnet import load_casnet
            ckpt = load_casnet(a.checkpoint, dev)
            models[f"{name} (num_out={ckpt.num_out})"] = ckpt
        except Exception as e:  # noqa: BLE001  (reported in its rows)
            models[name] = f"skipped (checkpoint did not load: {_error(e)[len('error: '):]})"

    print(f"== 1. sampling: N = {cloud.shape[0]:,}, m = {cloud.shape[0] // RATIO:,} ...", flush=True)
    sampling = bench_sampling(run, cloud, sizes, models)
    print_sampling(sampling, cloud_info, dev)

    print(f"== 3. whole cloud: N in {list(sizes.whole)} ...", flush=True)
    whole, whole_info = bench_whole_cloud(run, clouds, sizes)
    print_whole_cloud(whole, dev)

    # last: a capture that fails must not disturb the other measurements
    print("== 2. CUDA graphs ...", flush=True)
    if dev.type == "cuda" or a.full:
        full_cloud, _ = clouds.cloud(GRAPH_SEGMENTS * sizes.segment)
        graphs = bench_cuda_graphs(run, cloud, full_cloud.to(dev), sizes, next(iter(models.values())))
    else:
        why = "skipped (CUDA only: the eager rows run on CPU with --full)"
        graphs = [dict(_row("cuda_graph", case, impl, N=sizes.segment, segments=GRAPH_SEGMENTS),
                       device=dev.type, status=why, median_ms=None)
                  for case, impl in (("forward (padded segments)", "eager, value checks on"),
                                     ("forward (padded segments)", "eager, value checks off"),
                                     ("forward (padded segments)", "CUDA graph"),
                                     ("attention + head + argmax (full segments)", "eager"),
                                     ("attention + head + argmax (full segments)", "CUDA graph"))]
    print_cuda_graphs(graphs, dev)

    wall = time.perf_counter() - t0
    print(f"({dev.type} run took {wall:.0f} s)\n")
    if a.json:
        meta = env_meta(dev)
        flags = " ".join(f for f, on in (("--quick", a.quick), ("--full", a.full),
                                          (f"--threads {a.threads}", a.threads)) if on)
        meta.update(
            benchmark=f"benchmarks/bm_casnet.py --device {dev.type}" + (f" {flags}" if flags else "")
                      + (f" --checkpoint {a.checkpoint}" if a.checkpoint else ""),
            sweep_s=round(wall, 1),
            load_avg_1m_start=None if load0 is None else round(load0, 2),
            ratio=RATIO, segment=sizes.segment, cloud=cloud_info, whole_clouds=whole_info,
            float32_matmul_precision=torch.get_float32_matmul_precision(),
            notes={
                "sampling": "eager calls as users write them, m = N // 8; CASNetSampler with dedup (its default); "
                            "segment_and_sample(model, points, 8, dedup=False): the paper's raw picks; weights "
                            "untrained (seeded) unless a checkpoint",
                "cuda_graph": "eval, no grad, hard mode, no dedup; static inputs; a failed capture is a skip with "
                              "its reason",
                "whole_cloud": "whole = one CAS-Net with num_out = N // 8 on the whole cloud, chunk='auto'; "
                               "segmented = the full variant on segments, num_samples = N // 8; training step = "
                               "train mode, hard forward, casnet_loss (Chamfer + cosine, zero task loss), backward",
                "peak_mb": "CUDA: max_memory_allocated over one call (reset before) minus memory_allocated before it; "
                           "peak_allocated_mb: the absolute peak",
            },
        )
        # the whole section: its rows' names do not carry the sizes, which --quick and --full change
        path = write_results(SECTION, dev, sampling + graphs + whole, meta, replace_by=None,
                             results_dir=a.results_dir)
        print(f"wrote {path}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
