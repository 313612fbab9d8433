"""CounterNet's experiment scored (issue 38): every counter on held-out frames with the seed's query metrics.

    python tools/counternet/evaluate.py --val /tmp/cn_val --train /tmp/cn_train \\
        --counternet CN=runs/cn.pth CN_pt=runs/cn_pt.pth CN_pt_o=runs/cn_pt_o.pth CN_nocount=runs/cn_nocount.pth \\
        --select CN CN_pt CN_pt_o --detector runs/det/final.pth --device cuda \\
        --out results.json --counts counts.npz
    python tools/counternet/evaluate.py --rescore counts.npz --results results.json --out results.json

The counters, each over the same held-out frames (a KITTI folder, ``--val-split``, read as the trainer reads its
validation frames: the camera's field of view, no augmentation):

* every ``--counternet NAME=CHECKPOINT``: ``CounterNet.predict`` (heatmap peaks above ``max(Otsu, t)``);
* ``selection``: :class:`~lidarops.models.counternet_selection.SelectedCounter` over the ``--select`` models,
  fitted on the first ``--fit-frames`` frames of ``--train`` (training frames: each is assigned to the model
  that counts it best, as the seed does). The Chernoff epsilon is chosen on those training frames alone: the
  selector is fitted on their first 75 % for each epsilon of a grid (multiples of the median ``xi_m / sqrt(n_m)``)
  and the epsilon whose picks count the last 25 % best wins; then the final fit on all of them;
* ``oracle``: each held-out frame counted by the ``--select`` model that counts it best (it reads the labels:
  an upper bound of any selection, not a counter);
* ``detector`` (``--detector``): a PointPillars checkpoint used as a counter, its boxes scoring at least
  ``--score-thresh`` (the first value; further values add rows ``detector_t<NN>``) centred in CounterNet's map,
  per class by name.

The truth of a frame: its labelled objects (the simulator labels the objects the camera sees that hold at least
one point) per class whose centre lies in CounterNet's map (``CounterNet.true_counts``, what its training counts).

The metrics: :func:`lidarops.query.evaluate.evaluate` on a frame index holding the truth (``labels``) and every
counter as a source, when DuckDB is importable; else (the GPU machine has no DuckDB) the same
:class:`~lidarops.query.evaluate.Evaluation` computed from the arrays with the :mod:`lidarops.eval.counting`
functions that ``evaluate`` calls, in the same order, with the same seed (``--rescore`` re-scores the saved counts
through the index afterwards; the dry run checks that both give the same numbers). Beside them the trainer's
:class:`~lidarops.eval.counting.CountingEvaluator` metrics. ``--counts`` saves every counter's per-frame counts.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
CN_CONFIG = ROOT / "configs" / "counternet" / "counternet_synth.yaml"
DET_CONFIG = ROOT / "configs" / "pointpillars" / "pointpillars_synth_all.yaml"
EPSILON_GRID = (0.01, 0.1, 0.3, 1.0, 3.0, 10.0)  # multiples of the median xi_m / sqrt(n_m)


def say(msg: str) -> None:
    print(f"[counternet-eval] {msg}", flush=True)


# ------------------------------------------------------------------------------------------------ data
def frame_batches(root: str, split: str, class_names, config_path: Path, limit: int, batch: int,
                  workers: int) -> tuple[list[dict], list[int]]:
    """The frames of ``root``'s ``split`` as evaluation batches (CPU tensors, read once and kept)."""
    from torch.utils.data import DataLoader

    from lidarops.config import load_config
    from lidarops.data.detection import KittiDetectionDataset, collate_batch

    data_cfg = load_config(str(config_path))["DATA_CONFIG"]
    ds = KittiDetectionDataset(root, split, class_names, data_cfg, training=False)
    if limit:
        ds.ids = ds.ids[:limit]
    if not ds.ids:
        raise SystemExit(f"{root}: split {split!r} holds no frames")
    loader = DataLoader(ds, batch_size=batch, shuffle=False, num_workers=workers, collate_fn=collate_batch)
    out = [{k: b[k] for k in ("points", "gt_boxes", "batch_size", "frame_id")} for b in loader]
    return out, [int(i) for i in ds.ids]


def on(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


# ------------------------------------------------------------------------------------------------ counters
def counternet_counts(model, batches: list[dict], device) -> tuple[np.ndarray, np.ndarray, float]:
    """``(counts (F, C), true counts (F, C), seconds)`` of a CounterNet over the batches."""
    counts, truth = [], []
    t0 = time.perf_counter()
    for b in batches:
        for f in model.predict(on(b, device)):
            counts.append(f["counts"].cpu())
            truth.append(f["true_counts"].cpu())
    _sync(device)
    return torch.stack(counts).numpy(), torch.stack(truth).numpy(), time.perf_counter() - t0


def detector_counts(model, batches: list[dict], device, classes: list[str], point_cloud_range,
                    thresholds: list[float]) -> tuple[dict[float, np.ndarray], float]:
    """Per threshold ``(F, C)`` counts of a detector's boxes scoring at least it, centred in the range's x, y,
    per class of ``classes`` by name (the detector's other classes are not counted)."""
    names = list(model.config.class_names)
    column = torch.tensor([classes.index(n) if n in classes else -1 for n in names])  # detector label - 1 -> column
    x0, y0, _, x1, y1, _ = point_cloud_range
    out: dict[float, list] = {t: [] for t in thresholds}
    t0 = time.perf_counter()
    for b in batches:
        for f in model.predict(on(b, device)):
            boxes, scores, labels = f["boxes"].cpu(), f["scores"].cpu(), f["labels"].cpu()
            col = column[(labels - 1).clamp(min=0)]
            inside = (col >= 0) & (boxes[:, 0] >= x0) & (boxes[:, 0] < x1) & (boxes[:, 1] >= y0) & (boxes[:, 1] < y1)
            for t in thresholds:
                keep = inside & (scores >= t)
                out[t].append(torch.bincount(col[keep], minlength=len(classes)))
    _sync(device)
    return {t: torch.stack(v).numpy() for t, v in out.items()}, time.perf_counter() - t0


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def fit_selection(models: list, names: list[str], batches: list[dict], device, refit: bool = False) -> tuple[Any, dict]:
    """:class:`SelectedCounter` over ``models``, fitted on ``batches`` (training frames), its epsilon chosen on
    them (first 75 % fit, last 25 % scored); ``(counter, report)``. ``refit``: the final fit by
    ``SelectedCounter.fit`` (a second pass of every model over the frames), checked against the search's."""
    from lidarops.models.counternet_selection import SelectedCounter
    from lidarops.models.counting import ChernoffSelector

    probe = SelectedCounter(models)
    errors, feats = [], []
    for b in batches:
        bd = on(b, device)
        per = [torch.stack([(f["counts"] - f["true_counts"]).abs().sum() for f in m.predict(bd)]) for m in models]
        errors.append(torch.stack(per, 1).cpu())
        feats.append(probe.features(bd).double().cpu())
    errors, feats = torch.cat(errors), torch.cat(feats)
    best = torch.argmin(errors, 1)
    F, M = errors.shape
    whole = ChernoffSelector().fit(feats, best, M, 1.0)
    spread = (whole.variances / whole.counts.clamp(min=1)).sqrt()
    scale = float(spread[whole.counts > 0].median()) or 1.0
    split = max(1, int(0.75 * F))
    grid = {}
    if F - split >= 1:
        for k in EPSILON_GRID:
            sel = ChernoffSelector().fit(feats[:split], best[:split], M, k * scale)
            pick = sel.select(feats[split:])
            err = errors[split:][torch.arange(F - split), pick].float().mean()
            grid[k * scale] = {"multiple": k, "mean_error": float(err),
                               "share": torch.bincount(pick, minlength=M).div(F - split).tolist()}
    epsilon = min(grid, key=lambda e: (grid[e]["mean_error"], e)) if grid else scale
    if refit:  # SelectedCounter.fit runs every model over the frames again
        counter = SelectedCounter(models).fit((on(b, device) for b in batches), epsilon=epsilon)
        if not torch.equal(counter.best.cpu(), best):
            raise SystemExit("SelectedCounter.fit assigned the frames differently from the epsilon search")
    else:  # what SelectedCounter.fit computes (the same errors, ties to the lower model, float64 features)
        counter = SelectedCounter(models, selector=ChernoffSelector().fit(feats, best, M, epsilon))
    report = {"members": names, "feature_model": names[0], "fit_frames": F, "epsilon": epsilon,
              "epsilon_scale": scale, "epsilon_grid": [dict(epsilon=e, **v) for e, v in sorted(grid.items())],
              "best_share_train": torch.bincount(best, minlength=M).div(F).tolist(),
              "train_mean_error": {n: float(errors[:, m].float().mean()) for m, n in enumerate(names)},
              "train_oracle_error": float(errors.min(1).values.float().mean()),
              "chernoff_log_factors": counter.selector.log_factors.tolist(),
              "frames_per_model_train": counter.selector.counts.tolist()}
    return counter, report


def selection_counts(counter, batches: list[dict], device) -> tuple[np.ndarray, np.ndarray, float]:
    counts, chosen = [], []
    t0 = time.perf_counter()
    for b in batches:
        for f in counter.predict(on(b, device)):
            counts.append(f["counts"].cpu())
            chosen.append(f["model"])
    _sync(device)
    return torch.stack(counts).numpy(), np.asarray(chosen, np.int64), time.perf_counter() - t0


# ------------------------------------------------------------------------------------------------ scoring
def score(frame_ids: np.ndarray, true: np.ndarray, counts: dict[str, np.ndarray], classes: list[str], seed: int,
          groups: int, queries: int, group_frames: tuple[int, int], use_index: bool) -> tuple[dict, str]:
    """``({source: Evaluation.as_dict()}, how)``: through a frame index and ``lidarops.query.evaluate`` when
    ``use_index``, else from the arrays."""
    kw = dict(classes=classes, seed=seed, groups=groups, queries=queries, group_frames=group_frames)
    if use_index:
        from lidarops.query import FrameIndex
        from lidarops.query.evaluate import evaluate

        def table(a):
            return {"frame_id": frame_ids, **{c: a[:, k].astype(np.int64) for k, c in enumerate(classes)}}

        with tempfile.TemporaryDirectory() as tmp:
            index = FrameIndex.create(Path(tmp) / "index", counts=table(true), source="labels", classes=classes)
            for name, a in counts.items():
                index.append(table(a), source=name)
            return ({name: evaluate(index, source=name, **kw).as_dict() for name in counts},
                    "lidarops.query.evaluate on a FrameIndex (labels + one source per counter)")
    return ({name: evaluate_arrays(a, true, frame_ids, name, **kw).as_dict() for name, a in counts.items()},
            "lidarops.eval.counting, the calls of lidarops.query.evaluate on the arrays (no DuckDB)")


def evaluate_arrays(pred, true, frame_ids, source, classes, seed, groups, queries, group_frames):
    """:func:`lidarops.query.evaluate.evaluate`'s :class:`Evaluation` from ``(F, C)`` arrays of the frames in
    ascending id order (every class scored, as there): the same calls in the same order."""
    from lidarops.eval import counting
    from lidarops.query.evaluate import Evaluation

    order = np.argsort(frame_ids, kind="stable")
    pred, true = np.asarray(pred, np.int64)[order], np.asarray(true, np.int64)[order]
    qs = counting.random_count_queries(true, queries, groups, group_frames, seed)
    count = counting.count_query_accuracy(pred, true, qs)
    whole = counting.aggregation_errors(pred, true)
    grouped = counting.aggregation_errors(pred, true, (qs.starts, qs.lengths))
    tols = (0.1, 0.05)
    return Evaluation(
        source=source, truth="labels", classes=list(classes), frames=int(len(pred)),
        only_source=np.zeros(0, np.int64), only_truth=np.zeros(0, np.int64), tolerances=tols,
        max_count=true.max(0), allowed_error={t: counting.allowed_error(true, t) for t in tols},
        retrieval_single={t: counting.retrieval_single_accuracy(pred, true, t) for t in tols},
        retrieval_multiple={t: counting.retrieval_multiple_accuracy(pred, true, t) for t in tols},
        counting_accuracy=counting.counting_accuracy(pred, true), mean_abs_error=counting.mean_absolute_error(pred, true),
        mean_true=true.mean(0), mean_pred=pred.mean(0),
        count={k: count[k] for k in ("accuracy", "exact", "mean_abs_error")},
        aggregation={k: v[0] for k, v in whole.items()},
        aggregation_groups={"mean_abs_diff": grouped["abs_diff"].mean(0), "mean_q_error": grouped["q_error"].mean(0),
                            "median_q_error": np.median(grouped["q_error"], 0), "max_q_error": grouped["q_error"].max(0)},
        groups=len(qs.starts), group_lengths=(int(qs.lengths.min()), int(qs.lengths.max())), queries=len(qs),
        seed=int(seed))


def duckdb_available() -> bool:
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("duckdb", "pyarrow"))


def counting_evaluator(pred: np.ndarray, true: np.ndarray, classes: list[str]) -> dict:
    from lidarops.eval.counting import CountingEvaluator

    metrics, text = CountingEvaluator(classes)([{"counts": p, "true_counts": t} for p, t in zip(pred, true)], [])
    return {"metrics": metrics, "text": text}


def checkpoint_facts(path: str) -> dict:
    """What a checkpoint says about its training (no weights)."""
    from lidarops.checkpoint import read_checkpoint

    ck = read_checkpoint(path)
    keep = ("model_class", "class_names", "config_path", "train_command", "epoch", "it", "elapsed_s", "frames",
            "data_recipe", "evaluation")
    return {k: ck[k] for k in keep if k in ck}


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, torch.Tensor):
        return v.tolist()
    return v


# ------------------------------------------------------------------------------------------------ main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--val", help="held-out KITTI folder (lidarops data synth ... --seed 5000)")
    ap.add_argument("--val-split", default="trainval", help="its split (default trainval: every frame)")
    ap.add_argument("--max-val-frames", type=int, default=0, help="only the first N held-out frames (0: all)")
    ap.add_argument("--train", help="the training KITTI folder (model selection is fitted on its frames)")
    ap.add_argument("--train-split", default="train")
    ap.add_argument("--fit-frames", type=int, default=400, help="training frames the selection is fitted on")
    ap.add_argument("--refit", action="store_true",
                    help="fit the selection with SelectedCounter.fit (a second pass over the frames), checked equal")
    ap.add_argument("--counternet", nargs="+", default=[], metavar="NAME=CHECKPOINT")
    ap.add_argument("--select", nargs="*", default=[], help="names of --counternet models behind the selection")
    ap.add_argument("--detector", default=None, help="a PointPillars checkpoint used as a counter")
    ap.add_argument("--detector-config", default=str(DET_CONFIG), help="its config (for its DATA_CONFIG)")
    ap.add_argument("--score-thresh", type=float, nargs="+", default=[0.5],
                    help="detector score thresholds: the first is the row 'detector', others 'detector_tNN'")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--workers", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0, help="seed of the random COUNT queries and groups")
    ap.add_argument("--groups", type=int, default=500)
    ap.add_argument("--queries", type=int, default=1000)
    ap.add_argument("--group-frames", default="100:500", help="FEWEST:MOST frames of a group")
    ap.add_argument("--scorer", choices=("auto", "index", "arrays", "both"), default="auto",
                    help="auto: the index when DuckDB is there, else the arrays; both: both, checked equal")
    ap.add_argument("--out", required=True, help="the results JSON")
    ap.add_argument("--counts", default=None, help="save every counter's per-frame counts (.npz)")
    ap.add_argument("--rescore", default=None, metavar="COUNTS_NPZ",
                    help="only re-score saved counts (with --results: their JSON, whose evaluations are replaced)")
    ap.add_argument("--results", default=None, help="with --rescore: the results JSON to update")
    a = ap.parse_args(argv)
    lo, hi = (int(v) for v in a.group_frames.split(":"))
    scorer = a.scorer if a.scorer != "auto" else ("index" if duckdb_available() else "arrays")

    if a.rescore:
        z = np.load(a.rescore, allow_pickle=False)
        classes = [str(c) for c in z["classes"]]
        names = [str(n) for n in z["sources"]]
        counts = {n: z[f"counts_{n}"] for n in names}
        results = json.loads(Path(a.results).read_text()) if a.results else {"models": {n: {} for n in names}}
        results = _score_into(results, z["frame_ids"], z["true"], counts, classes, a, (lo, hi), scorer)
        Path(a.out).write_text(json.dumps(_plain(results), indent=1) + "\n")
        say(f"re-scored {len(names)} sources ({results['scored_by']}); wrote {a.out}")
        return 0

    from lidarops.models import load_model

    device = torch.device(a.device)
    t_start = time.perf_counter()
    cns = {}
    for spec in a.counternet:
        name, _, path = spec.partition("=")
        if not path:
            ap.error(f"--counternet takes NAME=CHECKPOINT, got {spec!r}")
        cns[name] = (load_model(path).to(device).eval(), path)
    for n in a.select:
        if n not in cns:
            ap.error(f"--select {n}: not a --counternet name ({', '.join(cns)})")
    if not cns and not a.detector:
        ap.error("nothing to score: give --counternet and/or --detector")
    from lidarops.models.counternet import ROAD_CLASSES, CounterNet

    first = next(iter(cns.values()))[0] if cns else CounterNet(str(CN_CONFIG)).to(device).eval()
    classes = list(first.config.class_names)
    if sorted(classes) != sorted(ROAD_CLASSES):
        say(f"note: the CounterNets count {classes}, not the seven road classes")

    t = time.perf_counter()
    val, frame_ids = frame_batches(a.val, a.val_split, classes, CN_CONFIG, a.max_val_frames, a.batch, a.workers)
    say(f"{len(frame_ids)} held-out frames of {a.val} ({a.val_split}) read in {time.perf_counter() - t:.1f} s")
    counts: dict[str, np.ndarray] = {}
    models: dict[str, dict] = {}
    true = None
    for name, (model, path) in cns.items():
        c, tr, s = counternet_counts(model, val, device)
        if true is None:
            true = tr
        elif not np.array_equal(true, tr):
            raise SystemExit(f"{name}: its true counts differ from the first model's (another map or classes?)")
        counts[name] = c
        cfg = model.config
        models[name] = {"kind": "counternet", "checkpoint": str(path), "partitions": cfg.partitions, "delta": cfg.delta,
                        "count_weight": cfg.count_weight, "threshold": cfg.threshold, "otsu": cfg.otsu,
                        "count_seconds": round(s, 2), "training": checkpoint_facts(path)}
        say(f"{name}: counted in {s:.1f} s (pt {cfg.partitions}, delta {cfg.delta}, count weight {cfg.count_weight})")
    if true is None:  # no CounterNet: the truth as a CounterNet of the shipped config counts it
        true = torch.cat([first.true_counts(b["gt_boxes"].to(device)).cpu() for b in val]).numpy()

    if a.select:
        t = time.perf_counter()
        fit, _ = frame_batches(a.train, a.train_split, classes, CN_CONFIG, a.fit_frames, a.batch, a.workers)
        members = [cns[n][0] for n in a.select]
        counter, report = fit_selection(members, list(a.select), fit, device, a.refit)
        c, chosen, s = selection_counts(counter, val, device)
        counts["selection"] = c
        report.update(kind="selection", count_seconds=round(s, 2),
                      chosen_share_val={n: float((chosen == m).mean()) for m, n in enumerate(a.select)},
                      fit_seconds=round(time.perf_counter() - t - s, 2))
        models["selection"] = report
        err = np.stack([np.abs(counts[n] - true).sum(1) for n in a.select], 1)
        pick = err.argmin(1)
        counts["oracle"] = np.stack([counts[a.select[m]][f] for f, m in enumerate(pick)])
        models["oracle"] = {"kind": "oracle", "members": list(a.select), "note": "reads the labels: an upper bound",
                            "share": {n: float((pick == m).mean()) for m, n in enumerate(a.select)}}
        say(f"selection over {a.select}: epsilon {report['epsilon']:.4g}, fitted on {report['fit_frames']} training "
            f"frames; held-out frames per model {report['chosen_share_val']}")
        del fit

    if a.detector:
        det = load_model(a.detector).to(device).eval()
        dval, det_ids = frame_batches(a.val, a.val_split, list(det.config.class_names), Path(a.detector_config),
                                      a.max_val_frames, a.batch, a.workers)
        if det_ids != frame_ids:
            raise SystemExit("the detector's held-out frames differ from the CounterNets'")
        rng = first.config.floor_config().point_cloud_range
        by_t, s = detector_counts(det, dval, device, classes, rng, list(a.score_thresh))
        for k, thr in enumerate(a.score_thresh):
            name = "detector" if k == 0 else f"detector_t{int(round(thr * 100)):02d}"
            counts[name] = by_t[thr]
            models[name] = {"kind": "detector", "checkpoint": a.detector, "score_thresh": thr,
                            "detector_classes": list(det.config.class_names), "count_seconds": round(s, 2),
                            "training": checkpoint_facts(a.detector) if k == 0 else "as 'detector'"}
        say(f"detector: counted in {s:.1f} s at score thresholds {a.score_thresh}")
        del dval

    results = {"issue": 38, "classes": classes, "frames": len(frame_ids), "val": a.val, "val_split": a.val_split,
               "truth": "labelled objects (camera field of view, >= 1 point) centred in CounterNet's map, per class",
               "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
               "torch": torch.__version__,
               "command": "python " + " ".join([sys.argv[0]] + list(sys.argv[1:] if argv is None else argv)),
               "models": models}
    results = _score_into(results, np.asarray(frame_ids, np.int64), true, counts, classes, a, (lo, hi), scorer)
    results["seconds"] = round(time.perf_counter() - t_start, 1)
    Path(a.out).write_text(json.dumps(_plain(results), indent=1) + "\n")
    if a.counts:
        names = list(counts)
        np.savez_compressed(a.counts, frame_ids=np.asarray(frame_ids, np.int64), true=true, classes=np.array(classes),
                            sources=np.array(names), **{f"counts_{n}": counts[n] for n in names})
    _print_summary(results)
    say(f"wrote {a.out}" + (f" and {a.counts}" if a.counts else "") + f" ({results['seconds']} s)")
    return 0


def _score_into(results: dict, frame_ids, true, counts, classes, a, group_frames, scorer) -> dict:
    kw = dict(seed=a.seed, groups=a.groups, queries=a.queries, group_frames=group_frames)
    if scorer == "both":
        by_index, how = score(frame_ids, true, counts, classes, use_index=True, **kw)
        by_arrays, _ = score(frame_ids, true, counts, classes, use_index=False, **kw)
        same = json.dumps(_plain(by_index), sort_keys=True) == json.dumps(_plain(by_arrays), sort_keys=True)
        if not same:
            raise SystemExit("the index and the arrays score the counts differently")
        say("the index (lidarops.query.evaluate) and the arrays give identical metrics")
        evals = by_index
    else:
        evals, how = score(frame_ids, true, counts, classes, use_index=scorer == "index", **kw)
    results["scored_by"] = how
    results["scoring"] = {"seed": a.seed, "groups": a.groups, "queries": a.queries, "group_frames": list(group_frames),
                          "tolerances": [0.1, 0.05]}
    for name in counts:
        entry = results["models"].setdefault(name, {})
        entry["evaluation"] = evals[name]
        entry["counting_evaluator"] = counting_evaluator(counts[name], true, classes)["metrics"]
    return results


def _print_summary(results: dict) -> None:
    classes = results["classes"]
    print(f"\n{results['frames']} held-out frames; counting accuracy (% exact) per class, RETRIEVAL-SINGLE / "
          f"-MULTIPLE @10 %, COUNT accuracy, AGGREGATION mean Q-error over the groups")
    head = f"{'model':<14}" + "".join(f"{c[:8]:>9}" for c in classes) + f"{'mean':>8}{'RS@10':>8}{'RM@10':>8}" \
        f"{'COUNT':>8}{'Q':>8}"
    print(head)
    for name, m in results["models"].items():
        ev = m.get("evaluation")
        if not ev:
            continue
        acc = [100 * ev["counting_accuracy"][c] for c in classes]
        rs = np.mean([ev["retrieval_single"]["0.1"][c] for c in classes]) * 100
        cnt = np.mean([ev["count"]["accuracy"][c] for c in classes]) * 100
        q = np.mean([ev["aggregation_groups"]["mean_q_error"][c] for c in classes])
        print(f"{name:<14}" + "".join(f"{v:9.1f}" for v in acc) + f"{np.mean(acc):8.1f}{rs:8.1f}"
              f"{100 * ev['retrieval_multiple']['0.1']:8.1f}{cnt:8.1f}{q:8.3f}")
    print()


if __name__ == "__main__":
    sys.exit(main())
