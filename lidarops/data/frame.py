"""The :class:`Frame` record that every source in :mod:`lidarops.data` returns, and the class list."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lidarops._checks import real

from lidarops.data.geometry import count_points_in_boxes

__all__ = ["CLASSES", "CLASS_COLORS", "Frame", "class_index"]

#: Object classes of the labelled boxes; ``labels`` index into this tuple.
CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist", "Truck", "Bus", "Barrier", "TrafficCone", "Drone")

#: A matplotlib colour per class (BEV plots).
CLASS_COLORS: dict[str, str] = {
    "Car": "tab:blue",
    "Pedestrian": "tab:red",
    "Cyclist": "tab:orange",
    "Truck": "tab:purple",
    "Bus": "tab:brown",
    "Barrier": "tab:gray",
    "TrafficCone": "gold",
    "Drone": "tab:green",
}


def class_index(name: str) -> int:
    """Index of a class name in :data:`CLASSES` (``-1`` when unknown)."""
    try:
        return CLASSES.index(name)
    except ValueError:
        return -1


def _empty(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    return np.zeros(shape, dtype=dtype)


@dataclass
class Frame:
    """One LiDAR frame with its labelled boxes.

    Attributes:
        points (ndarray float32[N, 4]): ``x, y, z, intensity`` in the LiDAR frame (intensity in [0, 1]
            for simulated and KITTI data; raw for other formats unless normalised by the reader).
        t (ndarray float64[N] or None): per-point timestamps in seconds (``None`` for formats without
            them, e.g. KITTI object).
        boxes (ndarray float32[M, 7]): ``x, y, z, dx, dy, dz, heading`` in the LiDAR frame, z = box centre.
        labels (ndarray int64[M]): indices into ``class_names`` (``-1``: a class not in the list).
        num_points_in_box (ndarray int64[M]): points of ``points`` inside each box.
        class_names (tuple[str, ...]): names for ``labels``.
        frame_index (int): index of the frame in its sequence or dataset.
        timestamp (float): reference time of the frame (the time the boxes refer to), seconds.
        sensor_pose (ndarray float64[4, 4]): world-from-LiDAR transform at ``timestamp`` (identity if
            unknown).
        object_ids (ndarray int64[M]): track ids, stable across frames of one sequence (-1: unknown).
        velocities (ndarray float32[M, 3]): box velocities in the LiDAR frame at ``timestamp``, m/s
            (zeros if unknown).
        yaw_rates (ndarray float32[M]): rates of change of the boxes' headings (yaw rates), rad/s.
        visibility (ndarray float32[M]): fraction of the sensor rays through the box that reach it
            (NaN if unknown).
        instance (ndarray int32[N] or None): index into ``boxes`` of the object each point hit, ``-1`` for
            background (simulated frames only).
        surface (ndarray uint8[N] or None): kind of surface hit (see
            :data:`lidarops.data.scene.SURFACE_KINDS`; simulated frames only).
        ring (ndarray int16[N] or None): beam (spinning) or channel (Risley) index.
        source (str): where the frame came from (scenario name or file path).
        meta (dict): anything else (calibration, sensor name, ...).
    """

    points: np.ndarray
    t: np.ndarray | None = None
    boxes: np.ndarray = field(default_factory=lambda: _empty((0, 7), np.float32))
    labels: np.ndarray = field(default_factory=lambda: _empty((0,), np.int64))
    num_points_in_box: np.ndarray | None = None
    class_names: tuple[str, ...] = CLASSES
    frame_index: int = 0
    timestamp: float = 0.0
    sensor_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    object_ids: np.ndarray | None = None
    velocities: np.ndarray | None = None
    yaw_rates: np.ndarray | None = None
    visibility: np.ndarray | None = None
    instance: np.ndarray | None = None
    surface: np.ndarray | None = None
    ring: np.ndarray | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float32).reshape(-1, 4)
        if self.t is not None:
            self.t = np.ascontiguousarray(self.t, dtype=np.float64).reshape(-1)
            if self.t.shape[0] != self.points.shape[0]:
                raise ValueError(f"t has {self.t.shape[0]} entries but points has {self.points.shape[0]} rows")
        self.boxes = np.ascontiguousarray(self.boxes, dtype=np.float32).reshape(-1, 7)
        m = self.boxes.shape[0]
        self.labels = np.ascontiguousarray(self.labels, dtype=np.int64).reshape(-1)
        if self.labels.shape[0] != m:
            raise ValueError(f"labels has {self.labels.shape[0]} entries but boxes has {m} rows")
        if self.num_points_in_box is None:
            self.num_points_in_box = count_points_in_boxes(self.points, self.boxes)
        self.num_points_in_box = np.asarray(self.num_points_in_box, dtype=np.int64).reshape(-1)
        if self.object_ids is None:
            self.object_ids = np.full(m, -1, dtype=np.int64)
        if self.velocities is None:
            self.velocities = np.zeros((m, 3), dtype=np.float32)
        if self.yaw_rates is None:
            self.yaw_rates = np.zeros(m, dtype=np.float32)
        if self.visibility is None:
            self.visibility = np.full(m, np.nan, dtype=np.float32)
        self.object_ids = np.asarray(self.object_ids, dtype=np.int64).reshape(-1)
        self.velocities = np.asarray(self.velocities, dtype=np.float32).reshape(-1, 3)
        self.yaw_rates = np.asarray(self.yaw_rates, dtype=np.float32).reshape(-1)
        self.visibility = np.asarray(self.visibility, dtype=np.float32).reshape(-1)
        self.sensor_pose = np.asarray(self.sensor_pose, dtype=np.float64).reshape(4, 4)
        self.class_names = tuple(self.class_names)

    # ------------------------------------------------------------------ convenience
    @property
    def num_points(self) -> int:
        """Number of points ``N``."""
        return int(self.points.shape[0])

    @property
    def num_boxes(self) -> int:
        """Number of boxes ``M``."""
        return int(self.boxes.shape[0])

    @property
    def names(self) -> list[str]:
        """Class name of each box (``"?"`` for label -1)."""
        return [self.class_names[i] if 0 <= i < len(self.class_names) else "?" for i in self.labels]

    def select_points(self, mask: np.ndarray) -> "Frame":
        """A copy keeping only the points where ``mask`` is true (boxes kept, counts recomputed).

        Args:
            mask (ndarray bool[N] or int indices): points to keep.

        Returns:
            Frame.
        """
        idx = np.asarray(mask)
        per_point = {
            name: (None if getattr(self, name) is None else getattr(self, name)[idx])
            for name in ("t", "instance", "surface", "ring")
        }
        points = self.points[idx]
        return dataclasses.replace(
            self, points=points, num_points_in_box=count_points_in_boxes(points, self.boxes), **per_point
        )

    def select_boxes(self, mask: np.ndarray) -> "Frame":
        """A copy keeping only the boxes where ``mask`` is true (``instance`` renumbered).

        Args:
            mask (ndarray bool[M] or int indices): boxes to keep.

        Returns:
            Frame.
        """
        keep = np.zeros(self.num_boxes, dtype=bool)
        keep[np.asarray(mask)] = True
        instance = self.instance
        if instance is not None:
            new_index = np.full(self.num_boxes + 1, -1, dtype=np.int32)
            new_index[:-1][keep] = np.arange(int(keep.sum()), dtype=np.int32)
            instance = new_index[instance]  # -1 maps to the last entry (-1)
        return dataclasses.replace(
            self,
            boxes=self.boxes[keep],
            labels=self.labels[keep],
            num_points_in_box=self.num_points_in_box[keep],
            object_ids=self.object_ids[keep],
            velocities=self.velocities[keep],
            yaw_rates=self.yaw_rates[keep],
            visibility=self.visibility[keep],
            instance=instance,
        )

    def filter_boxes(self, min_points: int = 1) -> "Frame":
        """A copy keeping the boxes with at least ``min_points`` points."""
        return self.select_boxes(self.num_points_in_box >= min_points)

    def crop_forward(self, fov_deg: float = 90.0) -> "Frame":
        """KITTI-like forward crop: points with ``x > 0`` and ``|atan2(y, x)| < fov/2``; boxes whose
        centre lies in the same wedge.

        Args:
            fov_deg (float): full horizontal opening angle in degrees.

        Returns:
            Frame.
        """
        half = np.deg2rad(real(fov_deg, "fov_deg", 0, 360, lo_open=True, unit=" degrees")) / 2.0

        def inside(xy: np.ndarray) -> np.ndarray:
            return (xy[:, 0] > 0) & (np.abs(np.arctan2(xy[:, 1], xy[:, 0])) < half)

        return self.select_points(inside(self.points[:, :2])).select_boxes(inside(self.boxes[:, :2]))

    def __repr__(self) -> str:
        counts = ", ".join(f"{n}={c}" for n, c in zip(*np.unique(self.names, return_counts=True))) if self.num_boxes else ""
        return (
            f"Frame(source={self.source!r}, index={self.frame_index}, points={self.num_points}, "
            f"t={'yes' if self.t is not None else 'no'}, boxes={self.num_boxes}{' [' + counts + ']' if counts else ''})"
        )
