"""Benchmark of CounterNet inference (lidarops.models.counternet, issue 38) beside the shipped PointPillars
detector used as a counter, on KITTI-sized frames already in device memory.

    python benchmarks/bm_counternet.py                          # CUDA when available, else CPU
    python benchmarks/bm_counternet.py --device cuda --json     # write benchmarks/results/<device>.json
    python benchmarks/bm_counternet.py --device cpu             # CPU: 4 frames, batch 2 (about 1-2 minutes)
    python benchmarks/bm_counternet.py --device cpu --quick     # smoke test: 2 frames, batch 2

Target (issue 38): at least 1,000 frames/s for CounterNet on CUDA (batched); the seed reports 152 ms per frame
on an RTX 3080.

The frames: ``lidarops.data.synthetic.SyntheticFrames("driving_city", object_counts="dense", fov_deg=90)``, i.e.
independent simulated city scenes with dense object counts, cropped to KITTI's camera field of view (``x > 0``
and ``|atan2(y, x)| < 45`` degrees) as the KITTI dataset gives them (about 31,000 points a frame; the models'
voxelization drops what lies outside their point cloud range). N frames (16 on CUDA, 4 on CPU, 2 with
``--quick``; ``--frames``) are held as OpenPCDet batches (``points (P, 1 + 4)``, ``batch_size``) on the device.

The models, in eval mode:

* ``CN_pt=1``: the shipped ``counternet_road7_pt1`` (PARTITIONS 1, no overlap);
* ``CN_pt=4^o``: the shipped ``counternet_road7`` (CN_pt^o: PARTITIONS 4, OVERLAP 0.2: four heatmap branches on
  overlapping regions, centres found twice merged);
* ``PointPillars counter``: the shipped detector ``lidarops.models.weights.load("pointpillars_synth")``;
  its count of a frame = the boxes with score >= 0.5, per class.

The trained CounterNets find the frames' objects as peaks, so the post-processing (thresholds, peaks, centres,
merge) works on as many peaks as a user's frames give.

Rows, per model:

* ``latency``: batch 1, the eager ``model.predict(batch)`` a user writes, the per-class counts read to the
  host; the calls cycle over the frames; median (and IQR) over the calls (on CPU: one call per frame).
* ``throughput``: ``model.predict`` on batches of ``--batch`` frames (8 on CUDA, 2 on CPU), counts read to the
  host; frames/s = batch / median batch time.
* ``graph <precision>`` (CUDA): each model as one replayed CUDA graph of a whole batch
  (:class:`~lidarops.models.cuda_graph.GraphedCounterNet`, :class:`~lidarops.models.cuda_graph.GraphedPointPillars`,
  as ``lidarops index build`` runs them, pillar rows sized as it sizes them: a quarter more than the batches need),
  called on a list of frames, for each of ``--graph-batches`` (8, 32, 64) and
  ``--graph-precisions`` (fp32, fp16); ``graph <precision> optimized``: the same with ``optimize=True`` (a copy of
  the model with BatchNorm folded into the convolutions, channels-last);
* for CounterNet also ``postprocess`` alone (batch 1, on the forward's precomputed outputs) and its share of
  the latency; the rest (batch checks, voxelization, network) is the network's share.

Times are medians in ms with the timers of ``benchmarks/common.py``: on CUDA CUDA events (one cold call,
warm-up, then as many calls as fit in the budget), on CPU ``time.perf_counter`` with the three models' calls
interleaved (:func:`~benchmarks.common.time_cpu_interleaved`). A case that fails is reported with its error and
the others go on. ``--json`` writes the rows (``op`` = ``counternet/<model>/<case>``) as section
``"counternet"`` of ``benchmarks/results/<device>.json``, replacing that section whole (other sections kept).
"""
from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path
from typing import Any, Callable

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch

from benchmarks.common import (
    Timing,
    add_common_args,
    bench_device,
    load_average_warning,
    run_with_threads,
    device_name,
    env_meta,
    fmt_ms,
    print_table,
    short_status,
    time_cpu,
    time_cpu_interleaved,
    time_cuda,
    write_results,
)

import lidarops
from lidarops.models.counternet import CounterNet

SECTION = "counternet"
SCENARIO, SEED, FOV_DEG = "driving_city", 0, 90.0  # full opening: |azimuth| < 45 degrees
SCORE_THRESHOLD = 0.5  # the PointPillars counter's score threshold


# ------------------------------------------------------------------ frames and models

def make_frames(n: int) -> tuple[list[torch.Tensor], dict]:
    """``n`` simulated dense driving_city frames in KITTI's field of view: (P, 4) float32 each, and their summary."""
    from lidarops.data.synthetic import SyntheticFrames

    src = SyntheticFrames(SCENARIO, num_frames=n, seed=SEED, object_counts="dense", fov_deg=FOV_DEG)
    frames, boxes = [], []
    for i in range(n):
        f = src[i]
        frames.append(torch.from_numpy(f.points[:, :4]).float())
        boxes.append(len(f.boxes))
    points = [int(p.shape[0]) for p in frames]
    info = dict(frames=n, points_mean=round(sum(points) / n), points_min=min(points), points_max=max(points),
                boxes_mean=round(sum(boxes) / n, 1),
                source=f'SyntheticFrames("{SCENARIO}", num_frames={n}, seed={SEED}, object_counts="dense", '
                       f'fov_deg={FOV_DEG:g})')
    return frames, info


def make_batch(frames: list[torch.Tensor], device: torch.device) -> dict:
    """OpenPCDet's batch of ``frames``: ``points (P, 1 + 4)`` (frame index first) and ``batch_size``."""
    pts = torch.cat([torch.cat([torch.full((len(p), 1), float(i)), p], dim=1) for i, p in enumerate(frames)])
    return {"points": pts.to(device), "batch_size": len(frames)}


def counternet(device: torch.device, name: str) -> CounterNet:
    """A shipped CounterNet, in float32."""
    from lidarops.models import weights

    return weights.load(name, map_location=device).float().to(device).eval()


def models(device: torch.device) -> dict[str, tuple[Any, Callable[[Any, dict], Any]]]:
    """name -> (model, count(model, batch): per-class counts read to the host), or an error string."""
    def cn_count(model, batch):
        return torch.stack([f["counts"] for f in model.predict(batch)]).tolist()

    def pp_count(model, batch):
        c = len(model.config.class_names) + 1  # labels are 1-based
        return torch.stack([torch.bincount(f["labels"][f["scores"] >= SCORE_THRESHOLD], minlength=c)[1:]
                            for f in model.predict(batch)]).tolist()

    out: dict[str, Any] = {}
    for name, shipped in (("CN_pt=1", "counternet_road7_pt1"), ("CN_pt=4^o", "counternet_road7")):
        try:
            out[name] = (counternet(device, shipped), cn_count)
        except Exception as e:  # noqa: BLE001  (reported in its rows)
            out[name] = _error(e)
    try:
        from lidarops.models import weights

        out["PointPillars counter"] = (weights.load("pointpillars_synth", map_location=device).to(device).eval(),
                                       pp_count)
    except Exception as e:  # noqa: BLE001  (reported in its rows)
        out["PointPillars counter"] = _error(e)
    return out


# ------------------------------------------------------------------ timing

def _error(e: BaseException) -> str:
    return f"error: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}".rstrip(": ")


def _cycler(fn: Callable, model: Any, batches: list[dict]) -> Callable[[], Any]:
    """A call that runs ``fn(model, batch)`` on the next batch of ``batches`` (cycling)."""
    it = itertools.cycle(batches)
    return lambda: fn(model, next(it))


def time_models(calls: dict[str, Callable | str], n: int, device: torch.device) -> dict[str, Timing | str]:
    """Median per call of each model's cycling call; on CPU interleaved, ``n`` calls each (one per batch)."""
    out: dict[str, Timing | str] = {k: v for k, v in calls.items() if isinstance(v, str)}
    live = {k: v for k, v in calls.items() if not isinstance(v, str)}
    if device.type == "cuda":
        for name, call in live.items():
            try:
                out[name] = time_cuda(call, (), warmup=max(3, n), min_runs=max(10, n), max_runs=max(100, n),
                                      budget_s=1.0, rotate=False)
            except Exception as e:  # noqa: BLE001  (reported in its row)
                out[name] = _error(e)
            torch.cuda.empty_cache()
        return out
    timed = time_cpu_interleaved([(call, ()) for call in live.values()], min_runs=n, max_runs=n,
                                 slow_single_s=float("inf"))
    for name, t in zip(live, timed):
        out[name] = t if isinstance(t, Timing) else _error(t)
    return out


def time_postprocess(model: CounterNet, batches: list[dict], device: torch.device) -> Timing | str:
    """CounterNet's postprocess alone, on the forward's precomputed outputs (cycling over the frames)."""
    try:
        with torch.no_grad():
            raws = [(model(b), b) for b in batches]
        it = itertools.cycle(raws)

        def call():
            raw, b = next(it)
            return torch.stack([f["counts"] for f in model.postprocess(raw, b)]).tolist()

        if device.type == "cuda":
            return time_cuda(call, (), warmup=max(3, len(raws)), min_runs=max(10, len(raws)), budget_s=0.5,
                             rotate=False)
        return time_cpu(call, (), min_runs=len(raws), max_runs=10 * len(raws), budget_s=1.0)
    except Exception as e:  # noqa: BLE001  (reported in its row)
        return _error(e)


def _row(model: str, case: str, batch: int, t: Timing | str, device: torch.device) -> dict:
    row: dict[str, Any] = dict(section=SECTION, op=f"{SECTION}/{model}/{case}", model=model, case=case,
                               batch=batch, device=device.type)
    if isinstance(t, str):
        return dict(row, status=t, median_ms=None)
    row.update(status="ok", **t.as_dict())
    row["frames_per_s"] = float(f"{batch * 1e3 / t.median:.4g}")
    return row


def bench(model_set: dict, frames: list[torch.Tensor], batch: int, device: torch.device) -> list[dict]:
    singles = [make_batch([f], device) for f in frames]
    n_batches = max(1, len(frames) // batch)
    groups = [make_batch([frames[(k * batch + j) % len(frames)] for j in range(batch)], device)
              for k in range(n_batches)]
    rows = []
    for case, batches, bsz in (("latency", singles, 1), ("throughput", groups, batch)):
        print(f"== {case}: batch {bsz}, {len(batches)} input(s) ...", flush=True)
        calls = {name: m if isinstance(m, str) else _cycler(m[1], m[0], batches) for name, m in model_set.items()}
        timed = time_models(calls, len(batches), device)
        rows += [_row(name, case, bsz, timed[name], device) for name in model_set]
    latency = {r["model"]: r for r in rows if r["case"] == "latency"}
    for name, m in model_set.items():
        if isinstance(m, str) or not isinstance(m[0], CounterNet):
            continue
        r = _row(name, "postprocess", 1, time_postprocess(m[0], singles, device), device)
        r.pop("frames_per_s", None)
        whole = latency[name].get("median_ms")
        if r.get("median_ms") and whole:
            r["share_of_latency"] = round(min(r["median_ms"] / whole, 1.0), 4)
        rows.append(r)
    return rows


def graph_count(model: Any, graphed: Any, group: list[torch.Tensor]) -> list:
    """The per-class counts of ``group`` through a graphed model, read to the host once."""
    dets = graphed(group)
    if isinstance(model, CounterNet):
        return torch.stack([d["counts"] for d in dets]).tolist()
    c = len(model.config.class_names) + 1  # labels are 1-based
    counts = [torch.zeros(c, dtype=torch.int64, device=d["labels"].device).index_add_(
        0, d["labels"].long(), (d["scores"] >= SCORE_THRESHOLD).long())[1:] for d in dets]
    return torch.stack(counts).tolist()


def pillar_rows(model: Any, groups: list[list[torch.Tensor]]) -> int:
    """Pillar rows for a graph of these batches, as ``lidarops index build`` sizes them: a quarter more than the
    most a batch needs (each frame's pillars, at most the config's ``max_voxels_test``), in steps of 8,192."""
    cfg = model.config.floor_config() if isinstance(model, CounterNet) else model.config
    x0, y0, z0, x1, y1, z1 = cfg.point_cloud_range
    vx, vy = cfg.voxel_size[:2]
    most = 0
    for group in groups:
        need = 0
        for f in group:
            inside = (f[:, 0] >= x0) & (f[:, 0] < x1) & (f[:, 1] >= y0) & (f[:, 1] < y1) & (f[:, 2] >= z0) & (f[:, 2] < z1)
            cells = ((f[inside, 1] - y0) / vy).floor().long() * 100_000 + ((f[inside, 0] - x0) / vx).floor().long()
            need += min(int(cells.unique().numel()), cfg.max_voxels_test)
        most = max(most, need)
    return -(-(most + most // 4 + 1) // 8192) * 8192


def bench_graphs(model_set: dict, frames: list[torch.Tensor], batches: list[int], precisions: list[str],
                 device: torch.device) -> list[dict]:
    """Each model as one replayed CUDA graph per batch (``GraphedCounterNet`` / ``GraphedPointPillars``, what
    ``lidarops index build`` runs, with pillar rows sized as it sizes them), called on lists of frames as a user
    calls it: frames/s = batch / median."""
    from lidarops.models.cuda_graph import GraphedCounterNet, GraphedPointPillars

    on_device = [f.to(device) for f in frames]
    capacity = -(-max(len(f) for f in frames) // 4096) * 4096
    rows = []
    for precision, optimize in [(p, o) for p in precisions for o in (False, True)]:
        for bsz in batches:
            groups = [[on_device[(k * bsz + j) % len(frames)] for j in range(bsz)]
                      for k in range(max(1, len(frames) // bsz))]
            case = f"graph {precision}" + (" optimized" if optimize else "")
            print(f"== {case}: batch {bsz} ...", flush=True)
            for name, m in model_set.items():
                if isinstance(m, str):
                    rows.append(_row(name, case, bsz, m, device))
                    continue
                model = m[0]
                try:
                    kind = GraphedCounterNet if isinstance(model, CounterNet) else GraphedPointPillars
                    graphed = kind(model, capacity, precision, batch_size=bsz, optimize=optimize,
                                   max_pillars=pillar_rows(model, groups))
                    t = time_cuda(lambda m=model, g=graphed, it=itertools.cycle(groups): graph_count(m, g, next(it)),
                                  (), warmup=3, min_runs=10, max_runs=200, budget_s=1.0, rotate=False)
                    graphed = None  # its memory goes before the next is recorded
                except Exception as e:  # noqa: BLE001  (reported in its row)
                    t = _error(e)
                rows.append(_row(name, case, bsz, t, device))
                torch.cuda.empty_cache()
    return rows


def print_rows(rows: list[dict], info: dict, device: torch.device) -> None:
    table = []
    for r in rows:
        share = r.get("share_of_latency")
        table.append([r["model"], r["case"], r["batch"],
                      fmt_ms(r.get("median_ms")) if r["status"] == "ok" else short_status(r["status"]),
                      fmt_ms(r.get("iqr_ms")), r.get("runs", ""),
                      f"{r['frames_per_s']:,.1f}" if r.get("frames_per_s") else "",
                      "" if share is None else f"{100 * share:.0f}% post / {100 * (1 - share):.0f}% net"])
    print_table(f"== CounterNet vs the PointPillars counter ({device_name(device)}); {info['frames']} frames of "
                f"{info['points_mean']:,} points on average ({info['boxes_mean']} boxes); ms per call",
                ["model", "case", "batch", "ms", "IQR", "runs", "frames/s", "share of latency"], table,
                right=(2, 3, 4, 5, 6))
    for r in rows:
        if r["status"] != "ok":
            print(f"  {r['op']}: {r['status']}")
    print()


# ------------------------------------------------------------------ main

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(ap)
    ap.add_argument("--quick", action="store_true", help="2 frames, for smoke tests")
    ap.add_argument("--frames", type=int, default=0, help="frames (default: 16 on CUDA, 4 on CPU, 2 with --quick)")
    ap.add_argument("--batch", type=int, default=0, help="batch of the throughput rows (default: 8 on CUDA, 2 on CPU)")
    ap.add_argument("--graph-batches", default="8,32,64", help="CUDA: batches of the CUDA-graph rows (default 8,32,64)")
    ap.add_argument("--graph-precisions", default="fp32,fp16", help="CUDA: precisions of the CUDA-graph rows")
    return run_with_threads(_main, ap.parse_args(argv))


def _main(a: argparse.Namespace) -> int:
    dev = bench_device(a.device)
    if dev is None:
        return 2
    cuda = dev.type == "cuda"
    n = a.frames or (2 if a.quick else 16 if cuda else 4)
    batch = a.batch or (8 if cuda else 2)
    t0 = time.perf_counter()
    load0 = load_average_warning(dev)
    print(f"# {device_name(dev)}: torch {torch.__version__}, lidarops {lidarops.__version__}", flush=True)

    frames, info = make_frames(n)
    model_set = models(dev)
    rows = bench(model_set, frames, batch, dev)
    if cuda:
        rows += bench_graphs(model_set, frames, [int(b) for b in a.graph_batches.split(",") if b],
                             [p for p in a.graph_precisions.split(",") if p], dev)
    print_rows(rows, info, dev)

    wall = time.perf_counter() - t0
    print(f"({dev.type} run took {wall:.0f} s)\n")
    if a.json:
        meta = env_meta(dev)
        flags = " ".join(f for f, on in (("--quick", a.quick), (f"--frames {a.frames}", a.frames),
                                          (f"--batch {a.batch}", a.batch), (f"--threads {a.threads}", a.threads)) if on)
        meta.update(
            benchmark=f"benchmarks/bm_counternet.py --device {dev.type}" + (f" {flags}" if flags else ""),
            sweep_s=round(wall, 1),
            load_avg_1m_start=None if load0 is None else round(load0, 2),
            frames=info, batch=batch, target="CounterNet >= 1,000 frames/s on CUDA (issue 38)",
            float32_matmul_precision=torch.get_float32_matmul_precision(),
            notes={
                "models": "CN_pt=1: the shipped counternet_road7_pt1; CN_pt=4^o: the shipped counternet_road7 "
                          "(PARTITIONS 4, OVERLAP 0.2); PointPillars counter: pointpillars_synth, "
                          f"boxes with score >= {SCORE_THRESHOLD} counted per class",
                "latency": "batch 1, eager model.predict(batch), counts read to the host, calls cycling over the "
                           "frames",
                "throughput": "model.predict on batches of `batch` frames; frames_per_s = batch / median",
                "postprocess": "CounterNet.postprocess alone on precomputed outputs, batch 1; share_of_latency = "
                               "its median / the latency median",
                "graph": "case 'graph <precision>': GraphedCounterNet / GraphedPointPillars(model, capacity, "
                         "precision, batch_size=batch, max_pillars=a quarter more than the batches need (as the "
                         "index build sizes them)[, optimize=True]) called on a list of `batch` device frames "
                         "(copy into the "
                         "graph's input, one replay, one host read), counts read to the host; frames_per_s = "
                         "batch / median",
            },
        )
        path = write_results(SECTION, dev, rows, meta, replace_by=None, results_dir=a.results_dir)
        print(f"wrote {path}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
