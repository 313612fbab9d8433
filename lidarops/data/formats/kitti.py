"""KITTI 3D object detection format: ``velodyne/*.bin``, ``label_2/*.txt``, ``calib/*.txt``.

Layout (either the dataset root holding ``training/`` and ``testing/``, or one split directory)::

    training/velodyne/000000.bin   float32 x, y, z, reflectance per point (LiDAR frame)
    training/label_2/000000.txt    one object per line, 15 fields (+ score = 16), rectified camera frame
    training/calib/000000.txt      P0..P3 (3x4), R0_rect (3x3), Tr_velo_to_cam (3x4), Tr_imu_to_velo (3x4)
    ImageSets/train.txt            optional frame id lists

Label fields: ``type truncated occluded alpha left top right bottom h w l x y z rotation_y [score]``
where ``(x, y, z)`` is the *bottom* centre of the box in the rectified camera frame (x right, y down,
z forward) and ``rotation_y`` the heading about the camera y axis.

Box conversion (the convention of common KITTI tool chains): the LiDAR box centre is the bottom
centre mapped by ``inv(R0_rect @ Tr_velo_to_cam)`` and lifted by ``h / 2``; ``dx, dy, dz = l, w, h``;
``yaw = -rotation_y - pi / 2``.  The two directions are exact inverses.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from lidarops.data._checks import read_float32_records, read_text, require_file
from lidarops.data.frame import Frame, class_index
from lidarops.data.geometry import box_corners, wrap_angle

__all__ = [
    "KittiCalib",
    "KittiLabels",
    "read_velodyne",
    "write_velodyne",
    "read_calib",
    "write_calib",
    "read_label",
    "write_label",
    "camera_to_lidar_boxes",
    "lidar_to_camera_boxes",
    "kitti_fov_mask",
    "png_size",
    "forward_fov_mask",
    "KittiDataset",
    "read_kitti_frame",
    "write_kitti_frame",
    "frame_to_kitti_labels",
    "boxes_to_kitti_labels",
    "write_image_sets",
    "KITTI_IMAGE_SIZE",
    "kitti_difficulty",
]

#: (width, height) of KITTI's left colour images (they vary slightly, 1224-1242 x 370-376).
KITTI_IMAGE_SIZE = (1242, 375)


def _require_file(path: str | Path, what: str) -> Path:
    return require_file(path, f"KITTI {what}")


# ---------------------------------------------------------------------------------------------
# velodyne
# ---------------------------------------------------------------------------------------------
def read_velodyne(path: str | Path) -> np.ndarray:
    """Reads a KITTI velodyne scan.

    Args:
        path (str or Path): ``.bin`` file of float32 ``x, y, z, reflectance`` records.

    Returns:
        ndarray float32[N, 4].

    Raises:
        FileNotFoundError: missing file.
        ValueError: a size in bytes that is not a multiple of 16 (a truncated scan, or another format),
            or a NaN or infinite value (the file and the first bad point are named).
    """
    path = _require_file(path, "velodyne")
    return read_float32_records(path, 4, "float32 x, y, z, reflectance", "point")


def write_velodyne(path: str | Path, points: np.ndarray) -> Path:
    """Writes a KITTI velodyne scan.

    Args:
        path (str or Path): output ``.bin`` file.
        points (ndarray[N, 4]): ``x, y, z, reflectance``.

    Returns:
        Path written.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 4:
        raise ValueError(f"points must have shape [N, 4], got {points.shape}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.ascontiguousarray(points, dtype=np.float32).tofile(path)
    return path


# ---------------------------------------------------------------------------------------------
# calibration
# ---------------------------------------------------------------------------------------------
_DEFAULT_P2 = np.array([[721.5377, 0.0, 609.5593, 44.85728], [0.0, 721.5377, 172.854, 0.2163791], [0.0, 0.0, 1.0, 0.002745884]])
_DEFAULT_R0 = np.array([[0.9999239, 0.00983776, -0.007445048], [-0.009869795, 0.9999421, -0.004278459],
                        [0.007402527, 0.004351614, 0.9999631]])
_DEFAULT_TR = np.array([[0.007533745, -0.9999714, -0.000616602, -0.004069766],
                        [0.01480249, 0.0007280733, -0.9998902, -0.07631618],
                        [0.9998621, 0.00752379, 0.01480755, -0.2717806]])


@dataclass
class KittiCalib:
    """KITTI calibration.

    Attributes:
        P (ndarray float64[4, 3, 4]): camera projection matrices P0..P3 (rectified frame -> pixels).
        R0_rect (ndarray float64[3, 3]): rectifying rotation.
        Tr_velo_to_cam (ndarray float64[3, 4]): LiDAR -> (unrectified) camera 0.
        Tr_imu_to_velo (ndarray float64[3, 4]): IMU -> LiDAR.
    """

    P: np.ndarray
    R0_rect: np.ndarray
    Tr_velo_to_cam: np.ndarray
    Tr_imu_to_velo: np.ndarray = field(default_factory=lambda: np.eye(3, 4))

    @property
    def P2(self) -> np.ndarray:
        """Left colour camera projection (3x4)."""
        return self.P[2]

    @staticmethod
    def default() -> "KittiCalib":
        """A typical KITTI calibration (the values of a 2011_09_26 drive)."""
        P = np.stack([_DEFAULT_P2.copy() for _ in range(4)])
        P[0][:, 3] = 0.0
        return KittiCalib(P, _DEFAULT_R0.copy(), _DEFAULT_TR.copy())

    def velo_to_rect_matrix(self) -> np.ndarray:
        """4x4 transform LiDAR -> rectified camera frame (``R0_rect @ Tr_velo_to_cam``)."""
        r0 = np.eye(4)
        r0[:3, :3] = self.R0_rect
        tr = np.eye(4)
        tr[:3, :] = self.Tr_velo_to_cam
        return r0 @ tr

    def velo_to_rect(self, xyz: np.ndarray) -> np.ndarray:
        """LiDAR points (ndarray[N, 3]) -> rectified camera frame (float64[N, 3])."""
        m = self.velo_to_rect_matrix()
        return np.asarray(xyz, dtype=np.float64)[:, :3] @ m[:3, :3].T + m[:3, 3]

    def rect_to_velo(self, xyz: np.ndarray) -> np.ndarray:
        """Rectified camera points (ndarray[N, 3]) -> LiDAR frame (float64[N, 3])."""
        m = np.linalg.inv(self.velo_to_rect_matrix())
        return np.asarray(xyz, dtype=np.float64)[:, :3] @ m[:3, :3].T + m[:3, 3]

    def rect_to_image(self, xyz: np.ndarray, camera: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Projects rectified-frame points.

        Args:
            xyz (ndarray[N, 3]): rectified camera points.
            camera (int): which P matrix.

        Returns:
            uv (ndarray float64[N, 2]) pixel coordinates, depth (ndarray float64[N]).
        """
        xyz = np.asarray(xyz, dtype=np.float64)
        h = np.concatenate([xyz, np.ones((xyz.shape[0], 1))], axis=1) @ self.P[camera].T
        depth = h[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = h[:, :2] / depth[:, None]
        return uv, depth

    def lidar_to_image(self, xyz: np.ndarray, camera: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """LiDAR points -> pixel coordinates and depth (see :meth:`rect_to_image`)."""
        return self.rect_to_image(self.velo_to_rect(xyz), camera)


_CALIB_KEYS = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")


def read_calib(path: str | Path) -> KittiCalib:
    """Reads a KITTI object calibration file.

    Raises:
        FileNotFoundError: missing file.
        ValueError: not UTF-8 text, a missing or repeated key, a wrong number of values, a non-numeric,
            NaN or infinite value, or ``R0_rect @ Tr_velo_to_cam`` not invertible (boxes could not be
            mapped to the LiDAR frame); the file (and line) are named.
    """
    path = _require_file(path, "calib")
    values: dict[str, np.ndarray] = {}
    for line_no, line in enumerate(read_text(path, "KITTI calibration").splitlines(), 1):
        if not line.strip():
            continue
        key, sep, rest = line.partition(":")
        if not sep:
            raise ValueError(f"{path}:{line_no}: expected 'KEY: values', got {line[:60]!r}")
        key = key.strip()
        if key in values:
            raise ValueError(f"{path}:{line_no}: {key!r} is given twice")
        try:
            values[key] = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            raise ValueError(f"{path}:{line_no}: non-numeric value in {key!r}") from None
        if not np.isfinite(values[key]).all():
            raise ValueError(f"{path}:{line_no}: {key!r} holds a NaN or infinite value")
    if "R0_rect" not in values and "R_rect" in values:
        values["R0_rect"] = values["R_rect"]
    if "Tr_velo_to_cam" not in values and "Tr_velo_cam" in values:
        values["Tr_velo_to_cam"] = values["Tr_velo_cam"]
    expected = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12, "Tr_imu_to_velo": 12}
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        if key not in values:
            raise ValueError(f"{path}: calibration key {key!r} missing (found {sorted(values)})")
    for key, n in expected.items():
        if key in values and values[key].size != n:
            raise ValueError(f"{path}: {key} has {values[key].size} values, expected {n}")
    P = np.stack([values.get(f"P{i}", values["P2"]).reshape(3, 4) for i in range(4)])
    imu = values.get("Tr_imu_to_velo", np.eye(3, 4).ravel()).reshape(3, 4)
    calib = KittiCalib(P, values["R0_rect"].reshape(3, 3), values["Tr_velo_to_cam"].reshape(3, 4), imu)
    if not np.linalg.cond(calib.velo_to_rect_matrix()) < 1e12:  # also catches NaN
        raise ValueError(f"{path}: R0_rect @ Tr_velo_to_cam is singular (or nearly), so boxes cannot be mapped "
                         "from the camera to the LiDAR frame")
    return calib


def write_calib(path: str | Path, calib: KittiCalib) -> Path:
    """Writes a KITTI object calibration file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = [(f"P{i}", calib.P[i]) for i in range(4)]
    rows += [("R0_rect", calib.R0_rect), ("Tr_velo_to_cam", calib.Tr_velo_to_cam), ("Tr_imu_to_velo", calib.Tr_imu_to_velo)]
    path.write_text("".join(f"{key}: " + " ".join(f"{v:.12e}" for v in np.ravel(m)) + "\n" for key, m in rows))
    return path


# ---------------------------------------------------------------------------------------------
# labels
# ---------------------------------------------------------------------------------------------
@dataclass
class KittiLabels:
    """The objects of one ``label_2`` file (M rows).

    Attributes:
        names (list[str]): object types.
        truncated (float64[M]), occluded (int64[M]), alpha (float64[M]),
        bbox (float64[M, 4]: left, top, right, bottom), dimensions (float64[M, 3]: h, w, l),
        location (float64[M, 3]: bottom centre, rectified camera frame), rotation_y (float64[M]),
        score (float64[M] or None). Read as KITTI's evaluator reads them (float64), so that a field on a
        difficulty boundary (truncation 0.15, 0.30, 0.50; a 40 or 25 pixel box) lands on the same side.
    """

    names: list[str]
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.names)

    @staticmethod
    def empty() -> "KittiLabels":
        return KittiLabels([], np.zeros(0), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 4)), np.zeros((0, 3)),
                           np.zeros((0, 3)), np.zeros(0))

    def select(self, mask: np.ndarray) -> "KittiLabels":
        idx = np.flatnonzero(np.asarray(mask))
        return KittiLabels([self.names[i] for i in idx], self.truncated[idx], self.occluded[idx], self.alpha[idx],
                           self.bbox[idx], self.dimensions[idx], self.location[idx], self.rotation_y[idx],
                           None if self.score is None else self.score[idx])


_LABEL_FIELDS = ("truncated", "occluded", "alpha", "left", "top", "right", "bottom", "h", "w", "l", "x", "y", "z",
                 "rotation_y", "score")
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def read_label(path: str | Path) -> KittiLabels:
    """Reads a KITTI ``label_2`` file (15 fields per line, or 16 with a score).

    Raises:
        FileNotFoundError: missing file.
        ValueError: not UTF-8 text, a line with the wrong number of fields, a non-numeric, NaN or
            infinite field (or one beyond float32), an ``occluded`` that is not an integer in [-1, 3]
            (file, line and field named).
    """
    path = _require_file(path, "label")
    rows: list[list[str]] = []
    for line_no, line in enumerate(read_text(path, "KITTI label").splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) not in (15, 16):
            raise ValueError(f"{path}:{line_no}: expected 15 or 16 fields, got {len(fields)}: {line[:80]!r}")
        try:
            values = [float(v) for v in fields[1:]]
        except ValueError:
            raise ValueError(f"{path}:{line_no}: non-numeric field in {line[:80]!r}") from None
        for name, v in zip(_LABEL_FIELDS, values):
            if not abs(v) <= _FLOAT32_MAX:  # NaN too
                raise ValueError(f"{path}:{line_no}: {name} is {v!r}; expected a finite number (float32 range)")
        if values[1] not in (-1, 0, 1, 2, 3):
            raise ValueError(f"{path}:{line_no}: occluded is {fields[2]!r}; expected an integer in [-1, 3] "
                             "(0 visible, 1 partly, 2 largely occluded, 3 unknown; -1 in result files)")
        if fields[0] != "DontCare" and not all(v > 0 for v in values[7:10]):
            raise ValueError(f"{path}:{line_no}: a {fields[0]} with dimensions h, w, l = {fields[8:11]}; an object's "
                             "sizes must be > 0 (only DontCare regions carry placeholder sizes)")
        rows.append(fields)
    if not rows:
        return KittiLabels.empty()
    if len({len(r) for r in rows}) > 1:
        raise ValueError(f"{path}: lines mix 15 and 16 fields")
    # float64 throughout, as KITTI's evaluator reads them: a truncation of 0.15 in float32 is above 0.15
    num = np.array([[float(v) for v in r[1:]] for r in rows], dtype=np.float64)
    return KittiLabels(
        names=[r[0] for r in rows],
        truncated=num[:, 0].copy(),
        occluded=num[:, 1].astype(np.int64),
        alpha=num[:, 2].copy(),
        bbox=num[:, 3:7].copy(),
        dimensions=num[:, 7:10].copy(),
        location=num[:, 10:13].copy(),
        rotation_y=num[:, 13].copy(),
        score=num[:, 14].copy() if num.shape[1] == 15 else None,
    )


def write_label(path: str | Path, labels: KittiLabels, decimals: int = 6) -> Path:
    """Writes a KITTI ``label_2`` file.

    Args:
        path (str or Path): output file.
        labels (KittiLabels): objects.
        decimals (int): decimals for the 3D fields (KITTI's own files use 2; more keeps round trips exact).

    Returns:
        Path written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = int(decimals)
    lines = []
    for i, name in enumerate(labels.names):
        if any(c.isspace() for c in name) or not name:
            raise ValueError(f"object type {name!r} must be a non-empty word without spaces")
        fields = [name, f"{labels.truncated[i]:.2f}", f"{int(labels.occluded[i])}", f"{labels.alpha[i]:.{d}f}"]
        fields += [f"{v:.2f}" for v in labels.bbox[i]]
        fields += [f"{v:.{d}f}" for v in labels.dimensions[i]]
        fields += [f"{v:.{d}f}" for v in labels.location[i]]
        fields.append(f"{labels.rotation_y[i]:.{d}f}")
        if labels.score is not None:
            fields.append(f"{labels.score[i]:.4f}")
        lines.append(" ".join(fields))
    path.write_text("\n".join(lines) + ("\n" if lines else ""))
    return path


# ---------------------------------------------------------------------------------------------
# box conversions and field of view
# ---------------------------------------------------------------------------------------------
def camera_to_lidar_boxes(location: np.ndarray, dimensions: np.ndarray, rotation_y: np.ndarray,
                          calib: KittiCalib) -> np.ndarray:
    """KITTI camera-frame boxes -> LiDAR boxes.

    Args:
        location (ndarray[M, 3]): bottom centres, rectified camera frame.
        dimensions (ndarray[M, 3]): ``h, w, l``.
        rotation_y (ndarray[M]): heading about the camera y axis.
        calib (KittiCalib): calibration.

    Returns:
        ndarray float64[M, 7]: ``x, y, z, dx, dy, dz, heading`` (z = box centre).
    """
    location = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dimensions = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    h, w, l = dimensions[:, 0], dimensions[:, 1], dimensions[:, 2]
    bottom = calib.rect_to_velo(location)
    out = np.empty((location.shape[0], 7))
    out[:, :3] = bottom
    out[:, 2] += h / 2
    out[:, 3], out[:, 4], out[:, 5] = l, w, h
    out[:, 6] = wrap_angle(-np.asarray(rotation_y, dtype=np.float64).reshape(-1) - np.pi / 2)
    return out


def lidar_to_camera_boxes(boxes: np.ndarray, calib: KittiCalib) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """LiDAR boxes -> KITTI camera-frame boxes (inverse of :func:`camera_to_lidar_boxes`).

    Args:
        boxes (ndarray[M, 7]): LiDAR boxes.
        calib (KittiCalib): calibration.

    Returns:
        location (float64[M, 3], bottom centres), dimensions (float64[M, 3], h w l), rotation_y (float64[M]).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bottom = boxes[:, :3].copy()
    bottom[:, 2] -= boxes[:, 5] / 2
    location = calib.velo_to_rect(bottom)
    dimensions = np.stack([boxes[:, 5], boxes[:, 4], boxes[:, 3]], axis=1)
    rotation_y = wrap_angle(-boxes[:, 6] - np.pi / 2)
    return location, dimensions, rotation_y


def png_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) of a PNG image from its header, without decoding it; None when ``path`` is not a readable PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def kitti_fov_mask(points: np.ndarray, calib: KittiCalib, image_size: tuple[int, int] = KITTI_IMAGE_SIZE,
                   camera: int = 2) -> np.ndarray:
    """KITTI detection crop: points in front of the camera that project inside the image.

    Args:
        points (ndarray[N, >=3]): LiDAR points.
        calib (KittiCalib): calibration.
        image_size (tuple[int, int]): (width, height) in pixels.
        camera (int): camera index.

    Returns:
        ndarray bool[N].
    """
    # one 3x4 matrix LiDAR -> pixels, applied column by column: no BLAS call, which in a DataLoader worker
    # would start a thread pool per process (the points are many, the matrix tiny)
    m = calib.P[camera] @ calib.velo_to_rect_matrix()
    xyz = np.asarray(points)[:, :3]
    x, y, z = (xyz[:, i].astype(np.float64) for i in range(3))
    u, v, depth = (m[r, 0] * x + m[r, 1] * y + m[r, 2] * z + m[r, 3] for r in range(3))
    w, h = image_size
    with np.errstate(invalid="ignore", divide="ignore"):
        u, v = u / depth, v / depth
        return (depth > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)


def forward_fov_mask(points: np.ndarray, fov_deg: float = 90.0) -> np.ndarray:
    """Simple forward crop: ``x > 0`` and ``|atan2(y, x)| < fov / 2``.

    Args:
        points (ndarray[N, >=2]): LiDAR points.
        fov_deg (float): full horizontal opening, degrees.

    Returns:
        ndarray bool[N].
    """
    points = np.asarray(points)
    return (points[:, 0] > 0) & (np.abs(np.arctan2(points[:, 1], points[:, 0])) < np.deg2rad(fov_deg) / 2)


def _image_boxes(boxes: np.ndarray, calib: KittiCalib, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """2D boxes of 3D boxes (clipped to the image) and the truncation (fraction of the 2D box outside).

    The 2D box spans the projections of the corners more than 0.1 m in front of the camera; a box with a
    corner behind that plane is at least 0.5 truncated, one with none in front has the box (0, 0, 0, 0)
    and truncation 1.
    """
    m = boxes.shape[0]
    bbox = np.zeros((m, 4), np.float32)
    truncated = np.ones(m, np.float32)
    if m == 0:
        return bbox, truncated
    uv, depth = calib.lidar_to_image(box_corners(boxes).reshape(-1, 3))
    u, v = uv[:, 0].reshape(m, 8), uv[:, 1].reshape(m, 8)
    front = depth.reshape(m, 8) > 0.1
    seen = front.any(axis=1)
    w, h = image_size
    with np.errstate(invalid="ignore"):
        full = np.stack([np.where(front, u, np.inf).min(1), np.where(front, v, np.inf).min(1),
                         np.where(front, u, -np.inf).max(1), np.where(front, v, -np.inf).max(1)], axis=1)[seen]
        clipped = np.clip(full, 0, [w - 1, h - 1, w - 1, h - 1])
        area = np.maximum((full[:, 2] - full[:, 0]) * (full[:, 3] - full[:, 1]), 1e-6)
        inside = np.maximum(clipped[:, 2] - clipped[:, 0], 0) * np.maximum(clipped[:, 3] - clipped[:, 1], 0)
        outside = 1.0 - inside / area
        bbox[seen] = clipped
        truncated[seen] = np.where(front[seen].all(axis=1), outside, np.maximum(outside, 0.5))
    return bbox, np.clip(truncated, 0.0, 1.0)


def boxes_to_kitti_labels(boxes: np.ndarray, names: Sequence[str], calib: KittiCalib | None = None,
                          image_size: tuple[int, int] = KITTI_IMAGE_SIZE, visibility: np.ndarray | None = None,
                          score: np.ndarray | None = None) -> KittiLabels:
    """KITTI label rows of LiDAR boxes: the 3D fields, the 2D box, truncation, occlusion and alpha.

    The 2D box is the box's corners projected with ``P2`` and clipped to the image; ``truncated`` is the
    fraction of that projection outside the image; ``occluded`` is 0, 1 or 2 for a ``visibility``
    (fraction of the sensor rays through the box that reach it) > 0.8, > 0.5 or lower, 3 where unknown;
    ``alpha = rotation_y - arctan2(x, z)`` of the camera-frame location (KITTI's observation angle).

    Args:
        boxes (ndarray[M, 7]): LiDAR boxes ``x, y, z, dx, dy, dz, heading``.
        names (sequence of str): object type of each box.
        calib (KittiCalib or None): calibration; default :meth:`KittiCalib.default`.
        image_size (tuple[int, int]): image (width, height).
        visibility (ndarray[M] or None): per-box visibility (NaN: unknown); ``None``: all unknown.
        score (ndarray[M] or None): detection scores (result files).

    Returns:
        KittiLabels.
    """
    calib = calib or KittiCalib.default()
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    location, dimensions, rotation_y = lidar_to_camera_boxes(boxes, calib)
    bbox, truncated = _image_boxes(boxes, calib, image_size)
    vis = np.full(boxes.shape[0], np.nan, np.float32) if visibility is None else np.asarray(visibility)
    occluded = np.where(np.isnan(vis), 3, np.where(vis > 0.8, 0, np.where(vis > 0.5, 1, 2))).astype(np.int64)
    alpha = wrap_angle(rotation_y - np.arctan2(location[:, 0], location[:, 2]))
    return KittiLabels(list(names), truncated, occluded, alpha.astype(np.float32), bbox, dimensions, location,
                       rotation_y, score)


# ---------------------------------------------------------------------------------------------
# frames and datasets
# ---------------------------------------------------------------------------------------------
def _plain_name(name: str) -> bool:
    """A file name without directories (``000042``), not ``..`` or ``a/b``."""
    return bool(name) and name not in (".", "..") and "/" not in name and "\\" not in name and "\0" not in name


def _split_dir(root: str | Path, split: str) -> Path:
    root = Path(root)
    if not root.exists():
        raise FileNotFoundError(f"KITTI directory not found: {root}")
    if (root / "velodyne").is_dir():
        return root
    if (root / split / "velodyne").is_dir():
        return root / split
    if (root / "object" / split / "velodyne").is_dir():
        return root / "object" / split
    raise FileNotFoundError(f"{root} is not a KITTI object directory: no velodyne/ or {split}/velodyne/ inside")


def _frame_from_files(velodyne: Path, label: Path | None, calib_path: Path | None, frame_index: int,
                      unknown: str) -> Frame:
    points = read_velodyne(velodyne)
    calib = read_calib(calib_path) if calib_path is not None and calib_path.is_file() else None
    meta: dict = {"calib": calib, "frame_id": velodyne.stem}
    boxes = np.zeros((0, 7), np.float32)
    labels = np.zeros(0, np.int64)
    if label is not None and label.is_file():
        if calib is None:
            raise FileNotFoundError(f"{label} needs its calibration file {calib_path} to convert boxes to the LiDAR frame")
        kitti = read_label(label)
        keep = np.array([n != "DontCare" for n in kitti.names], dtype=bool)
        index = np.array([class_index(n) for n in kitti.names], dtype=np.int64)
        if unknown == "drop":
            keep &= index >= 0
        elif unknown != "keep":
            raise ValueError("unknown must be 'drop' or 'keep'")
        kitti = kitti.select(keep)
        labels = index[keep]
        boxes = camera_to_lidar_boxes(kitti.location, kitti.dimensions, kitti.rotation_y, calib).astype(np.float32)
        meta["kitti"] = kitti
    return Frame(points=points, t=None, boxes=boxes, labels=labels, frame_index=frame_index, source=str(velodyne),
                 meta=meta)


class KittiDataset:
    """Frames of a KITTI object split (a :class:`~lidarops.data.datasets.FrameSource`).

    Args:
        root (str or Path): the KITTI root (holding ``training/``) or a split directory (holding
            ``velodyne/``).
        split (str): ``"training"`` or ``"testing"`` (used when ``root`` is the dataset root).
        image_set (str or None): name of an ``ImageSets/<name>.txt`` id list (e.g. ``"train"``,
            ``"val"``); ``None`` takes every scan in ``velodyne/``.
        unknown (str): what to do with label types outside :data:`CLASSES` (``Van``, ``Tram``...):
            ``"drop"`` (default) or ``"keep"`` (label -1).  ``DontCare`` is always dropped.
        fov (str or None): ``"camera"`` keeps only points that project into the image, ``None`` keeps all.

    Raises:
        FileNotFoundError: a missing directory or id list.
        ValueError: a bad option, or an id list that is not UTF-8 text or holds an id that is not a
            plain file name (``../x`` would read outside the split).
    """

    def __init__(self, root: str | Path, split: str = "training", image_set: str | None = None,
                 unknown: str = "drop", fov: str | None = None) -> None:
        for name, value in (("split", split), ("image_set", image_set)):
            if value is not None and (not isinstance(value, str) or not _plain_name(value)):
                raise ValueError(f"{name} must be a plain name such as 'training' or 'val', got {value!r}")
        if unknown not in ("drop", "keep"):
            raise ValueError(f"unknown must be 'drop' or 'keep', got {unknown!r}")
        if fov not in (None, "camera"):
            raise ValueError(f"fov must be None or 'camera', got {fov!r}")
        self.split_dir = _split_dir(root, split)
        self.unknown = unknown
        self.fov = fov
        if image_set is not None:
            candidates = [self.split_dir.parent / "ImageSets" / f"{image_set}.txt", self.split_dir / "ImageSets" / f"{image_set}.txt"]
            for c in candidates:
                if c.is_file():
                    self.ids = [line.strip() for line in read_text(c, "KITTI image set").splitlines() if line.strip()]
                    bad = next((i for i in self.ids if not _plain_name(i)), None)
                    if bad is not None:
                        raise ValueError(f"{c}: {bad!r} is not a frame id (a plain file name such as 000042)")
                    break
            else:
                raise FileNotFoundError(f"image set {image_set!r} not found (looked for {', '.join(map(str, candidates))})")
        else:
            self.ids = sorted(p.stem for p in (self.split_dir / "velodyne").glob("*.bin"))

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(f"frame {i} out of range ({len(self)} frames)")
        frame_id = self.ids[i]
        frame = _frame_from_files(
            self.split_dir / "velodyne" / f"{frame_id}.bin",
            self.split_dir / "label_2" / f"{frame_id}.txt",
            self.split_dir / "calib" / f"{frame_id}.txt",
            i % len(self),
            self.unknown,
        )
        if self.fov == "camera" and frame.meta.get("calib") is not None:
            frame = frame.select_points(kitti_fov_mask(frame.points, frame.meta["calib"]))
        return frame

    def __repr__(self) -> str:
        return f"KittiDataset({str(self.split_dir)!r}, {len(self)} frames)"


def read_kitti_frame(path: str | Path, unknown: str = "drop") -> Frame:
    """Reads one KITTI frame from its velodyne ``.bin`` path, with the labels and calibration found
    next to it (``../label_2/<id>.txt``, ``../calib/<id>.txt``) when they exist.

    Raises:
        FileNotFoundError: missing scan.
    """
    path = _require_file(path, "velodyne")
    base = path.parent.parent
    label = base / "label_2" / f"{path.stem}.txt"
    calib = base / "calib" / f"{path.stem}.txt"
    index = int(path.stem) if path.stem.isdigit() else 0
    return _frame_from_files(path, label if label.is_file() else None, calib if calib.is_file() else None, index, unknown)


def write_kitti_frame(
    root: str | Path,
    frame: Frame,
    frame_id: int | str | None = None,
    split: str = "training",
    calib: KittiCalib | None = None,
    image_size: tuple[int, int] = KITTI_IMAGE_SIZE,
    camera_fov_only: bool = True,
    min_points: int = 1,
    decimals: int = 6,
) -> str:
    """Writes a frame as KITTI ``velodyne``, ``label_2`` and ``calib`` files.

    All points are written (KITTI scans are full 360 degree sweeps); the labels are those of
    :func:`frame_to_kitti_labels`: like KITTI's, only boxes whose centre projects into the image
    (``camera_fov_only``) and that hold at least ``min_points`` points are written.  ``occluded`` comes
    from the frame's ``visibility`` when known (0: > 0.8, 1: > 0.5, 2: otherwise, 3: unknown) and
    ``truncated`` from the projected 3D box.

    Args:
        root (str or Path): dataset root (the ``split`` directory is created inside).
        frame (Frame): the frame (boxes in the LiDAR frame).
        frame_id (int, str or None): file stem; default ``frame.frame_index`` as 6 digits.
        split (str): split directory name.
        calib (KittiCalib or None): calibration; default :meth:`KittiCalib.default`.
        image_size (tuple[int, int]): image (width, height) for the 2D boxes and the field of view.
        camera_fov_only (bool): only label boxes in the camera's field of view.
        min_points (int): only label boxes with at least this many points.
        decimals (int): decimals of the 3D label fields.

    Returns:
        str: the frame id written.
    """
    calib = calib or KittiCalib.default()
    frame_id = f"{frame.frame_index:06d}" if frame_id is None else (f"{frame_id:06d}" if isinstance(frame_id, int) else str(frame_id))
    split_dir = Path(root) / split
    write_velodyne(split_dir / "velodyne" / f"{frame_id}.bin", frame.points)
    write_calib(split_dir / "calib" / f"{frame_id}.txt", calib)
    write_label(split_dir / "label_2" / f"{frame_id}.txt",
                frame_to_kitti_labels(frame, calib, image_size, camera_fov_only, min_points), decimals=decimals)
    return frame_id


def frame_to_kitti_labels(frame: Frame, calib: KittiCalib | None = None, image_size: tuple[int, int] = KITTI_IMAGE_SIZE,
                          camera_fov_only: bool = True, min_points: int = 1) -> KittiLabels:
    """The KITTI labels of a frame, as :func:`write_kitti_frame` writes them (and
    :func:`lidarops.eval.kitti.evaluate_lidar` scores them).

    Like KITTI's labels, only boxes whose centre projects into the image (``camera_fov_only``) and that
    hold at least ``min_points`` points get a row; the fields are those of :func:`boxes_to_kitti_labels`
    with the frame's ``visibility``. Labels outside ``frame.class_names`` are named ``Misc``.

    Args:
        frame (Frame): the frame (boxes in the LiDAR frame).
        calib (KittiCalib or None): calibration; default :meth:`KittiCalib.default`.
        image_size (tuple[int, int]): image (width, height) for the 2D boxes and the field of view.
        camera_fov_only (bool): only label boxes in the camera's field of view.
        min_points (int): only label boxes with at least this many points.

    Returns:
        KittiLabels.
    """
    calib = calib or KittiCalib.default()
    keep = frame.num_points_in_box >= min_points
    if camera_fov_only and frame.num_boxes:
        keep &= kitti_fov_mask(frame.boxes[:, :3], calib, image_size)
    idx = np.flatnonzero(keep)
    names = [frame.class_names[i] if 0 <= i < len(frame.class_names) else "Misc" for i in frame.labels[idx]]
    return boxes_to_kitti_labels(frame.boxes[idx], names, calib, image_size, visibility=frame.visibility[idx])


def write_image_sets(root: str | Path, ids: Sequence[str], val_fraction: float = 0.0, seed: int = 0) -> None:
    """Writes ``ImageSets/{train,val,trainval}.txt`` for the given frame ids."""
    root = Path(root)
    (root / "ImageSets").mkdir(parents=True, exist_ok=True)
    ids = list(ids)
    rng = np.random.default_rng(seed)
    val = set(rng.choice(ids, size=int(round(len(ids) * val_fraction)), replace=False).tolist()) if ids and val_fraction > 0 else set()
    train = [i for i in ids if i not in val]
    (root / "ImageSets" / "trainval.txt").write_text("".join(f"{i}\n" for i in ids))
    (root / "ImageSets" / "train.txt").write_text("".join(f"{i}\n" for i in train))
    (root / "ImageSets" / "val.txt").write_text("".join(f"{i}\n" for i in sorted(val)))


def kitti_difficulty(labels: KittiLabels) -> np.ndarray:
    """KITTI's difficulty of each label (OpenPCDet's ``Object3d.get_kitti_obj_level``): 0 easy (2D box
    >= 40 px high, truncation <= 0.15, fully visible), 1 moderate (>= 25 px, <= 0.3, occlusion <= 1),
    2 hard (>= 25 px, <= 0.5, occlusion <= 2), -1 otherwise.

    Returns:
        ndarray int64[M].
    """
    height = labels.bbox[:, 3].astype(np.float64) - labels.bbox[:, 1] + 1
    trunc, occ = labels.truncated, labels.occluded
    out = np.full(len(labels), -1, dtype=np.int64)
    for level, (min_h, max_t, max_o) in reversed(list(enumerate(((40, 0.15, 0), (25, 0.3, 1), (25, 0.5, 2))))):
        out[(height >= min_h) & (trunc <= max_t) & (occ <= max_o)] = level
    return out
