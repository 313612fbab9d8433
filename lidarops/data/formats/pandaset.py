"""PandaSet-style sequences: per-point timestamped LiDAR frames as gzip-pickled pandas DataFrames.

Layout of one sequence (as PandaSet ships it)::

    <seq>/lidar/00.pkl.gz              DataFrame, columns x, y, z, i, t, d (world frame; i in 0..255,
                                       t in seconds, d = sensor id: 0 spinning Pandar64, 1 front PandarGT)
    <seq>/lidar/poses.json             per frame {"position": {x, y, z}, "heading": {w, x, y, z}}: the
                                       LiDAR pose in the world (world <- LiDAR)
    <seq>/lidar/timestamps.json        per frame timestamp (s)
    <seq>/annotations/cuboids/00.pkl.gz  DataFrame with label, yaw, position.{x,y,z}, dimensions.{x,y,z}
                                       (world frame; dimensions.x = width, dimensions.y = length)

PandaSet's LiDAR ("ego") frame has x to the right and y forward.  The reader returns frames in the
LiDAR frame of :mod:`lidarops.data` (x forward, y left, z up): world points are moved by the inverse
pose, then rotated ``(x, y) <- (y_pandaset, -x_pandaset)``; box yaws follow the convention of
common PandaSet tool chains (``yaw_ego = yaw_world + zrot_world_to_ego``).  Reading pickles runs code
from the file: only open data you trust.
"""
from __future__ import annotations

import gzip
import io
import json
import math
import numbers
import pickle
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from lidarops.data._checks import flag, integer, read_text
from lidarops.data.frame import Frame, class_index
from lidarops.data.geometry import wrap_angle

__all__ = [
    "PANDASET_NAMES",
    "PANDASET_TO_CLASS",
    "PandaSetSequence",
    "read_pandaset_frame",
    "write_pandaset_frame",
    "write_pandaset_sequence",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "world_to_ego",
    "pose_to_matrix",
    "write_pose_files",
]

#: PandaSet label written for each class of :data:`~lidarops.data.CLASSES`.
PANDASET_NAMES = {
    "Car": "Car",
    "Pedestrian": "Pedestrian",
    "Cyclist": "Bicycle",
    "Truck": "Medium-sized Truck",
    "Bus": "Bus",
    "Barrier": "Temporary Construction Barriers",
    "TrafficCone": "Cones",
    "Drone": "Drone",
}

#: Class of each PandaSet label read (labels missing here are dropped or kept as -1).
PANDASET_TO_CLASS = {
    "Car": "Car",
    "Pickup Truck": "Car",
    "Pedestrian": "Pedestrian",
    "Pedestrian with Object": "Pedestrian",
    "Bicycle": "Cyclist",
    "Motorcycle": "Cyclist",
    "Medium-sized Truck": "Truck",
    "Semi-truck": "Truck",
    "Bus": "Bus",
    "Temporary Construction Barriers": "Barrier",
    "Road Barriers": "Barrier",
    "Cones": "TrafficCone",
    "Pylons": "TrafficCone",
    "Drone": "Drone",
}

# our LiDAR frame (x fwd, y left) -> PandaSet LiDAR frame (x right, y fwd)
_OURS_TO_PS = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _pandas():
    try:
        import pandas as pd
    except ImportError as e:  # pragma: no cover
        raise ImportError("PandaSet files need pandas: pip install 'lidarops[data]' or pip install pandas") from e
    return pd


def quaternion_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` (w >= 0) of a rotation matrix."""
    r = np.asarray(r, dtype=np.float64)
    m = np.array([
        [r[0, 0] - r[1, 1] - r[2, 2], r[1, 0] + r[0, 1], r[2, 0] + r[0, 2], r[2, 1] - r[1, 2]],
        [r[1, 0] + r[0, 1], r[1, 1] - r[0, 0] - r[2, 2], r[2, 1] + r[1, 2], r[0, 2] - r[2, 0]],
        [r[2, 0] + r[0, 2], r[2, 1] + r[1, 2], r[2, 2] - r[0, 0] - r[1, 1], r[1, 0] - r[0, 1]],
        [r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1], r[0, 0] + r[1, 1] + r[2, 2]],
    ]) / 3.0
    values, vectors = np.linalg.eigh(m)
    x, y, z, w = vectors[:, np.argmax(values)]
    q = np.array([w, x, y, z])
    return q if q[0] >= 0 else -q


def pose_to_matrix(pose: dict) -> np.ndarray:
    """4x4 world <- LiDAR transform of a PandaSet pose dict.

    Raises:
        ValueError: a missing key, a value that is not a finite number, or a zero quaternion.
    """
    try:
        h, p = pose["heading"], pose["position"]
        q, t = [h["w"], h["x"], h["y"], h["z"]], [p["x"], p["y"], p["z"]]
    except (KeyError, TypeError, IndexError) as e:
        raise ValueError(f"malformed PandaSet pose {pose!r}: {type(e).__name__}: {e}") from None
    if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in q + t):
        raise ValueError(f"malformed PandaSet pose {pose!r}: position and heading must be finite numbers")
    if not any(q):
        raise ValueError(f"malformed PandaSet pose {pose!r}: the heading quaternion is zero")
    out = np.eye(4)
    out[:3, :3] = quaternion_to_matrix(q)
    out[:3, 3] = t
    return out


def _matrix_to_pose(m: np.ndarray) -> dict:
    w, x, y, z = matrix_to_quaternion(m[:3, :3])
    return {"position": {"x": float(m[0, 3]), "y": float(m[1, 3]), "z": float(m[2, 3])},
            "heading": {"w": float(w), "x": float(x), "y": float(y), "z": float(z)}}


def world_to_ego(xyz: np.ndarray, pose: dict | np.ndarray) -> np.ndarray:
    """World points -> PandaSet LiDAR frame (x right, y forward), like the PandaSet devkit's
    ``lidar_points_to_ego``.

    Args:
        xyz (ndarray[N, 3]): world points.
        pose (dict or ndarray[4, 4]): PandaSet pose (world <- LiDAR).

    Returns:
        ndarray float64[N, 3].
    """
    m = pose_to_matrix(pose) if isinstance(pose, dict) else np.asarray(pose, dtype=np.float64)
    return (np.asarray(xyz, dtype=np.float64) - m[:3, 3]) @ m[:3, :3]


def _zrot_world_to_ego(pose_ps: np.ndarray) -> float:
    y_axis = np.array([0.0, 1.0, 0.0]) @ pose_ps[:3, :3]  # world y axis in PandaSet LiDAR coordinates
    return float(np.arctan2(-y_axis[0], y_axis[1]))


#: Largest decompressed ``.pkl.gz`` accepted (a PandaSet frame is about 10 MB).
MAX_PICKLE_BYTES = 1 << 30


def _gunzip(path: Path) -> bytes:
    """The whole decompressed content of a gzip file, CRC-checked, at most :data:`MAX_PICKLE_BYTES`.

    Decompressed whole before unpickling: unpickling straight from the gzip stream stops at the
    pickle's end and never reaches the CRC, so a damaged byte becomes a damaged DataFrame (a row count
    of billions, found when a column is touched) instead of an error.
    """
    out, total = [], 0
    with gzip.GzipFile(fileobj=io.BytesIO(path.read_bytes())) as f:
        while True:
            chunk = f.read(1 << 20)  # chunks: a read(n) would allocate n bytes up front
            if not chunk:
                return b"".join(out)
            total += len(chunk)
            if total > MAX_PICKLE_BYTES:
                raise ValueError(f"{path}: decompresses to more than {MAX_PICKLE_BYTES} bytes; not a PandaSet frame")
            out.append(chunk)


def _read_pickle(path: Path, what: str):
    if not path.is_file():
        raise FileNotFoundError(f"PandaSet {what} file not found: {path}")
    pd = _pandas()
    try:
        data = _gunzip(path)
    except (OSError, EOFError, zlib.error) as e:  # gzip.BadGzipFile is an OSError
        raise ValueError(f"{path}: not a gzip file, or a truncated or damaged one ({type(e).__name__}: {e})") from None
    try:  # pandas' reader carries the compatibility shims for pickles of older pandas versions
        df = pd.read_pickle(io.BytesIO(data), compression=None)
    except (OSError, EOFError, pickle.UnpicklingError, ValueError, AttributeError, ImportError, TypeError,
            ModuleNotFoundError, KeyError, IndexError, MemoryError, OverflowError, RecursionError,
            UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not a pickled DataFrame ({type(e).__name__}: {e})") from None
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"{path}: holds a pickled {type(df).__name__}, not a DataFrame")
    return df


def _read_json(path: Path) -> list:
    if not path.is_file():
        raise FileNotFoundError(f"PandaSet file not found: {path}")
    try:
        data = json.loads(read_text(path, "JSON"))
    except (json.JSONDecodeError, RecursionError) as e:  # RecursionError: '[' nested thousands deep
        raise ValueError(f"{path}: malformed JSON ({type(e).__name__}: {e})") from None
    if not isinstance(data, list):
        raise ValueError(f"{path}: expected a JSON list, got {type(data).__name__}")
    return data


def _poses(path: Path, n: int) -> list:
    """The first ``n`` poses of ``poses.json``, each checked (a bad one names the file and its index)."""
    poses = _read_json(path)
    if len(poses) < n:
        raise ValueError(f"{path}: {len(poses)} poses for {n} frames")
    for i, pose in enumerate(poses[:n]):
        try:
            pose_to_matrix(pose)
        except ValueError as e:
            raise ValueError(f"{path}: pose {i}: {e}") from None
    return poses


def _timestamps(path: Path, n: int) -> list[float]:
    """``timestamps.json``: a number per frame (NaN, as our writer stores an unknown time, is kept)."""
    values = _read_json(path)
    if len(values) < n:
        raise ValueError(f"{path}: {len(values)} timestamps for {n} frames")
    for i, v in enumerate(values):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isinf(v):
            raise ValueError(f"{path}: timestamp {i} is {v!r}; expected a number of seconds")
    return [float(v) for v in values]


def _columns(df, columns: Sequence[str], path: Path) -> np.ndarray:
    """float64[len(df), len(columns)] of numeric, finite columns (a bad one names the file and column)."""
    out = np.empty((len(df), len(columns)))
    for j, c in enumerate(columns):
        try:
            out[:, j] = df[c].to_numpy(dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: column {c!r} is not numeric ({e})") from None
        bad = np.flatnonzero(~np.isfinite(out[:, j]))
        if bad.size:
            raise ValueError(f"{path}: column {c!r} holds {bad.size} NaN or infinite value(s), first in row {int(bad[0])}")
    return out


_LIDAR_COLUMNS = ("x", "y", "z", "i", "t", "d")
_CUBOID_COLUMNS = ("label", "yaw", "position.x", "position.y", "position.z", "dimensions.x", "dimensions.y", "dimensions.z")


class PandaSetSequence:
    """Frames of one PandaSet-style sequence (a :class:`~lidarops.data.datasets.FrameSource`).

    Args:
        path (str or Path): the sequence directory (holding ``lidar/``).
        sensor_id (int or None): keep only points of this sensor (``d`` column); ``None`` keeps all.
        coordinates (str): ``"lidar"`` (default; x forward, y left, as everywhere in lidarops) or
            ``"world"``.
        unknown (str): labels without a class in :data:`PANDASET_TO_CLASS`: ``"drop"`` or ``"keep"``
            (label -1).
        normalize_intensity (bool): divide ``i`` by 255.

    Raises:
        FileNotFoundError: no ``lidar/`` directory or no frames.
        ValueError: a bad option; ``poses.json`` or ``timestamps.json`` that is not UTF-8 JSON, has
            fewer entries than frames, or a pose/timestamp that is not made of finite numbers; when a
            frame is read, a file that is not a gzip-pickled DataFrame (the whole file is decompressed
            and its CRC checked before unpickling, so a damaged byte is an error, not other values), a
            missing or non-numeric column, a NaN or infinite coordinate, intensity or time, a value
            beyond float32 once in the LiDAR frame, or a negative cuboid dimension (the file and column
            named).
    """

    def __init__(self, path: str | Path, sensor_id: int | None = None, coordinates: str = "lidar",
                 unknown: str = "drop", normalize_intensity: bool = True) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"PandaSet sequence not found: {self.path}")
        lidar = self.path / "lidar"
        if not lidar.is_dir():
            raise FileNotFoundError(f"{self.path} is not a PandaSet sequence: no lidar/ directory")
        self.files = sorted(lidar.glob("*.pkl.gz"), key=lambda p: p.name)
        if not self.files:
            raise FileNotFoundError(f"no lidar/*.pkl.gz frames in {self.path}")
        if coordinates not in ("lidar", "world"):
            raise ValueError(f"coordinates must be 'lidar' or 'world', got {coordinates!r}")
        if unknown not in ("drop", "keep"):
            raise ValueError(f"unknown must be 'drop' or 'keep', got {unknown!r}")
        if sensor_id is not None:
            sensor_id = integer(sensor_id, "sensor_id", 0)
        self.sensor_id, self.coordinates, self.unknown = sensor_id, coordinates, unknown
        self.normalize_intensity = flag(normalize_intensity, "normalize_intensity")
        self.poses = _poses(lidar / "poses.json", len(self.files))
        ts = lidar / "timestamps.json"
        self.timestamps = _timestamps(ts, len(self.files)) if ts.is_file() else [float("nan")] * len(self.files)

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range ({len(self)} frames)")
        i %= len(self)
        path = self.files[i]
        df = _read_pickle(path, "lidar")
        missing = [c for c in _LIDAR_COLUMNS if c not in getattr(df, "columns", ())]
        if missing:
            raise ValueError(f"{path}: missing column(s) {missing} (PandaSet lidar frames have {list(_LIDAR_COLUMNS)})")
        if self.sensor_id is not None:
            df = df[df["d"] == self.sensor_id]
        values = _columns(df, ("x", "y", "z", "i", "t"), path)
        xyz, intensity, t = values[:, :3], values[:, 3], values[:, 4].copy()
        pose_ps = pose_to_matrix(self.poses[i])
        pose = pose_ps.copy()
        pose[:3, :3] = pose_ps[:3, :3] @ _OURS_TO_PS  # world <- our LiDAR frame
        if self.coordinates == "lidar":
            xyz = (xyz - pose[:3, 3]) @ pose[:3, :3]
        points = np.empty((xyz.shape[0], 4), np.float32)
        with np.errstate(over="ignore"):  # refused just below, naming the file
            points[:, :3] = xyz
            points[:, 3] = intensity / 255.0 if self.normalize_intensity else intensity
        if not np.isfinite(points).all():
            row = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
            raise ValueError(f"{path}: row {row} lies beyond the float32 range once in the "
                             f"{self.coordinates} frame ({values[row, :4].tolist()})")
        boxes, labels, extra = self._cuboids(i, pose_ps, pose)
        return Frame(points=points, t=t, boxes=boxes, labels=labels, frame_index=i, timestamp=self.timestamps[i],
                     sensor_pose=pose, object_ids=extra.get("ids"), source=str(path),
                     meta={"pose": self.poses[i], "coordinates": self.coordinates, **extra.get("meta", {})})

    def _cuboids(self, i: int, pose_ps: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        path = self.path / "annotations" / "cuboids" / self.files[i].name
        if not path.is_file():
            return np.zeros((0, 7), np.float32), np.zeros(0, np.int64), {}
        df = _read_pickle(path, "cuboids")
        missing = [c for c in _CUBOID_COLUMNS if c not in getattr(df, "columns", ())]
        if missing:
            raise ValueError(f"{path}: missing cuboid column(s) {missing}")
        names = [str(n) for n in df["label"].tolist()]
        index = np.array([class_index(PANDASET_TO_CLASS.get(n, "")) for n in names], dtype=np.int64)
        keep = np.ones(len(names), bool) if self.unknown == "keep" else index >= 0
        values = _columns(df, _CUBOID_COLUMNS[1:], path)[keep]
        yaw, center, dims = values[:, 0], values[:, 1:4], values[:, 4:7]
        if (dims < 0).any():
            row = int(np.flatnonzero((dims < 0).any(axis=1))[0])
            raise ValueError(f"{path}: cuboid {row} has a negative dimension ({dims[row].tolist()})")
        boxes = np.empty((center.shape[0], 7))
        if self.coordinates == "lidar":
            boxes[:, :3] = (center - pose[:3, 3]) @ pose[:3, :3]
            boxes[:, 6] = wrap_angle(yaw + _zrot_world_to_ego(pose_ps))
        else:
            boxes[:, :3] = center
            boxes[:, 6] = wrap_angle(yaw + np.pi / 2)  # world heading of the length axis
        boxes[:, 3], boxes[:, 4], boxes[:, 5] = dims[:, 1], dims[:, 0], dims[:, 2]
        ids = None
        if "uuid" in df.columns:
            uuids = df["uuid"].to_numpy()[keep]
            ids = np.array([int(u) if str(u).lstrip("-").isdigit() else -1 for u in uuids], dtype=np.int64)
        with np.errstate(over="ignore"):
            boxes32 = boxes.astype(np.float32)
        if not np.isfinite(boxes32).all():
            raise ValueError(f"{path}: a cuboid lies beyond the float32 range once in the {self.coordinates} frame")
        return boxes32, index[keep], {"ids": ids, "meta": {"pandaset_labels": [n for n, k in zip(names, keep) if k]}}

    def __repr__(self) -> str:
        return f"PandaSetSequence({str(self.path)!r}, {len(self)} frames)"


def read_pandaset_frame(path: str | Path, **kwargs) -> Frame:
    """Reads one frame from its ``lidar/NN.pkl.gz`` path (see :class:`PandaSetSequence` for options)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PandaSet lidar file not found: {path}")
    seq = PandaSetSequence(path.parent.parent, **kwargs)
    names = [p.name for p in seq.files]
    return seq[names.index(path.name)]


def write_pandaset_frame(seq_dir: str | Path, frame: Frame, index: int, world_xyz: np.ndarray | None = None,
                         sensor_id: int = 0) -> Path:
    """Writes one frame's ``lidar/NN.pkl.gz`` and ``annotations/cuboids/NN.pkl.gz``.

    Poses and timestamps are written by :func:`write_pandaset_sequence` (or by calling
    :func:`write_pose_files` yourself).

    Args:
        seq_dir (str or Path): sequence directory.
        frame (Frame): the frame, points and boxes in its LiDAR frame, ``sensor_pose`` world <- LiDAR.
        index (int): frame number (file ``NN.pkl.gz``).
        world_xyz (ndarray[N, 3] or None): exact world coordinates of the points (e.g. from
            :meth:`Simulator.points_to_world`, which applies each point's own pose); default moves the
            points with ``frame.sensor_pose``.
        sensor_id (int): value of the ``d`` column.

    Returns:
        Path of the lidar file.
    """
    pd = _pandas()
    seq_dir = Path(seq_dir)
    pose = frame.sensor_pose
    if world_xyz is None:
        world_xyz = frame.points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    world_xyz = np.asarray(world_xyz, dtype=np.float64)
    t = frame.t if frame.t is not None else np.full(frame.num_points, frame.timestamp)
    df = pd.DataFrame({
        "x": world_xyz[:, 0], "y": world_xyz[:, 1], "z": world_xyz[:, 2],
        "i": frame.points[:, 3].astype(np.float64) * 255.0,
        "t": np.asarray(t, dtype=np.float64),
        "d": np.full(frame.num_points, sensor_id, dtype=np.int64),
    })
    lidar_path = seq_dir / "lidar" / f"{index:02d}.pkl.gz"
    lidar_path.parent.mkdir(parents=True, exist_ok=True)
    df.to_pickle(lidar_path, compression="gzip")
    pose_ps = pose.copy()
    pose_ps[:3, :3] = pose[:3, :3] @ _OURS_TO_PS.T
    boxes = frame.boxes.astype(np.float64)
    center = boxes[:, :3] @ pose[:3, :3].T + pose[:3, 3]
    yaw = np.mod(boxes[:, 6] - _zrot_world_to_ego(pose_ps), 2 * np.pi)
    names = [PANDASET_NAMES.get(frame.class_names[i], frame.class_names[i]) if 0 <= i < len(frame.class_names) else "Other"
             for i in frame.labels]
    cuboids = pd.DataFrame({
        "uuid": [str(i) for i in frame.object_ids],
        "label": names,
        "yaw": yaw,
        "stationary": np.linalg.norm(frame.velocities, axis=1) < 0.1,
        "camera_used": np.full(frame.num_boxes, -1, dtype=np.int64),
        "position.x": center[:, 0], "position.y": center[:, 1], "position.z": center[:, 2],
        "dimensions.x": boxes[:, 4], "dimensions.y": boxes[:, 3], "dimensions.z": boxes[:, 5],
        "cuboids.sibling_id": ["-"] * frame.num_boxes,
        "cuboids.sensor_id": np.full(frame.num_boxes, -1, dtype=np.int64),
    })
    cub_path = seq_dir / "annotations" / "cuboids" / f"{index:02d}.pkl.gz"
    cub_path.parent.mkdir(parents=True, exist_ok=True)
    cuboids.to_pickle(cub_path, compression="gzip")
    return lidar_path


def write_pose_files(seq_dir: str | Path, poses: Sequence[np.ndarray], timestamps: Sequence[float]) -> None:
    """Writes ``lidar/poses.json`` (world <- PandaSet LiDAR) and ``lidar/timestamps.json``."""
    lidar = Path(seq_dir) / "lidar"
    lidar.mkdir(parents=True, exist_ok=True)
    out = []
    for pose in poses:
        pose_ps = np.asarray(pose, dtype=np.float64).copy()
        pose_ps[:3, :3] = pose_ps[:3, :3] @ _OURS_TO_PS.T
        out.append(_matrix_to_pose(pose_ps))
    (lidar / "poses.json").write_text(json.dumps(out, indent=1))
    (lidar / "timestamps.json").write_text(json.dumps([float(t) for t in timestamps]))


def write_pandaset_sequence(seq_dir: str | Path, frames: Sequence[Frame], world_xyz: Sequence[np.ndarray] | None = None,
                            sensor_id: int = 0) -> Path:
    """Writes frames as one PandaSet-style sequence (lidar frames, cuboids, poses, timestamps).

    Args:
        seq_dir (str or Path): sequence directory (created).
        frames (sequence of Frame): the frames, in order.
        world_xyz (sequence of ndarray[N_i, 3] or None): exact world coordinates per frame (see
            :func:`write_pandaset_frame`).
        sensor_id (int): value of the ``d`` column.

    Returns:
        Path of the sequence directory.
    """
    seq_dir = Path(seq_dir)
    for i, frame in enumerate(frames):
        write_pandaset_frame(seq_dir, frame, i, None if world_xyz is None else world_xyz[i], sensor_id)
    write_pose_files(seq_dir, [f.sensor_pose for f in frames], [f.timestamp for f in frames])
    return seq_dir

