"""Scaling out on the GPUs of one host: training and index building on 1, 2, 4, 8 GPUs, as users launch them.

    python benchmarks/bm_scaling.py --gpus 1,2 --work /tmp/scaling --json --plot docs/img/scaling.png
    python benchmarks/bm_scaling.py --device cpu --gpus 1,2 --tasks index,allreduce --index-frames 16   # gloo

Each row is one ``torchrun --standalone --nproc_per_node=G`` launch of a lidarops command, timed by the
command's own report:

* ``train_pointpillars``, ``train_counternet``, ``train_casnet``: ``lidarops train`` on simulated frames
  (``lidarops data synth``, written into ``--work`` once). The batch per GPU is fixed (the configs' recipes: 8
  frames, 4 for CAS-Net), so the global batch is ``G x`` that; the learning rate is the config's whatever G
  (OpenPCDet's rule: its one-cycle peak LR is not scaled with the GPU count), and every G trains the same
  epochs over the same frames, so G GPUs take 1/G of the steps. Read from the run's ``summary.json``:
  frames/s of all ranks (the warm-up step left out), each rank's wait for data, evaluation and checkpoint
  time, and the metrics of the evaluation after the last epoch (PointPillars: KITTI moderate 3D AP, R40).
  Scaling efficiency = frames/s at G / (G x frames/s at 1).
* ``train_pointpillars`` with ``--sync-bn`` at the largest G: the AP SyncBatchNorm reaches in the same
  epochs, beside the run without it.
* ``index``: ``lidarops index build --source detector`` over ``--index-frames`` KITTI ``.bin`` scans (64
  distinct held-out frames, copied), frames/s from its report; then the union of the ranks' Parquet parts
  is checked against the 1-GPU index: every frame once, none missing, the same counts.
* ``allreduce``: an all-reduce (NCCL on CUDA, gloo on CPU) of a float32 tensor the size of each trained
  model's gradients, median of 30: what the gradient exchange can cost a step at most (DDP overlaps it with
  the backward pass).

Where a G loses efficiency, the rows say where the time went: the step time per GPU against one GPU, the
part of that growth spent waiting for data (the slowest rank) and the bound of the all-reduce; what is left
is ranks waiting for each other at the all-reduce (stragglers: frames differ in points and objects).
``--json`` merges the rows into ``benchmarks/results/<device>.json`` under ``"scaling"``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import env_meta, print_table, write_results  # noqa: E402

TASKS = ("pointpillars", "counternet", "casnet", "index", "allreduce")
#: the training recipes measured: config, data set, batch per GPU, extra arguments (the shipped models' own)
RECIPES = {
    "pointpillars": ("configs/pointpillars/pointpillars_synth.yaml", "pp", 8, []),
    "counternet": ("configs/counternet/counternet_synth.yaml", "cn", 8,
                   ["--set", "MODEL.COUNT_HEAD.PARTITIONS", "4", "MODEL.COUNT_HEAD.OVERLAP", "0.2",
                    "MODEL.COUNT_HEAD.COUNT_WEIGHT", "1.0"]),
    "casnet": ("configs/casnet/casnet_pointpillars_synth.yaml", "pp", 4, []),
}
# NVLink multicast stays off wherever a process is started (a program using it can take the host's GPUs down)
SAFE_ENV = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}


def torchrun(gpus: int, *args: str) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={gpus}", *args]


def run(cmd: list[str], log: Path, timeout: float) -> float:
    """Runs ``cmd`` (output to ``log``); its wall time. A failure raises with the log's end."""
    env = {**os.environ, **SAFE_ENV, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT),
                                                                                  os.environ.get("PYTHONPATH")]))}
    t0 = time.perf_counter()
    with log.open("w") as f:
        try:
            rc = subprocess.run(cmd, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=env, timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    if rc != 0:  # the command's own error, not torchrun's traceback of the child that died
        text = log.read_text()
        said = [ln for ln in text.splitlines() if re.search(r"error:|Error:", ln) and "torch/distributed" not in ln]
        raise RuntimeError(f"{' '.join(cmd[5:9])} ... failed ({rc}); see {log}:\n" + "\n".join(said[:8])
                           if said else text[-3000:])
    return time.perf_counter() - t0


def synth(work: Path, name: str, frames: int, workers: int) -> Path:
    """The simulated KITTI-format training data of a recipe, made once: ``pp`` (driving_city, the detector's
    classes) or ``cn`` (dense traffic of seven road classes, CounterNet's data)."""
    out = work / f"data_{name}_{frames}"
    if (out / "training" / "ImageSets" / "val.txt").is_file():
        return out
    cmd = [sys.executable, "-m", "lidarops", "data", "synth", "--scenario", "driving_city", "--frames", str(frames),
           "--seed", "0", "--val-fraction", "0.1", "--workers", str(workers), "--no-progress", "--out", str(out)]
    if name == "cn":
        cmd += ["--object-counts", "dense"]
    t = run(cmd, work / f"synth_{name}.log", timeout=3600)
    print(f"simulated {frames} frames ({name}) in {t:.0f} s", flush=True)
    return out


def headline(task: str, metrics: dict | None) -> tuple[str, float | None]:
    """The metric a row shows: PointPillars' and CAS-Net's mean moderate 3D AP (R40), CounterNet's exact counts."""
    if not metrics:
        return "", None
    if task == "counternet":
        exact = [v for k, v in metrics.items() if k.startswith("counting_accuracy_")]
        return ("counting_accuracy_mean", sum(exact) / len(exact)) if exact else ("", None)
    aps = [v for k, v in metrics.items() if k.endswith("_3d_moderate_R40")]
    return ("mAP_3d_moderate_R40", sum(aps) / len(aps)) if aps else ("", None)


def train_row(task: str, gpus: int, args: argparse.Namespace, data: Path, sync_bn: bool = False) -> dict:
    config, _, batch, extra = RECIPES[task]
    out = args.work / f"train_{task}_g{gpus}{'_syncbn' if sync_bn else ''}"
    shutil.rmtree(out, ignore_errors=True)
    frames, epochs = {"pointpillars": (None, args.epochs), "counternet": (None, args.cn_epochs),
                      "casnet": (args.casnet_frames, 1)}[task]
    cmd = ["-m", "lidarops", "train", "--config", config, "--data", str(data), "--out", str(out),
           "--epochs", str(epochs), "--batch-size", str(batch), "--workers", str(args.workers), "--eval-every", "0",
           "--max-val-frames", str(args.val_frames), "--no-progress", "--device", args.device]
    if args.device == "cuda":
        cmd += ["--amp", "bf16"]
    if frames:
        cmd += ["--max-train-frames", str(frames)]
    if task == "pointpillars":
        cmd += ["--gt-database-frames", str(args.gt_database_frames)]
    if sync_bn:
        cmd += ["--sync-bn"]
    wall = run(torchrun(gpus, *cmd, *extra), args.work / f"{out.name}.log", timeout=args.timeout)
    s = json.loads((out / "summary.json").read_text())
    slowest = max(s["ranks"], key=lambda r: r["data_seconds"] / max(r["train_seconds"], 1e-9))
    metric, value = headline(task, s["metrics"])
    row = {"op": "scaling", "case": f"train_{task}" + ("_syncbn" if sync_bn else ""), "task": task, "gpus": gpus,
           "sync_bn": sync_bn, "batch_per_gpu": s["batch_size_per_process"],
           "global_batch": s["global_batch_size"], "lr": s["lr"], "amp": s["amp"], "workers_per_gpu": s["num_workers"],
           "epochs": s["epoch"], "steps": s["steps"], "frames": s["frames"],
           "frames_per_s": round(s["frames_per_s_total"], 1),
           "step_ms": round(1000 * s["train_seconds"] / max(s["steps"], 1), 1),
           "data_wait_ms": round(1000 * slowest["data_seconds"] / max(slowest["steps"], 1), 1),
           "data_share_max": round(slowest["data_seconds"] / max(slowest["train_seconds"], 1e-9), 3),
           "train_s": round(s["train_seconds"], 1), "eval_s": round(s["eval_seconds"], 1),
           "checkpoint_s": round(s["checkpoint_seconds"], 1), "fit_wall_s": round(s["wall_seconds"], 1),
           "launch_wall_s": round(wall, 1), "parameters": s.get("trainable_parameters"),
           "metric": metric, "value": None if value is None else round(value, 2),
           "command": "torchrun --standalone --nproc_per_node=%d %s" % (gpus, " ".join(cmd + extra))}
    print(f"{row['case']} on {gpus}: {row['frames_per_s']} frames/s, step {row['step_ms']} ms (data wait "
          f"{row['data_wait_ms']} ms), eval {row['eval_s']} s, {metric} {row['value']}", flush=True)
    return row


def index_frames(idx_root: Path, source: str = "detector"):
    """The counts table of an index's source: a pandas DataFrame ordered by frame id."""
    from lidarops.query import FrameIndex

    idx = FrameIndex.open(idx_root)
    cols = ", ".join(f'"{c}"' for c in idx.classes)
    return idx.sql(f"SELECT frame_id, {cols} FROM counts WHERE source = ? ORDER BY frame_id", [source]), idx.classes


def compare_indexes(reference: Path, other: Path, expected_ids, source: str = "detector") -> dict:
    """The union check: ``other``'s frames against ``expected_ids`` (missing, extra, held twice) and its counts
    against ``reference``'s (frames whose counts differ in any class)."""
    ref, classes = index_frames(reference, source)
    got, classes_other = index_frames(other, source)
    if classes != classes_other:
        raise ValueError(f"the indexes count different classes: {classes} and {classes_other}")
    ids = got["frame_id"].to_numpy()
    expected = set(int(i) for i in expected_ids)
    held = [int(i) for i in ids]
    merged = got.drop_duplicates("frame_id").merge(ref.drop_duplicates("frame_id"), on="frame_id",
                                                    suffixes=("", "_ref"))
    differ = int(((merged[classes].to_numpy() != merged[[f"{c}_ref" for c in classes]].to_numpy()).any(axis=1)).sum())
    return {"frames": len(held), "missing": len(expected - set(held)), "extra": len(set(held) - expected),
            "duplicated": len(held) - len(set(held)), "counts_differ": differ,
            "compared": int(len(merged))}


def index_row(gpus: int, args: argparse.Namespace, scans: Path) -> dict:
    out = args.work / f"index_g{gpus}"
    shutil.rmtree(out, ignore_errors=True)
    cmd = ["-m", "lidarops", "index", "build", str(scans), "--source", "detector", "--fov", "all", "--out", str(out),
           "--batch", str(args.index_batch), "--workers", str(args.workers), "--device", args.device,
           "--no-progress"]
    if args.device == "cuda":
        cmd += ["--precision", "fp16"]
    log = args.work / f"index_g{gpus}.log"
    wall = run(torchrun(gpus, *cmd), log, timeout=args.timeout)
    m = re.search(r"indexed (\d+) frame\(s\).* in ([\d.]+) s(?: on \d+ ranks)? \(([\d.]+) frames/s; ([^)]*)\)",
                  log.read_text())
    if not m:
        raise RuntimeError(f"no 'indexed ... frames/s' line in {log}")
    row = {"op": "scaling", "case": "index", "task": "index", "gpus": gpus, "batch_per_gpu": args.index_batch,
           "workers_per_gpu": args.workers, "frames": int(m.group(1)), "build_s": float(m.group(2)),
           "frames_per_s": float(m.group(3)), "stages": m.group(4), "launch_wall_s": round(wall, 1),
           "precision": "fp16" if args.device == "cuda" else "fp32",
           "command": "torchrun --standalone --nproc_per_node=%d %s" % (gpus, " ".join(cmd))}
    print(f"index on {gpus}: {row['frames_per_s']} frames/s ({row['stages']})", flush=True)
    return row


def allreduce_probe(numels: list[int], out: Path) -> None:
    """Run under torchrun: the median time of an all-reduce of a float32 tensor of each size (rank 0 writes)."""
    import torch
    import torch.distributed as dist

    local = int(os.environ.get("LOCAL_RANK", "0"))
    cuda = torch.cuda.is_available() and os.environ.get("BM_DEVICE", "cuda") == "cuda"
    device = torch.device("cuda", local) if cuda else torch.device("cpu")
    if cuda:
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if cuda else "gloo", device_id=device if cuda else None)
    results = {}
    for numel in numels:
        x = torch.ones(numel, dtype=torch.float32, device=device)
        times = []
        for i in range(40):
            if cuda:
                torch.cuda.synchronize()
            dist.barrier()
            t0 = time.perf_counter()
            dist.all_reduce(x)
            if cuda:
                torch.cuda.synchronize()
            if i >= 10:
                times.append(time.perf_counter() - t0)
        if x[0].item() != dist.get_world_size() ** 40:  # every call summed the ranks' tensors
            raise RuntimeError(f"all-reduce gave {x[0].item()}, expected {dist.get_world_size() ** 40}")
        times.sort()
        results[numel] = 1000 * times[len(times) // 2]
    if dist.get_rank() == 0:
        out.write_text(json.dumps({str(k): v for k, v in results.items()}))
    dist.destroy_process_group()


def allreduce_rows(gpus: int, args: argparse.Namespace, params: dict[str, int]) -> list[dict]:
    out = args.work / f"allreduce_g{gpus}.json"
    numels = sorted(set(params.values()))
    os.environ["BM_DEVICE"] = args.device
    run(torchrun(gpus, str(Path(__file__).resolve()), "--allreduce-probe", ",".join(map(str, numels)),
                 "--probe-out", str(out)), args.work / f"allreduce_g{gpus}.log", timeout=300)
    ms = {int(k): v for k, v in json.loads(out.read_text()).items()}
    rows = []
    for task, numel in params.items():
        bus = 2 * (gpus - 1) / gpus * 4 * numel / ms[numel] / 1e6  # ring all-reduce bus bandwidth, GB/s
        rows.append({"op": "scaling", "case": f"allreduce_{task}", "task": "allreduce", "gpus": gpus,
                     "parameters": numel, "allreduce_ms": round(ms[numel], 3), "bus_gb_per_s": round(bus, 1)})
        print(f"all-reduce of {task}'s {numel / 1e6:.2f} M gradients on {gpus}: {ms[numel]:.3f} ms", flush=True)
    return rows


def add_efficiency(rows: list[dict], allreduce: dict[tuple[str, int], float]) -> None:
    """Efficiency against the same case on one GPU, and where a step's growth went."""
    base = {r["case"]: r for r in rows if r.get("gpus") == 1 and "frames_per_s" in r}
    base["train_pointpillars_syncbn"] = base.get("train_pointpillars")
    for r in rows:
        b = base.get(r["case"])
        if b is None or "frames_per_s" not in r or not b["frames_per_s"]:
            continue
        r["speedup"] = round(r["frames_per_s"] / b["frames_per_s"], 2)
        r["efficiency"] = round(r["frames_per_s"] / (r["gpus"] * b["frames_per_s"]), 3)
        if "step_ms" in r and r["gpus"] > 1:
            growth = r["step_ms"] - b["step_ms"]
            data = r["data_wait_ms"] - b["data_wait_ms"]
            bound = allreduce.get((r["task"], r["gpus"]))
            r["step_growth_ms"] = round(growth, 1)
            r["growth_data_ms"] = round(data, 1)
            if bound is not None:
                r["allreduce_bound_ms"] = round(bound, 2)
                r["growth_sync_ms"] = round(growth - data - bound, 1)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ones = {r["case"] for r in rows if r["gpus"] == 1}  # cases measured on 1 GPU and more: the scaling curves
    cases = [c for c in dict.fromkeys(r["case"] for r in rows) if c in ones and len({r["gpus"] for r in rows if r["case"] == c}) > 1]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    gmax = max(r["gpus"] for r in rows)
    axes[0].plot([1, gmax], [1, gmax], ":", color="gray", lw=1)
    for case in cases:
        pts = sorted((r["gpus"], r["frames_per_s"], r.get("efficiency", 1.0)) for r in rows if r["case"] == case)
        g, fps, eff = zip(*pts)
        label = f"{case} ({' / '.join(f'{f:.0f}' for f in fps)} frames/s)"
        axes[0].plot(g, [f / fps[0] for f in fps], "o-", label=label)
        axes[1].plot(g, [100 * e for e in eff], "o-", label=case)
    axes[0].set(xlabel="GPUs", ylabel="speed-up over 1 GPU", title="speed-up (dotted: linear)")
    axes[0].legend(fontsize=7, loc="upper left")
    axes[1].axhline(90, color="gray", ls="--", lw=1)
    axes[1].set(xlabel="GPUs", ylabel="scaling efficiency (%)", title="efficiency (dashed: 90 % target)",
                ylim=(0, 110))
    for ax in axes:
        ax.set_xticks(sorted({r["gpus"] for r in rows}))
        ax.grid(alpha=0.3)

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gpus", default="1,2", help="process counts, comma-separated (1 first: the baseline)")
    p.add_argument("--tasks", default=",".join(TASKS), help=f"comma-separated, of {', '.join(TASKS)}")
    p.add_argument("--device", default="cuda", choices=("cuda", "cpu"), help="cpu: gloo processes (a check)")
    p.add_argument("--work", type=Path, default=Path("/tmp/bm_scaling"), help="data, runs and logs")
    p.add_argument("--pp-frames", type=int, default=1200, help="simulated frames of the detector's data (10 %% val)")
    p.add_argument("--cn-frames", type=int, default=1200, help="simulated frames of CounterNet's data (10 %% val)")
    p.add_argument("--epochs", type=int, default=6, help="PointPillars epochs (every G the same)")
    p.add_argument("--cn-epochs", type=int, default=2)
    p.add_argument("--casnet-frames", type=int, default=320, help="CAS-Net: training frames of its one epoch")
    p.add_argument("--val-frames", type=int, default=120, help="frames of the evaluation after the last epoch")
    p.add_argument("--gt-database-frames", type=int, default=400)
    p.add_argument("--index-frames", type=int, default=6000)
    p.add_argument("--index-batch", type=int, default=16)
    p.add_argument("--workers", type=int, default=None, help="DataLoader workers per GPU (default: the cores over "
                                                              "the largest G, less 2, at most 12)")
    p.add_argument("--no-syncbn", action="store_true", help="skip the SyncBatchNorm run")
    p.add_argument("--timeout", type=float, default=900, help="seconds per launch")
    p.add_argument("--json", action="store_true")
    p.add_argument("--plot", type=Path, default=None)
    p.add_argument("--prepare", action="store_true", help="only make the data and scans of --tasks, then stop")
    p.add_argument("--replot", type=Path, default=None, metavar="RESULTS_JSON",
                   help="only draw --plot from the 'scaling' rows of a result file")
    p.add_argument("--allreduce-probe", default=None, help=argparse.SUPPRESS)
    p.add_argument("--probe-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.allreduce_probe:
        allreduce_probe([int(n) for n in args.allreduce_probe.split(",")], args.probe_out)
        return 0
    if args.replot:
        from benchmarks.common import read_results

        if not args.plot:
            p.error("--replot needs --plot PATH")
        rows = read_results(args.replot)["sections"]["scaling"]["rows"]
        plot([r for r in rows if "frames_per_s" in r], args.plot)
        return 0
    gpus = [int(g) for g in args.gpus.split(",")]
    tasks = args.tasks.split(",")
    if gpus[0] != 1 or any(g < 1 for g in gpus):
        p.error(f"--gpus {args.gpus}: start with 1 (the baseline of every efficiency)")
    if any(t not in TASKS for t in tasks):
        p.error(f"--tasks: {args.tasks!r}; valid: {', '.join(TASKS)}")
    import torch

    if args.device == "cuda" and torch.cuda.device_count() < max(gpus):
        p.error(f"--gpus {args.gpus}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    cores = os.cpu_count() or 2
    args.workers = args.workers if args.workers is not None else max(1, min(12, cores // max(gpus) - 2))
    args.work.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    data = {}
    for task in (t for t in ("pointpillars", "counternet", "casnet") if t in tasks):
        kind = RECIPES[task][1]
        if kind not in data:
            data[kind] = synth(args.work, kind, args.pp_frames if kind == "pp" else args.cn_frames, cores)
        if args.prepare:
            continue
        for g in gpus:
            rows.append(train_row(task, g, args, data[kind]))
        if task == "pointpillars" and max(gpus) > 1 and not args.no_syncbn:
            rows.append(train_row(task, max(gpus), args, data[kind], sync_bn=True))
    if "index" in tasks:
        from benchmarks.bm_index_build import write_scans

        scans = args.work / f"scans_{args.index_frames}"
        if not (scans / "velodyne" / f"{args.index_frames - 1:06d}.bin").is_file():
            write_scans(scans, args.index_frames, min(64, args.index_frames))
        if args.prepare:
            print(f"data and scans in {args.work}")
            return 0
        for g in gpus:
            row = index_row(g, args, scans)
            row.update(compare_indexes(args.work / "index_g1", args.work / f"index_g{g}", range(args.index_frames)))
            rows.append(row)
    if args.prepare:
        print(f"data in {args.work}")
        return 0
    allreduce: dict[tuple[str, int], float] = {}
    if "allreduce" in tasks:
        params = {r["task"]: r["parameters"] for r in rows if r.get("parameters")}
        if not params:  # no training measured here: the detector's size
            from lidarops.config import load_config
            from lidarops.models import model_class

            cfg = load_config(RECIPES["pointpillars"][0])
            model = model_class(cfg["MODEL"]["NAME"])(cfg)
            params = {"pointpillars": sum(q.numel() for q in model.parameters() if q.requires_grad)}
        for g in (g for g in gpus if g > 1):
            for r in allreduce_rows(g, args, params):
                rows.append(r)
                allreduce[(r["case"][len("allreduce_"):], g)] = r["allreduce_ms"]
    add_efficiency(rows, allreduce)
    keys = ["case", "gpus", "global_batch", "frames_per_s", "speedup", "efficiency", "step_ms", "data_wait_ms",
            "allreduce_bound_ms", "growth_sync_ms", "eval_s", "value", "allreduce_ms"]
    print_table(f"scaling, {args.device}", keys, [[r.get(k, "") for k in keys] for r in rows],
                right=range(1, len(keys)))
    if args.json:
        meta = env_meta(args.device)
        meta["gpus_on_host"] = torch.cuda.device_count() if args.device == "cuda" else 0
        meta["cores"] = cores
        for r in rows:
            r["key"] = f"{r['case']}@{r['gpus']}"
        print("results:", write_results("scaling", args.device, rows, meta, replace_by="key"))
    if args.plot:
        plot([r for r in rows if "frames_per_s" in r], args.plot)
    (args.work / "rows.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
