"""Speed of the frame index's queries (lidarops.query.FrameIndex, DuckDB embedded) against the same queries
in plain pandas over the same data held in memory, measured in the same run.

    python benchmarks/bm_query.py                          # 1,000,000 and 10,000,000 frames
    python benchmarks/bm_query.py --frames 1000000 --json  # one size; merge rows into benchmarks/results/<cpu>.json
    python benchmarks/bm_query.py --cache /tmp/lidarops-bm-query   # where the generated indexes live

The indexes are generated once and kept in ``--cache`` (default ``benchmarks/.cache/query``, git-ignored;
about 26 MB per million frames: 14 of Parquet, 12 of index.duckdb), then reused: a run over existing
indexes only times (and rebuilds index.duckdb, to time the first open). Each holds one source
(``labels``) of N frames x 8 classes with realistic counts: drives (``sequence``) of 200-2,000 frames at
10 Hz (``timestamp``), each class's count Poisson around a per-drive density drawn from a Gamma
distribution (a negative binomial over the fleet: busy and empty drives, as real fleets have), class means
from 6 cars to 0.2 buses per frame; written in parts of 1,000,000 frames, so 10,000,000 frames are
generated in bounded memory. Region queries run on a smaller index of ``--region-frames`` (100,000) frames
that also holds the counted objects' BEV centres (about 12 objects per frame).

Each query is timed as a user calls it: ``FrameIndex.open(dir)`` once (its time is reported as ``open``),
then ``idx.retrieve({...})``, ``idx.count(...)``, ``idx.sum(...)``, ``idx.avg(...)``, without and with a
``frames=range(...)`` filter of 10 % of the frames; the answer is part of the call (``retrieve``'s ids
included). The pandas peer is what a user writes with the same Parquet files loaded into one DataFrame
per source (``pd.read_parquet``, load time reported), e.g.
``df.loc[(df["Car"] >= 5) & (df["Pedestrian"] <= 2), "frame_id"]``; for regions, a filter on the centres,
a group-by and a reindex onto the frames. The two are timed with their calls interleaved (median of
repeated calls, benchmarks/common.py's rules) and must give the same answers (checked before timing).
Targets (issue 36): every query <= 20 ms at 1,000,000 frames and <= 100 ms at 10,000,000 frames on two
cores. ``--json`` merges the rows into ``benchmarks/results/<cpu>.json`` under ``"query"``.
"""
from __future__ import annotations

import argparse
import json
import operator
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if __package__ in (None, ""):  # run as a script: import lidarops from this checkout
    sys.path.insert(0, str(ROOT))

from benchmarks.common import (  # noqa: E402
    env_meta, fmt_ms, fmt_ratio, print_table, time_cpu_interleaved, write_results)

#: the 8 classes and their mean counts per frame over the fleet
CLASSES = ("Car", "Pedestrian", "Cyclist", "Van", "Truck", "Bus", "Motorcyclist", "Misc")
MEANS = (6.0, 2.5, 0.6, 1.0, 0.8, 0.2, 0.3, 0.5)
DENSITY_SHAPE = 2.0  # Gamma shape of a drive's density: variance mean + mean^2 / 2 (negative binomial)
PART_FRAMES = 1_000_000
GENERATOR_VERSION = 3  # bump when the generated data change: cached indexes of another version are rebuilt
DEFAULT_CACHE = ROOT / "benchmarks" / ".cache" / "query"
SOURCE = "labels"


# ---------------------------------------------------------------- generated indexes

def _drives(rng: np.random.Generator, n: int, first_drive: int):
    """Per-frame drive number, timestamp and per-class densities of ``n`` frames, drives numbered from
    ``first_drive``; and the next drive's number."""
    lengths = []
    while sum(lengths) < n:
        lengths.append(int(rng.integers(200, 2001)))
    lengths[-1] -= sum(lengths) - n
    lengths = np.array(lengths)
    drive = np.repeat(np.arange(first_drive, first_drive + len(lengths)), lengths)
    start = np.repeat(np.cumsum(lengths) - lengths, lengths)
    t0 = 1.6e9 + np.repeat(rng.uniform(0, 3e7, len(lengths)), lengths)  # drives spread over a year
    timestamp = t0 + 0.1 * (np.arange(n) - start)
    density = rng.gamma(DENSITY_SHAPE, 1 / DENSITY_SHAPE, (len(lengths), len(CLASSES)))
    return drive, timestamp, np.repeat(density, lengths, axis=0), first_drive + len(lengths)


def _centres(rng: np.random.Generator, frame_id: np.ndarray, counts: dict[str, np.ndarray]):
    import pyarrow as pa

    per_frame = np.stack([counts[c] for c in CLASSES], 1)  # (n, classes)
    fid = np.repeat(np.repeat(frame_id, len(CLASSES)), per_frame.reshape(-1))
    cls = np.repeat(np.tile(np.arange(len(CLASSES), dtype=np.int32), len(frame_id)), per_frame.reshape(-1))
    m = len(fid)
    r = rng.uniform(5, 70, m)  # within 70 m of the sensor, denser near it (density ~ 1 / range)
    a = rng.uniform(-np.pi, np.pi, m)
    return {"source": pa.DictionaryArray.from_arrays(np.zeros(m, np.int32), [SOURCE]).cast(pa.string()),
            "frame_id": pa.array(fid, pa.int64()),
            "class": pa.DictionaryArray.from_arrays(cls, list(CLASSES)).cast(pa.string()),
            "x": pa.array((r * np.cos(a)).astype(np.float32)), "y": pa.array((r * np.sin(a)).astype(np.float32)),
            "score": pa.array(rng.uniform(0.3, 1, m).astype(np.float32))}


def generate_index(root: Path, frames: int, seed: int = 0, centres: bool = False) -> None:
    """Writes an index of ``frames`` frames at ``root`` in the layout of lidarops.query.index (docs/query.md),
    a part of up to 1,000,000 frames at a time; ``index.json`` last, so an interrupted run leaves no index."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from lidarops.query.index import FORMAT, FORMAT_VERSION

    if root.exists():
        shutil.rmtree(root)
    rng = np.random.default_rng(seed)
    drive_no = 0
    for part, first in enumerate(range(0, frames, PART_FRAMES)):
        n = min(PART_FRAMES, frames - first)
        frame_id = np.arange(first, first + n, dtype=np.int64)
        drive, timestamp, density, next_drive = _drives(rng, n, drive_no)
        counts = {c: rng.poisson(mean * density[:, j]).astype(np.int32)
                  for j, (c, mean) in enumerate(zip(CLASSES, MEANS))}
        names = [f"drive-{seed:02d}-{d:06d}" for d in range(drive_no, next_drive)]
        table = {"source": pa.DictionaryArray.from_arrays(np.zeros(n, np.int32), [SOURCE]).cast(pa.string()),
                 "frame_id": pa.array(frame_id, pa.int64()),
                 "sequence": pa.DictionaryArray.from_arrays((drive - drive_no).astype(np.int32),
                                                            names).cast(pa.string()),
                 "timestamp": pa.array(timestamp, pa.float64()), "path": pa.nulls(n, pa.string()),
                 **{c: pa.array(v, pa.int32()) for c, v in counts.items()}}
        drive_no = next_drive
        kinds = [("counts", table)] + ([("centres", _centres(rng, frame_id, counts))] if centres else [])
        for kind, data in kinds:
            folder = root / kind / SOURCE
            folder.mkdir(parents=True, exist_ok=True)
            pq.write_table(pa.table(data), folder / f"part-{part:05d}.parquet")
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "classes": list(CLASSES),
            "sources": {SOURCE: {"centres": centres}}}
    (root / "index.json").write_text(json.dumps(meta, indent=1) + "\n")


def cached_index(cache: Path, frames: int, seed: int = 0, centres: bool = False) -> Path:
    """The folder of a generated index of ``frames`` frames under ``cache``, generated when missing."""
    root = cache / f"v{GENERATOR_VERSION}-frames{frames}-seed{seed}{'-centres' if centres else ''}"
    if not (root / "index.json").is_file():
        t0 = time.perf_counter()
        print(f"generating {frames:,} frames{' with centres' if centres else ''} into {root} ...", flush=True)
        generate_index(root, frames, seed, centres)
        print(f"  done in {time.perf_counter() - t0:.1f} s", flush=True)
    return root


def disk_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


# ---------------------------------------------------------------- the queries, as a user writes them

RETRIEVE = {"Car": (">=", 5), "Pedestrian": ("<=", 2)}  # issue 36's example
REGION = (0.0, -7.5, 15.0, 7.5)  # 15 m ahead, 7.5 m either side
REGION_RETRIEVE = {"Pedestrian": (">=", 1)}  # a pedestrian within 15 m ahead
OPS = {"<": operator.lt, "<=": operator.le, "=": operator.eq, ">=": operator.ge, ">": operator.gt}


def cases(idx, df, frames: range | None, centres=None, region=None) -> list[tuple[str, object, object]]:
    """``(query, DuckDB call, pandas call)`` of each query type, over ``frames`` (None: all), counting within
    ``region`` from ``centres`` when given. The pandas calls are what one writes over a DataFrame of the counts."""
    kw = {"frames": frames, "region": region}
    if frames is not None:  # the frame filter a pandas user writes
        df = df[(df["frame_id"] >= frames.start) & (df["frame_id"] < frames.stop)]
    if region is None:
        def column(c):
            return df[c]
    else:
        x0, y0, x1, y1 = region

        def column(c):  # objects of class c within the region, per frame of df (0 where none)
            inside = centres[(centres["x"] >= x0) & (centres["x"] < x1) & (centres["y"] >= y0) & (centres["y"] < y1)
                             & (centres["class"] == c)]
            return inside["frame_id"].value_counts().reindex(df["frame_id"], fill_value=0)

    where = RETRIEVE if region is None else REGION_RETRIEVE
    count = ("Pedestrian", ">", 4) if region is None else ("Car", ">=", 2)

    def pd_retrieve():  # e.g. df.loc[(df["Car"] >= 5) & (df["Pedestrian"] <= 2), "frame_id"]
        mask = np.ones(len(df), bool)
        for c, (op, v) in where.items():
            mask &= OPS[op](column(c), v).to_numpy()
        return df["frame_id"].to_numpy()[mask]

    def pd_mean(c):
        value = column(c).mean()
        return None if value != value else float(value)  # NaN over no frames

    return [
        ("retrieve", lambda: idx.retrieve(where, **kw), pd_retrieve),
        ("count", lambda: idx.count(*count, **kw), lambda: int(OPS[count[1]](column(count[0]), count[2]).sum())),
        ("sum", lambda: idx.sum("Car", **kw), lambda: int(column("Car").sum())),
        ("avg", lambda: idx.avg("Pedestrian", **kw), lambda: pd_mean("Pedestrian")),
    ]


def _same(a, b) -> bool:
    if isinstance(a, float) or isinstance(b, float):
        return a is not None and b is not None and abs(a - b) <= 1e-9 * max(1.0, abs(b))
    if np.ndim(a) or np.ndim(b) or hasattr(a, "__len__"):
        return bool(np.array_equal(np.asarray(a), np.asarray(b)))
    return a == b


def _answer(value) -> str:
    return f"{len(value):,} frames" if hasattr(value, "__len__") else (f"{value:.4f}" if isinstance(value, float)
                                                                      else f"{value:,}")


# ---------------------------------------------------------------- measuring

def measure_open(root: Path, runs: int = 5) -> dict:
    """Open times: the first (building index.duckdb from the parts), later ones (median), a later one with its
    first query (``retrieve``: DuckDB reads the blocks it needs on first use), and the sizes on disk."""
    from lidarops.query import FrameIndex
    from lidarops.query.index import STORE_FILE

    (root / STORE_FILE).unlink(missing_ok=True)
    t0 = time.perf_counter()
    FrameIndex.open(root)
    first = (time.perf_counter() - t0) * 1e3
    later = []
    for _ in range(runs):
        t0 = time.perf_counter()
        FrameIndex.open(root)
        later.append((time.perf_counter() - t0) * 1e3)
    t0 = time.perf_counter()
    FrameIndex.open(root).retrieve(RETRIEVE)
    with_query = (time.perf_counter() - t0) * 1e3
    store = root / STORE_FILE
    return {"open_first_ms": round(first, 3), "open_ms": round(float(np.median(later)), 3),
            "open_and_first_query_ms": round(with_query, 3),
            "parquet_bytes": sum(p.stat().st_size for p in root.rglob("*.parquet")),
            "duckdb_bytes": store.stat().st_size if store.is_file() else 0}


def run(cache: Path, sizes: list[int], region_frames: int, budget_s: float) -> tuple[list[dict], list[dict]]:
    import pandas as pd

    from lidarops.query import FrameIndex

    rows, opens = [], []
    plan = [(n, False) for n in sizes] + ([(region_frames, True)] if region_frames else [])
    for n, with_centres in plan:
        root = cached_index(cache, n, centres=with_centres)
        opened = measure_open(root)
        idx = FrameIndex.open(root)
        t0 = time.perf_counter()
        df = pd.read_parquet(root / "counts" / SOURCE)  # what a pandas user holds: one DataFrame per source
        centres = pd.read_parquet(root / "centres" / SOURCE) if with_centres else None
        load_ms = (time.perf_counter() - t0) * 1e3
        memory = int(df.memory_usage(deep=True).sum() + (centres.memory_usage(deep=True).sum() if with_centres else 0))
        opens.append({"op": "open", "case": f"{n:,} frames" + (" with centres" if with_centres else ""), "frames": n,
                      **opened, "pandas_load_ms": round(load_ms, 3), "pandas_bytes": memory,
                      "centres": int(len(centres)) if with_centres else 0})
        tenth = range(n // 2, n // 2 + n // 10)
        for frames in (None, tenth):
            region = REGION if with_centres else None
            case = (f"{n:,} frames" + (f", region={REGION}" if region else "")
                    + (f", frames=range({tenth.start}, {tenth.stop})" if frames is not None else ""))
            for query, duck, peer in cases(idx, df, frames, centres, region):
                common = {"op": query, "case": case, "frames": n, "frame_filter": frames is not None,
                          "region": region is not None, "target_ms": 20.0 if n <= 1_000_000 else 100.0}
                a, b = duck(), peer()
                if not _same(a, b):
                    rows.append({**common, "impl": "lidarops (DuckDB)",
                                 "status": f"error: answers differ ({_answer(a)} vs pandas {_answer(b)})"})
                    continue
                timings = time_cpu_interleaved([(duck, ()), (peer, ())], min_runs=5, max_runs=50, budget_s=budget_s)
                for impl, t in zip(("lidarops (DuckDB)", "pandas"), timings):
                    if isinstance(t, BaseException):
                        rows.append({**common, "impl": impl, "status": f"error: {type(t).__name__}: {t}"})
                    else:
                        rows.append({**common, "impl": impl, "status": "ok", "answer": _answer(a), **t.as_dict()})
            print(f"  measured {case}", flush=True)
        del idx, df, centres
    return rows, opens


def print_rows(rows: list[dict], opens: list[dict]) -> None:
    by = {}
    for r in rows:
        by.setdefault((r["frames"], r["region"], r["frame_filter"], r["op"]), {})[r["impl"]] = r
    table = []
    for (n, region, filtered, op), impls in by.items():
        d, p = impls.get("lidarops (DuckDB)", {}), impls.get("pandas", {})
        dm, pm = d.get("median_ms"), p.get("median_ms")
        ok = "" if dm is None else ("yes" if dm <= d["target_ms"] else "NO")
        where = ", ".join(["region" if region else "", "range 10 %" if filtered else ""]).strip(", ") or "-"
        table.append([f"{n:,}", where, op, fmt_ms(dm), fmt_ms(pm), fmt_ratio(pm / dm if dm and pm else None),
                      f"{d.get('target_ms', 0):.0f}", ok, d.get("answer", d.get("status", ""))])
    print_table("frame index queries: median ms of the call as a user makes it (DuckDB embedded vs pandas in memory)",
                ["frames", "filter", "query", "DuckDB ms", "pandas ms", "pandas/DuckDB", "target ms", "met", "answer"],
                table, right=(0, 3, 4, 5, 6))
    print_table("opening an index (DuckDB) vs loading it into pandas",
                ["index", "open, builds index.duckdb ms", "open ms", "open + 1st query ms", "Parquet MB",
                 "index.duckdb MB", "pandas load ms", "pandas MB"],
                [[o["case"], fmt_ms(o["open_first_ms"]), fmt_ms(o["open_ms"]), fmt_ms(o["open_and_first_query_ms"]),
                  f"{o['parquet_bytes'] / 1e6:.1f}", f"{o['duckdb_bytes'] / 1e6:.1f}", fmt_ms(o["pandas_load_ms"]),
                  f"{o['pandas_bytes'] / 1e6:.0f}"] for o in opens], right=(1, 2, 3, 4, 5, 6, 7))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="1000000,10000000", help="comma-separated index sizes (default 1M,10M)")
    ap.add_argument("--region-frames", type=int, default=100_000,
                    help="frames of the index with centres for region queries (0: none; default 100000)")
    ap.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help=f"generated indexes (default {DEFAULT_CACHE})")
    ap.add_argument("--budget", type=float, default=1.0, help="seconds of timed calls per case (default 1)")
    ap.add_argument("--json", action="store_true", help="merge results into benchmarks/results/<cpu>.json")
    args = ap.parse_args(argv)
    sizes = [int(float(s)) for s in args.frames.split(",") if s]
    meta = env_meta("cpu")
    import duckdb
    import pandas as pd
    meta.update({"duckdb": duckdb.__version__, "pandas": pd.__version__})
    rows, opens = run(args.cache, sizes, args.region_frames, args.budget)
    print(f"\n{meta['device']}; DuckDB {duckdb.__version__}, pandas {pd.__version__}; "
          f"load average {meta.get('load_avg_1m')} at the start\n")
    print_rows(rows, opens)
    if args.json:
        print(f"wrote {write_results('query', 'cpu', rows + opens, meta, replace_by='case')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
