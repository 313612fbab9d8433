"""Shared benchmark machinery: timers, device names, inputs, result files and tables.

Timing rules (every ``bm_*.py`` uses them):

* CUDA: warm-up calls, then one pair of CUDA events around each call, many calls; the median and
  the interquartile range are reported. When one input set fits in the L2 cache, calls rotate over
  enough copies of it (up to ``2 x L2`` bytes) that every call reads its inputs from memory, as a
  call inside a network would.
* CPU: ``time.perf_counter`` around each call after an untimed warm-up call, median and IQR over as
  many calls as fit in a time budget (at least ``min_runs``). A warm call slower than
  ``slow_single_s`` is measured once.
* The run count is sized from a warm call, never from the first (cold) one: a slow first call (lazy
  initialisation, allocator growth, a kernel's first launch) cannot cut the timed runs short.
  The implementations of one case are timed with their calls interleaved
  (:func:`time_cpu_interleaved`), so that load drifting on a shared machine hits them alike.

Results go to ``benchmarks/results/<device-slug>.json``; each benchmark file owns one section of
that file and :func:`write_results` keeps the other sections (and, within its section, the rows of
ops that were not run this time).
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import torch

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"

__all__ = [
    "Timing", "Skip", "time_call", "time_cpu", "time_cpu_interleaved", "time_cuda", "device_name", "device_slug", "env_meta",
    "available_memory", "write_results", "read_results", "print_table", "fmt_ms", "fmt_ratio", "short_status",
    "uniform_clouds", "lidar_clouds", "lidar_generator_name",
]


# ---------------------------------------------------------------- timing

@dataclass
class Timing:
    """Per-call times of one measurement, in milliseconds."""

    times_ms: list[float] = field(default_factory=list)
    n_sets: int = 1  # input sets rotated over (CUDA)

    @property
    def median(self) -> float:
        return statistics.median(self.times_ms)

    @property
    def iqr(self) -> float:
        if len(self.times_ms) < 4:
            return max(self.times_ms) - min(self.times_ms)
        q = statistics.quantiles(self.times_ms, n=4)
        return q[2] - q[0]

    @property
    def runs(self) -> int:
        return len(self.times_ms)

    def as_dict(self) -> dict:
        return {"median_ms": round(self.median, 6), "iqr_ms": round(self.iqr, 6), "runs": self.runs,
                "input_sets": self.n_sets}


class Skip(Exception):
    """A measurement that is not taken; the message says why (memory, time, missing package)."""


def _nbytes(obj: Any) -> int:
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, (list, tuple)):
        return sum(_nbytes(o) for o in obj)
    if hasattr(obj, "nbytes"):  # numpy
        return int(obj.nbytes)
    return 0


def _clone(obj: Any) -> Any:
    if isinstance(obj, torch.Tensor):
        return obj.clone()
    if isinstance(obj, tuple):
        return tuple(_clone(o) for o in obj)
    if isinstance(obj, list):
        return [_clone(o) for o in obj]
    return obj


def l2_cache_bytes(device: torch.device) -> int:
    props = torch.cuda.get_device_properties(device)
    return int(getattr(props, "L2_cache_size", 0) or 50 * 2**20)


def time_cuda(fn: Callable[..., Any], args: Sequence[Any], *, warmup: int = 3, min_runs: int = 10,
              max_runs: int = 200, budget_s: float = 0.3, slow_single_s: float = 2.0,
              rotate: bool = True) -> Timing:
    """Median of CUDA-event times of ``fn(*args)``; rotates over copies of ``args`` that fit in L2.

    One untimed cold call, then ``warmup`` warm-up calls whose mean sets the run count:
    ``clamp(budget_s / warm time, min_runs, max_runs)``. A call still slower than ``slow_single_s``
    when warm counts alone.
    """
    dev = next((a.device for a in args if isinstance(a, torch.Tensor) and a.is_cuda), torch.device("cuda"))
    torch.cuda.synchronize(dev)
    fn(*args)  # cold: not timed, and not used to size the run count
    torch.cuda.synchronize(dev)
    t0 = time.perf_counter()
    fn(*args)
    torch.cuda.synchronize(dev)
    warm = time.perf_counter() - t0
    if warm >= slow_single_s:
        return Timing([warm * 1e3])
    sets = [tuple(args)]
    nbytes = _nbytes(args)
    if rotate and nbytes > 0:
        want = min(1024, math.ceil(2 * l2_cache_bytes(dev) / nbytes))
        sets += [_clone(tuple(args)) for _ in range(want - 1)]
    t0 = time.perf_counter()
    for i in range(warmup):
        fn(*sets[i % len(sets)])
    torch.cuda.synchronize(dev)
    per_call = (time.perf_counter() - t0) / warmup if warmup > 0 else warm
    runs = _run_count(per_call, min_runs, max_runs, budget_s)
    start = [torch.cuda.Event(enable_timing=True) for _ in range(runs)]
    end = [torch.cuda.Event(enable_timing=True) for _ in range(runs)]
    for i in range(runs):
        a = sets[(i + warmup) % len(sets)]
        start[i].record()
        fn(*a)
        end[i].record()
    torch.cuda.synchronize(dev)
    return Timing([s.elapsed_time(e) for s, e in zip(start, end)], n_sets=len(sets))


def _run_count(per_call_s: float, min_runs: int, max_runs: int, budget_s: float) -> int:
    """Timed runs for a warm call of ``per_call_s`` seconds: as many as fit in ``budget_s``, clamped."""
    return int(max(min_runs, min(max_runs, budget_s / max(per_call_s, 1e-7))))


def _warm_time(fn: Callable[..., Any], args: Sequence[Any]) -> float:
    """Seconds of one warm call: an untimed cold call first, then a timed one."""
    fn(*args)
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def time_cpu(fn: Callable[..., Any], args: Sequence[Any], *, min_runs: int = 3, max_runs: int = 30,
             budget_s: float = 1.0, slow_single_s: float = 2.0) -> Timing:
    """Median wall time of ``fn(*args)``: an untimed cold call, then a timed warm call that sizes the run
    count (``clamp(budget_s / warm time, min_runs, max_runs)``, the warm call being the first run; a
    warm call slower than ``slow_single_s`` counts alone)."""
    warm = _warm_time(fn, args)
    times = [warm * 1e3]
    if warm >= slow_single_s:
        return Timing(times)
    for _ in range(_run_count(warm, min_runs, max_runs, budget_s) - 1):
        t0 = time.perf_counter()
        fn(*args)
        times.append((time.perf_counter() - t0) * 1e3)
    return Timing(times)


def time_cpu_interleaved(calls: Sequence[tuple[Callable[..., Any], Sequence[Any]]], *, min_runs: int = 3,
                         max_runs: int = 30, budget_s: float = 1.0,
                         slow_single_s: float = 2.0) -> list[Timing | BaseException]:
    """:func:`time_cpu` for several implementations of one case, their calls interleaved.

    On a shared machine the load drifts during a measurement; interleaving the calls (each
    implementation's runs spread evenly over the whole window) makes the ratios between them far
    less sensitive to that drift than timing one implementation after the other. Each gets the same
    warm-up (an untimed cold call, then a timed warm call, which is its first run) and the same run
    count, ``clamp(budget_s / mean warm time, min_runs, max_runs)``; only an
    implementation whose warm call is slower than ``slow_single_s`` counts that call alone. A call
    that raises gives its exception in place of a Timing.
    """
    out: list[Timing | BaseException] = [Timing() for _ in calls]
    warm: dict[int, float] = {}
    for i, (fn, args) in enumerate(calls):
        try:
            t = _warm_time(fn, args)
        except Exception as e:  # noqa: BLE001  (reported by the caller)
            out[i] = e
            continue
        out[i].times_ms.append(t * 1e3)
        if t < slow_single_s:
            warm[i] = t
    if not warm:
        return out
    runs = _run_count(sum(warm.values()) / len(warm), min_runs, max_runs, budget_s)
    for _ in range(runs - 1):
        for i, (fn, args) in enumerate(calls):
            if i in warm:
                t0 = time.perf_counter()
                fn(*args)
                out[i].times_ms.append((time.perf_counter() - t0) * 1e3)
    return out


class _CudaClock:
    """CUDA events and a device synchronisation (what :func:`time_cuda_interleaved` times with)."""

    def __init__(self, device: torch.device):
        self.device = device

    def event(self):
        return torch.cuda.Event(enable_timing=True)

    def sync(self) -> None:
        torch.cuda.synchronize(self.device)


def time_cuda_interleaved(calls: Sequence[tuple[Callable[..., Any], Sequence[Any]]], *, warmup: int = 3,
                          min_runs: int = 10, max_runs: int = 200, budget_s: float = 0.3, slow_single_s: float = 2.0,
                          clock: Any = None, idle: bool = False, rotate: bool = False,
                          block: int = 1) -> list[Timing | BaseException]:
    """:func:`time_cuda` for several implementations of one case, their calls interleaved (A, B, C, A, B, C, ...),
    as :func:`time_cpu_interleaved` on the CPU: a ratio between two columns then compares calls made side by side,
    not two windows of a machine whose speed drifts. Each gets an untimed cold call and ``warmup`` timed warm-up
    calls, whose mean (over the implementations) sets the common run count, ``clamp(budget_s / mean,
    min_runs, max_runs)``; one slower than ``slow_single_s`` counts its warm-up alone. A call that raises gives
    its exception in place of a Timing. ``clock`` (tests): ``event()`` and ``sync()``, CUDA's by default.

    ``idle``: a synchronisation before each timed call, so that every call starts on an idle GPU (a host-bound
    call's latency; without it a call's start event waits for the work the call before it left queued, and the
    host time spent meanwhile goes unmeasured). ``rotate``: the order of the implementations turns by one each
    round (A, B, C, then B, C, A, ...), so that none always follows the same other one (a call that follows
    another library's pays for the host's caches that one left cold). ``block``: each implementation's turn is
    ``block`` calls in a row, the first not timed (when ``block`` > 1), as in a user's loop that calls one library
    again and again: the call that pays for the switch from the other library is left out, and each still gets
    the common run count of timed calls (rounded up to whole turns)."""
    if not isinstance(block, int) or block < 1:
        raise ValueError(f"block must be an int >= 1, got {block!r}")
    clock = clock or _CudaClock(next((a.device for _, args in calls for a in args
                                      if isinstance(a, torch.Tensor) and a.is_cuda), torch.device("cuda")))
    out: list[Timing | BaseException] = [Timing() for _ in calls]
    warm: dict[int, float] = {}
    for i, (fn, args) in enumerate(calls):
        try:
            clock.sync()
            fn(*args)  # cold: not timed
            clock.sync()
            t0 = time.perf_counter()
            for _ in range(max(warmup, 1)):
                fn(*args)
            clock.sync()
        except Exception as e:  # noqa: BLE001  (reported by the caller)
            out[i] = e
            continue
        per_call = (time.perf_counter() - t0) / max(warmup, 1)
        if per_call >= slow_single_s:
            out[i].times_ms.append(per_call * 1e3)
        else:
            warm[i] = per_call
    if not warm:
        return out
    runs = _run_count(sum(warm.values()) / len(warm), min_runs, max_runs, budget_s)
    runs = -(-runs // max(block - 1, 1))  # rounds of block - 1 timed calls each
    marks: dict[int, list] = {i: [] for i in warm}
    turn = list(warm)
    for r in range(runs):
        for i in (turn[r % len(turn):] + turn[:r % len(turn)] if rotate else turn):
            if not isinstance(out[i], Timing):
                continue
            fn, args = calls[i]
            try:
                if block > 1:
                    fn(*args)  # the switch from the other implementation: not timed
                for _ in range(max(block - 1, 1)):
                    start, end = clock.event(), clock.event()
                    if idle:
                        clock.sync()
                    start.record()
                    fn(*args)
                    end.record()
                    marks[i].append((start, end))
            except Exception as e:  # noqa: BLE001  (a call that fails later: reported in its place)
                out[i] = e
                continue
    clock.sync()
    for i, pairs in marks.items():
        if isinstance(out[i], Timing):
            out[i].times_ms.extend(start.elapsed_time(end) for start, end in pairs)
    return out


def time_interleaved(calls: Sequence[tuple[Callable[..., Any], Sequence[Any]]], device: torch.device,
                     **kw) -> list[Timing | BaseException]:
    """:func:`time_cuda_interleaved` for CUDA, :func:`time_cpu_interleaved` otherwise (keyword options passed
    through)."""
    if torch.device(device).type == "cuda":
        return time_cuda_interleaved(calls, **{k: v for k, v in kw.items()
                                               if k in ("warmup", "min_runs", "max_runs", "budget_s", "slow_single_s",
                                                        "idle", "rotate", "block")})
    return time_cpu_interleaved(calls, **{k: v for k, v in kw.items()
                                          if k in ("min_runs", "max_runs", "budget_s", "slow_single_s")})


def time_call(fn: Callable[..., Any], args: Sequence[Any], device: torch.device, **kw) -> Timing:
    """:func:`time_cuda` for CUDA, :func:`time_cpu` otherwise (keyword options passed through)."""
    if torch.device(device).type == "cuda":
        return time_cuda(fn, args, **{k: v for k, v in kw.items() if k in ("warmup", "min_runs", "max_runs",
                                                                           "budget_s", "slow_single_s", "rotate")})
    return time_cpu(fn, args, **{k: v for k, v in kw.items() if k in ("min_runs", "max_runs", "budget_s",
                                                                      "slow_single_s")})


# ---------------------------------------------------------------- devices and environment

def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "CPU"


def device_name(device: str | torch.device) -> str:
    """``torch.cuda.get_device_name`` for CUDA; CPU model and core count for CPU."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{_cpu_model()}, {os.cpu_count()} cores ({torch.get_num_threads()} torch threads)"


def device_slug(device: str | torch.device) -> str:
    """File-name form of the device, e.g. ``cuda-nvidia-h100-80gb-hbm3`` or ``cpu-amd-epyc-2c``."""
    device = torch.device(device)
    if device.type == "cuda":
        name = "cuda-" + torch.cuda.get_device_name(device)
    else:
        name = f"cpu-{_cpu_model()}-{os.cpu_count()}c"
    name = re.sub(r"\((r|tm)\)|cpu @.*|processor", "", name, flags=re.I)
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def available_memory(device: str | torch.device) -> int:
    """Bytes that can still be allocated on ``device`` (MemAvailable on CPU, free memory on CUDA)."""
    device = torch.device(device)
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return int(free)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 8 * 2**30


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=5)
        return out.stdout.strip() if out.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


def _git_commit() -> str | None:
    """Short commit id, with ``+dirty`` when tracked files differ from it. ``LIDAROPS_COMMIT`` names it
    where the checkout has no git history (the GPU machine's copy of the working tree)."""
    if os.environ.get("LIDAROPS_COMMIT"):
        return os.environ["LIDAROPS_COMMIT"]
    commit = _git("rev-parse", "--short", "HEAD")
    if commit and _git("status", "--porcelain", "--untracked-files=no"):
        commit += "+dirty"
    return commit or None


def env_meta(device: str | torch.device) -> dict:
    """What a result depends on: device, versions, threads, commit, date."""
    device = torch.device(device)
    meta = {
        "device": device_name(device),
        "device_type": device.type,
        "torch": torch.__version__,
        "python": sys.version.split()[0],
        "threads": torch.get_num_threads(),
        "commit": _git_commit(),
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "host": platform.node(),
    }
    if hasattr(os, "getloadavg"):  # other work on the machine skews CPU timings
        meta["load_avg_1m"] = round(os.getloadavg()[0], 2)
    if hasattr(os, "nice"):
        meta["nice"] = os.nice(0)
    omp = {k: os.environ[k] for k in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if k in os.environ}
    if omp:
        meta["omp_env"] = omp
    try:
        import lidarops
        from lidarops import extension
        meta["lidarops"] = lidarops.__version__
        meta["lidarops_build"] = extension.build_info()
    except Exception:  # noqa: BLE001
        pass
    if device.type == "cuda":
        meta["cuda"] = torch.version.cuda
        meta["l2_cache_bytes"] = l2_cache_bytes(device)
    return meta


# ---------------------------------------------------------------- result files

def results_path(device: str | torch.device, results_dir: str | Path | None = None) -> Path:
    """``<results_dir>/<device-slug>.json``; the folder defaults to ``$LIDAROPS_RESULTS_DIR``, else
    ``benchmarks/results``."""
    folder = results_dir or os.environ.get("LIDAROPS_RESULTS_DIR") or RESULTS_DIR
    return Path(folder) / f"{device_slug(device)}.json"


def read_results(path: str | Path) -> dict:
    with open(path) as f:
        return json.load(f)


def write_results(section: str, device: str | torch.device, rows: list[dict], meta: dict,
                  replace_by: str | None = "op", results_dir: str | Path | None = None) -> Path:
    """Write ``rows`` as ``section`` of the device's result file and return its path.

    Other sections are kept. Within the section, old rows are kept unless their ``replace_by``
    value (e.g. the op) occurs among the new rows; ``replace_by=None`` replaces the whole section.
    ``results_dir`` as in :func:`results_path`.
    """
    path = results_path(device, results_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    data: dict = {}
    if path.exists():
        try:
            data = read_results(path)
        except (OSError, json.JSONDecodeError):
            data = {}
    data["device"] = meta.get("device", device_name(device))
    data["device_type"] = torch.device(device).type
    sections = data.setdefault("sections", {})
    old = sections.get(section, {})
    kept: list[dict] = []
    if replace_by is not None and old.get("rows"):
        new_keys = {r.get(replace_by) for r in rows}
        kept = [r for r in old["rows"] if r.get(replace_by) not in new_keys]
    # each row says which commit measured it (the section's meta is the newest run's)
    for r, m in [(r, old.get("meta", {})) for r in kept] + [(r, meta) for r in rows]:
        if m.get("commit") is not None:
            r.setdefault("commit", m["commit"])
    sections[section] = {"meta": meta, "rows": kept + rows}
    tmp = path.with_suffix(".json.tmp")
    with open(tmp, "w") as f:
        json.dump(data, f, indent=1, sort_keys=False)
        f.write("\n")
    os.replace(tmp, path)
    return path


# ---------------------------------------------------------------- tables

def fmt_ms(ms: float | None) -> str:
    if ms is None or not math.isfinite(ms):
        return "-"
    if ms >= 1000:
        return f"{ms:,.0f}"
    if ms >= 100:
        return f"{ms:.0f}"
    if ms >= 10:
        return f"{ms:.1f}"
    if ms >= 1:
        return f"{ms:.2f}"
    return f"{ms:.3f}"


def short_status(status: str) -> str:
    """Table form of a status: "skipped (memory: needs ...)" -> "skipped (memory)", "error: ..." -> "error"."""
    if status.startswith("skipped (") and ":" in status:
        return status.split(":")[0] + ")"
    if status.startswith("error"):
        return "error"
    return status


def fmt_ratio(r: float | None) -> str:
    if r is None or not math.isfinite(r):
        return ""
    if r >= 100:
        return f"{r:,.0f}x"
    if r >= 10:
        return f"{r:.0f}x"
    return f"{r:.1f}x" if r >= 1 else f"{r:.2f}x"


def print_table(title: str, headers: Sequence[str], rows: Iterable[Sequence[Any]], right: Sequence[int] = (),
                file=None) -> None:
    """Print a plain-text table; columns whose index is in ``right`` are right-aligned."""
    rows = [[("" if c is None else str(c)) for c in r] for r in rows]
    headers = [str(h) for h in headers]
    widths = [max([len(headers[i])] + [len(r[i]) for r in rows]) for i in range(len(headers))]

    def line(cells):
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))

    out = file or sys.stdout
    if title:
        print(title, file=out)
    print(line(headers).rstrip(), file=out)
    print("  ".join("-" * w for w in widths), file=out)
    for r in rows:
        print(line(r).rstrip(), file=out)
    print(file=out, flush=True)


# ---------------------------------------------------------------- inputs

def uniform_clouds(B: int, N: int, seed: int = 0, device: str | torch.device = "cpu",
                   dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(B, N, 3) points uniform in the unit cube."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, N, 3, generator=g, dtype=dtype).to(device)



def lidar_generator_name() -> str:
    """Which generator :func:`lidar_clouds` uses in this checkout."""
    try:
        import lidarops.data.synthetic  # noqa: F401
        return 'lidarops.data.synthetic.Simulator("driving_city") (sweeps, order-preserving subset)'
    except ImportError:
        return "lidarops.data.clouds.lidar_like_cloud (ring ground + boxes + clutter)"


def lidar_clouds(B: int, N: int, seed: int = 0, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(B, N, 3) LiDAR-like clouds in metres, one sweep per batch row (seeds ``seed``..``seed+B-1``).

    Uses the project's simulator when importable, else the built-in ring + boxes + clutter
    generator (both through :func:`lidarops.data.clouds.simulated_sweep`).
    """
    from lidarops.data.clouds import simulated_sweep
    clouds = [simulated_sweep(N, seed + b)[0] for b in range(B)]
    return torch.stack(clouds).to(device=device, dtype=dtype)


def add_common_args(ap) -> None:
    """``--device``, ``--threads``, ``--json`` and ``--results-dir``, as the model benchmarks take them."""
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), default="auto",
                    help="auto = cuda when available, else cpu (default)")
    ap.add_argument("--threads", type=int, default=0,
                    help="CPU threads (default: torch's choice; on a loaded 2-core machine 1 gives steadier times)")
    ap.add_argument("--json", action="store_true", help="merge the rows into benchmarks/results/<device>.json")
    ap.add_argument("--results-dir", default=None, help="folder of the result files (default benchmarks/results)")


def run_with_threads(main: Callable[[Any], int], a) -> int:
    """``main(a)`` with ``a.threads`` CPU threads, torch's own count restored after (smoke tests call benchmarks
    inside pytest's process)."""
    threads = torch.get_num_threads()
    if a.threads:
        torch.set_num_threads(a.threads)
    try:
        return main(a)
    finally:
        torch.set_num_threads(threads)


def bench_device(asked: str) -> torch.device | None:
    """The device of ``--device cpu|cuda|auto``; None (after saying why) when CUDA is asked for and missing."""
    from lidarops import extension

    cuda_ok = torch.cuda.is_available() and extension.cuda_available()
    if asked == "cuda" and not cuda_ok:
        print("CUDA asked for but not available (torch sees no GPU or lidarops was built without CUDA)",
              file=sys.stderr)
        return None
    return torch.device("cuda" if asked == "cuda" or (asked == "auto" and cuda_ok) else "cpu")


def load_average_warning(device: torch.device) -> float | None:
    """The 1-minute load average, with a warning on stderr when it skews CPU timings."""
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    if device.type == "cpu" and load is not None and load > 0.5 * (os.cpu_count() or 1):
        print(f"warning: load average {load:.1f} on {os.cpu_count()} cores; other work skews CPU timings",
              file=sys.stderr)
    return load
