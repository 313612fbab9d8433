"""Detection augmentation on NumPy frames, as OpenPCDet's ``DATA_AUGMENTOR`` does it: world flips,
rotation and scaling (:func:`flip_along_x`, :func:`flip_along_y`, :func:`rotate_world`,
:func:`scale_world`), and ground-truth sampling (:class:`GtDatabase` built by :func:`build_gt_database`,
pasted by :class:`GtSampler`). Boxes are ``(M, 7 + C)`` ``x, y, z, dx, dy, dz, heading, ...``;
:class:`~lidarops.data.detection.KittiDetectionDataset` applies them in a config's order.
"""
from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np

from lidarops.conventions import KITTI_CLASSES
from lidarops.data._checks import read_npz
from lidarops.data.formats.kitti import (
    KittiDataset,
    KittiLabels,
    camera_to_lidar_boxes,
    kitti_difficulty,
    read_calib,
    read_label,
    read_velodyne,
)
from lidarops.data.geometry import box_index_of_points, points_in_boxes_mask

if TYPE_CHECKING:
    from lidarops.data.detection import KittiDetectionDataset

__all__ = ["flip_along_x", "flip_along_y", "rotate_world", "scale_world", "GtDatabase", "GtSampler",
           "build_gt_database", "BOX_MARGIN_XY"]

#: OpenPCDet's ``points_in_boxes_cpu`` -- what its ``create_groundtruth_database`` gathers an object's points
#: with, and its gt sampling clears the scene under the pasted boxes with -- counts a point in a box when
#: ``|local x| < dx / 2 + 0.01``, ``|local y| < dy / 2 + 0.01`` (metres) and ``|z - z_centre| <= dz / 2``.
#: The centimetre takes in the surface points that range noise puts just outside the labelled faces: without
#: it an object of ``lidarops data synth`` frames keeps about three quarters of its points.
BOX_MARGIN_XY = 0.01


def _counts(entries: Mapping[str, int] | Sequence[str] | None, what: str) -> dict[str, int]:
    """``{'Car': 15}`` from ``['Car:15', ...]`` (OpenPCDet's notation) or a mapping."""
    if entries is None:
        return {}
    if isinstance(entries, Mapping):
        items = list(entries.items())
    else:
        items = []
        for entry in entries:
            name, sep, num = str(entry).partition(":")
            if not sep:
                raise ValueError(f"{what} entries look like 'Car:15', got {entry!r}")
            items.append((name.strip(), num))
    out = {}
    for name, num in items:
        try:
            value = int(num)
        except (TypeError, ValueError):
            raise ValueError(f"{what}: {name!r} needs an integer count, got {num!r}") from None
        if value < 0:
            raise ValueError(f"{what}: {name!r} needs a count >= 0, got {value}")
        out[str(name)] = value
    return out



def flip_along_x(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror in the x axis (OpenPCDet's ``random_flip_along_x`` when it fires): ``y -> -y``,
    ``heading -> -heading``. Returns new arrays."""
    points, boxes = points.copy(), boxes.copy()
    points[:, 1] = -points[:, 1]
    boxes[:, 1] = -boxes[:, 1]
    boxes[:, 6] = -boxes[:, 6]
    return points, boxes


def flip_along_y(points: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mirror in the y axis (``random_flip_along_y``): ``x -> -x``, ``heading -> -(heading + pi)``."""
    points, boxes = points.copy(), boxes.copy()
    points[:, 0] = -points[:, 0]
    boxes[:, 0] = -boxes[:, 0]
    boxes[:, 6] = -(boxes[:, 6] + np.pi)
    return points, boxes


def rotate_world(points: np.ndarray, boxes: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotation about +z by ``angle`` (counter-clockwise seen from above, x towards y; OpenPCDet's
    ``global_rotation``): points and box centres rotate, headings grow by ``angle`` (not wrapped).
    Computed in float64. Returns new arrays of the input dtypes."""
    c, s = math.cos(angle), math.sin(angle)

    def turn(xy: np.ndarray) -> np.ndarray:
        x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
        return np.stack([c * x - s * y, s * x + c * y], axis=1)

    points, boxes = points.copy(), boxes.copy()
    points[:, :2] = turn(points)
    boxes[:, :2] = turn(boxes)
    boxes[:, 6] = boxes[:, 6].astype(np.float64) + angle
    return points, boxes


def scale_world(points: np.ndarray, boxes: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Uniform scaling about the sensor (``global_scaling``): point coordinates, box centres and sizes."""
    points, boxes = points.copy(), boxes.copy()
    points[:, :3] = points[:, :3].astype(np.float64) * scale
    boxes[:, :6] = boxes[:, :6].astype(np.float64) * scale
    return points, boxes


def _iou_bev(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """:func:`lidarops.box_iou_bev` on NumPy boxes (float32, as the op's callers in training)."""
    import torch

    from lidarops.ops.boxes import box_iou_bev

    if a.shape[0] == 0 or b.shape[0] == 0:
        return np.zeros((a.shape[0], b.shape[0]), dtype=np.float32)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x[:, :7], dtype=np.float32))  # noqa: E731
    return box_iou_bev(t(a), t(b)).numpy()


# ---------------------------------------------------------------------------------------------
# ground-truth database and sampler
# ---------------------------------------------------------------------------------------------
@dataclass
class GtDatabase:
    """The labelled objects of a set of frames with their points (OpenPCDet's ``gt_database`` +
    ``kitti_dbinfos_*.pkl`` in one file).

    Attributes:
        points (ndarray float32[P, 4]): the points of every object, object after object, with x, y, z
            relative to the box centre (as OpenPCDet stores them).
        offsets (ndarray int64[K + 1]): object ``i`` owns ``points[offsets[i]:offsets[i + 1]]``.
        boxes (ndarray float32[K, 7]): LiDAR boxes ``x, y, z, dx, dy, dz, heading`` in their frame.
        names (ndarray str[K]): object types.
        num_points (ndarray int64[K]): points of each object.
        difficulty (ndarray int64[K]): :func:`kitti_difficulty` (-1: unknown).
        frame_ids (ndarray str[K]): frame of each object.
        gt_index (ndarray int64[K]): row of the object in its label file.
        source_ids (ndarray str[F]): the frames the database was built from.
        margin (float): metres added to each box's half-length and half-width (not its height) when its
            points were gathered (:data:`BOX_MARGIN_XY`, OpenPCDet's; files written before lidarops recorded
            it were gathered with 0.0).
    """

    points: np.ndarray
    offsets: np.ndarray
    boxes: np.ndarray
    names: np.ndarray
    num_points: np.ndarray
    difficulty: np.ndarray
    frame_ids: np.ndarray
    gt_index: np.ndarray
    source_ids: np.ndarray
    margin: float = 0.0

    _FIELDS = ("points", "offsets", "boxes", "names", "num_points", "difficulty", "frame_ids", "gt_index", "source_ids")

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    def object_points(self, i: int) -> np.ndarray:
        """Points of object ``i`` back at its box centre (float32[n, 4])."""
        pts = self.points[self.offsets[i]:self.offsets[i + 1]].copy()
        pts[:, :3] += self.boxes[i, :3]
        return pts

    def save(self, path: str | Path) -> Path:
        """Writes an uncompressed ``.npz`` (atomically: a temporary file renamed)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".npz", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                np.savez(f, **{name: getattr(self, name) for name in self._FIELDS}, margin=np.float64(self.margin))
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | Path) -> "GtDatabase":
        """Reads a database written by :meth:`save`.

        Raises:
            FileNotFoundError: missing file.
            ValueError: a damaged or truncated ``.npz``, missing arrays, or arrays that do not describe
                the same objects (the file is named).
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"gt database not found: {path}")
        what = "a lidarops gt database"
        try:
            data = read_npz(path, cls._FIELDS + ("margin",), what)
        except ValueError as e:
            if "missing ['margin']" not in str(e):
                raise
            data = read_npz(path, cls._FIELDS, what)  # written before the margin was recorded: gathered without
            data["margin"] = np.float64(0.0)
        m = data["boxes"].shape[0] if data["boxes"].ndim == 2 else -1
        off = data["offsets"]
        problem = None
        if m < 0 or data["boxes"].shape[1] != 7 or data["boxes"].dtype.kind != "f":
            problem = f"boxes must be float [M, 7], got {data['boxes'].dtype} {data['boxes'].shape}"
        elif data["points"].ndim != 2 or data["points"].shape[1] != 4 or data["points"].dtype.kind != "f":
            problem = f"points must be float [P, 4], got {data['points'].dtype} {data['points'].shape}"
        elif any(data[k].shape != (m,) for k in ("names", "num_points", "difficulty", "frame_ids", "gt_index")):
            problem = f"names, num_points, difficulty, frame_ids and gt_index must hold one entry per box ({m})"
        elif off.shape != (m + 1,) or off.dtype.kind not in "iu" or (m >= 0 and (off[0] != 0 or (np.diff(off) < 0).any()
                                                                             or off[-1] != data["points"].shape[0])):
            problem = f"offsets must rise from 0 to the {data['points'].shape[0]} points in {m + 1} steps"
        elif data["source_ids"].ndim != 1:
            problem = "source_ids must be 1-D"
        elif data["margin"].shape != () or data["margin"].dtype.kind != "f" or not 0 <= float(data["margin"]) < 1:
            problem = f"margin must be a float scalar in [0, 1) metres, got {data['margin']!r}"
        if problem:
            raise ValueError(f"{path}: not a gt database written by GtDatabase.save ({problem})")
        data["margin"] = float(data["margin"])
        return cls(**data)

    def __repr__(self) -> str:
        names, counts = np.unique(self.names, return_counts=True)
        summary = ", ".join(f"{n}={c}" for n, c in zip(names, counts))
        return (f"GtDatabase({len(self)} objects [{summary}], {self.points.shape[0]} points, "
                f"{len(self.source_ids)} frames, margin {self.margin:g} m)")


def _frame_labels(split_dir: Path, frame_id: str) -> KittiLabels:
    """The labels of a frame; none for a split without ``label_2`` (KITTI's testing set)."""
    if not (split_dir / "label_2").is_dir():
        return KittiLabels.empty()
    return read_label(split_dir / "label_2" / f"{frame_id}.txt")


def _care(labels: KittiLabels) -> np.ndarray:
    return np.array([n != "DontCare" for n in labels.names], dtype=bool)


def build_gt_database(source: "KittiDetectionDataset | str | Path", ids: str | Sequence[str] | None = None,
                      class_names: Sequence[str] | None = KITTI_CLASSES,
                      out_path: str | Path | None = None, margin: float = BOX_MARGIN_XY) -> GtDatabase:
    """Extracts the labelled objects of KITTI-format frames with their points (OpenPCDet's
    ``create_groundtruth_database``).

    Each object's points are those of the whole scan (not only the camera's field of view; as OpenPCDet)
    inside its box grown by ``margin`` on each side in length and width, not in height (OpenPCDet's
    ``points_in_boxes_cpu`` grows them by :data:`BOX_MARGIN_XY`; computed by ``lidarops.points_in_boxes``, a
    point in two overlapping boxes goes to both), stored relative to the box centre. ``DontCare`` labels are
    skipped. Building twice gives the same database.

    Args:
        source: a :class:`KittiDetectionDataset` (its folder and, by default, its ids), or a KITTI root /
            split directory.
        ids: frame ids, an ``ImageSets`` name (e.g. ``"train"``: build from the training frames only), or
            ``None`` (the dataset's ids, or every scan of the folder).
        class_names (sequence of str or None): object types to keep (``None``: all).
        out_path (str or Path or None): where to save the ``.npz`` (not saved if ``None``).
        margin (float): metres added to each half-length and half-width, in [0, 1) (0: the box itself).

    Returns:
        GtDatabase.
    """
    if not 0 <= margin < 1:
        raise ValueError(f"margin must be in [0, 1) metres, got {margin!r}")
    if hasattr(source, "split_dir") and hasattr(source, "ids"):  # a KittiDetectionDataset
        split_dir = source.split_dir
        if ids is None:
            ids = source.ids
        elif isinstance(ids, str):
            ids = KittiDataset(source.root, image_set=ids).ids
    else:
        kitti = KittiDataset(source, image_set=ids if isinstance(ids, str) else None)
        split_dir = kitti.split_dir
        if ids is None or isinstance(ids, str):
            ids = kitti.ids
    ids = [str(i) for i in ids]
    keep_names = None if class_names is None else set(class_names)
    parts: dict[str, list] = {name: [] for name in GtDatabase._FIELDS if name not in ("offsets", "source_ids")}
    for frame_id in ids:
        labels = _frame_labels(split_dir, frame_id)
        wanted = _care(labels) & np.array([keep_names is None or n in keep_names for n in labels.names], bool)
        rows = np.flatnonzero(wanted)
        if rows.size == 0:
            continue
        labels = labels.select(wanted)  # a boolean mask: select() takes the nonzero entries
        calib = read_calib(split_dir / "calib" / f"{frame_id}.txt")
        points = read_velodyne(split_dir / "velodyne" / f"{frame_id}.bin")
        boxes = camera_to_lidar_boxes(labels.location, labels.dimensions, labels.rotation_y, calib).astype(np.float32)
        members = _object_members(points, boxes, margin)
        for j, idx in enumerate(members):
            pts = points[idx].copy()
            pts[:, :3] -= boxes[j, :3]
            parts["points"].append(pts)
            parts["num_points"].append(idx.size)
        parts["boxes"].append(boxes)
        parts["names"].extend(labels.names)
        parts["difficulty"].append(kitti_difficulty(labels))
        parts["frame_ids"].extend([frame_id] * rows.size)
        parts["gt_index"].append(rows)
    num_points = np.asarray(parts["num_points"], dtype=np.int64)
    db = GtDatabase(
        points=np.concatenate(parts["points"]) if parts["points"] else np.zeros((0, 4), np.float32),
        offsets=np.concatenate([[0], np.cumsum(num_points)]).astype(np.int64),
        boxes=np.concatenate(parts["boxes"]) if parts["boxes"] else np.zeros((0, 7), np.float32),
        names=np.array(parts["names"], dtype=str),
        num_points=num_points,
        difficulty=np.concatenate(parts["difficulty"]) if parts["difficulty"] else np.zeros(0, np.int64),
        frame_ids=np.array(parts["frame_ids"], dtype=str),
        gt_index=np.concatenate(parts["gt_index"]).astype(np.int64) if parts["gt_index"] else np.zeros(0, np.int64),
        source_ids=np.array(ids, dtype=str),
        margin=float(margin),
    )
    if out_path is not None:
        db.save(out_path)
    return db


def _grown_xy(boxes: np.ndarray, margin: float) -> np.ndarray:
    """(M, 7) float64 boxes with ``margin`` added to each half-length and half-width (not the height)."""
    grown = np.asarray(boxes, dtype=np.float64)[:, :7].copy()
    grown[:, 3:5] += 2.0 * margin
    return grown


def _object_members(points: np.ndarray, boxes: np.ndarray, margin: float) -> list[np.ndarray]:
    """Indices of the points inside each box grown by ``margin`` in x and y; a point in several (overlapping)
    boxes counts for each."""
    mask = points_in_boxes_mask(points, _grown_xy(boxes, margin))
    return [np.flatnonzero(mask[:, j]) for j in range(boxes.shape[0])]


class GtSampler:
    """OpenPCDet's ``gt_sampling`` (``DataBaseSampler``): pastes objects of a :class:`GtDatabase` into a scene.

    For each class of ``sample_groups`` (in order), ``group`` database objects are drawn (``group - objects of
    the class in the scene`` with ``limit_whole_scene``) uniformly without replacement (``rng.choice``; OpenPCDet
    walks a shuffled list with a pointer kept across calls instead, which would tie an item to the items
    drawn before it); drawn boxes overlapping (BEV IoU > 0) a scene box, an object pasted before or another
    drawn box are dropped; the scene's points inside the kept boxes (grown by ``remove_extra_width``, then by
    :data:`BOX_MARGIN_XY` in length and width: OpenPCDet's ``remove_points_in_boxes3d``) are removed and the
    objects' points put first. Objects keep their height (no road planes: OpenPCDet's
    ``USE_ROAD_PLANE`` is not supported) and may come from the scene's own frame.

    Args:
        database (GtDatabase or path): the objects.
        sample_groups (dict or list): objects per class, ``{"Car": 15}`` or ``["Car:15"]``.
        min_points (dict or list or None): objects with fewer points are never drawn (``["Car:5"]``).
        class_names (sequence of str or None): classes sampled (groups of other classes are ignored);
            ``None``: those of ``sample_groups``.
        rng (numpy Generator or None): default generator, when a call passes none.
        remove_difficulty (sequence of int): objects of these difficulties are never drawn.
        remove_extra_width (sequence of 3 float): growth of the boxes that clear the scene's points.
        limit_whole_scene (bool): see above.
    """

    def __init__(self, database: "GtDatabase | str | Path", sample_groups: Mapping[str, int] | Sequence[str],
                 min_points: Mapping[str, int] | Sequence[str] | None = None, class_names: Sequence[str] | None = None,
                 rng: np.random.Generator | None = None, *, remove_difficulty: Sequence[int] = (-1,),
                 remove_extra_width: Sequence[float] = (0.0, 0.0, 0.0), limit_whole_scene: bool = False) -> None:
        self.database = database if isinstance(database, GtDatabase) else GtDatabase.load(database)
        groups = _counts(sample_groups, "sample_groups")
        class_names = tuple(groups) if class_names is None else tuple(class_names)
        self.sample_groups = {name: n for name, n in groups.items() if name in class_names}
        db = self.database
        usable = ~np.isin(db.difficulty, np.asarray(list(remove_difficulty), dtype=np.int64))
        for name, m in _counts(min_points, "min_points").items():
            usable &= ~((db.names == name) & (db.num_points < m))
        #: database rows each class draws from
        self.pools = {name: np.flatnonzero(usable & (db.names == name)) for name in self.sample_groups}
        self.remove_extra_width = np.asarray(remove_extra_width, dtype=np.float32).reshape(3)
        self.limit_whole_scene = bool(limit_whole_scene)
        self.rng = rng if rng is not None else np.random.default_rng()

    def __call__(self, points: np.ndarray, boxes: np.ndarray, names: np.ndarray,
                 rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pastes objects into a scene.

        Args:
            points (ndarray float32[N, 4]): the scene.
            boxes (ndarray float32[M, 7]): its boxes (all of them: other classes block sampling too).
            names (ndarray str[M]): their types.
            rng (numpy Generator or None): the draws (default: the sampler's).

        Returns:
            points (float32[N', 4], the pasted objects' points first), boxes (float32[M + S, 7]),
            names (str[M + S]).
        """
        rng = self.rng if rng is None else rng
        db = self.database
        names = np.asarray(names, dtype=str).reshape(-1)
        existing = np.asarray(boxes, dtype=np.float32).reshape(-1, 7)
        chosen: list[np.ndarray] = []
        for name, group in self.sample_groups.items():
            num = group - int(np.sum(names == name)) if self.limit_whole_scene else group
            pool = self.pools[name]
            if num <= 0 or pool.size == 0:
                continue
            drawn = pool[rng.choice(pool.size, size=min(num, pool.size), replace=False)]
            cand = db.boxes[drawn]
            among = _iou_bev(cand, cand)
            np.fill_diagonal(among, 0.0)
            blocked = _iou_bev(cand, existing).max(axis=1, initial=0.0) + among.max(axis=1, initial=0.0) > 0
            valid = drawn[~blocked]
            existing = np.concatenate([existing, db.boxes[valid]])
            chosen.append(valid)
        picked = np.concatenate(chosen) if chosen else np.zeros(0, np.int64)
        if picked.size == 0:
            return points, existing, names
        grown = db.boxes[picked].astype(np.float64)
        grown[:, 3:6] += self.remove_extra_width
        scene = points[box_index_of_points(points, _grown_xy(grown, BOX_MARGIN_XY)) < 0]
        pasted = [db.object_points(i) for i in picked]
        return (np.concatenate(pasted + [scene]).astype(np.float32, copy=False), existing,
                np.concatenate([names, db.names[picked]]))
