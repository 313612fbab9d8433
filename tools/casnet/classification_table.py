"""CAS-Net's classification table: accuracy of one trained PointNet fed 1/D of each test object's points by
random sampling, FPS and trained CAS-Nets (full and fast), at every ratio D, with the sampling time per
object; a JSON report and a plot (issue 37, docs/casnet.md).

    python tools/casnet/classification_table.py --pointnet runs/pointnet/final.pth \\
        --casnet runs/cas_d*_*/final.pth --ratios 2 4 8 16 32 --device cuda --out casnet_classification.json \\
        --plot docs/img/casnet_classification.png

Each CAS-Net checkpoint is a ``lidarops train`` run of ``configs/casnet/casnet_pointnet_objects.yaml``: its
ratio and variant come from its config, and it is scored with its own frozen PointNet (the one of
``--pointnet``; a different one is refused). CAS-Net keeps its raw hard picks, repeats included, as the
paper evaluates it; the table also gives the distinct points it kept. Times: the whole test set sampled in
batches of ``--batch`` (per object: the total over the objects), and one object at a time (the median
over ``--latency-objects`` calls); CUDA calls are synchronised.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _casnet_sampler(model, dedup: bool):
    """``sampler(points, m)`` of a CASNetPointNet's CAS-Net: its hard picks, raw (repeats kept, as the paper)
    or with repeats reassigned (``dedup``: m distinct points, what ``CASNetSampler`` gives)."""
    def sample(points, m):
        out = model.casnet(points, mode="hard", dedup=bool(dedup))
        return out.indices
    return sample


def _casnet_pointnet(path, pointnet):
    """A CASNetPointNet from a training checkpoint, or from a CAS-Net file (``CASNet.save``; its run's config
    in ``model_config_of_run``) and the PointNet of ``--pointnet``."""
    import dataclasses

    from lidarops.models.casnet import CASNet
    from lidarops.models.casnet_pointnet import CASNetPointNet, CASNetPointNetConfig

    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if ckpt.get("model_class") == "CASNetPointNet":
        return CASNetPointNet.from_checkpoint(path).eval().to(next(pointnet.parameters()).device)
    cfg = CASNetPointNetConfig.from_dict({**ckpt["model_config_of_run"], "task_checkpoint": None})
    model = CASNetPointNet(dataclasses.replace(cfg, task=pointnet.config.to_dict()), load_task=False)
    model.task.load_state_dict(pointnet.state_dict())
    model.casnet = CASNet.from_checkpoint(path)
    return model.eval().to(next(pointnet.parameters()).device)


def evaluate(pointnet, sampler, m: int | None, test_set, collate, batch: int, device, latency_objects: int):
    """Accuracy (overall, mean per class), distinct points kept and sampling times of one sampler."""
    from lidarops.eval.classification import ClassificationEvaluator
    from lidarops.models.samplers import sample_features

    evaluator = ClassificationEvaluator(pointnet.config.class_names)
    preds, frames, distinct, sample_s = [], [], [], 0.0
    loader = torch.utils.data.DataLoader(test_set, batch_size=batch, shuffle=False, collate_fn=collate)
    with torch.no_grad():
        for b in loader:
            points = b["points"].to(device)
            if m is not None:
                _sync(device)
                t = time.perf_counter()
                idx = sampler(points, m)
                _sync(device)
                sample_s += time.perf_counter() - t
                distinct += [len(set(row.tolist()) - {-1}) for row in idx.cpu()]
                points = sample_features(points, idx)
            logits, _ = pointnet.network(points)
            preds += [{"label": int(k)} for k in logits.argmax(1).cpu()]
            frames += [{"gt_label": g} for g in b["gt_label"]]
        metrics, _ = evaluator(preds, frames)
        latency = []
        if m is not None:
            for i in range(min(latency_objects, len(test_set))):
                one = test_set[i]["points"].unsqueeze(0).to(device)
                sampler(one, m)  # warm (first call of a shape)
                _sync(device)
                t = time.perf_counter()
                sampler(one, m)
                _sync(device)
                latency.append(time.perf_counter() - t)
    row = {"accuracy": metrics["accuracy"], "mean_class_accuracy": metrics["mean_class_accuracy"]}
    if m is not None:
        row.update(m=m, distinct_points=statistics.mean(distinct), sample_ms_per_object_batched=1e3 * sample_s / len(preds),
                   sample_ms_one_object=1e3 * statistics.median(latency) if latency else None, batch=batch)
    return row


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    full = report["full_density"]["accuracy"]
    ax.axhline(full, color="grey", ls="--", lw=1, label=f"all {report['num_points']} points ({full:.1f} %)")
    by_method: dict[str, list] = {}
    for row in report["rows"]:
        by_method.setdefault(row["method"], []).append((row["ratio"], row["accuracy"]))
    styles = {"random": ("tab:orange", "o"), "fps": ("tab:blue", "s"), "casnet-full": ("tab:green", "^"),
              "casnet-fast": ("tab:olive", "v"), "casnet-full-dedup": ("tab:red", "^"),
              "casnet-fast-dedup": ("tab:purple", "v"), "casnet-full-anchored": ("tab:green", "^"),
              "casnet-fast-anchored": ("tab:red", "v"), "casnet-full-anchored-dedup": ("tab:olive", "^"),
              "casnet-fast-anchored-dedup": ("tab:purple", "v")}
    for method, pts in by_method.items():
        pts.sort()
        colour, marker = styles.get(method, (None, "x"))
        ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=marker, color=colour, label=method,
                ls="--" if method.endswith("-dedup") else "-")
    ax.set_xscale("log", base=2)
    ax.set_xticks(report["ratios"], [str(r) for r in report["ratios"]])
    ax.set_xlabel("sampling ratio D (points kept: N / D)")
    ax.set_ylabel("test accuracy (%)")
    ax.set_title(f"PointNet on simulated objects behind each sampler ({report['device']})", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    from lidarops.config import load_config
    from lidarops.data.object_sets import datasets_from_config
    from lidarops.models.pointnet import PointNet
    from lidarops.models.samplers import FPSSampler, RandomSampler

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pointnet", help="the trained PointNet (lidarops train's final.pth)")
    p.add_argument("--casnet", nargs="*", default=[], help="trained CASNetPointNet checkpoints (any ratios)")
    p.add_argument("--config", default=str(ROOT / "configs/casnet/pointnet_objects.yaml"))
    p.add_argument("--data", default=None, help="the object-set cache (default: the config's DATA_PATH)")
    p.add_argument("--ratios", type=int, nargs="+", default=[2, 4, 8, 16, 32])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--latency-objects", type=int, default=50)
    p.add_argument("--max-objects", type=int, default=None, help="the first N test objects only")
    p.add_argument("--seed", type=int, default=0, help="random sampling's seed")
    p.add_argument("--dedup", type=int, nargs="+", choices=(0, 1), default=[0, 1],
                   help="CAS-Net rows: 0 raw picks (the paper), 1 repeats reassigned (default both)")
    p.add_argument("--out", help="JSON report")
    p.add_argument("--plot", default=None, help="PNG of accuracy against the ratio")
    p.add_argument("--replot", default=None, metavar="JSON", help="only redraw --plot from a report of this script")
    args = p.parse_args(argv)
    if args.replot:
        if not args.plot:
            p.error("--replot needs --plot")
        plot(json.loads(Path(args.replot).read_text()), Path(args.plot))
        return 0
    if not args.pointnet or not args.out:
        p.error("--pointnet and --out are required (unless --replot)")
    device = torch.device(args.device)
    cfg = load_config(args.config)
    _, test_set, collate = datasets_from_config(cfg, data_path=args.data)
    if args.max_objects:
        test_set = test_set.subset(range(min(args.max_objects, len(test_set))))
    pointnet = PointNet.from_checkpoint(args.pointnet).eval().to(device)
    n = test_set.num_points
    report = {"device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
              "threads": torch.get_num_threads(), "num_points": n, "objects": len(test_set),
              "ratios": args.ratios, "pointnet": str(args.pointnet), "command": " ".join(sys.argv), "rows": []}
    report["full_density"] = evaluate(pointnet, None, None, test_set, collate, args.batch, device, 0)
    print(f"full density ({n} points): accuracy {report['full_density']['accuracy']:.2f} %", flush=True)
    casnets = []
    for path in args.casnet:
        model = _casnet_pointnet(path, pointnet)
        state = {k: v.to(device) for k, v in pointnet.state_dict().items()}
        if any(not torch.equal(v, state[k]) for k, v in model.task.state_dict().items()):
            raise SystemExit(f"{path}: its frozen PointNet is not the one of --pointnet {args.pointnet}")
        casnets.append((path, model))
    for ratio in args.ratios:
        m = n // ratio
        samplers = [("random", RandomSampler(args.seed), None), ("fps", FPSSampler(), None)]
        samplers += [(f"casnet-{model.config.variant}{'-anchored' if model.config.head == 'anchored' else ''}"
                      f"{'-dedup' if dedup else ''}", _casnet_sampler(model, dedup), path)
                     for path, model in casnets if model.config.ratio == ratio for dedup in args.dedup]
        for name, sampler, path in samplers:
            if hasattr(sampler, "reset"):
                sampler.reset()
            row = {"method": name, "ratio": ratio, "checkpoint": path and str(path),
                   **evaluate(pointnet, sampler, m, test_set, collate, args.batch, device, args.latency_objects)}
            report["rows"].append(row)
            print(f"D={ratio:>2} {name:<22} accuracy {row['accuracy']:6.2f} %  "
                  f"mean class {row['mean_class_accuracy']:6.2f} %"
                  f"  distinct {row['distinct_points']:7.1f}/{m}  {row['sample_ms_per_object_batched']:.3f} ms/object "
                  f"(batched), {row['sample_ms_one_object']:.2f} ms one object", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1))
    if args.plot:
        plot(report, Path(args.plot))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
