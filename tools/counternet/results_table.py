"""The markdown tables of docs/counternet.md from tools/counternet/evaluate.py's results JSON.

    python tools/counternet/results_table.py results.json              # markdown to stdout
    python tools/counternet/results_table.py results.json --out tables.md

Per model (rows) and class (columns): counting accuracy (share of frames counted exactly), RETRIEVAL-SINGLE at
10 % and 5 % with RETRIEVAL-MULTIPLE beside them, COUNT accuracy, AGGREGATION (SUM over the random groups of
frames) mean absolute difference and mean Q-error; a summary table (means over the classes); and each counter's
counting accuracy against the detector's, class by class (the seed's claim: counting beats the detector by
5-20 %). Percentages are of frames (or queries); the definitions are lidarops.eval.counting's.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def label(name: str, m: dict) -> str:
    kind = m.get("kind")
    if kind == "counternet":
        parts = [f"pt {m['partitions']}"]
        if m.get("delta"):
            parts.append(f"δ {m['delta']:g}")
        if m.get("count_weight") != 1.0:
            parts.append(f"count loss × {m['count_weight']:g}")
        return f"{name} ({', '.join(parts)})"
    if kind == "selection":
        return f"selection over {', '.join(m['members'])} (ε {m['epsilon']:.3g})"
    if kind == "oracle":
        return f"oracle pick of {', '.join(m['members'])} (reads the labels)"
    if kind == "detector":
        return f"PointPillars as a counter (score ≥ {m['score_thresh']:g})"
    return name


def _row(cells) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(header: list[str], rows: list[list]) -> str:
    align = ["---"] + ["---:"] * (len(header) - 1)
    return "\n".join([_row(header), _row(align)] + [_row(r) for r in rows])


def _pct(v: float) -> str:
    return f"{100 * v:.1f}"


def tables(results: dict, order: list[str] | None = None) -> str:
    classes = results["classes"]
    models = {n: m for n, m in results["models"].items() if m.get("evaluation")}
    names = [n for n in (order or list(models)) if n in models]
    ev = {n: models[n]["evaluation"] for n in names}
    lab = {n: label(n, models[n]) for n in names}
    mean = lambda d: sum(d[c] for c in classes) / len(classes)  # noqa: E731
    out = []
    first = ev[names[0]]
    sc = results.get("scoring", {})
    out.append(f"{results['frames']} held-out frames ({results.get('val', '')}), {results.get('device', '')}; "
               f"truth: {results.get('truth', 'the labels')}. COUNT: {first['queries']} queries per class over "
               f"{first['groups']} groups of {first['group_lengths'][0]}-{first['group_lengths'][1]} consecutive "
               f"frames (seed {sc.get('seed', first.get('seed'))}); scored by {results.get('scored_by', '?')}.")

    rows = []
    for n in names:
        e = ev[n]
        rows.append([lab[n], _pct(mean(e["counting_accuracy"])), f"{mean(e['mean_abs_error']):.2f}",
                     _pct(mean(e["retrieval_single"]["0.1"])), _pct(e["retrieval_multiple"]["0.1"]),
                     _pct(mean(e["retrieval_single"]["0.05"])), _pct(e["retrieval_multiple"]["0.05"]),
                     _pct(mean(e["count"]["accuracy"])), f"{mean(e['aggregation_groups']['mean_abs_diff']):.1f}",
                     f"{mean(e['aggregation_groups']['mean_q_error']):.3f}"])
    out.append("**Summary** (means over the seven classes; %, except the absolute differences in objects and the "
               "Q-errors)\n\n" + _table(["model", "counting acc.", "MAE / frame", "R-SINGLE @10%", "R-MULTIPLE @10%",
                                          "R-SINGLE @5%", "R-MULTIPLE @5%", "COUNT acc.", "AGG \\|Σp−Σt\\|",
                                          "AGG Q-error"], rows))

    def per_class(title: str, get, fmt=_pct, extra=None) -> None:
        header = ["model"] + classes + ([extra[0]] if extra else [])
        rows = [[lab[n]] + [fmt(get(ev[n])[c]) for c in classes] + ([extra[1](ev[n])] if extra else [])
                for n in names]
        out.append(f"**{title}**\n\n" + _table(header, rows))

    truth = ev[names[0]]
    out.append("**Objects per frame** (truth: mean and largest count; the tolerances' allowed errors are "
               "floor(tolerance × largest))\n\n" + _table(
                   ["", *classes],
                   [["mean true count", *[f"{truth['mean_true'][c]:.2f}" for c in classes]],
                    ["largest true count", *[str(truth["max_count"][c]) for c in classes]],
                    ["allowed error @10%", *[str(truth["allowed_error"]["0.1"][c]) for c in classes]],
                    ["allowed error @5%", *[str(truth["allowed_error"]["0.05"][c]) for c in classes]]]))
    per_class("Counting accuracy per class (% of frames counted exactly)",
              lambda e: e["counting_accuracy"], extra=("mean", lambda e: _pct(mean(e["counting_accuracy"]))))
    for tol, pc in (("0.1", "10 %"), ("0.05", "5 %")):
        per_class(f"RETRIEVAL-SINGLE @{pc}, and RETRIEVAL-MULTIPLE (all classes at once)",
                  lambda e, t=tol: e["retrieval_single"][t],
                  extra=("MULTIPLE", lambda e, t=tol: _pct(e["retrieval_multiple"][t])))
    per_class("COUNT accuracy (mean min(a, b) / max(a, b) over the queries)", lambda e: e["count"]["accuracy"])
    per_class("AGGREGATION: mean \\|Σp − Σt\\| over the groups (objects)",
              lambda e: e["aggregation_groups"]["mean_abs_diff"],
              fmt=lambda v: f"{v:.1f}")
    per_class("AGGREGATION: mean Q-error over the groups", lambda e: e["aggregation_groups"]["mean_q_error"],
              fmt=lambda v: f"{v:.3f}")
    per_class("AGGREGATION over all the frames: \\|Σp − Σt\\| / Q-error",
              lambda e: {c: (e["aggregation"]["abs_diff"][c], e["aggregation"]["q_error"][c]) for c in classes},
              fmt=lambda v: f"{v[0]} / {v[1]:.3f}")

    det = next((n for n in names if models[n].get("kind") == "detector"), None)
    if det:
        rows = []
        for n in names:
            if n == det or models[n].get("kind") == "detector":
                continue
            a, d = ev[n]["counting_accuracy"], ev[det]["counting_accuracy"]
            rows.append([lab[n]] + [f"{100 * (a[c] - d[c]):+.1f}" for c in classes]
                        + [f"{100 * (mean(a) - mean(d)):+.1f}"])
        out.append(f"**Counting accuracy minus the detector's** ({lab[det]}), percentage points\n\n"
                   + _table(["model", *classes, "mean"], rows))
    sel = next((n for n in names if models[n].get("kind") == "selection"), None)
    if sel:
        m = models[sel]
        share = ", ".join(f"{k} {100 * v:.0f} %" for k, v in m["chosen_share_val"].items())
        train = ", ".join(f"{k} {100 * v:.0f} %" for k, v in zip(m["members"], m["best_share_train"]))
        out.append(f"Model selection: fitted on {m['fit_frames']} training frames (best model there: {train}); "
                   f"ε = {m['epsilon']:.3g} chosen on those frames (fit on 75 %, scored on 25 %); the held-out frames "
                   f"went to {share}.")
    return "\n\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", help="tools/counternet/evaluate.py's JSON")
    ap.add_argument("--models", nargs="*", default=None, help="rows, in this order (default: the JSON's)")
    ap.add_argument("--out", default=None, help="write the markdown here (default: stdout)")
    a = ap.parse_args(argv)
    text = tables(json.loads(Path(a.results).read_text()), a.models)
    if a.out:
        Path(a.out).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
