"""Pictures of frames: bird's-eye views with class-coloured boxes, object clouds, the Risley rosette.

matplotlib is imported inside the functions (``pip install lidarops[data]``); figures are drawn with
the Agg canvas directly, so nothing here touches pyplot's global state.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from lidarops._checks import real
from lidarops.data.frame import CLASS_COLORS, CLASSES, Frame
from lidarops.data.geometry import box_corners

__all__ = ["plot_bev", "save_bev", "save_object", "save_rosette", "new_figure"]


def new_figure(width: float = 8.0, height: float = 8.0, dpi: int = 110):
    """A matplotlib ``Figure`` with an Agg canvas (no pyplot).

    Returns:
        matplotlib.figure.Figure.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'lidarops[data]' or pip install matplotlib") from e
    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    return fig


def _auto_extent(xy: np.ndarray, boxes: np.ndarray, max_extent: float) -> tuple[float, float, float, float]:
    if xy.shape[0]:
        lo = np.percentile(xy, 1, axis=0)
        hi = np.percentile(xy, 99, axis=0)
    else:
        lo, hi = np.array([-10.0, -10.0]), np.array([10.0, 10.0])
    if boxes.shape[0]:
        lo = np.minimum(lo, boxes[:, :2].min(axis=0))
        hi = np.maximum(hi, boxes[:, :2].max(axis=0))
    lo = np.maximum(lo - 3.0, -max_extent)
    hi = np.minimum(hi + 3.0, max_extent)
    return float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])


def plot_bev(
    ax,
    points: np.ndarray,
    boxes: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    class_names: Sequence[str] = CLASSES,
    extent: tuple[float, float, float, float] | None = None,
    color_by: str = "z",
    point_size: float = 0.3,
    max_extent: float = 80.0,
    legend: bool = True,
) -> Any:
    """Draws a bird's-eye view on a matplotlib axes; returns the points' scatter (for a colour key: its
    ``key_label`` names what the colours show).

    Args:
        ax: matplotlib axes.
        points (ndarray[N, >=3]): x, y, z (, intensity).
        boxes (ndarray[M, 7] or None): boxes drawn as footprints with a heading tick.
        labels (ndarray int[M] or None): class indices into ``class_names`` (colours).
        class_names (sequence of str): class list.
        extent (tuple or None): ``(xmin, xmax, ymin, ymax)``; default fits the data within ``max_extent``.
        color_by (str): ``"z"``, ``"intensity"`` or ``"range"``.
        point_size (float): marker size.
        max_extent (float): bound of the automatic extent (m).
        legend (bool): add a legend of the classes present.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    max_extent = real(max_extent, "max_extent", 0, None, lo_open=True, unit=" m")
    if extent is not None:
        extent = tuple(real(v, f"extent[{i}]", unit=" m") for i, v in enumerate(extent))
        if len(extent) != 4 or not (extent[0] < extent[1] and extent[2] < extent[3]):
            raise ValueError(f"extent must be (xmin, xmax, ymin, ymax) with xmin < xmax and ymin < ymax, got {extent}")
    points = np.asarray(points, dtype=np.float32)
    boxes = np.zeros((0, 7), np.float32) if boxes is None else np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    labels = np.full(boxes.shape[0], -1) if labels is None else np.asarray(labels)
    xmin, xmax, ymin, ymax = extent or _auto_extent(points[:, :2], boxes, max_extent)
    inside = (points[:, 0] >= xmin) & (points[:, 0] <= xmax) & (points[:, 1] >= ymin) & (points[:, 1] <= ymax)
    p = points[inside]
    if color_by == "intensity" and p.shape[1] > 3:
        values, cmap, vmin, vmax = p[:, 3], "viridis", 0.0, max(float(np.percentile(p[:, 3], 99)) if len(p) else 1.0, 1e-3)
    elif color_by == "range":
        values, cmap, vmin, vmax = np.linalg.norm(p[:, :3], axis=1), "turbo", 0.0, None
    else:
        zs = p[:, 2] if len(p) else np.zeros(1)
        values, cmap = p[:, 2], "turbo"
        vmin, vmax = float(np.percentile(zs, 2)), float(np.percentile(zs, 98))
    shade = ax.scatter(p[:, 0], p[:, 1], c=values, s=point_size, cmap=cmap, vmin=vmin, vmax=vmax, linewidths=0,
                       rasterized=True)
    shade.key_label = {"intensity": "intensity", "range": "range (m)"}.get(color_by, "height z (m)")
    seen = {}
    for box, label in zip(boxes, labels):
        name = class_names[label] if 0 <= label < len(class_names) else "?"
        color = CLASS_COLORS.get(name, "black")
        world = box_corners(box[None, :7])[0, :4, :2]  # the footprint, counter-clockwise from front-left
        ax.add_patch(Polygon(world, closed=True, fill=False, edgecolor=color, linewidth=1.2))
        front = world[[0, 3]].mean(axis=0)  # the middle of the front edge
        ax.plot([box[0], front[0]], [box[1], front[1]], color=color, linewidth=1.0)
        seen[name] = color
    ax.plot([0], [0], marker="^", color="black", markersize=6)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if legend and seen:
        handles = [Line2D([0], [0], color=col, lw=2, label=name) for name, col in sorted(seen.items())]
        ax.legend(handles=handles, loc="upper right", fontsize=8, framealpha=0.8)
    return shade


def save_bev(frame: Frame, path: str | Path, title: str | None = None, **kwargs) -> Path:
    """Writes a bird's-eye-view PNG of a frame with its boxes coloured by class.

    Args:
        frame (Frame): the frame.
        path (str or Path): output file (``.png``).
        title (str or None): figure title (default: the frame's source and counts).
        **kwargs: passed to :func:`plot_bev`.

    Returns:
        Path of the written file.
    """
    path = Path(path)
    fig = new_figure()
    ax = fig.add_subplot(1, 1, 1)
    shade = plot_bev(ax, frame.points, frame.boxes, frame.labels, frame.class_names, **kwargs)
    fig.colorbar(shade, ax=ax, fraction=0.025, pad=0.01, label=shade.key_label)
    # the figure takes the drawn area's shape (a wide street view would otherwise float in white space)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    width = 10.0
    fig.set_size_inches(width, min(max(width * (y1 - y0) / max(x1 - x0, 1e-9) + 1.2, 3.5), 12.0))
    ax.set_title(title if title is not None else f"{frame.source or 'frame'} #{frame.frame_index}: "
                 f"{frame.num_points} points, {frame.num_boxes} box{'' if frame.num_boxes == 1 else 'es'}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def save_object(points: np.ndarray, path: str | Path, title: str = "") -> Path:
    """Writes a three-view PNG (top, front, side) of one object cloud.

    Args:
        points (ndarray[P, >=3]): the object's points.
        path (str or Path): output file.
        title (str): figure title.

    Returns:
        Path of the written file.
    """
    path = Path(path)
    points = np.asarray(points, dtype=np.float32)
    fig = new_figure(12, 4.4)
    views = (("top (x, y)", 0, 1), ("front (y, z)", 1, 2), ("side (x, z)", 0, 2))
    for i, (name, a, b) in enumerate(views):
        ax = fig.add_subplot(1, 3, i + 1)
        ax.scatter(points[:, a], points[:, b], s=2, c=points[:, 2], cmap="turbo", linewidths=0)
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def save_rosette(sensor, path: str | Path, durations: Sequence[float] = (0.01, 0.05, 0.1)) -> Path:
    """Writes the scan pattern (azimuth vs elevation) of a Risley sensor integrated over several
    durations, side by side.

    Args:
        sensor (RisleyLidar): the sensor.
        path (str or Path): output file.
        durations (sequence of float): integration times in seconds.

    Returns:
        Path of the written file.
    """
    path = Path(path)
    fig = new_figure(4.2 * len(durations), 4.6)
    for i, duration in enumerate(durations):
        k = np.arange(int(round(duration * sensor.firing_rate)))
        az, el = sensor.angles(k)
        ax = fig.add_subplot(1, len(durations), i + 1)
        ax.scatter(np.degrees(az).ravel(), np.degrees(el).ravel(), s=0.15, c="k", linewidths=0, rasterized=True)
        ax.set_xlim(-sensor.fov_h_deg / 2 - 2, sensor.fov_h_deg / 2 + 2)
        ax.set_ylim(-sensor.fov_v_deg / 2 - 2, sensor.fov_v_deg / 2 + 2)
        ax.set_aspect("equal")
        ax.set_title(f"{duration * 1000:.0f} ms: {az.size:,} points", fontsize=10)
        ax.set_xlabel("azimuth (deg)")
        if i == 0:
            ax.set_ylabel("elevation (deg)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
