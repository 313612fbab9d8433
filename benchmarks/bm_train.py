"""Training throughput and accuracy of PointPillars: lidarops beside OpenPCDet's own train.py.

    python benchmarks/bm_train.py --data DATA --vs-openpcdet .peers/OpenPCDet [--epochs 5] [--batch-size 8]
                                  [--workers 8] [--amp none|fp16] [--seeds 0 1 2] [--out OUT] [--json]

DATA: a KITTI-format folder from ``lidarops data synth``, prepared for OpenPCDet by
``tools/upstream/openpcdet/prepare_kitti.py`` (its infos and gt database). OpenPCDet's checkout has its
ops built (``tools/upstream/openpcdet/build_ops.py``); README.md there says how. Without
``--vs-openpcdet`` only lidarops runs.

Both sides train the same model from the same file, OpenPCDet's ``tools/cfgs/kitti_models/pointpillar.yaml``
(with ``USE_ROAD_PLANE: False``: simulated data has no road planes; written beside it as
``pointpillar_lidarops_bm.yaml``), on the same frames, with the same batch size, epochs, DataLoader
workers and precision (``--amp fp16``: OpenPCDet's ``--use_amp`` and lidarops' ``--amp fp16``):

* OpenPCDet: ``tools/train.py`` as its users run it (its KittiDataset with gt sampling from its database,
  its augmentations, spconv's voxel generator, ``adam_onecycle``);
* lidarops: ``lidarops train --config <the same yaml>``.

Measured from each side's own log: the time of the training steps (OpenPCDet: its per-epoch mean
"Batch time" x iterations; lidarops: the "steps in S s" of train.log; both include waiting for data and
the first step, neither the checkpoint writes or evaluation), frames/s = frames trained / that time,
and the share of it spent waiting for the next batch (OpenPCDet's "Data time"; lidarops' "waiting for
data"). Accuracy: both final checkpoints scored on the validation split by the same evaluator
(``lidarops detect --split val``: KITTI AP, R40), and OpenPCDet's own evaluation of its checkpoint
beside it. ``--seeds``: lidarops trains once per seed (its runs are the cheap side), so the table shows
the spread one training run has, against which OpenPCDet's single run is judged "equal" or not.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.common import env_meta, print_table, write_results  # noqa: E402

BM_CFG = "pointpillar_lidarops_bm.yaml"


def derived_config(openpcdet: Path) -> Path:
    """OpenPCDet's pointpillar.yaml with road planes off, beside it (its base config is found from tools/)."""
    src = openpcdet / "tools/cfgs/kitti_models/pointpillar.yaml"
    text = src.read_text()
    if "USE_ROAD_PLANE: True" not in text:
        raise SystemExit(f"{src}: no 'USE_ROAD_PLANE: True' to turn off (a changed OpenPCDet config?)")
    out = src.with_name(BM_CFG)
    out.write_text(text.replace("USE_ROAD_PLANE: True", "USE_ROAD_PLANE: False"))
    return out


def run(cmd: list[str], cwd: Path, log: Path, env: dict | None = None, done_marker: str | None = None) -> float:
    """Runs ``cmd``; a failure after ``done_marker`` appeared in its output is reported, not fatal."""
    t0 = time.perf_counter()
    with log.open("w") as f:
        rc = subprocess.run(cmd, cwd=cwd, stdout=f, stderr=subprocess.STDOUT,
                            env={**os.environ, **(env or {})}).returncode
    wall = time.perf_counter() - t0
    if rc != 0 and done_marker is not None and done_marker in log.read_text():
        print(f"{' '.join(cmd[:3])} ...: exit {rc} after '{done_marker}' (its output: {log}); going on")
        return wall
    if rc != 0:
        print(log.read_text()[-4000:])
        raise SystemExit(f"{' '.join(cmd[:3])} ... failed (exit {rc}); its output: {log}")
    return wall


def evaluate(checkpoint: Path, data: Path, out: Path, config: Path | None, cwd: Path) -> dict:
    """KITTI AP of a checkpoint on DATA's val split, by lidarops' evaluator (``lidarops detect``)."""
    cmd = [sys.executable, "-m", "lidarops", "detect", str(data), "--split", "val", "--checkpoint",
           str(checkpoint), "--out", str(out), "--no-progress", "--print-frames", "0"]
    if config is not None:
        cmd += ["--config", str(config)]
    run(cmd, cwd, out.with_suffix(".log"))
    return json.loads((out / "eval.json").read_text())


def headline(results: dict, classes=("Car", "Pedestrian", "Cyclist")) -> dict:
    """3D moderate R40 per class, and Car BEV (the first to move while a short run's boxes are still loose)."""
    return {**{c: results.get(f"{c}_3d_moderate_R40") for c in classes}, "Car BEV": results.get("Car_bev_moderate_R40")}


def openpcdet_train(args, cfg: Path) -> dict:
    tools = args.vs_openpcdet / "tools"
    tag = f"bm_e{args.epochs}_b{args.batch_size}_{args.amp}"
    runner = [sys.executable, "train.py"] if args.openpcdet_ops == "own" else \
        [sys.executable, str(ROOT / "tools/upstream/openpcdet/with_faces.py"), str(tools / "train.py")]
    cmd = runner + ["--cfg_file", f"cfgs/kitti_models/{cfg.name}", "--batch_size",
           str(args.batch_size), "--epochs", str(args.epochs), "--workers", str(args.workers), "--extra_tag", tag,
           "--wo_gpu_stat", "--logger_iter_interval", "20", "--ckpt_save_interval", str(args.epochs),
           "--num_epochs_to_eval", "1", "--set", "DATA_CONFIG.DATA_PATH", str(args.data)]
    if args.amp == "fp16":
        cmd.insert(cmd.index("--set"), "--use_amp")  # --set takes the rest of the line
    # OpenPCDet's test.py reloads its own checkpoints with torch.load's default, which torch >= 2.6 made
    # weights_only=True: its numpy scalars are then refused (our own files, trusted)
    # its own evaluation after training needs numba's CUDA target, which may not import with a recent NumPy:
    # the training is what this measures, so a failure after it is reported and the run goes on
    wall = run(cmd, tools, args.out / "openpcdet_train.log", env={"TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD": "1"},
               done_marker="End training")
    out_dir = args.vs_openpcdet / "output/kitti_models" / cfg.stem / tag
    parsed = parse_openpcdet_log(sorted(out_dir.glob("train_*.log"))[-1].read_text())
    ckpt = out_dir / "ckpt" / f"checkpoint_epoch_{args.epochs}.pth"
    return {**parsed, "frames": parsed["frames_per_epoch"] * args.epochs, "wall_seconds": wall, "checkpoint": str(ckpt)}


def parse_openpcdet_log(log: str) -> dict:
    """Training set size, step and data-wait seconds, and OpenPCDet's own 3D moderate R40 AP from its log."""
    frames = int(re.search(r"Total samples for KITTI dataset: (\d+)", log).group(1))
    # the last logged line of each epoch carries the epoch's mean data and batch times
    per_epoch: dict[int, tuple[float, float, int]] = {}
    for m in re.finditer(r"Train:\s+(\d+)/\d+ .*?\[\s*(\d+)/(\d+) .*?Data time: [\d.]+\(([\d.]+)\).*?"
                         r"Batch time: [\d.]+\(([\d.]+)\)", log):
        per_epoch[int(m.group(1))] = (float(m.group(4)), float(m.group(5)), int(m.group(3)))
    step_s = sum(b * n for _, b, n in per_epoch.values())
    data_s = sum(d * n for d, _, n in per_epoch.values())
    own = {}
    for cls in ("Car", "Pedestrian", "Cyclist"):
        m = re.search(cls + r" AP_R40@0\.\d+, 0\.\d+, 0\.\d+:\nbbox AP:[^\n]*\nbev  AP:[^\n]*\n3d   AP:([\d.]+), ([\d.]+),",
                      log.split("Start evaluation")[-1])
        own[cls] = float(m.group(2)) if m else None
    return {"frames_per_epoch": frames, "step_seconds": step_s, "data_seconds": data_s, "epochs_logged": len(per_epoch),
            "own_eval_3d_moderate_R40": own}


def lidarops_train(args, cfg: Path, seed: int) -> dict:
    out = args.out / f"lidarops_run_seed{seed}"
    cmd = [sys.executable, "-m", "lidarops", "train", "--config", str(cfg), "--data", str(args.data), "--out",
           str(out), "--epochs", str(args.epochs), "--batch-size", str(args.batch_size), "--workers",
           str(args.workers), "--amp", args.amp, "--eval-every", "0", "--no-progress", "--seed", str(seed)]
    wall = run(cmd, cfg.parent.parent.parent, args.out / f"lidarops_train_seed{seed}.log")
    text = (out / "train.log").read_text()
    m = re.search(r"(\d+) steps in ([\d.]+) s \((\d+) % waiting for data\)", text)
    steps, step_s, share = int(m.group(1)), float(m.group(2)), float(m.group(3)) / 100
    rows = [line for line in (out / "log.csv").read_text().splitlines()[1:] if line]
    return {"frames": None, "steps": steps, "step_seconds": step_s, "data_seconds": share * step_s,
            "wall_seconds": wall, "checkpoint": str(out / "final.pth"), "log_rows": len(rows)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--vs-openpcdet", type=Path, default=None, help="OpenPCDet checkout with its ops built")
    p.add_argument("--openpcdet-ops", choices=["own", "faces"], default="own",
                   help="OpenPCDet's compiled ops (default), or lidarops.compat.pcdet in their place")
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--workers", type=int, default=8)
    p.add_argument("--amp", choices=["none", "fp16"], default="none")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="lidarops trains once per seed")
    p.add_argument("--out", type=Path, default=Path("bm_train_out"))
    p.add_argument("--json", action="store_true", help="add the rows to benchmarks/results/<device>.json")
    args = p.parse_args()
    args.data = args.data.resolve()
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.vs_openpcdet is None:
        raise SystemExit("--vs-openpcdet DIR is required (the comparison is the point of this benchmark)")
    args.vs_openpcdet = args.vs_openpcdet.resolve()
    cfg = derived_config(args.vs_openpcdet)
    train_frames = len((args.data / "ImageSets/train.txt").read_text().split())
    partial = args.out / "bm_train_partial.json"  # what is done so far, should the run be cut short
    results = {"openpcdet": openpcdet_train(args, cfg)}
    partial.write_text(json.dumps(results, indent=1))
    for seed in args.seeds:
        results[f"lidarops seed {seed}"] = {**lidarops_train(args, cfg, seed), "frames": train_frames * args.epochs}
        partial.write_text(json.dumps(results, indent=1))
    for side, r in results.items():
        r["frames_per_s"] = r["frames"] / r["step_seconds"] if r["step_seconds"] else None
        r["data_share"] = r["data_seconds"] / r["step_seconds"] if r["step_seconds"] else None
        r["ap"] = headline(evaluate(Path(r["checkpoint"]), args.data, args.out / f"eval_{side.replace(' ', '_')}",
                                    cfg if side == "openpcdet" else None, cfg.parents[2]))
    ours = [r for side, r in results.items() if side != "openpcdet"]
    speedup = sum(r["frames_per_s"] for r in ours) / len(ours) / results["openpcdet"]["frames_per_s"]
    rows = []
    for side, r in results.items():
        rows.append([side, f"{r['frames']}", f"{r['step_seconds']:.1f}", f"{r['frames_per_s']:.1f}",
                     f"{100 * r['data_share']:.0f} %"] + [f"{v:.1f}" if v is not None else "-" for v in r["ap"].values()])
    if len(ours) > 1:  # the seeds' range: what one lidarops run may land on
        lo_hi = [(min(r["ap"][c] or 0 for r in ours), max(r["ap"][c] or 0 for r in ours)) for c in ours[0]["ap"]]
        rows.append(["lidarops, range over seeds", "", "", "", ""] + [f"{lo:.1f}-{hi:.1f}" for lo, hi in lo_hi])
    print_table(f"PointPillars training, {args.epochs} epochs of {train_frames} frames, batch {args.batch_size}, "
                f"{args.workers} workers, amp {args.amp}, OpenPCDet with "
                f"{'its own ops' if args.openpcdet_ops == 'own' else 'lidarops faces'} "
                f"(lidarops / OpenPCDet frames/s: {speedup:.2f}x)",
                ["trainer", "frames", "step s", "frames/s", "data wait", "Car 3D", "Ped 3D", "Cyc 3D", "Car BEV"],
                rows, right=range(1, 9))
    own = results["openpcdet"]["own_eval_3d_moderate_R40"]
    print(f"OpenPCDet's own evaluation of its checkpoint (3D moderate R40): {own}")
    report = {"args": {k: str(v) for k, v in vars(args).items()}, "results": results, "speedup": speedup,
              "meta": env_meta("cuda")}
    (args.out / "bm_train.json").write_text(json.dumps(report, indent=1))
    if args.json:
        write_results("train_vs_openpcdet", "cuda", [
            {"trainer": side, **{k: v for k, v in r.items() if k not in ("checkpoint",)}} for side, r in results.items()],
            env_meta("cuda"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
