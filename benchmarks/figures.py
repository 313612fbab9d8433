"""Explanatory figures of docs/ that are drawn, not measured.

    python benchmarks/figures.py        # docs/img/boxes_convention.png, detector_training.png, shapes.png
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def boxes_convention(path: Path) -> None:
    """A box (x, y, z, dx, dy, dz, heading) seen from above in the LiDAR frame, and two overlapping
    boxes with their intersection polygon (what box_overlap_bev measures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    import lidarops

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    ax = axes[0]
    x, y, dx, dy, h = 2.0, 1.0, 4.0, 1.8, math.radians(30)
    c, s = math.cos(h), math.sin(h)
    corners = np.array([[x + c * u - s * v, y + s * u + c * v]
                        for u, v in ((dx / 2, dy / 2), (-dx / 2, dy / 2), (-dx / 2, -dy / 2), (dx / 2, -dy / 2))])
    ax.fill(corners[:, 0], corners[:, 1], color="tab:blue", alpha=0.25, lw=0)
    ax.plot(*np.vstack([corners, corners[:1]]).T, color="tab:blue")
    ax.annotate("", xy=(x + c * dx / 2, y + s * dx / 2), xytext=(x, y),
                arrowprops=dict(arrowstyle="->", color="tab:blue", lw=2))
    ax.plot([x, x + 3], [y, y], color="gray", ls=":")
    arc = np.linspace(0, h, 30)
    ax.plot(x + 1.5 * np.cos(arc), y + 1.5 * np.sin(arc), color="tab:red")
    ax.text(x + 1.65, y + 0.35, "heading", color="tab:red")
    ax.text(x - 0.3, y - 0.45, "(x, y)")
    mid_long = (corners[0] + corners[3]) / 2
    ax.text(*(corners[1] + corners[0]) / 2 + np.array([-0.7, 0.25]), "dx (length)", rotation=30)
    ax.text(*mid_long + np.array([0.15, -0.3]), "dy", rotation=30)
    ax.annotate("", xy=(-1.5, 3.5), xytext=(-3, 3.5), arrowprops=dict(arrowstyle="->"))
    ax.annotate("", xy=(-3, 5), xytext=(-3, 3.5), arrowprops=dict(arrowstyle="->"))
    ax.text(-1.4, 3.4, "+x (forward)")
    ax.text(-3.2, 5.15, "+y (left)")
    ax.set_title("a box seen from above (LiDAR frame; z up, out of the page)")
    ax.set_aspect("equal")
    ax.set_xlim(-3.5, 6.5)
    ax.set_ylim(-2.5, 5.8)
    ax.grid(alpha=0.3)
    ax = axes[1]
    a = torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]], dtype=torch.float64)
    b = torch.tensor([[1.2, 0.6, 0.0, 3.5, 1.6, 1.5, math.radians(40)]], dtype=torch.float64)
    for box, color, name in ((a, "tab:blue", "a"), (b, "tab:orange", "b")):
        bx, by, _, bdx, bdy, _, bh = box[0].tolist()
        c, s = math.cos(bh), math.sin(bh)
        pts = np.array([[bx + c * u - s * v, by + s * u + c * v]
                        for u, v in ((bdx / 2, bdy / 2), (-bdx / 2, bdy / 2), (-bdx / 2, -bdy / 2), (bdx / 2, -bdy / 2))])
        ax.plot(*np.vstack([pts, pts[:1]]).T, color=color, label=f"box {name}")
    inter = lidarops.box_overlap_bev(a, b).item()
    iou_bev = lidarops.box_iou_bev(a, b).item()
    from shapely.geometry import Polygon  # only to shade the polygon

    def poly(box):
        bx, by, _, bdx, bdy, _, bh = box[0].tolist()
        c, s = math.cos(bh), math.sin(bh)
        return Polygon([(bx + c * u - s * v, by + s * u + c * v)
                        for u, v in ((bdx / 2, bdy / 2), (-bdx / 2, bdy / 2), (-bdx / 2, -bdy / 2), (bdx / 2, -bdy / 2))])

    shared = poly(a).intersection(poly(b))
    ax.fill(*shared.exterior.xy, color="tab:green", alpha=0.4, lw=0, label=f"overlap {inter:.2f} m²")
    ax.set_title(f"box_overlap_bev = {inter:.2f} m², box_iou_bev = {iou_bev:.3f}")
    ax.set_aspect("equal")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")




def _training_figure(name: str):
    """(figure, axes, evaluations) of a shipped detector's training: its loss panel drawn from
    ``benchmarks/results/<name>_train_log.csv``, the evaluations of ``<name>_eval_progress.json``."""
    import csv
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = ROOT / "benchmarks" / "results"
    rows = list(csv.DictReader(open(results / f"{name}_train_log.csv")))
    prog = json.load(open(results / f"{name}_eval_progress.json"))["evaluations"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    _loss_panel(axes[0], rows)
    return fig, axes, prog


def _finish(fig, ax, xlabel: str, ylabel: str, title: str, path: Path) -> None:
    """The AP panel's labels, then the figure written to ``path``."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def _loss_panel(ax, rows: list) -> None:
    """A detector's loss terms per step (``log.csv`` rows of ``lidarops train``), log scale."""
    step = [int(r["step"]) for r in rows]
    for key, label in (("loss", "total"), ("loss_cls", "classification"), ("loss_box", "box"), ("loss_dir", "direction")):
        ax.plot(step, [float(r[key]) for r in rows], label=label, lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("optimisation step (2 GPUs x 8 frames)")
    ax.set_ylabel("loss (per frame)")
    ax.legend(fontsize=8)
    ax.set_title("training loss")


def detector_training(path: Path) -> None:
    """The shipped PointPillars' training: loss terms per step and moderate AP (R40) per evaluation."""
    fig, axes, prog = _training_figure("pointpillars_synth")
    epochs = [p["epoch"] for p in prog]
    for cls, color in (("Car", "tab:blue"), ("Pedestrian", "tab:red"), ("Cyclist", "tab:orange")):
        axes[1].plot(epochs, [p[f"{cls}_3d_moderate_R40"] for p in prog], marker="o", color=color, label=f"{cls} 3D")
        axes[1].plot(epochs, [p[f"{cls}_bev_moderate_R40"] for p in prog], ls="--", color=color, label=f"{cls} BEV")
    axes[1].axhline(75, color="gray", lw=0.8, ls=":")
    axes[1].text(epochs[0], 76, "target: Car 3D 75", fontsize=7, color="gray")
    _finish(fig, axes[1], "epoch (3,100 frames)", "moderate AP, R40 (%)", "validation (500 held-out frames)", path)


def aerial_training(path: Path) -> None:
    """The shipped Aerial-PointPillars' training: loss terms per step and moderate Drone AP (R40, whole view) per
    evaluation, at the strict (0.5) and the loose (0.25) overlap."""
    fig, axes, prog = _training_figure("aerial_pointpillars")
    epochs = [p["epoch"] for p in prog]
    for suffix, overlap, style in (("", "0.5", "-"), ("_loose", "0.25", ":")):
        axes[1].plot(epochs, [p[f"Drone_bev_moderate_R40{suffix}"] for p in prog], ls=style, marker="o",
                     color="tab:blue", label=f"BEV, IoU {overlap}")
        axes[1].plot(epochs, [p[f"Drone_3d_moderate_R40{suffix}"] for p in prog], ls=style, marker="o",
                     color="tab:red", label=f"3D, IoU {overlap}")
    _finish(fig, axes[1], "epoch (4,000 frames)", "moderate Drone AP, R40 (%)",
            "validation (500 held-out frames, whole view)", path)


def shapes(path: Path) -> None:
    """The realism profile's object shapes (lidarops.data.shapes) inside their labelled boxes, as a sensor
    8 m away and 1.7 m up sees them: the returns of a dense fan of rays traced onto each shape."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lidarops.data.shapes import SHAPES, trace

    sizes = {"Car": (4.2, 1.75, 1.5), "Truck": (8.0, 2.5, 3.2), "Bus": (11.0, 2.6, 3.2),
             "Pedestrian": (0.8, 0.6, 1.75), "Cyclist": (1.76, 0.6, 1.73)}
    rng = np.random.default_rng(0)
    fig, axes = plt.subplots(1, len(SHAPES), figsize=(16, 3.4), gridspec_kw={"width_ratios": [4.2, 8, 11, 1.6, 2.4]})
    for ax, (name, size) in zip(axes, sizes.items()):
        half = np.asarray(size) / 2
        o = np.array([-0.3 * half[0], -8.0, 1.7 - half[2]])  # the sensor, beside the object's left flank
        aim = rng.uniform(-1, 1, (80_000, 3)) * half
        d = aim - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-half - o) / d, (half - o) / d
        near = np.minimum(t1, t2).max(1)
        entry = o + d * near[:, None]
        t, hit, cos = trace(name, entry, d, np.tile(half, (len(d), 1)), np.tile([0.3, 0.5, 0.5, 0.5], (len(d), 1)))
        q = entry[hit] + d[hit] * t[hit, None]
        ax.scatter(q[:, 0], q[:, 2], s=0.2, c=cos[hit], cmap="viridis", vmin=0, vmax=1)
        ax.plot([-half[0], half[0], half[0], -half[0], -half[0]], [-half[2], -half[2], half[2], half[2], -half[2]],
                color="tab:red", lw=0.8)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: {100 * hit.mean():.0f} % of the rays", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("shapes inside their labelled boxes (red), seen from the side; colour: cos of incidence", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    print(f"wrote {path}")


def main() -> int:
    boxes_convention(ROOT / "docs" / "img" / "boxes_convention.png")
    detector_training(ROOT / "docs" / "img" / "detector_training.png")
    aerial_training(ROOT / "docs" / "img" / "aerial_training.png")
    shapes(ROOT / "docs" / "img" / "shapes.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
