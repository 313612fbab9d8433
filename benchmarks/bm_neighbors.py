"""Benchmark of the neighbourhood ops (fps, knn, ball_query, gather) against their usual peers.

    python benchmarks/bm_neighbors.py                     # CPU, and CUDA when available
    python benchmarks/bm_neighbors.py --device cpu --json # CPU only, write benchmarks/results/<device>.json
    python benchmarks/bm_neighbors.py --quick             # smoke test, < 1 min on 2 CPU cores
    python benchmarks/bm_neighbors.py --only fps,knn

What is measured, per case (all times are medians in ms; the IQR and run count are in the JSON):

* ``lidarops``: the validated wrapper (``lidarops.knn`` ...) as users call it, value checks on (on
  CUDA these cost a device-to-host sync per call). Ratios are taken against this column.
* ``raw op``: the registered op (``torch.ops.lidarops.knn`` ...), method "auto", no checks.
* one column per forced ``method`` of the raw op (knn: brute, grid, tree (CPU); ball_query: brute,
  grid; fps: plain, leaves),
  to show where the automatic choice switches.
* peers, measured in the same run on the same inputs: plain PyTorch everywhere (``torch.cdist`` +
  ``topk`` for kNN; ``cdist`` + mask + first k by index for ball query; the Python-loop FPS of
  pure-PyTorch PointNet++ ports; ``torch.gather`` and advanced indexing for gather); on CPU also
  ``scipy.spatial.cKDTree`` (build + query, ``workers=-1``) and ``fpsample`` (``fps_sampling``,
  ``bucket_fps_kdline_sampling`` with ``h=7``). A ratio ``peer / lidarops`` above 1 means lidarops
  is faster.

Sizes: B in {1, 8}; N in {4096, 16384, 120000}; k in {16, 32}; FPS K in {1024, 4096, 16384} (K <= N)
plus the N = 50000, K = 4096 CPU target case. kNN and ball-query queries are the cloud's own points:
all of them (M = N) for N <= 16384, a random quarter (M = N / 4 = 30000) for N = 120000, as a
set-abstraction layer queries a subset. The ball-query radius is set per cloud kind, N and k so that
queries have k neighbours on average (the query itself included; counts capped at 4k; bisection on
1024 sampled queries of the first cloud). Gather: x (B, N, 64) float32 with random (B, M, k) indices.
Clouds: uniform in the unit cube, and LiDAR-like sweeps (see ``benchmarks.common.lidar_clouds``).

A peer that would not fit in memory (e.g. ``cdist`` at B = 8, N = 120000 needs 8 x 30000 x 120000
floats) or whose single call is estimated (from a short probe) to exceed the time cap is skipped
and the table says why.
"""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from benchmarks.common import (
    Skip,
    available_memory,
    device_name,
    env_meta,
    fmt_ms,
    fmt_ratio,
    lidar_clouds,
    lidar_generator_name,
    print_table,
    short_status,
    time_call,
    time_cpu_interleaved,
    uniform_clouds,
    write_results,
)

import lidarops
from lidarops import extension
from lidarops.ops.neighbors import _FPS_METHODS, _KNN_METHODS, _METHODS

extension.load()

try:
    import numpy as np
    from scipy.spatial import cKDTree
except ImportError:  # scipy is optional on the GPU machine
    cKDTree = None
try:
    import fpsample
except ImportError:
    fpsample = None

OPS = ("fps", "knn", "ball_query", "gather")
SECTION = "neighbors"
FPSAMPLE_H = 7


# ------------------------------------------------------------------ peers

def knn_cdist_topk(query, points, k):
    """kNN in plain PyTorch: full distance matrix, then the k smallest."""
    d = torch.cdist(query, points)
    v, i = d.topk(k, dim=-1, largest=False, sorted=True)
    return v.square(), i


def ball_cdist_first_k(query, points, r2, k):
    """Ball query in plain PyTorch: distance matrix, mask d2 < r2, first k indices by index order.

    Selects with ``topk`` over index keys (out-of-ball points keyed N), which is cheaper than the
    full ``sort`` of the PointNet++ PyTorch ports and gives the same answer.
    """
    N = points.shape[1]
    d = torch.cdist(query, points)
    d.square_()
    key = torch.where(d < r2, torch.arange(N, dtype=torch.int32, device=d.device), N)
    first, _ = key.topk(k, dim=-1, largest=False, sorted=True)
    valid = first < N
    first = first.long().clamp_max_(N - 1)
    dist = torch.where(valid, d.gather(-1, first), math.inf)
    return dist, torch.where(valid, first, -1)


def fps_python_loop(points, K):
    """The usual pure-PyTorch FPS: K steps of torch ops, no host sync (runs on the GPU as is)."""
    B, N, _ = points.shape
    out = torch.empty(B, K, dtype=torch.long, device=points.device)
    dist = torch.full((B, N), math.inf, dtype=points.dtype, device=points.device)
    far = torch.zeros(B, dtype=torch.long, device=points.device)
    rows = torch.arange(B, device=points.device)
    for i in range(K):
        out[:, i] = far
        c = points[rows, far].unsqueeze(1)
        dist = torch.minimum(dist, ((points - c) ** 2).sum(-1))
        far = dist.argmax(-1)
    return out


def ckdtree_knn(qs, ps, k):
    out = []
    for q, p in zip(qs, ps):
        _, i = cKDTree(p).query(q, k, workers=-1)
        out.append(i)
    return out


def ckdtree_ball(qs, ps, r, k):
    out = []
    for q, p in zip(qs, ps):
        hits = cKDTree(p).query_ball_point(q, r, workers=-1, return_sorted=True)
        idx = np.full((len(q), k), -1, dtype=np.int64)
        for m, h in enumerate(hits):
            h = h[:k]
            idx[m, :len(h)] = h
        out.append(idx)
    return out


def fpsample_plain(ps, K):
    return [fpsample.fps_sampling(p, K, start_idx=0) for p in ps]


def fpsample_kdline(ps, K):
    return [fpsample.bucket_fps_kdline_sampling(p, K, h=FPSAMPLE_H, start_idx=0) for p in ps]


def gather_torch(x, idx):
    B, C = x.shape[0], x.shape[2]
    return x.gather(1, idx.reshape(B, -1, 1).expand(-1, -1, C)).reshape(*idx.shape, C)


def gather_index(x, idx, rows):
    return x[rows, idx]


# ------------------------------------------------------------------ measurement plumbing

@dataclass
class Impl:
    name: str
    kind: str  # "lidarops" | "raw" | "method" | "peer"
    fn: Callable[..., Any]
    args: tuple
    mem: int = 0  # bytes it needs beyond its inputs
    probe: Callable[[], float] | None = None  # estimated seconds of one call, measured cheaply
    skip: str | None = None


@dataclass
class Runner:
    device: torch.device
    quick: bool = False
    rows: list[dict] = field(default_factory=list)

    def __post_init__(self):
        cuda = self.device.type == "cuda"
        self.cap_s = 5.0  # longest single call we agree to wait for
        self.mem_budget = int((0.6 if cuda else 0.35) * available_memory(self.device))
        self.budget_s = 0.2 if cuda else (0.3 if self.quick else 0.5)  # per measurement

    def sync(self):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def run(self, case: dict, impls: list[Impl]) -> list[dict]:
        out = [dict(case, impl=im.name, kind=im.kind, device=self.device.type) for im in impls]
        todo = []  # indices of the implementations to time
        for i, im in enumerate(impls):
            try:
                if im.skip:
                    raise Skip(im.skip)
                if im.mem > self.mem_budget:
                    raise Skip(f"skipped (memory: needs {im.mem / 2**30:.1f} GiB, budget "
                               f"{self.mem_budget / 2**30:.1f} GiB)")
                if im.probe is not None:
                    est = im.probe()
                    if est > self.cap_s:
                        raise Skip(f"skipped (time: est. {est:.0f} s per call > {self.cap_s:.0f} s cap)")
                todo.append(i)
            except Skip as e:
                out[i].update(status=str(e), median_ms=None)
            except Exception as e:  # noqa: BLE001
                self._failed(out[i], im, e)
        if self.device.type == "cuda":
            for i in todo:
                try:
                    t = time_call(impls[i].fn, impls[i].args, self.device, budget_s=self.budget_s,
                                  slow_single_s=1.0, max_runs=200)
                    out[i].update(status="ok", **t.as_dict())
                except Exception as e:  # noqa: BLE001
                    self._failed(out[i], impls[i], e)
                torch.cuda.empty_cache()
        else:
            timings = time_cpu_interleaved([(impls[i].fn, impls[i].args) for i in todo], budget_s=self.budget_s,
                                           slow_single_s=1.0, max_runs=30)
            for i, t in zip(todo, timings):
                if isinstance(t, BaseException):
                    self._failed(out[i], impls[i], t)
                else:
                    out[i].update(status="ok", **t.as_dict())
        ref = next((r["median_ms"] for r in out if r["kind"] == "lidarops" and r["median_ms"]), None)
        for r in out:
            if ref and r["median_ms"] and r["kind"] == "peer":
                r["ratio"] = r["median_ms"] / ref
        self.rows += out
        return out

    @staticmethod
    def _failed(row: dict, im: Impl, e: BaseException):
        if isinstance(e, torch.OutOfMemoryError) or "out of memory" in str(e).lower():
            row.update(status="skipped (memory: out of memory)", median_ms=None)
            return
        if not isinstance(e, RuntimeError):  # a bug in this script: do not hide it
            raise e
        msg = str(e).strip().splitlines()[0][:160]  # e.g. a method a device does not implement
        print(f"  error in {im.name}: {msg}", file=sys.stderr)
        row.update(status=f"error: {msg}", median_ms=None)

    # probes: time a small slice of the work, extrapolate linearly
    def probe(self, fn: Callable[[], Any], scale: float) -> Callable[[], float]:
        def est() -> float:
            fn()
            self.sync()
            t0 = time.perf_counter()
            fn()
            self.sync()
            return (time.perf_counter() - t0) * scale
        return est


def _queries(points: torch.Tensor, N: int, seed: int = 1) -> torch.Tensor:
    M = N if N <= 16384 else N // 4
    if M == N:
        return points
    g = torch.Generator().manual_seed(seed)
    sel = torch.randperm(N, generator=g)[:M].sort().values.to(points.device)
    return points[:, sel].contiguous()


_RADIUS: dict = {}


def radius_for(cloud: str, points: torch.Tensor, k: int) -> tuple[float, float]:
    """Radius with about k neighbours per query on average, and the mean hits (capped at k) it gives."""
    key = (cloud, points.shape[1], k)
    if key not in _RADIUS:
        p = points[:1].float().cpu()
        N = p.shape[1]
        g = torch.Generator().manual_seed(7)
        q = p[:, torch.randperm(N, generator=g)[:min(1024, N)]]
        d, _ = lidarops.knn(q, p, min(4 * k, N))
        d = d[0].double()
        lo, hi = 0.0, float(d[torch.isfinite(d)].max().sqrt()) * 2 + 1e-9
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if float((d < mid * mid).sum(1).double().mean()) < k:
                lo = mid
            else:
                hi = mid
        r = float(f"{hi:.4g}")
        fill = float((d < r * r).sum(1).clamp_max(k).double().mean())
        _RADIUS[key] = (r, fill)
    return _RADIUS[key]


_CLOUDS: dict = {}


def clouds(kind: str, B: int, N: int, device: torch.device) -> torch.Tensor:
    key = (kind, B, N, str(device))
    if key not in _CLOUDS:
        gen = uniform_clouds if kind == "uniform" else lidar_clouds
        _CLOUDS[key] = gen(B, N, seed=0, device=device).contiguous()
    return _CLOUDS[key]


def full(B: int, n: int, device) -> torch.Tensor:
    return torch.full((B,), n, dtype=torch.int64, device=device)


# ------------------------------------------------------------------ cases

def sizes(quick: bool):
    if quick:
        return dict(B=(1,), N=(4096,), k=(16,), K=(1024,), fps_extra=())
    return dict(B=(1, 8), N=(4096, 16384, 120000), k=(16, 32), K=(1024, 4096, 16384), fps_extra=((1, 50000, 4096),))


def bench_knn_like(run: Runner, op: str, cloud_kinds, quick: bool):
    dev = run.device
    cpu = dev.type == "cpu"
    S = sizes(quick)
    table = _KNN_METHODS if op == "knn" and cpu else _METHODS  # the k-d tree is CPU-only
    methods = [m for m in table if m != "auto"]
    for kind in cloud_kinds:
        for N in S["N"]:
            for B in S["B"]:
                points = clouds(kind, B, N, dev)
                query = _queries(points, N)
                M = query.shape[1]
                ql, pl = full(B, M, dev), full(B, N, dev)
                for k in S["k"]:
                    case = dict(op=op, cloud=kind, B=B, N=N, M=M, k=k)
                    sub = max(1, M // 256)  # probes use M / sub queries
                    qsub = query[:, ::sub].contiguous()
                    qls = full(B, qsub.shape[1], dev)
                    if op == "knn":
                        wrapper = (lambda q, p, k=k: lidarops.knn(q, p, k), (query, points))
                        raw = lambda q, p, a, b, m, k=k: torch.ops.lidarops.knn(q, p, a, b, k, m)
                        pe = Impl("cdist+topk", "peer", knn_cdist_topk, (query, points, k), mem=8 * B * M * N,
                                  probe=run.probe(lambda: knn_cdist_topk(qsub, points, k), sub))
                    else:
                        r, fill = radius_for(kind, points, k)
                        case.update(radius=r, mean_hits=round(fill, 2))
                        r2 = float(torch.tensor(r, dtype=torch.float32) ** 2)
                        wrapper = (lambda q, p, k=k, r=r: lidarops.ball_query(q, p, r, k), (query, points))
                        raw = lambda q, p, a, b, m, k=k, r=r: torch.ops.lidarops.ball_query(q, p, a, b, k, r, m)
                        pe = Impl("cdist+mask+first-k", "peer", ball_cdist_first_k, (query, points, r2, k),
                                  mem=10 * B * M * N,
                                  probe=run.probe(lambda: ball_cdist_first_k(qsub, points, r2, k), sub))
                    impls = [Impl("lidarops", "lidarops", *wrapper),
                             Impl("raw op", "raw", raw, (query, points, ql, pl, 0))]
                    for m in methods:
                        code = table[m]
                        probe = None
                        if m == "brute":
                            probe = run.probe(lambda raw=raw, code=code: raw(qsub, points, qls, pl, code), sub)
                        impls.append(Impl(m, "method", raw, (query, points, ql, pl, code), probe=probe))
                    impls.append(pe)
                    if cpu:
                        if cKDTree is None:
                            impls.append(Impl("cKDTree", "peer", None, (), skip="skipped (scipy not installed)"))
                        else:
                            qn = [q.numpy() for q in query]
                            pn = [p.numpy() for p in points]
                            if op == "knn":
                                impls.append(Impl("cKDTree", "peer", ckdtree_knn, (qn, pn, k)))
                            else:
                                impls.append(Impl("cKDTree", "peer", ckdtree_ball, (qn, pn, r, k)))
                    rows = run.run(case, impls)
                    _progress(rows)


def bench_fps(run: Runner, cloud_kinds, quick: bool):
    dev = run.device
    cpu = dev.type == "cpu"
    S = sizes(quick)
    cases = [(B, N, K) for N in S["N"] for B in S["B"] for K in S["K"] if K <= N]
    if cpu:
        cases += list(S["fps_extra"])
    cases.sort(key=lambda c: (c[1], c[0], c[2]))
    methods = [m for m in _FPS_METHODS if m != "auto"]
    for kind in cloud_kinds:
        for B, N, K in cases:
            points = clouds(kind, B, N, dev)
            lengths, start = full(B, N, dev), torch.zeros(B, dtype=torch.int64, device=dev)
            case = dict(op="fps", cloud=kind, B=B, N=N, K=K)
            kp = min(K, 64)  # probe steps; FPS costs grow linearly in K
            raw = torch.ops.lidarops.fps
            impls = [Impl("lidarops", "lidarops", lambda p, K=K: lidarops.fps(p, K), (points,)),
                     Impl("raw op", "raw", raw, (points, lengths, start, K, 0))]
            for m in methods:
                code = _FPS_METHODS[m]
                probe = run.probe(lambda code=code: raw(points, lengths, start, kp, code), K / kp) \
                    if m == "plain" else None
                impls.append(Impl(m, "method", raw, (points, lengths, start, K, code), probe=probe))
            impls.append(Impl("python loop", "peer", fps_python_loop, (points, K),
                              probe=run.probe(lambda: fps_python_loop(points, kp), K / kp)))
            if cpu:
                if fpsample is None:
                    for name in ("fpsample", f"fpsample bucket h={FPSAMPLE_H}"):
                        impls.append(Impl(name, "peer", None, (), skip="skipped (fpsample not installed)"))
                else:
                    pn = [p.numpy() for p in points]
                    impls.append(Impl("fpsample", "peer", fpsample_plain, (pn, K),
                                      probe=run.probe(lambda: fpsample_plain(pn, kp), K / kp)))
                    impls.append(Impl(f"fpsample bucket h={FPSAMPLE_H}", "peer", fpsample_kdline, (pn, K)))
            _progress(run.run(case, impls))


def bench_gather(run: Runner, quick: bool):
    dev = run.device
    S = sizes(quick)
    C = 64
    for N in S["N"]:
        for B in S["B"]:
            M = N if N <= 16384 else N // 4
            for k in S["k"]:
                g = torch.Generator().manual_seed(N + k + B)
                x = torch.randn(B, N, C, generator=g).to(dev)
                idx = torch.randint(0, N, (B, M, k), generator=g).to(dev)
                flat = idx.reshape(B, -1)
                rows = torch.arange(B, device=dev).view(B, 1, 1)
                case = dict(op="gather", cloud="random idx", B=B, N=N, M=M, k=k, C=C)
                impls = [Impl("lidarops", "lidarops", lidarops.gather, (x, idx)),
                         Impl("raw op", "raw", torch.ops.lidarops.gather, (x, flat)),
                         Impl("torch.gather", "peer", gather_torch, (x, idx)),
                         Impl("x[rows, idx]", "peer", gather_index, (x, idx, rows))]
                _progress(run.run(case, impls))


def _progress(rows: list[dict]):
    r0 = rows[0]
    size = " ".join(f"{k}={r0[k]}" for k in ("cloud", "B", "N", "M", "k", "K") if k in r0)
    cells = [f"{r['impl']} {fmt_ms(r['median_ms']) if r['median_ms'] else 'skip'}" for r in rows]
    print(f"  [{r0['device']}] {r0['op']} {size}: " + ", ".join(cells), file=sys.stderr, flush=True)


# ------------------------------------------------------------------ tables and targets

def _cell(r: dict | None) -> str:
    if r is None:
        return ""
    if r["median_ms"] is None:
        s = r["status"]
        return short_status(s)
    if r.get("ratio"):
        return f"{fmt_ms(r['median_ms'])} ({fmt_ratio(r['ratio'])})"
    return fmt_ms(r["median_ms"])


def print_tables(rows: list[dict], device: torch.device):
    name = device_name(device)
    for op in OPS:
        op_rows = [r for r in rows if r["op"] == op and r["device"] == device.type]
        if not op_rows:
            continue
        impl_names = list(dict.fromkeys(r["impl"] for r in op_rows))
        keys = {"fps": ("cloud", "B", "N", "K"), "gather": ("B", "N", "M", "k", "C")}.get(
            op, ("cloud", "B", "N", "M", "k") + (("radius", "mean_hits") if op == "ball_query" else ()))
        cases: dict = {}
        for r in op_rows:
            cases.setdefault(tuple(r.get(k) for k in keys), {})[r["impl"]] = r
        table = [[*ck, *(_cell(cr.get(n)) for n in impl_names)] for ck, cr in cases.items()]
        headers = [k if k != "mean_hits" else "hits" for k in keys] + impl_names
        print_table(f"== {op} on {name}: median ms (peer / lidarops)", headers, table,
                    right=range(1, len(headers)))
        lines = skip_summary(op_rows)
        for line in lines:
            print(f"   {line}")
        if lines:
            print()
    print("lidarops = validated wrapper (value checks on); raw op = torch.ops.lidarops.<op>, method auto, no checks;"
          "\nmethod columns = raw op with the method forced; (Nx) = peer time / lidarops time, > 1: lidarops faster.")
    if device.type == "cuda":
        print("fps methods on CUDA: plain = one block per cloud, leaves = several blocks (a cluster) per cloud.")
    print()


def skip_summary(rows: list[dict]) -> list[str]:
    """One line per (implementation, reason) of the measurements not taken."""
    groups: dict = {}
    for r in rows:
        if r["median_ms"] is None:
            groups.setdefault((r["impl"], short_status(r["status"])), []).append(r["status"])
    out = []
    for (impl, short), full in groups.items():
        if short == "skipped (time)":
            est = [float(re.search(r"est\. ([0-9.]+) s", f).group(1)) for f in full if "est." in f]
            detail = f"est. {min(est):.0f}-{max(est):.0f} s per call" if est else ""
            cap = re.search(r"> ([0-9.]+ s cap)", full[0])
            detail += f" > {cap.group(1)}" if cap else ""
        elif short == "skipped (memory)":
            need = [float(re.search(r"needs ([0-9.]+) GiB", f).group(1)) for f in full if "needs" in f]
            budget = re.search(r"budget ([0-9.]+ GiB)", full[0])
            detail = f"needs {min(need):.0f}-{max(need):.0f} GiB, budget {budget.group(1)}" if need and budget else ""
        else:
            detail = full[0]
        out.append(f"{impl}: {short} in {len(full)} case{'s' if len(full) > 1 else ''}" + (f" ({detail})" if detail else ""))
    return out


def _find(rows, impl, **case):
    for r in rows:
        if r["impl"] == impl and all(r.get(k) == v for k, v in case.items()):
            return r
    return None


def evaluate_targets(rows: list[dict]) -> list[dict]:
    """The issue's targets, from this run's rows: PASS / MISS / not measured."""
    out = []

    def t(ms):
        return ms["median_ms"] if ms and ms.get("median_ms") else None

    for cloud in ("uniform", "lidar"):
        # GPU: absolute times of the wrapper (raw op shown too)
        for op, label in (("knn", "kNN"), ("ball_query", "ball query")):
            case = dict(op=op, device="cuda", cloud=cloud, B=1, N=16384, M=16384, k=16)
            w, raw = _find(rows, "lidarops", **case), _find(rows, "raw op", **case)
            out.append(_target(f"GPU {label} B=1 M=N=16384 k=16, {cloud}", t(w), 0.5, "<=",
                               extra=f"raw op {fmt_ms(t(raw))} ms" if t(raw) else ""))
        for B, N, K, lim in ((8, 16384, 4096, 6.0), (1, 120000, 16384, 30.0)):
            case = dict(op="fps", device="cuda", cloud=cloud, B=B, N=N, K=K)
            w, raw = _find(rows, "lidarops", **case), _find(rows, "raw op", **case)
            out.append(_target(f"GPU FPS B={B} N={N} K={K}, {cloud}", t(w), lim, "<=",
                               extra=f"raw op {fmt_ms(t(raw))} ms" if t(raw) else ""))
        # CPU: relative to peers
        case = dict(op="knn", device="cpu", cloud=cloud, B=1, N=16384, M=16384, k=16)
        w, kd = _find(rows, "lidarops", **case), _find(rows, "cKDTree", **case)
        out.append(_ratio_target(f"CPU kNN B=1 M=N=16384 k=16 faster than cKDTree (build+query), {cloud}",
                                 t(w), t(kd), "cKDTree", lambda r: r > 1.0, "> 1x"))
        case = dict(op="fps", device="cpu", cloud=cloud, B=1, N=50000, K=4096)
        w = _find(rows, "lidarops", **case)
        kdl = _find(rows, f"fpsample bucket h={FPSAMPLE_H}", **case)
        van = _find(rows, "fpsample", **case)
        out.append(_ratio_target(f"CPU FPS N=50000 K=4096 within 2x of fpsample bucket h={FPSAMPLE_H}, {cloud}",
                                 t(w), t(kdl), "bucket", lambda r: r >= 0.5, ">= 0.5x"))
        out.append(_ratio_target(f"CPU FPS N=50000 K=4096 >= 10x faster than fpsample.fps_sampling, {cloud}",
                                 t(w), t(van), "fps_sampling", lambda r: r >= 10.0, ">= 10x"))
    return out


def _target(name, ms, limit, op, extra=""):
    if ms is None:
        return dict(target=name, status="not measured", detail="")
    ok = ms <= limit
    return dict(target=name, status="PASS" if ok else "MISS", value_ms=ms, limit_ms=limit,
                detail=f"{fmt_ms(ms)} ms (limit {limit} ms){'; ' + extra if extra else ''}")


def _ratio_target(name, ms, peer_ms, peer, ok_fn, rule):
    if ms is None or peer_ms is None:
        return dict(target=name, status="not measured", detail="")
    r = peer_ms / ms
    return dict(target=name, status="PASS" if ok_fn(r) else "MISS", value_ms=ms, peer_ms=peer_ms, ratio=r,
                detail=f"lidarops {fmt_ms(ms)} ms vs {peer} {fmt_ms(peer_ms)} ms = {fmt_ratio(r)} (need {rule})")


def print_targets(targets: list[dict], show_unmeasured: bool = False):
    print("== targets (issue 2; lidarops = validated wrapper)")
    for tg in targets:
        if tg["status"] == "not measured" and not show_unmeasured:
            continue
        print(f"  [{tg['status']}] {tg['target']}: {tg['detail']}")
    n = sum(tg["status"] == "not measured" for tg in targets)
    if n and not show_unmeasured:
        print(f"  ({n} targets not measured in this run: other device or sizes)")
    print(flush=True)


# ------------------------------------------------------------------ main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=("cpu", "cuda", "all"), default="all",
                    help="all = cpu, and cuda when available (default)")
    ap.add_argument("--quick", action="store_true", help="a small subset, for smoke tests")
    ap.add_argument("--json", action="store_true", help="write benchmarks/results/<device>.json")
    ap.add_argument("--only", default=",".join(OPS), help=f"comma-separated subset of {','.join(OPS)}")
    ap.add_argument("--clouds", default="uniform,lidar", help="comma-separated subset of uniform,lidar")
    a = ap.parse_args(argv)
    ops = [o.strip() for o in a.only.split(",") if o.strip()]
    bad = [o for o in ops if o not in OPS]
    if bad:
        ap.error(f"--only: unknown ops {bad}; choose from {','.join(OPS)}")
    kinds = [c.strip() for c in a.clouds.split(",") if c.strip()]
    if any(c not in ("uniform", "lidar") for c in kinds):
        ap.error("--clouds: choose from uniform,lidar")
    devices = []
    if a.device in ("cpu", "all"):
        devices.append(torch.device("cpu"))
    if a.device in ("cuda", "all"):
        if torch.cuda.is_available() and extension.cuda_available():
            devices.append(torch.device("cuda"))
        elif a.device == "cuda":
            print("CUDA asked for but not available (torch sees no GPU or lidarops was built without CUDA)",
                  file=sys.stderr)
            return 2
    all_rows = []
    for dev in devices:
        t0 = time.perf_counter()
        load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        if dev.type == "cpu" and load0 is not None and load0 > 0.5 * (os.cpu_count() or 1):
            print(f"warning: load average {load0:.1f} on {os.cpu_count()} cores; other work skews CPU timings",
                  file=sys.stderr)
        run = Runner(dev, quick=a.quick)
        print(f"# {device_name(dev)}: torch {torch.__version__}, lidarops {lidarops.__version__}; "
              f"lidar clouds: {lidar_generator_name()}", flush=True)
        for op in ops:
            if op == "fps":
                bench_fps(run, kinds, a.quick)
            elif op == "gather":
                bench_gather(run, a.quick)
            else:
                bench_knn_like(run, op, kinds, a.quick)
        print_tables(run.rows, dev)
        wall = time.perf_counter() - t0
        print(f"({dev.type} sweep took {wall:.0f} s)\n")
        all_rows += run.rows
        if a.json:
            meta = env_meta(dev)
            meta.update(
                benchmark="benchmarks/bm_neighbors.py" + (" --quick" if a.quick else ""),
                sweep_s=round(wall, 1),
                load_avg_1m_start=None if load0 is None else round(load0, 2),
                lidar_generator=lidar_generator_name(),
                notes={
                    "lidarops": "validated wrapper, value checks on (a host sync per call on CUDA)",
                    "raw op": "torch.ops.lidarops.<op>, method auto, no checks",
                    "queries": "the cloud's own points: M = N for N <= 16384, a random N/4 for N = 120000",
                    "radius": "mean neighbour count (query included, capped at 4k) of 1024 sampled queries = k",
                    "ratio": "peer median / lidarops median (> 1: lidarops faster)",
                    "cdist+mask+first-k": "torch.cdist, mask d2 < r2, first k indices by topk over index keys",
                    "python loop": "K steps of torch ops (min of distances, argmax), no host sync",
                    "cKDTree": "scipy.spatial.cKDTree build + query, workers=-1, per cloud; ball query trims "
                               "query_ball_point(return_sorted=True) to the first k",
                    "fpsample": f"fps_sampling and bucket_fps_kdline_sampling(h={FPSAMPLE_H}), start_idx=0, "
                                "one cloud at a time",
                    "gather": "x (B, N, 64) float32, random int64 indices (B, M, k)",
                    "fps methods": "CPU: plain = O(NK) loop, leaves = bounding-box pruning; CUDA: plain = one "
                                   "block per cloud, leaves = several blocks (a cluster) per cloud",
                },
                targets=[tg for tg in evaluate_targets(run.rows) if tg["status"] != "not measured"],
            )
            path = write_results(SECTION, dev, run.rows, meta, replace_by="op")
            print(f"wrote {path}\n")
    print_targets(evaluate_targets(all_rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
