"""KITTI object detection evaluation: average precision (R11 and R40) of the 2D (``bbox``), bird's-eye-view
(``bev``), 3D (``3d``) and orientation (``aos``) metrics, per class and difficulty, as KITTI's benchmark
defines them and as the Python evaluation vendored in OpenPCDet and mmdet3d (``kitti_object_eval_python``)
runs them.

Annotations are one dict per frame with KITTI's label fields, as OpenPCDet and mmdet3d hold them::

    name        (K,) str         object type ("Car", "Pedestrian", "Van", "DontCare", ...)
    truncated   (K,) float       fraction of the object outside the image (ground truth)
    occluded    (K,) int         0 fully visible, 1 partly occluded, 2 largely occluded, 3 unknown (ground truth)
    alpha       (K,) float       observation angle; -10 in detections means "no angle" (no AOS)
    bbox        (K, 4) float     2D box left, top, right, bottom in pixels
    dimensions  (K, 3) float     l, h, w in metres -- NOT the h, w, l order of KITTI's label files
    location    (K, 3) float     bottom centre in the rectified camera frame (x right, y down, z forward)
    rotation_y  (K,) float       heading about the camera y axis
    score       (K,) float       detection confidence (detections only)

``dimensions`` is in OpenPCDet's annotation order **l, h, w**: its ``get_label_anno`` reorders the h, w, l
of the label files and its prediction dicts use l, h, w, so the annotations and predictions of an OpenPCDet
or mmdet3d pipeline are scored unchanged. :func:`read_annos` and :func:`annos_from_labels` do the reordering
for label files and :class:`~lidarops.data.formats.kitti.KittiLabels` (which keep KITTI's h, w, l).

The per-frame greedy matching runs in the registered op ``torch.ops.lidarops.kitti_match`` (all frames in one
call); rotated BEV and 3D IoUs come from :func:`lidarops.box_iou_bev` / :func:`lidarops.box_iou_3d` in float64
(the official code uses a float32 numba kernel).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from lidarops.data.formats.kitti import (
    KITTI_IMAGE_SIZE,
    KittiCalib,
    KittiLabels,
    boxes_to_kitti_labels,
    camera_to_lidar_boxes,
    frame_to_kitti_labels,
    kitti_fov_mask,
    lidar_to_camera_boxes,
    read_label,
)
from lidarops.conventions import KITTI_CLASSES
from lidarops.data.frame import Frame
from lidarops.ops.boxes import box_iou_3d, box_iou_bev
from lidarops.ops.validation import validation

__all__ = [
    "evaluate",
    "evaluate_lidar",
    "annos_from_labels",
    "read_annos",
    "frame_annos",
    "detection_annos",
    "whole_view_annos",
    "count_difficulties",
    "get_thresholds",
    "KittiEvaluator",
    "iou_boxes",
    "DEFAULT_MIN_OVERLAPS",
    "METRICS",
    "DIFFICULTIES",
]

#: Metric names, in the order of the printout.
METRICS: tuple[str, ...] = ("bbox", "bev", "3d", "aos")
#: Difficulty names; a ground truth counts at a difficulty when it is tall, visible and inside the image
#: enough (:data:`MIN_HEIGHT`, :data:`MAX_OCCLUSION`, :data:`MAX_TRUNCATION`).
DIFFICULTIES: tuple[str, ...] = ("easy", "moderate", "hard")
MIN_HEIGHT: tuple[float, ...] = (40.0, 25.0, 25.0)
MAX_OCCLUSION: tuple[int, ...] = (0, 1, 2)
MAX_TRUNCATION: tuple[float, ...] = (0.15, 0.3, 0.5)
#: Recall positions of the precision curve (R11 takes 0, 4, ..., 40 of them, R40 takes 1..40).
NUM_SAMPLE_POINTS = 41
#: Ground truths of these classes are ignored (neither hit nor miss) when evaluating the key class.
NEIGHBOUR_CLASSES: dict[str, str] = {"car": "van", "pedestrian": "person_sitting"}

#: Minimum overlaps ``((bbox, bev, 3d) strict, (bbox, bev, 3d) loose)`` per class: KITTI's table for its
#: classes (note its loose set lowers Truck's 2D overlap too), and for lidarops' other classes the strict
#: overlap with its BEV and 3D halves as the loose set.
DEFAULT_MIN_OVERLAPS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "Car": ((0.7, 0.7, 0.7), (0.7, 0.5, 0.5)),
    "Pedestrian": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "Cyclist": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "Van": ((0.7, 0.7, 0.7), (0.7, 0.5, 0.5)),
    "Person_sitting": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "Truck": ((0.7, 0.7, 0.7), (0.5, 0.5, 0.5)),
    "Bus": ((0.7, 0.7, 0.7), (0.7, 0.35, 0.35)),
    "Barrier": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "TrafficCone": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "Drone": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
}
_OVERLAP_SETS = ("", "_loose")  # dict key suffix of the strict and the loose set
_NO_ALPHA = -10.0


# ---------------------------------------------------------------------------------------------
# annotations: reading, converting, validating
# ---------------------------------------------------------------------------------------------
def annos_from_labels(labels: KittiLabels) -> dict[str, np.ndarray]:
    """The annotation dict of one frame's :class:`KittiLabels` (``dimensions`` reordered h, w, l -> l, h, w).

    Returns:
        dict: ``name``, ``truncated``, ``occluded``, ``alpha``, ``bbox``, ``dimensions`` (l, h, w),
        ``location``, ``rotation_y`` and, for result files (or empty files), ``score``; float64 arrays.
    """
    anno = {
        "name": np.array(labels.names, dtype=str).reshape(-1),
        "truncated": np.asarray(labels.truncated, dtype=np.float64).reshape(-1),
        "occluded": np.asarray(labels.occluded, dtype=np.int64).reshape(-1),
        "alpha": np.asarray(labels.alpha, dtype=np.float64).reshape(-1),
        "bbox": np.asarray(labels.bbox, dtype=np.float64).reshape(-1, 4),
        "dimensions": np.asarray(labels.dimensions, dtype=np.float64).reshape(-1, 3)[:, [2, 0, 1]],
        "location": np.asarray(labels.location, dtype=np.float64).reshape(-1, 3),
        "rotation_y": np.asarray(labels.rotation_y, dtype=np.float64).reshape(-1),
    }
    if labels.score is not None or len(labels) == 0:
        anno["score"] = np.zeros(0) if labels.score is None else np.asarray(labels.score, dtype=np.float64).reshape(-1)
    return anno


def read_annos(path: str | Path | Sequence[str | Path], frame_ids: Sequence[int | str] | None = None) -> list[dict]:
    """Reads KITTI label files (``label_2``) or result files (16 fields, with a score) as annotation dicts.

    Args:
        path: a directory of ``<id>.txt`` files, or a list of files.
        frame_ids (sequence of int or str, optional): with a directory, the frames to read, in this order
            (ints are written with 6 digits, as KITTI names its files); default every ``*.txt`` file, sorted.

    Returns:
        list[dict]: one :func:`annos_from_labels` dict per file.

    Raises:
        FileNotFoundError: a missing directory or file.
        ValueError: a malformed line (file and line named).
    """
    if isinstance(path, (str, Path)):
        folder = Path(path)
        if not folder.is_dir():
            raise FileNotFoundError(f"KITTI label directory not found: {folder}")
        if frame_ids is None:
            files = sorted(folder.glob("*.txt"))
        else:
            files = [folder / (f"{i:06d}.txt" if isinstance(i, (int, np.integer)) else f"{i}.txt") for i in frame_ids]
    else:
        if frame_ids is not None:
            raise ValueError("frame_ids selects files of a directory; pass a directory or only a list of files")
        files = [Path(p) for p in path]
    return [annos_from_labels(read_label(f)) for f in files]


def frame_annos(frame: Frame, calib: KittiCalib | None = None, image_size: tuple[int, int] = KITTI_IMAGE_SIZE,
                camera_fov_only: bool = True, min_points: int = 1) -> dict[str, np.ndarray]:
    """The ground-truth annotation dict of a LiDAR frame: the labels :func:`write_kitti_frame` writes
    (:func:`~lidarops.data.formats.kitti.frame_to_kitti_labels`), each field as the written file reads back
    (truncation and 2D box to 2 decimals, the 3D fields to 6), so that scoring a frame and scoring its files
    put every object on the same side of a difficulty boundary."""
    labels = frame_to_kitti_labels(frame, calib, image_size, camera_fov_only, min_points)
    return annos_from_labels(_as_written(labels))


def _as_written(labels: KittiLabels, decimals: int = 6) -> KittiLabels:
    """``labels`` with each field rounded as :func:`~lidarops.data.formats.kitti.write_label` prints it."""
    def r(a, d):
        return np.array([float(f"{v:.{d}f}") for v in np.asarray(a, dtype=np.float64).reshape(-1)]).reshape(np.shape(a))

    return KittiLabels(list(labels.names), r(labels.truncated, 2), np.asarray(labels.occluded, np.int64),
                       r(labels.alpha, decimals), r(labels.bbox, 2), r(labels.dimensions, decimals),
                       r(labels.location, decimals), r(labels.rotation_y, decimals),
                       None if labels.score is None else r(labels.score, 4))


def _numpy(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def detection_annos(detection: Mapping[str, Any], calib: KittiCalib | None = None,
                    image_size: tuple[int, int] = KITTI_IMAGE_SIZE, class_names: Sequence[str] = KITTI_CLASSES,
                    index: int = 0, camera_fov_only: bool = True) -> dict[str, np.ndarray]:
    """The annotation dict of one frame's LiDAR-frame detections.

    Detections whose centre does not project into the image are dropped (as OpenPCDet does before it
    writes KITTI results); the others get the 2D box of their corners projected with ``P2`` and clipped
    to the image, ``alpha = rotation_y - arctan2(x, z)`` and their score. With ``camera_fov_only=False``
    every detection is kept, as :func:`whole_view_annos` (no image box, no alpha).

    Args:
        detection (dict): ``boxes`` (K, 7) ``x, y, z, dx, dy, dz, heading`` (LiDAR frame, z = centre),
            ``scores`` (K,), and ``labels`` (K,) int class ids, 1-based into ``class_names`` (a model's
            ``pred_labels``), or ``names`` (K,) str; NumPy arrays or tensors.
        calib (KittiCalib or None): calibration; default :meth:`KittiCalib.default`.
        image_size (tuple[int, int]): image (width, height).
        class_names (sequence of str): names of ``labels`` (label k is ``class_names[k - 1]``).
        index (int): the frame's index (for error messages).
        camera_fov_only (bool): keep only detections whose centre projects into the image.

    Raises:
        ValueError: a missing key, a wrong shape, a label out of range, non-finite values.
    """
    where = f"detections[{index}]"
    if not isinstance(detection, Mapping):
        raise ValueError(f"{where} must be a dict with 'boxes', 'scores' and 'labels' or 'names', "
                         f"got {type(detection).__name__}")
    for key in ("boxes", "scores"):
        if key not in detection:
            raise ValueError(f"{where} has no {key!r} entry (expected 'boxes', 'scores' and 'labels' or 'names')")
    boxes = _numpy(detection["boxes"]).astype(np.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 7:
        raise ValueError(f"{where}['boxes'] must be (K, 7) x, y, z, dx, dy, dz, heading, got shape {boxes.shape}")
    k = boxes.shape[0]
    scores = _numpy(detection["scores"]).astype(np.float64).reshape(-1)
    if scores.shape[0] != k:
        raise ValueError(f"{where}['scores'] must have {k} entries (one per box), got shape {scores.shape}")
    if "names" in detection:
        names = _numpy(detection["names"]).astype(str).reshape(-1)
    elif "labels" in detection:
        labels = _numpy(detection["labels"]).reshape(-1)
        if labels.size and (labels.dtype.kind not in "iu" or labels.min() < 1 or labels.max() > len(class_names)):
            raise ValueError(f"{where}['labels'] must be integer class ids 1..{len(class_names)} (1-based into "
                             f"{tuple(class_names)}), got dtype {labels.dtype}, values {np.unique(labels)[:8].tolist()}")
        names = np.array([class_names[i - 1] for i in labels], dtype=str)
    else:
        raise ValueError(f"{where} needs 'labels' (class ids, 1-based into the class names) or 'names'")
    if names.shape[0] != k:
        raise ValueError(f"{where}: {names.shape[0]} labels/names for {k} boxes")
    if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
        raise ValueError(f"{where}: boxes and scores must be finite")
    if (boxes[:, 3:6] < 0).any():
        raise ValueError(f"{where}['boxes']: sizes dx, dy, dz must be >= 0")
    calib = calib or KittiCalib.default()
    if not camera_fov_only:
        location, dimensions, rotation_y = lidar_to_camera_boxes(boxes, calib)
        return {"name": names, "truncated": np.zeros(k), "occluded": np.zeros(k, np.int64),
                "dimensions": dimensions[:, [2, 0, 1]], "location": location, "rotation_y": rotation_y,
                "score": scores}
    keep = kitti_fov_mask(boxes[:, :3], calib, image_size) if k else np.zeros(0, bool)
    labels = boxes_to_kitti_labels(boxes[keep], names[keep], calib, image_size, score=scores[keep])
    return annos_from_labels(_as_written(labels))  # as the result file reads back: in memory == from files


def whole_view_annos(anno: Mapping[str, Any], calib: KittiCalib | None = None,
                     point_cloud_range: Sequence[float] | None = None) -> dict[str, np.ndarray]:
    """Ground-truth annotations for a sensor whose view is not a camera's (a drone's Avia sees far above a
    KITTI image): without ``bbox`` and ``alpha`` (so :func:`evaluate` skips the 2D and AOS metrics and no
    object is too small), with ``truncated`` 0 (there is no image border), without ``DontCare`` rows (they
    only mark image regions), and, given ``point_cloud_range``, without the objects whose LiDAR-frame centre
    lies outside it (the model cannot see them). Occlusion still sets the difficulty.

    Args:
        anno (dict): one frame's annotations (module docstring; ``dimensions`` l, h, w).
        calib (KittiCalib or None): calibration (camera frame -> LiDAR frame); default :meth:`KittiCalib.default`.
        point_cloud_range (sequence of 6 float or None): ``x_min, y_min, z_min, x_max, y_max, z_max``.

    Returns:
        dict: the kept rows of every field but ``bbox`` and ``alpha``.
    """
    names = np.asarray(anno["name"]).astype(str).reshape(-1)
    keep = np.char.lower(names) != "dontcare"
    if point_cloud_range is not None and keep.any():
        lo, hi = np.asarray(point_cloud_range[:3], np.float64), np.asarray(point_cloud_range[3:], np.float64)
        dims = np.asarray(anno["dimensions"], np.float64).reshape(-1, 3)  # l, h, w
        centre = camera_to_lidar_boxes(np.asarray(anno["location"], np.float64).reshape(-1, 3), dims[:, [1, 2, 0]],
                                       np.asarray(anno["rotation_y"], np.float64).reshape(-1),
                                       calib or KittiCalib.default())[:, :3]
        keep &= ((centre >= lo) & (centre <= hi)).all(axis=1)
    out = {key: np.asarray(value)[keep] for key, value in anno.items() if key not in ("bbox", "alpha")}
    out["truncated"] = np.zeros(int(keep.sum()))
    return out


def _field(anno: Mapping, key: str, k: int, width: int, where: str) -> np.ndarray:
    value = anno[key]
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}[{key!r}] must be numeric, got {type(value).__name__}") from None
    shape = (k,) if width == 1 else (k, width)
    if a.shape != shape and not (a.size == k * width and a.ndim >= 1 and a.shape[0] == k):
        raise ValueError(f"{where}[{key!r}] must have shape {shape} (K = {k}, the length of 'name'), got {a.shape}")
    return a.reshape(shape)


class _Objects:
    """Every frame's objects of one side (ground truths or detections) concatenated; ``offsets`` (F + 1)."""

    def __init__(self, annos: Sequence[Mapping], which: str, fields: Sequence[tuple[str, int]],
                 optional: Sequence[tuple[str, int]]) -> None:
        names, counts = [], []
        columns: dict[str, list] = {key: [] for key, _ in list(fields) + list(optional)}
        present: dict[str, set] = {key: set() for key, _ in optional}
        for f, anno in enumerate(annos):
            where = f"{which}[{f}]"
            if not isinstance(anno, Mapping):
                raise ValueError(f"{where} must be a dict of KITTI fields (name, bbox, dimensions, ...), "
                                 f"got {type(anno).__name__}")
            if "name" not in anno:
                raise ValueError(f"{where} has no 'name' field")
            name = np.asarray(anno["name"])
            if name.ndim > 1 or (name.size and name.dtype.kind not in "UO"):
                raise ValueError(f"{where}['name'] must be a 1-D array of strings, got dtype {name.dtype}, "
                                 f"shape {name.shape}")
            name = name.astype(str).reshape(-1)
            k = name.shape[0]
            for key, width in fields:
                if key not in anno:
                    if k == 0:
                        continue
                    raise ValueError(f"{where} has no {key!r} field (required: "
                                     f"{', '.join(repr(key) for key, _ in fields)})")
                columns[key].append(_field(anno, key, k, width, where))
            for key, width in optional:
                if key in anno:
                    present[key].add(f)
                    columns[key].append(_field(anno, key, k, width, where))
            names.append(name)
            counts.append(k)
        self.offsets = np.zeros(len(counts) + 1, np.int64)
        np.cumsum(counts, out=self.offsets[1:])
        self.names = np.concatenate(names) if names else np.zeros(0, str)
        self.has = {}
        for key, width in list(fields) + list(optional):
            if key in present:  # an optional field: in every frame with objects, or in none
                have = present[key]
                missing = [f for f, k in enumerate(counts) if k and f not in have]
                self.has[key] = not missing
                if missing and any(counts[f] for f in have):
                    raise ValueError(f"{which}[{missing[0]}] has no {key!r} field but other frames have one; "
                                     f"give it for every frame or for none")
                if missing:
                    columns[key] = []
            parts = columns[key]
            value = np.concatenate(parts) if parts else np.zeros((0,) if width == 1 else (0, width))
            finite = np.isfinite(value) if width == 1 else np.isfinite(value).all(1)
            if not finite.all():
                row = int(np.argmin(finite))
                frame = int(np.searchsorted(self.offsets, row, side="right") - 1)
                raise ValueError(f"{which}[{frame}][{key!r}] contains NaN or infinite values "
                                 f"(object {row - self.offsets[frame]})")
            setattr(self, key, value)

    def __len__(self) -> int:
        return int(self.offsets[-1])


def iou_boxes(location: np.ndarray, dimensions: np.ndarray, rotation_y: np.ndarray) -> torch.Tensor:
    """Camera boxes (annotation ``location``, ``dimensions`` l h w, ``rotation_y``) as lidarops boxes (float64
    (K, 7)) in an equivalent right-handed frame: x = z_cam, y = -x_cam, z = -y_cam + h / 2 (box centre),
    dx, dy, dz = l, w, h, heading = -rotation_y - pi / 2. A rigid motion, so :func:`lidarops.box_iou_bev` and
    :func:`lidarops.box_iou_3d` of these are the camera boxes' BEV and 3D IoUs."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    out = np.empty((loc.shape[0], 7))
    out[:, 0], out[:, 1], out[:, 2] = loc[:, 2], -loc[:, 0], dims[:, 1] / 2 - loc[:, 1]
    out[:, 3], out[:, 4], out[:, 5] = dims[:, 0], dims[:, 2], dims[:, 1]
    out[:, 6] = -np.asarray(rotation_y, dtype=np.float64).reshape(-1) - math.pi / 2
    return torch.from_numpy(out)


def _iou_boxes(obj: _Objects) -> torch.Tensor:
    return iou_boxes(obj.location, obj.dimensions, obj.rotation_y)


# ---------------------------------------------------------------------------------------------
# the protocol
# ---------------------------------------------------------------------------------------------
def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_points: int = NUM_SAMPLE_POINTS) -> np.ndarray:
    """The score thresholds of the precision curve: KITTI's ``get_thresholds``.

    Going down the scores of the true positives (descending), score ``i`` is taken when its recall
    ``l = (i + 1) / num_gt`` is at least as close to the next recall position ``current`` as the next
    score's ``r = (i + 2) / num_gt`` is (precisely: unless ``r - current < current - l``), and the last
    score always; each taken score advances ``current`` by ``1 / (num_sample_points - 1)``. The test is
    false from some index on, so each threshold is found by bisection with that same floating-point test
    (the result is exactly the sequential rule's) instead of a Python loop over every score.

    Args:
        scores (ndarray[N]): scores of the detections matched in the first pass.
        num_gt (int): counted ground truths (the recall's denominator).
        num_sample_points (int): recall positions (41).

    Returns:
        ndarray float64[T]: descending thresholds (T <= num_sample_points when N <= num_gt, as in the
        evaluation, where every matched score belongs to a counted gt).
    """
    scores = np.sort(np.asarray(scores, dtype=np.float64).reshape(-1))[::-1]
    n = scores.shape[0]
    if n and num_gt <= 0:
        raise ValueError(f"num_gt must be > 0 when there are matched scores, got {num_gt} for {n} scores")
    step = 1 / (num_sample_points - 1.0)
    current = 0.0
    picked: list[float] = []

    def skip(i: int) -> bool:  # the protocol's test for i < n - 1
        return (i + 2) / num_gt - current < current - (i + 1) / num_gt

    i = 0
    while i < n:
        lo, hi = i, n - 1  # first index in [i, n - 1] that is not skipped (n - 1 never is)
        while lo < hi:
            mid = (lo + hi) // 2
            if skip(mid):
                lo = mid + 1
            else:
                hi = mid
        picked.append(scores[lo])
        current += step
        i = lo + 1
    return np.array(picked, dtype=np.float64)


def _average_precision(curve: np.ndarray) -> tuple[float, float]:
    """R11 and R40 (in percent) of a precision curve over the first thresholds (the rest are 0)."""
    full = np.zeros(NUM_SAMPLE_POINTS)
    full[: curve.shape[0]] = curve
    monotone = np.maximum.accumulate(full[::-1])[::-1]  # max over the later positions (NaN propagates)
    r11 = sum(monotone[0::4].tolist()) / 11 * 100
    r40 = sum(monotone[1:].tolist()) / 40 * 100
    return r11, r40


def _resolve_min_overlaps(classes: Sequence[str], min_overlaps: Mapping | None) -> np.ndarray:
    """(num_sets = 2, 3 metrics, C) minimum overlaps."""
    if min_overlaps is not None and not isinstance(min_overlaps, Mapping):
        raise ValueError("min_overlaps must map class names to (bbox, bev, 3d) or ((strict), (loose)) overlaps, "
                         f"got {type(min_overlaps).__name__}")
    given = {} if min_overlaps is None else dict(min_overlaps)
    defaults = {k.lower(): v for k, v in DEFAULT_MIN_OVERLAPS.items()}
    unknown = [k for k in given if k not in classes]
    if unknown:
        raise ValueError(f"min_overlaps names classes that are not evaluated: {unknown} (classes: {list(classes)})")
    out = np.zeros((2, 3, len(classes)))
    for c, name in enumerate(classes):
        value = given.get(name, defaults.get(name.lower()))
        if value is None:
            raise ValueError(f"no default minimum overlaps for class {name!r}; pass min_overlaps={{{name!r}: "
                             f"((bbox, bev, 3d), (bbox, bev, 3d) loose)}} (defaults exist for "
                             f"{', '.join(DEFAULT_MIN_OVERLAPS)})")
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape == (3,):
            a = np.stack([a, a])
        if a.shape != (2, 3) or not np.all((a >= 0) & (a <= 1)):
            raise ValueError(f"min_overlaps[{name!r}] must be (bbox, bev, 3d) or ((bbox, bev, 3d), (bbox, bev, 3d)) "
                             f"with values in [0, 1], got {value!r}")
        out[:, :, c] = a
    return out


def _pairs(dt_offsets: np.ndarray, gt_offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every frame's (detection, ground truth) pairs, detection-major: overlap offsets, detection and gt index."""
    nd, ng = np.diff(dt_offsets), np.diff(gt_offsets)
    per_frame = nd * ng
    offsets = np.zeros(per_frame.shape[0] + 1, np.int64)
    np.cumsum(per_frame, out=offsets[1:])
    frame = np.repeat(np.arange(per_frame.shape[0]), per_frame)
    local = np.arange(offsets[-1]) - offsets[frame]
    cols = np.maximum(ng[frame], 1)
    return offsets, dt_offsets[frame] + local // cols, gt_offsets[frame] + local % cols


def _image_iou(dt: np.ndarray, gt: np.ndarray, union: bool = True) -> np.ndarray:
    """Row-wise 2D overlap of boxes (left, top, right, bottom; no +1 pixel): IoU, or the intersection over
    the detection's area (``union=False``, KITTI's DontCare criterion)."""
    iw = np.minimum(dt[:, 2], gt[:, 2]) - np.maximum(dt[:, 0], gt[:, 0])
    ih = np.minimum(dt[:, 3], gt[:, 3]) - np.maximum(dt[:, 1], gt[:, 1])
    inter = np.where((iw > 0) & (ih > 0), iw * ih, 0.0)
    area_dt = (dt[:, 2] - dt[:, 0]) * (dt[:, 3] - dt[:, 1])
    denom = area_dt + (gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1]) - inter if union else area_dt
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(inter > 0, inter / denom, 0.0)


def _rotated_overlaps(fn, dt: torch.Tensor, gt: torch.Tensor, dt_off: np.ndarray, gt_off: np.ndarray,
                      offsets: np.ndarray) -> np.ndarray:
    out = np.zeros(int(offsets[-1]))
    with validation(False):  # the boxes were checked once for all frames
        for f in np.flatnonzero(np.diff(offsets)):
            out[offsets[f]:offsets[f + 1]] = fn(dt[dt_off[f]:dt_off[f + 1]], gt[gt_off[f]:gt_off[f + 1]]).numpy().ravel()
    return out


def _lower_ids(names: np.ndarray, vocabulary: dict[str, int]) -> np.ndarray:
    """Index of each (lower-cased) name in ``vocabulary``, -1 for other names."""
    uniq, inverse = np.unique(names, return_inverse=True)
    ids = np.array([vocabulary.get(u.lower(), -1) for u in uniq.tolist()], dtype=np.int64)
    return ids[inverse.reshape(-1)] if uniq.size else np.zeros(0, np.int64)


def _check_metrics(metrics: Sequence[str]) -> tuple[str, ...]:
    if isinstance(metrics, str):
        metrics = (metrics,)
    bad = [m for m in metrics if m not in METRICS]
    if bad:
        raise ValueError(f"unknown metric(s) {bad}; choose from {list(METRICS)}")
    return tuple(m for m in METRICS if m in metrics)


class _Evaluation:
    """Everything that does not depend on the class: the objects, their overlaps, the DontCare overlaps."""

    def __init__(self, gt_annos: Sequence[Mapping], dt_annos: Sequence[Mapping], classes: Sequence[str],
                 metrics: tuple[str, ...]) -> None:
        box_fields = [("dimensions", 3), ("location", 3), ("rotation_y", 1)]
        gts = _Objects(gt_annos, "gt_annos", [("truncated", 1), ("occluded", 1)] + box_fields,
                       [("bbox", 4), ("alpha", 1)])
        dts = _Objects(dt_annos, "dt_annos", [("score", 1)] + box_fields, [("bbox", 4), ("alpha", 1)])
        if gts.has["bbox"] != dts.has["bbox"] and len(gts) and len(dts):
            raise ValueError("either both ground truths and detections have 'bbox' (image boxes) or neither")
        self.has_bbox = gts.has["bbox"] and dts.has["bbox"]
        # AOS as the official code decides it: the first detection of the first frame with detections
        first = dts.alpha[0] if dts.has["alpha"] and len(dts) else _NO_ALPHA
        self.compute_aos = "aos" in metrics and self.has_bbox and first != _NO_ALPHA
        if self.compute_aos and not gts.has["alpha"]:
            raise ValueError("the detections have alpha (for the 'aos' metric) but the ground truths do not; "
                             "give gt 'alpha' or leave 'aos' out of metrics")
        self.metrics = tuple(m for m in metrics if (m != "bbox" or self.has_bbox) and (m != "aos" or self.compute_aos))
        if self.compute_aos and "bbox" not in self.metrics:
            self.metrics = ("bbox",) + self.metrics  # AOS is computed on the 2D matching
        self.report = tuple(m for m in metrics if m in self.metrics)
        self.classes = list(classes)

        # ids: 0..C-1 the classes, C.. their neighbours; other names -1
        lower = [c.lower() for c in classes]
        vocabulary = {c: i for i, c in enumerate(lower)}
        for c in lower:
            vocabulary.setdefault(NEIGHBOUR_CLASSES.get(c, ""), len(vocabulary))
        vocabulary.pop("", None)
        self.neighbour = [vocabulary.get(NEIGHBOUR_CLASSES.get(c, ""), -2) for c in lower]
        gt_id, dt_id = _lower_ids(gts.names, vocabulary), _lower_ids(dts.names, vocabulary)
        gt_height = gts.bbox[:, 3] - gts.bbox[:, 1] if self.has_bbox else np.full(len(gts), np.inf)
        dt_height = np.abs(dts.bbox[:, 3] - dts.bbox[:, 1]) if self.has_bbox else np.full(len(dts), np.inf)

        # Objects that take part in some matching: gts of the classes and their neighbours; detections of
        # the classes, and (as the official code marks every detection lower than the difficulty's minimum
        # height "ignored", whatever its class) detections of other classes that low.
        gt_keep = np.flatnonzero(gt_id >= 0)
        dt_keep = np.flatnonzero(((dt_id >= 0) & (dt_id < len(classes))) | (dt_height < max(MIN_HEIGHT)))
        gt_off = np.searchsorted(gt_keep, gts.offsets).astype(np.int64)
        dt_off = np.searchsorted(dt_keep, dts.offsets).astype(np.int64)
        for side, which, keep in ((gts, "gt_annos", gt_keep), (dts, "dt_annos", dt_keep)):
            bad = np.flatnonzero((side.dimensions[keep] < 0).any(1))
            if bad.size:
                frame = int(np.searchsorted(side.offsets, keep[bad[0]], side="right") - 1)
                raise ValueError(f"{which}[{frame}]['dimensions'] has negative sizes (object "
                                 f"{keep[bad[0]] - side.offsets[frame]}, {side.names[keep[bad[0]]]!r})")
        self.gt_off, self.dt_off = gt_off, dt_off
        self.gt_id, self.dt_id = gt_id[gt_keep], dt_id[dt_keep]
        self.gt_height, self.dt_height = gt_height[gt_keep], dt_height[dt_keep]
        self.occluded, self.truncated = gts.occluded[gt_keep], gts.truncated[gt_keep]
        self.scores = dts.score[dt_keep]
        self.gt_alpha = gts.alpha[gt_keep] if self.compute_aos else np.zeros(gt_keep.shape[0])
        self.dt_alpha = dts.alpha[dt_keep] if self.compute_aos else np.zeros(dt_keep.shape[0])

        self.overlap_offsets, pair_dt, pair_gt = _pairs(dt_off, gt_off)
        self.overlaps: dict[str, np.ndarray] = {}
        if "bbox" in self.metrics:
            self.overlaps["bbox"] = _image_iou(dts.bbox[dt_keep][pair_dt], gts.bbox[gt_keep][pair_gt])
        if "bev" in self.metrics or "3d" in self.metrics:
            dt_boxes, gt_boxes = _iou_boxes(dts)[dt_keep], _iou_boxes(gts)[gt_keep]
            for metric, fn in (("bev", box_iou_bev), ("3d", box_iou_3d)):
                if metric in self.metrics:
                    self.overlaps[metric] = _rotated_overlaps(fn, dt_boxes, gt_boxes, dt_off, gt_off,
                                                              self.overlap_offsets)
        # unmatched detections inside a DontCare region are not false positives (2D metric only, as in
        # the official code): each detection's largest intersection / detection area with one
        self.dontcare = np.zeros(dt_keep.shape[0])
        if self.has_bbox:
            dc = np.flatnonzero(gts.names == "DontCare")
            dc_off = np.searchsorted(dc, gts.offsets).astype(np.int64)
            _, d_idx, c_idx = _pairs(dt_off, dc_off)
            if d_idx.size:
                np.maximum.at(self.dontcare, d_idx, _image_iou(dts.bbox[dt_keep][d_idx], gts.bbox[dc[c_idx]], False))
        self._ignored: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]] = {}
        self._tensors = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in dict(
            overlap_offsets=self.overlap_offsets, gt_offsets=gt_off, dt_offsets=dt_off, scores=self.scores,
            dontcare=self.dontcare, no_dontcare=np.zeros_like(self.dontcare), gt_alpha=self.gt_alpha,
            dt_alpha=self.dt_alpha).items()}

    def ignored(self, c: int, d: int) -> tuple[np.ndarray, np.ndarray, int]:
        """KITTI's clean_data: ignored flags of the gts and detections (0 counted, 1 ignored, -1 not of the
        class) for class ``c`` at difficulty ``d``, and the number of counted gts."""
        if (c, d) not in self._ignored:
            of_class = self.gt_id == c
            too_hard = (self.occluded > MAX_OCCLUSION[d]) | (self.truncated > MAX_TRUNCATION[d]) | \
                (self.gt_height <= MIN_HEIGHT[d])
            ignored_gt = np.where(of_class & ~too_hard, 0, np.where(of_class | (self.gt_id == self.neighbour[c]), 1, -1))
            ignored_dt = np.where(self.dt_height < MIN_HEIGHT[d], 1, np.where(self.dt_id == c, 0, -1))
            self._ignored[(c, d)] = (ignored_gt.astype(np.int64), ignored_dt.astype(np.int64),
                                     int((ignored_gt == 0).sum()))
        return self._ignored[(c, d)]

    def precision(self, metric: str, c: int, d: int, min_overlap: float) -> tuple[np.ndarray, np.ndarray]:
        """Precision (and AOS similarity / (tp + fp)) at the thresholds of the first pass."""
        ignored_gt, ignored_dt, num_gt = self.ignored(c, d)
        t = self._tensors
        dontcare = t["dontcare"] if metric == "bbox" else t["no_dontcare"]
        args = (torch.from_numpy(self.overlaps[metric]), t["overlap_offsets"], t["gt_offsets"], t["dt_offsets"],
                torch.from_numpy(ignored_gt), torch.from_numpy(ignored_dt), t["scores"], dontcare, t["gt_alpha"],
                t["dt_alpha"])
        matched, _ = torch.ops.lidarops.kitti_match(*args, torch.zeros(0, dtype=torch.float64), float(min_overlap),
                                                    False, False)
        matched = matched.numpy()
        thresholds = get_thresholds(matched[~np.isnan(matched)], num_gt)
        if thresholds.size == 0:
            return np.zeros(0), np.zeros(0)
        _, counts = torch.ops.lidarops.kitti_match(*args, torch.from_numpy(thresholds), float(min_overlap), True,
                                                   self.compute_aos and metric == "bbox")
        tp, fp, _, similarity = counts.numpy().T
        with np.errstate(divide="ignore", invalid="ignore"):
            return tp / (tp + fp), similarity / (tp + fp)


def _format(classes: Sequence[str], overlaps: np.ndarray, metrics: tuple[str, ...], ap: dict) -> str:
    """The official printout: per class and overlap set, an R11 block and an R40 block."""
    lines = []
    labels = {"bbox": "bbox", "bev": "bev ", "3d": "3d  ", "aos": "aos "}
    for c, name in enumerate(classes):
        for s in range(overlaps.shape[0]):
            head = ", ".join(f"{v:.2f}" for v in overlaps[s, :, c])
            for r, tag in ((0, "AP"), (1, "AP_R40")):
                lines.append(f"{name} {tag}@{head}:")
                for m in metrics:
                    digits = 2 if m == "aos" else 4
                    values = ", ".join(f"{ap[(m, s, c, d)][r]:.{digits}f}" for d in range(len(DIFFICULTIES)))
                    lines.append(f"{labels[m]} AP:{values}")
    return "\n".join(lines) + "\n"


def evaluate(gt_annos: Sequence[Mapping], dt_annos: Sequence[Mapping],
             classes: Sequence[str] = KITTI_CLASSES, min_overlaps: Mapping | None = None,
             metrics: Sequence[str] = METRICS) -> tuple[str, dict[str, float]]:
    """KITTI's object evaluation: AP R11 and R40 per class, metric and difficulty, at the strict and the
    loose minimum overlaps.

    Per class and difficulty, ground truths that are too small (2D height <= 40 / 25 / 25 px), too
    occluded (> 0 / 1 / 2) or too truncated (> 0.15 / 0.3 / 0.5) for it, and those of the neighbouring class
    (Van for Car, Person_sitting for Pedestrian), are ignored: matching one is neither a hit nor a false
    positive; detections lower than 40 / 25 / 25 px are ignored; other classes are not considered.
    Unmatched detections inside a ``DontCare`` region are not false positives (2D metric only, as in the
    official code). A first pass matches each gt to the highest-scoring detection above the minimum
    overlap; the thresholds are picked from the matched scores (:func:`get_thresholds`); a counting pass
    at each threshold (the largest overlap wins) gives precision, made monotone; R11 averages recall
    positions 0, 4, ..., 40, R40 positions 1..40 (x 100).

    Args:
        gt_annos (sequence of dict): ground truth per frame (module docstring; ``dimensions`` l, h, w).
            ``bbox`` and ``alpha`` may be left out of every frame: without image boxes the ``bbox`` and
            ``aos`` metrics are skipped and no object is too small or inside a DontCare region.
        dt_annos (sequence of dict): detections per frame, with ``score``; AOS is computed when the first
            detection's ``alpha`` is not -10 (the official rule).
        classes (sequence of str): classes to evaluate (matched case-insensitively).
        min_overlaps (dict, optional): class -> ``((bbox, bev, 3d) strict, (bbox, bev, 3d) loose)``, or one
            ``(bbox, bev, 3d)`` for both sets; overrides :data:`DEFAULT_MIN_OVERLAPS` for those classes.
        metrics (sequence of str): any of ``"bbox"``, ``"bev"``, ``"3d"``, ``"aos"``.

    Returns:
        (str, dict): the printout of the official evaluation, and ``{"{Class}_{metric}_{difficulty}_{R11|R40}":
        AP}`` for the strict overlaps (e.g. ``Car_3d_moderate_R40``) and the same keys with the suffix
        ``_loose`` for the loose set; metrics ``bbox``, ``bev``, ``3d``, ``aos``; APs in percent.

    Raises:
        ValueError: mismatched frame counts, a malformed annotation (frame and field named), an unknown
            metric, a class without minimum overlaps.
    """
    metrics = _check_metrics(metrics)
    if isinstance(classes, str):
        classes = (classes,)
    classes = list(classes)
    if not classes or not all(isinstance(c, str) and c for c in classes):
        raise ValueError(f"classes must be a non-empty sequence of class names, got {classes!r}")
    if len({c.lower() for c in classes}) != len(classes):
        raise ValueError(f"classes must be distinct (case-insensitively), got {classes}")
    overlaps = _resolve_min_overlaps(classes, min_overlaps)
    if isinstance(gt_annos, Mapping) or isinstance(dt_annos, Mapping):
        raise ValueError("gt_annos and dt_annos must be sequences of per-frame dicts, not one dict")
    gt_annos, dt_annos = list(gt_annos), list(dt_annos)
    if len(gt_annos) != len(dt_annos):
        raise ValueError(f"gt_annos has {len(gt_annos)} frames but dt_annos has {len(dt_annos)}")
    if not gt_annos:  # an AP of 0 would read as a measured result
        raise ValueError("gt_annos and dt_annos hold no frames: there is nothing to evaluate")
    ev = _Evaluation(gt_annos, dt_annos, classes, metrics)

    ap: dict[tuple[str, int, int, int], tuple[float, float]] = {}
    done: dict[tuple[str, int, int, float], tuple[np.ndarray, np.ndarray]] = {}
    for c in range(len(classes)):
        for d in range(len(DIFFICULTIES)):
            for s in range(overlaps.shape[0]):
                for m, metric in enumerate(("bbox", "bev", "3d")):
                    if metric not in ev.metrics:
                        continue
                    key = (metric, c, d, float(overlaps[s, m, c]))
                    if key not in done:  # the strict and loose sets often share the 2D overlap
                        done[key] = ev.precision(metric, c, d, overlaps[s, m, c])
                    precision, orientation = done[key]
                    ap[(metric, s, c, d)] = _average_precision(precision)
                    if metric == "bbox" and ev.compute_aos:
                        ap[("aos", s, c, d)] = _average_precision(orientation)
    results: dict[str, float] = {}
    for c, name in enumerate(classes):
        for s, suffix in enumerate(_OVERLAP_SETS):
            for metric in ev.report:
                for d, difficulty in enumerate(DIFFICULTIES):
                    r11, r40 = ap[(metric, s, c, d)]
                    results[f"{name}_{metric}_{difficulty}_R11{suffix}"] = r11
                    results[f"{name}_{metric}_{difficulty}_R40{suffix}"] = r40
    return _format(classes, overlaps, ev.report, ap), results


def evaluate_lidar(gt_frames: Sequence[Frame], detections: Sequence[Mapping[str, Any]],
                   classes: Sequence[str] = KITTI_CLASSES, calib: KittiCalib | None = None,
                   image_size: tuple[int, int] = KITTI_IMAGE_SIZE, min_overlaps: Mapping | None = None,
                   metrics: Sequence[str] = METRICS, camera_fov_only: bool = True,
                   min_points: int = 1, class_names: Sequence[str] | None = None) -> tuple[str, dict[str, float]]:
    """:func:`evaluate` for frames and detections in lidarops' LiDAR box convention.

    Ground truths are the labels :func:`~lidarops.data.formats.kitti.write_kitti_frame` writes for each
    frame (2D boxes projected with ``P2`` and clipped to the image, truncation from the image border,
    occlusion from the frame's visibility, only boxes with ``min_points`` points whose centre projects
    into the image); detections are converted by :func:`detection_annos`. Both use ``calib`` (default
    :meth:`KittiCalib.default`), so a detection equal to a gt box scores exactly as that gt.

    Args:
        gt_frames (sequence of Frame): ground-truth frames (``boxes``, ``labels`` into ``class_names``,
            ``visibility``).
        detections (sequence of dict): per frame ``{"boxes": (K, 7), "scores": (K,), "labels": (K,)}``
            (``labels`` 1-based into ``class_names``: what ``model.predict`` returns) or ``"names"`` instead of
            ``"labels"``.
        classes, min_overlaps, metrics: as :func:`evaluate`.
        calib (KittiCalib or None): calibration; default :meth:`KittiCalib.default`.
        image_size (tuple[int, int]): image (width, height).
        camera_fov_only, min_points: which gt boxes get labels (as :func:`write_kitti_frame`).
        class_names (sequence of str or None): the names of the detections' labels (the model's
            ``class_names``); default ``classes``.

    Returns:
        (str, dict): as :func:`evaluate`.
    """
    gt_frames, detections = list(gt_frames), list(detections)
    if len(gt_frames) != len(detections):
        raise ValueError(f"gt_frames has {len(gt_frames)} frames but detections has {len(detections)}")
    for i, frame in enumerate(gt_frames):
        if not isinstance(frame, Frame):
            raise ValueError(f"gt_frames[{i}] must be a lidarops.data.Frame, got {type(frame).__name__}")
    calib = calib or KittiCalib.default()
    gt_annos = [frame_annos(f, calib, image_size, camera_fov_only, min_points) for f in gt_frames]
    names = tuple(classes if class_names is None else class_names)
    dt_annos = [detection_annos(d, calib, image_size, names, index=i) for i, d in enumerate(detections)]
    return evaluate(gt_annos, dt_annos, classes, min_overlaps, metrics)


def count_difficulties(gt_annos: Sequence[Mapping], classes: Sequence[str] = KITTI_CLASSES
                       ) -> dict[str, dict[str, int]]:
    """How many ground truths of each class count at each difficulty (as :func:`evaluate` counts them).

    Returns:
        dict: ``{class: {"labelled": n, "easy": ..., "moderate": ..., "hard": ...}}``; the difficulties
        are cumulative (a gt counted as easy also counts as moderate and hard).
    """
    classes = [classes] if isinstance(classes, str) else list(classes)
    empty = [{"name": np.zeros(0, str)} for _ in gt_annos]
    ev = _Evaluation(list(gt_annos), empty, classes, ("bev",))
    out = {}
    for c, name in enumerate(classes):
        row = {"labelled": int((ev.gt_id == c).sum())}
        for d, difficulty in enumerate(DIFFICULTIES):
            row[difficulty] = ev.ignored(c, d)[2]
        out[name] = row
    return out


def _item_annos(anno: Mapping[str, Any], index: int) -> dict[str, np.ndarray]:
    """An annotation dict from a dataset item's ``annos`` (``lidarops.data.detection``: ``dimensions_hwl``
    in the label file's h, w, l order) or an already converted one (``dimensions`` l, h, w)."""
    if "dimensions" in anno:
        return dict(anno)
    if "dimensions_hwl" not in anno:
        raise ValueError(f"frame {index}: annotations need 'dimensions' (l, h, w) or 'dimensions_hwl' (h, w, l)")
    out = {k: v for k, v in anno.items() if k != "dimensions_hwl"}
    out["dimensions"] = np.asarray(anno["dimensions_hwl"], dtype=np.float64).reshape(-1, 3)[:, [2, 0, 1]]
    return out


class KittiEvaluator:
    """The evaluator of a detection training run (``lidarops.train.fit(..., evaluator=...)``): model
    predictions in the LiDAR frame against the ground-truth annotations the dataset items carry.

    Args:
        class_names (sequence of str): the model's classes; a prediction's label k (1-based) is
            ``class_names[k - 1]``. All of them are evaluated.
        image_size (tuple[int, int]): image (width, height) of frames whose metadata gives none.
        metrics (sequence of str): as :func:`evaluate`.
        camera (bool): score the camera's view, as KITTI (detections whose centre leaves the image dropped,
            2D boxes, difficulties from their heights); ``False``: the sensor's whole view, as
            :func:`whole_view_annos` (BEV and 3D metrics only), for models trained on every point
            (``FOV_POINTS_ONLY: False``).
        point_cloud_range (sequence of 6 float or None): with ``camera=False``, the model's range: ground
            truths outside it are left out.

    Called as ``evaluator(predictions, metas) -> (results, text)``: ``predictions[i]`` a dict of ``boxes
    (K, 7)``, ``scores (K,)``, ``labels (K,)`` (1-based); ``metas[i]`` a dict with the frame's ``annos``
    and ``calib`` (and optionally ``image_size``).
    """

    def __init__(self, class_names: Sequence[str], image_size: tuple[int, int] = KITTI_IMAGE_SIZE,
                 metrics: Sequence[str] = METRICS, camera: bool = True,
                 point_cloud_range: Sequence[float] | None = None):
        self.class_names = list(class_names)
        self.image_size = tuple(image_size)
        self.metrics = tuple(metrics)
        self.camera = bool(camera)
        if point_cloud_range is not None:
            point_cloud_range = [float(v) for v in point_cloud_range]
            if len(point_cloud_range) != 6 or not all(math.isfinite(v) for v in point_cloud_range) or \
                    any(point_cloud_range[i] >= point_cloud_range[i + 3] for i in range(3)):
                raise ValueError(f"point_cloud_range must be 6 finite values x_min, y_min, z_min, x_max, y_max, "
                                 f"z_max with each min < max, got {point_cloud_range}")
        self.point_cloud_range = point_cloud_range

    def __call__(self, predictions: Sequence[Mapping[str, Any]], metas: Sequence[Mapping[str, Any]]
                 ) -> tuple[dict[str, float], str]:
        if len(predictions) != len(metas):
            raise ValueError(f"{len(predictions)} predictions for {len(metas)} frames")
        gt_annos, dt_annos = [], []
        for i, (pred, meta) in enumerate(zip(predictions, metas)):
            gt = _item_annos(meta["annos"], i)
            gt_annos.append(gt if self.camera else whole_view_annos(gt, meta.get("calib"), self.point_cloud_range))
            labels = _numpy(pred["labels"]).astype(np.int64)
            dt_annos.append(detection_annos({"boxes": pred["boxes"], "scores": pred["scores"], "labels": labels},
                                            meta.get("calib"), tuple(meta.get("image_size") or self.image_size),
                                            self.class_names, index=i, camera_fov_only=self.camera))
        text, results = evaluate(gt_annos, dt_annos, self.class_names, metrics=self.metrics)
        return results, text
