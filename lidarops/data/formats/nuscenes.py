"""nuScenes LiDAR scans: ``samples/LIDAR_TOP/*.pcd.bin`` (and ``sweeps/``), float32 x, y, z, intensity,
ring index per point, in the LIDAR_TOP sensor frame (nuScenes' own axes: x right, y forward, z up).

Only the point files are read here (boxes live in nuScenes' JSON tables).  The file name ends with the
capture time in microseconds (``..._LIDAR_TOP__1532402927647951.pcd.bin``), which becomes the frame's
``timestamp``.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from lidarops.data._checks import flag, read_float32_records, require_file
from lidarops.data.frame import Frame

__all__ = ["read_nuscenes_bin", "write_nuscenes_bin", "NUSCENES_TO_LIDAROPS"]

#: nuScenes LIDAR_TOP axes (x right, y forward) -> lidarops LiDAR axes (x forward, y left).
NUSCENES_TO_LIDAROPS = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

_TIMESTAMP = re.compile(r"__(\d{10,})\.pcd\.bin$")


def read_nuscenes_bin(path: str | Path, x_forward: bool = False, normalize_intensity: bool = False) -> Frame:
    """Reads a nuScenes ``.pcd.bin`` scan.

    Args:
        path (str or Path): the file.
        x_forward (bool): rotate into the lidarops axes (x forward, y left) instead of nuScenes'
            (x right, y forward).
        normalize_intensity (bool): divide the 0..255 intensity by 255.

    Returns:
        Frame with ``points`` (float32[N, 4]), ``ring`` (int16[N]), no boxes, ``t = None`` and
        ``timestamp`` from the file name (s; NaN when the name has none).

    Raises:
        FileNotFoundError: missing file.
        ValueError: a size in bytes that is not a whole number of 20-byte records (a truncated scan, or
            another format), a NaN or infinite value, or a ring index that is not an integer in
            [0, 32767] (the file and the first bad record are named).
    """
    x_forward, normalize_intensity = flag(x_forward, "x_forward"), flag(normalize_intensity, "normalize_intensity")
    path = require_file(path, "nuScenes scan")
    raw = read_float32_records(path, 5, "float32 x, y, z, intensity, ring", "record")
    ring = raw[:, 4]
    bad = (ring != np.round(ring)) | (ring < 0) | (ring > np.iinfo(np.int16).max)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{path}: record {row} has ring index {float(ring[row])!r}; expected an integer in [0, 32767] "
                         "(is this a nuScenes .pcd.bin of 5 floats per point?)")
    points = raw[:, :4].copy()
    if x_forward:
        points[:, :3] = points[:, :3] @ NUSCENES_TO_LIDAROPS.T.astype(np.float32)
    if normalize_intensity:
        points[:, 3] /= 255.0
    match = _TIMESTAMP.search(path.name)
    timestamp = int(match.group(1)) * 1e-6 if match else float("nan")
    return Frame(points=points, t=None, ring=raw[:, 4].astype(np.int16), timestamp=timestamp, source=str(path),
                 meta={"axes": "x forward, y left" if x_forward else "nuScenes LIDAR_TOP: x right, y forward"})


def write_nuscenes_bin(path: str | Path, points: np.ndarray, ring: np.ndarray | None = None) -> Path:
    """Writes a nuScenes-style ``.pcd.bin`` (float32 x, y, z, intensity, ring).

    Args:
        path (str or Path): output file.
        points (ndarray[N, 4]): x, y, z, intensity.
        ring (ndarray[N] or None): ring indices (zeros if None).

    Returns:
        Path written.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must have shape [N, 4], got {points.shape}")
    out = np.zeros((points.shape[0], 5), np.float32)
    out[:, :4] = points
    if ring is not None:
        out[:, 4] = np.asarray(ring, dtype=np.float32)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    out.tofile(path)
    return path
