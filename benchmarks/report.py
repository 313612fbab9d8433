"""Plots and markdown tables from ``benchmarks/results/*.json``.

    python benchmarks/report.py                 # draw docs/img/neighbors_<op>.png and docs/img/sparse_*.png
    python benchmarks/report.py --markdown      # also print the tables: neighbors (docs/ops.md), then every
                                                # other section (sparse, voxelize, sscater, boxes, ...)
    python benchmarks/report.py --markdown --sections voxelize,sparse

Plots: one figure per neighbourhood op (a row of panels per cloud kind, a column per device, grouped
bars of median time per case, log scale, one bar per implementation; skipped peers are marked), and
per CUDA device the sparse-convolution single layers and backbone. Tables: the neighbourhood ops'
per op; any other section as one table per device, a column per field, a timing cell per
implementation (its median, or its status when it was skipped or failed).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import RESULTS_DIR, ROOT, fmt_ms, fmt_ratio, short_status

IMG_DIR = ROOT / "docs" / "img"
OPS = ("fps", "knn", "ball_query", "gather")
TITLES = {"fps": "farthest point sampling", "knn": "k nearest neighbours", "ball_query": "ball query",
          "gather": "gather (grouping)"}
# raw op and forced methods are left out of the plots (they are in the tables)
PLOT_KINDS = ("lidarops", "peer")


def load(results_dir: Path, section: str = "neighbors") -> list[tuple[str, dict, list[dict]]]:
    out = []
    for path in sorted(results_dir.glob("*.json")):
        with open(path) as f:
            data = json.load(f)
        sec = data.get("sections", {}).get(section)
        if sec and sec.get("rows"):
            out.append((data.get("device", path.stem), sec.get("meta", {}), sec["rows"]))
    # CPU first, then GPUs
    out.sort(key=lambda d: (d[1].get("device_type") != "cpu", d[0]))
    return out


def _case_keys(op: str) -> tuple[str, ...]:
    return {"fps": ("B", "N", "K"), "gather": ("B", "N", "M", "k")}.get(op, ("B", "N", "M", "k"))


def _label(op: str, r: dict) -> str:
    def n(v):
        return f"{v // 1000}k" if v >= 1000 and v % 1000 == 0 else (f"{v / 1000:.0f}k" if v >= 1000 else str(v))
    if op == "fps":
        return f"B{r['B']} N{n(r['N'])}\nK{n(r['K'])}"
    return f"B{r['B']} N{n(r['N'])}\nk{r['k']}"


def plot(devices, op: str, out_path: Path) -> bool:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = []
    for dev, meta, rows in devices:
        op_rows = [r for r in rows if r["op"] == op and r.get("kind") in PLOT_KINDS]
        if op in ("knn", "ball_query"):
            op_rows = [r for r in op_rows if r.get("k") == 16]  # k=32 looks alike; it is in the tables
        for cloud in dict.fromkeys(r["cloud"] for r in op_rows):
            panels.append((dev, cloud, [r for r in op_rows if r["cloud"] == cloud]))
    if not panels:
        return False
    clouds = list(dict.fromkeys(p[1] for p in panels))
    devs = list(dict.fromkeys(p[0] for p in panels))
    n_cases = max(len({tuple(r[k] for k in _case_keys(op)) for r in p[2]}) for p in panels)
    width_in = max(7.5, 0.62 * n_cases)
    fig, axes = plt.subplots(len(clouds), len(devs), figsize=(width_in * len(devs), 3.8 * len(clouds)),
                             squeeze=False)
    colors = {}
    palette = ["#d62728", "#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#7f7f7f", "#17becf"]
    for (dev, cloud, rows) in panels:
        ax = axes[clouds.index(cloud)][devs.index(dev)]
        cases = list(dict.fromkeys(tuple(r[k] for k in _case_keys(op)) for r in rows))
        impls = list(dict.fromkeys(r["impl"] for r in rows))
        for name in impls:
            colors.setdefault(name, palette[len(colors) % len(palette)])
        width = 0.8 / max(len(impls), 1)
        ymin = min((r["median_ms"] for r in rows if r.get("median_ms")), default=1.0)
        for j, name in enumerate(impls):
            xs, ys, skipped = [], [], []
            for i, c in enumerate(cases):
                r = next((r for r in rows if r["impl"] == name and tuple(r[k] for k in _case_keys(op)) == c), None)
                if r is None:
                    continue
                x = i - 0.4 + width * (j + 0.5)
                if r.get("median_ms"):
                    xs.append(x)
                    ys.append(r["median_ms"])
                else:
                    skipped.append(x)
            ax.bar(xs, ys, width, color=colors[name], label=name, edgecolor="black" if name == "lidarops" else None,
                   linewidth=0.6)
            for x in skipped:
                ax.text(x, ymin * 0.7, "skip", rotation=90, fontsize=6, ha="center", va="top", color=colors[name])
        ax.set_yscale("log")
        ymax = max((r["median_ms"] for r in rows if r.get("median_ms")), default=10.0)
        ax.set_ylim(ymin * 0.12, ymax * 8)  # room for the legend above the bars
        ax.set_xticks(range(len(cases)))
        first = {tuple(r[k] for k in _case_keys(op)): r for r in rows}
        ax.set_xticklabels([_label(op, first[c]) for c in cases], fontsize=7)
        ax.set_ylabel("median time (ms), log")
        ax.set_title(f"{dev} - {cloud}" if op != "gather" else dev, fontsize=9)
        ax.grid(axis="y", which="major", alpha=0.3)
        ax.legend(fontsize=7, ncol=len(impls), loc="upper left")
    extra = " (k = 16)" if op in ("knn", "ball_query") else ""
    fig.suptitle(f"lidarops {TITLES[op]}{extra}: lower is better", fontsize=11)
    fig.tight_layout()
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=110)
    plt.close(fig)
    return True


def _slug(dev: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in dev.lower()).strip("-")


def plot_sparse(devices, out_dir: Path) -> list[Path]:
    """Per device with sparse-convolution results: the single layers (median ms against the channels, a
    panel per grid and kind: lidarops, spconv and dense cuDNN per precision, the 0.05 ms target) and the
    Sparse-PointPillars backbone (bars per precision, the 1.0 ms fp32 target)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    written = []
    colors = {"fp32": "#1f77b4", "tf32": "#2ca02c", "fp16": "#d62728"}
    for dev, meta, rows in devices:
        layers = [r for r in rows if r.get("section") == "layer"]
        if layers:
            grids = list(dict.fromkeys(r["grid"] for r in layers))
            kinds = list(dict.fromkeys(r["kind"] for r in layers))
            fig, axes = plt.subplots(len(grids), len(kinds), figsize=(5.2 * len(kinds), 3.4 * len(grids)),
                                     squeeze=False)
            for gi, grid in enumerate(grids):
                for ki, kind in enumerate(kinds):
                    ax = axes[gi][ki]
                    sel = [r for r in layers if r["grid"] == grid and r["kind"] == kind]
                    for prec in dict.fromkeys(r["precision"] for r in sel):
                        pr = sorted((r for r in sel if r["precision"] == prec), key=lambda r: r["channels"])
                        for impl, style, label in (("lidarops", "-o", "lidarops op"),
                                                   ("lidarops_module", "-.d", "lidarops module"),
                                                   ("spconv", "--s", "spconv module"), ("dense_cudnn", ":^", "dense")):
                            pts = [(r["channels"], r[impl]["median_ms"]) for r in pr
                                   if isinstance(r.get(impl), dict) and r[impl].get("median_ms")]
                            if pts:
                                ax.plot(*zip(*pts), style, color=colors.get(prec, "k"), ms=4,
                                        lw=1.6 if impl == "lidarops" else 1.0, label=f"{label} {prec}")
                    ax.axhline(0.05, color="k", lw=0.8, ls="-.", label="target 0.05 ms")
                    ax.set_xscale("log", base=2)
                    ax.set_yscale("log")
                    ax.set_xticks([16, 32, 64, 128])
                    ax.set_xticklabels(["16", "32", "64", "128"])
                    sites = sel[0]["sites"] if sel else ""
                    ax.set_title(f"{grid} ({sites} sites), {kind} 3x3" + (" s2" if kind == "conv" else ""), fontsize=9)
                    ax.set_xlabel("Cin = Cout")
                    ax.set_ylabel("median ms per call, log")
                    ax.grid(alpha=0.3, which="both")
                    ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                    ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                    ax.tick_params(axis="y", which="minor", labelsize=6)
            handles, labels = axes[0][0].get_legend_handles_labels()
            fig.legend(handles, labels, loc="upper center", ncol=5, fontsize=7, bbox_to_anchor=(0.5, 1.0))
            fig.suptitle(f"lidarops sparse convolution, single layers, {dev} (commit {meta.get('commit')}): lower is "
                         "better", fontsize=10, y=1.04)
            fig.tight_layout()
            path = out_dir / f"sparse_layers_{_slug(dev)}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=110, bbox_inches="tight")
            plt.close(fig)
            written.append(path)
        pillars = [r for r in rows if r.get("section") == "pillars"]
        if pillars:
            cols = [("lidarops_full", "lidarops, maps built"), ("lidarops_cached_maps", "lidarops, maps cached"),
                    ("lidarops_cached_maps_cuda_graph", "lidarops, maps cached + CUDA graph"),
                    ("dense_cudnn", "dense cuDNN"), ("spconv", "spconv 2.3.8")]
            cols = [c for c in cols if any(isinstance(r.get(c[0]), dict) for r in pillars)]
            fig, ax = plt.subplots(figsize=(7.5, 4.4))
            width = 0.8 / len(cols)
            palette = ["#9ecae1", "#3182bd", "#08519c", "#7f7f7f", "#ff7f0e"]
            for j, (key, label) in enumerate(cols):
                xs, ys = [], []
                for i, r in enumerate(pillars):
                    v = r.get(key)
                    if isinstance(v, dict) and v.get("median_ms"):
                        xs.append(i - 0.4 + width * (j + 0.5))
                        ys.append(v["median_ms"])
                bars = ax.bar(xs, ys, width, color=palette[j % len(palette)], label=label)
                ax.bar_label(bars, fmt="%.2f", fontsize=6)
            ax.axhline(1.0, color="k", lw=0.8, ls="-.", label="fp32 target 1.0 ms")
            ax.set_xticks(range(len(pillars)))
            ax.set_xticklabels([r["precision"] for r in pillars])
            ax.set_yscale("log")
            ax.set_ylabel("median ms per forward, log")
            grid = pillars[0].get("grid")
            ax.set_title(f"Sparse-PointPillars backbone, {grid[0]} x {grid[1]} grid, {pillars[0]['sites']} pillars, "
                         f"{dev}", fontsize=9)
            ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.1))
            ax.grid(axis="y", alpha=0.3, which="both")
            ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
            fig.tight_layout()
            path = out_dir / f"sparse_pillars_{_slug(dev)}.png"
            fig.savefig(path, dpi=110)
            plt.close(fig)
            written.append(path)
    return written


def markdown(devices, ops=OPS) -> str:
    lines = []
    for dev, meta, rows in devices:
        lines.append(f"#### {dev}")
        lines.append("")
        env = ", ".join(f"{k}={v}" for k, v in (meta.get("omp_env") or {}).items())
        load = meta.get("load_avg_1m_start")
        lines.append(f"torch {meta.get('torch')}, {meta.get('threads')} threads, commit {meta.get('commit')}, "
                     f"{meta.get('date')}; full sweep {meta.get('sweep_s')} s"
                     + (f"; {env}" if env else "")
                     + (f"; load average {load} at the start (other work on the machine)" if load and
                        meta.get("device_type") == "cpu" and load > 0.5 * (meta.get("threads") or 1) else "")
                     + f". LiDAR clouds: {meta.get('lidar_generator')}.")
        lines.append("")
        for op in ops:
            op_rows = [r for r in rows if r["op"] == op]
            if not op_rows:
                continue
            keys = {"fps": ("cloud", "B", "N", "K"), "gather": ("B", "N", "M", "k")}.get(
                op, ("cloud", "B", "N", "M", "k") + (("radius", "mean_hits") if op == "ball_query" else ()))
            impls = list(dict.fromkeys(r["impl"] for r in op_rows))
            cases: dict = {}
            for r in op_rows:
                cases.setdefault(tuple(r.get(k) for k in keys), {})[r["impl"]] = r
            hdr = [("hits" if k == "mean_hits" else k) for k in keys] + impls
            lines.append(f"**{op}** (median ms; peer / lidarops in brackets)")
            lines.append("")
            lines.append("| " + " | ".join(hdr) + " |")
            lines.append("|" + "|".join(["---"] * len(keys) + ["---:"] * len(impls)) + "|")
            for ck, cr in cases.items():
                cells = []
                for name in impls:
                    r = cr.get(name)
                    if r is None:
                        cells.append("")
                    elif r.get("median_ms") is None:
                        s = r.get("status", "skipped")
                        cells.append(short_status(s))
                    elif r.get("ratio"):
                        cells.append(f"{fmt_ms(r['median_ms'])} ({fmt_ratio(r['ratio'])})")
                    else:
                        cells.append(f"**{fmt_ms(r['median_ms'])}**" if name == "lidarops" else fmt_ms(r["median_ms"]))
                lines.append("| " + " | ".join(str(c) for c in ck) + " | " + " | ".join(cells) + " |")
            lines.append("")
        targets = meta.get("targets") or []
        if targets:
            lines.append("**targets**")
            lines.append("")
            for tg in targets:
                lines.append(f"- {tg['status']}: {tg['target']}: {tg['detail']}")
            lines.append("")
    return "\n".join(lines)


#: fields left out of the generic tables (in every row, or bookkeeping)
_SKIP_FIELDS = ("commit", "device", "iqr_ms", "input_sets", "section")


def _timing_cell(v: dict) -> str:
    if v.get("median_ms") is not None:
        return fmt_ms(v["median_ms"])
    return short_status(str(v.get("status", "skipped")))


def section_markdown(section: str, devices) -> str:
    """One markdown table per device for any result section: a column per scalar field, a timing cell per
    nested timing (``{"median_ms": ...}`` or ``{"status": ...}``); a row's own ``median_ms`` shows with its
    ``status`` when it has none. Rows are grouped by their ``section`` field when they have one."""
    lines = []
    for dev, meta, rows in devices:
        groups: dict = {}
        for r in rows:
            groups.setdefault(r.get("section", ""), []).append(r)
        for group, grows in groups.items():
            cols: list = []
            for r in grows:
                for k, v in r.items():
                    if k in _SKIP_FIELDS or k in cols:
                        continue
                    if isinstance(v, dict) and not ("median_ms" in v or "status" in v):
                        continue
                    if isinstance(v, list):
                        continue
                    cols.append(k)
            title = f"{section}" + (f" / {group}" if group else "")
            lines.append(f"#### {dev}: {title}")
            lines.append("")
            lines.append(f"torch {meta.get('torch')}, {meta.get('threads')} threads, commit {meta.get('commit')}, "
                         f"{meta.get('date')}." if meta else "(no run metadata in the result file)")
            lines.append("")
            lines.append("| " + " | ".join(cols) + " |")
            lines.append("|" + "|".join("---" for _ in cols) + "|")
            for r in grows:
                cells = []
                for k in cols:
                    v = r.get(k)
                    if isinstance(v, dict):
                        cells.append(_timing_cell(v))
                    elif k == "median_ms" and v is None:
                        cells.append(short_status(str(r.get("status", "skipped"))))
                    elif isinstance(v, float):
                        cells.append(fmt_ratio(v) if "ratio" in k or "speedup" in k else fmt_ms(v))
                    else:
                        cells.append("" if v is None else str(v))
                lines.append("| " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def sections_in(results_dir: Path) -> list[str]:
    """Every section name in the result files, in first-seen order."""
    names: dict = {}
    for path in sorted(results_dir.glob("*.json")):
        with open(path) as f:
            names.update(dict.fromkeys(json.load(f).get("sections", {})))
    return list(names)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", default=str(RESULTS_DIR), help="folder of result files")
    ap.add_argument("--out", default=str(IMG_DIR), help="folder for the plots")
    ap.add_argument("--markdown", action="store_true", help="print markdown tables (neighbors: docs/ops.md)")
    ap.add_argument("--sections", default="all", help="comma-separated sections for --markdown (default: all)")
    ap.add_argument("--no-plots", action="store_true", help="tables only")
    a = ap.parse_args(argv)
    results = Path(a.results)
    found = sections_in(results)
    if not found:
        print(f"no results in {a.results}; run a benchmark with --json first (benchmarks/bm_*.py)", file=sys.stderr)
        return 1
    devices = load(results)
    if not a.no_plots:
        if not devices:
            print(f"no neighbors results in {a.results} (benchmarks/bm_neighbors.py --json): no neighbors plots",
                  file=sys.stderr)
        for op in OPS:
            path = Path(a.out) / f"neighbors_{op}.png"
            if devices and plot(devices, op, path):
                print(f"wrote {path}")
        for path in plot_sparse([d for d in load(results, "sparse") if d[1].get("device_type") == "cuda"],
                                Path(a.out)):
            print(f"wrote {path}")
    if a.markdown:
        wanted = found if a.sections == "all" else [x for x in a.sections.split(",") if x]
        for name in wanted:
            print()
            if name == "neighbors":
                print(markdown(devices))
            else:
                print(section_markdown(name, load(results, name)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
