"""Detection training data as OpenPCDet feeds it: KITTI-format folders (real KITTI, or what
``lidarops data synth`` writes) turned into OpenPCDet-style items and batches, with OpenPCDet's data
processing and augmentations (the ``DATA_CONFIG`` of ``tools/cfgs/kitti_models/pointpillar.yaml``).

Example::

    from torch.utils.data import DataLoader
    from lidarops.data.detection import collate_batch, train_val_datasets

    train, val = train_val_datasets("/data/kitti_synth")      # ImageSets/train.txt and val.txt
    loader = DataLoader(train, batch_size=4, shuffle=True, num_workers=4, collate_fn=collate_batch)
    for epoch in range(80):
        train.set_epoch(epoch)                                 # before the epoch's iterator is created
        for batch in loader:
            ...                                                # batch["points"] (P, 5), batch["gt_boxes"] (B, M, 8)

One item, in training (OpenPCDet's ``KittiDataset.__getitem__`` + ``prepare_data``):

1. the scan, its calibration and labels; with ``fov_points_only`` the points that project into the image
   (:func:`~lidarops.data.formats.kitti.kitti_fov_mask`; the image size is read from ``image_2/<id>.png``
   when present, else KITTI's 1242 x 375, the size ``lidarops data synth`` assumes);
2. the boxes of every labelled object but ``DontCare`` in the LiDAR frame;
3. the augmentations of ``config.augmentations`` in their order (default OpenPCDet's: ``gt_sampling``,
   ``random_world_flip``, ``random_world_rotation``, ``random_world_scaling``), then the headings wrapped to
   ``[-pi, pi)``;
4. the boxes of classes outside ``class_names`` dropped (before that they block gt sampling, as in
   OpenPCDet), class ids 1..len(class_names) appended;
5. ``mask_points_and_boxes_outside_range`` (:func:`mask_points_by_range`,
   :func:`mask_boxes_outside_range`), then ``shuffle_points``;
6. no box left: another index is drawn and its item returned (OpenPCDet's resampling).

In evaluation only 1, 2, 4, the point-range crop and (if ``shuffle_test``) the shuffle run; every ground
truth of the classes is kept.

Determinism: every random draw of item ``index`` comes from ``np.random.default_rng((seed, epoch, index))``
(in the order gt sampling, flip, rotation, scaling, shuffle, resampling), so an item is a function of
``(seed, epoch, index)`` whatever the worker or the order of requests; :meth:`KittiDetectionDataset.set_epoch`
sets the epoch (DataLoader workers copy the dataset when an epoch's iterator is created).

Departures from OpenPCDet, all deliberate:

* gt sampling draws its objects with ``rng.choice`` (uniform, without replacement within a call) instead of
  walking a shuffled list with a pointer kept across calls: the pointer makes an item depend on the items a
  worker produced before it;
* ``USE_ROAD_PLANE`` is ignored: there are no road-plane files for simulated data (sampled objects keep
  their z, right for the simulator's flat ground and one sensor height; ``pointpillar.yaml`` runs without
  road planes too);
* the ground-truth database is one ``.npz`` file (:class:`GtDatabase`) instead of ``gt_database/*.bin`` +
  ``kitti_dbinfos_train.pkl``, built on demand (its objects' points gathered as OpenPCDet's
  ``points_in_boxes_cpu`` does, 1 cm beyond the box sides: :data:`~lidarops.data.augment.BOX_MARGIN_XY`; a
  cached file gathered otherwise, as lidarops wrote them before, is rebuilt);
* voxelization (``transform_points_to_voxels``) is not done here: the model voxelizes on the device.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from torch.utils.data import Dataset

from lidarops._moved import moved_attributes
from lidarops.conventions import KITTI_CLASSES
from lidarops.data._checks import read_text
from lidarops.data.datasets import collate_batch
from lidarops.data.augment import (BOX_MARGIN_XY, GtDatabase, GtSampler, _care, _counts, _frame_labels,
                                   build_gt_database, flip_along_x, flip_along_y, rotate_world, scale_world)
from lidarops.data.formats.kitti import (
    KITTI_IMAGE_SIZE,
    KittiDataset,
    KittiLabels,
    camera_to_lidar_boxes,
    kitti_difficulty,
    kitti_fov_mask,
    png_size,
    read_calib,
    read_velodyne,
)
from lidarops.data.geometry import box_corners, wrap_angle

__all__ = [
    "DetectionConfig",
    "TRANSFER_AUGMENTATIONS",
    "drop_points",
    "perturb_intensity",
    "drop_alternate_beams",
    "KittiDetectionDataset",
    "train_val_datasets",
    "collate_batch",
    "mask_points_by_range",
    "mask_boxes_outside_range",
    "AUGMENTATIONS",
]

log = logging.getLogger(__name__)

# names of lidarops 0.1 that moved (to lidarops.data.augment, lidarops.data.formats.kitti, lidarops.conventions)
__getattr__ = moved_attributes(__name__, {"DEFAULT_CLASS_NAMES": ("lidarops.conventions", "KITTI_CLASSES")})

#: The augmentations supported, by their OpenPCDet ``AUG_CONFIG_LIST`` names (and pointpillar.yaml's order).
#: lidarops' own, for transfer from simulated to real scans (OpenPCDet has none of them; off unless listed)
TRANSFER_AUGMENTATIONS: tuple[str, ...] = ("random_point_dropout", "random_intensity", "random_beam_drop")
_OPENPCDET_AUGMENTATIONS = ("gt_sampling", "random_world_flip", "random_world_rotation", "random_world_scaling")
AUGMENTATIONS: tuple[str, ...] = _OPENPCDET_AUGMENTATIONS + TRANSFER_AUGMENTATIONS
_PROCESSORS = ("mask_points_and_boxes_outside_range", "shuffle_points", "transform_points_to_voxels")
_MAX_RESAMPLES = 20  # OpenPCDet redraws without bound; a set without labels must not hang the trainer


def _pair(value: Any, what: str) -> tuple[float, float]:
    lo, hi = (float(v) for v in value)
    if not lo <= hi:
        raise ValueError(f"{what} must be [low, high] with low <= high, got {list(value)}")
    return lo, hi


@dataclass
class DetectionConfig:
    """Data processing and augmentation of detection training (OpenPCDet's ``DATA_CONFIG``).

    Defaults are OpenPCDet's KITTI PointPillars (``pointpillar.yaml``). :meth:`from_openpcdet` reads the
    OpenPCDet keys (given in brackets).

    Attributes:
        point_cloud_range (tuple of 6 float): ``x0, y0, z0, x1, y1, z1`` (``POINT_CLOUD_RANGE``).
        fov_points_only (bool): keep only the points that project into the camera image (``FOV_POINTS_ONLY``).
        augmentations (tuple of str): the training augmentations, in order (names of ``AUG_CONFIG_LIST``,
            a subset of :data:`AUGMENTATIONS`; leave one out to disable it). Default: OpenPCDet's four;
            :data:`TRANSFER_AUGMENTATIONS` only when listed.
        sample_groups (dict[str, int]): gt sampling, objects drawn per class (``SAMPLE_GROUPS``, 'Car:15').
        min_points (dict[str, int]): gt sampling, database objects with fewer points are never drawn
            (``PREPARE.filter_by_min_points``).
        remove_difficulty (tuple of int): gt sampling, database objects of these difficulties are never drawn
            (``PREPARE.filter_by_difficulty``; -1 is KITTI's "unknown": too small, occluded or truncated).
        remove_extra_width (tuple of 3 float): scene points inside the sampled boxes grown by this much are
            removed (``REMOVE_EXTRA_WIDTH``).
        limit_whole_scene (bool): draw ``group - objects of the class already in the scene`` instead of
            ``group`` (``LIMIT_WHOLE_SCENE``; False in pointpillar.yaml).
        flip_axes (tuple of str): ``random_world_flip`` axes, ``"x"`` (y -> -y) and/or ``"y"`` (``ALONG_AXIS_LIST``).
        rotation_range (tuple of 2 float): ``random_world_rotation`` angle range, radians (``WORLD_ROT_ANGLE``).
        scale_range (tuple of 2 float): ``random_world_scaling`` factor range (``WORLD_SCALE_RANGE``).
        point_dropout_range (tuple of 2 float): ``random_point_dropout`` (lidarops): each frame drops each point
            with a probability drawn from this range (``DROP_RANGE``).
        intensity_scale_range (tuple of 2 float), intensity_jitter (float), intensity_zero_range (tuple of 2
            float): ``random_intensity`` (lidarops): each frame's intensities are multiplied by a factor from
            ``SCALE_RANGE``, get Gaussian noise of ``JITTER``, and a share from ``ZERO_RANGE`` of them reads 0;
            clipped to [0, 1].
        beam_drop_prob (float), beam_bin_deg (float): ``random_beam_drop`` (lidarops): with probability
            ``PROB`` a frame keeps every other beam, the beams told apart by their elevation seen from the
            sensor in bins of ``BIN_DEG`` degrees (a 64-beam scan made to look like a 32-beam one).
        mask_outside_range (bool): run ``mask_points_and_boxes_outside_range`` (points: x and y in the range).
        remove_outside_boxes (bool): in training, drop the boxes :func:`mask_boxes_outside_range` rejects
            (``REMOVE_OUTSIDE_BOXES``).
        use_center_to_filter (bool): keep a box when its centre is in the range (x, y and z; OpenPCDet's
            default since 2022), else when ``min_num_corners`` of its corners are, in x and y
            (``USE_CENTER_TO_FILTER``).
        min_num_corners (int): see ``use_center_to_filter``.
        shuffle_train, shuffle_test (bool): ``shuffle_points`` (``SHUFFLE_ENABLED`` train / test).
    """

    point_cloud_range: tuple[float, ...] = (0.0, -39.68, -3.0, 69.12, 39.68, 1.0)
    fov_points_only: bool = True
    augmentations: tuple[str, ...] = _OPENPCDET_AUGMENTATIONS
    sample_groups: dict[str, int] = field(default_factory=lambda: {"Car": 15, "Pedestrian": 15, "Cyclist": 15})
    min_points: dict[str, int] = field(default_factory=lambda: {"Car": 5, "Pedestrian": 5, "Cyclist": 5})
    remove_difficulty: tuple[int, ...] = (-1,)
    remove_extra_width: tuple[float, float, float] = (0.0, 0.0, 0.0)
    limit_whole_scene: bool = False
    flip_axes: tuple[str, ...] = ("x",)
    rotation_range: tuple[float, float] = (-math.pi / 4, math.pi / 4)
    scale_range: tuple[float, float] = (0.95, 1.05)
    point_dropout_range: tuple[float, float] = (0.0, 0.3)
    intensity_scale_range: tuple[float, float] = (0.6, 1.4)
    intensity_jitter: float = 0.05
    intensity_zero_range: tuple[float, float] = (0.0, 0.3)
    beam_drop_prob: float = 0.2
    beam_bin_deg: float = 0.42
    mask_outside_range: bool = True
    remove_outside_boxes: bool = True
    use_center_to_filter: bool = True
    min_num_corners: int = 1
    shuffle_train: bool = True
    shuffle_test: bool = False

    def __post_init__(self) -> None:
        r = tuple(float(v) for v in self.point_cloud_range)
        if len(r) != 6 or not all(r[i] < r[i + 3] for i in range(3)):
            raise ValueError(f"point_cloud_range must be [x0, y0, z0, x1, y1, z1] with x0 < x1 etc., got {list(r)}")
        self.point_cloud_range = r
        self.augmentations = tuple(self.augmentations)
        unknown = [a for a in self.augmentations if a not in AUGMENTATIONS]
        if unknown or len(set(self.augmentations)) != len(self.augmentations):
            raise ValueError(f"augmentations must be distinct names from {list(AUGMENTATIONS)}, "
                             f"got {list(self.augmentations)}")
        self.sample_groups = _counts(self.sample_groups, "sample_groups")
        self.min_points = _counts(self.min_points, "min_points")
        self.remove_difficulty = tuple(int(v) for v in self.remove_difficulty)
        self.remove_extra_width = tuple(float(v) for v in self.remove_extra_width)
        if len(self.remove_extra_width) != 3:
            raise ValueError(f"remove_extra_width must have 3 values (dx, dy, dz), got {list(self.remove_extra_width)}")
        self.flip_axes = tuple(self.flip_axes)
        if any(a not in ("x", "y") for a in self.flip_axes):
            raise ValueError(f"flip_axes must hold 'x' and/or 'y', got {list(self.flip_axes)}")
        self.rotation_range = _pair(self.rotation_range, "rotation_range")
        self.scale_range = _pair(self.scale_range, "scale_range")
        if self.scale_range[0] <= 0:
            raise ValueError(f"scale_range must be positive, got {list(self.scale_range)}")
        for name in ("point_dropout_range", "intensity_zero_range"):
            lo, hi = _pair(getattr(self, name), name)
            if not (0 <= lo and hi <= 1):
                raise ValueError(f"{name} must lie in [0, 1], got {[lo, hi]}")
            setattr(self, name, (lo, hi))
        self.intensity_scale_range = _pair(self.intensity_scale_range, "intensity_scale_range")
        if not self.intensity_scale_range[0] >= 0:
            raise ValueError(f"intensity_scale_range must be >= 0, got {list(self.intensity_scale_range)}")
        for name, hi in (("intensity_jitter", 1.0), ("beam_drop_prob", 1.0), ("beam_bin_deg", 10.0)):
            v = float(getattr(self, name))
            if not 0 <= v <= hi or (name == "beam_bin_deg" and v == 0):
                raise ValueError(f"{name} must be in {'(0' if name == 'beam_bin_deg' else '[0'}, {hi}], got {v}")
            setattr(self, name, v)
        if not isinstance(self.use_center_to_filter, (bool, np.bool_)):
            raise ValueError(f"use_center_to_filter must be True or False, got {self.use_center_to_filter!r}")
        self.use_center_to_filter = bool(self.use_center_to_filter)
        if int(self.min_num_corners) not in range(1, 9):
            raise ValueError(f"min_num_corners must be 1..8, got {self.min_num_corners}")

    @classmethod
    def from_openpcdet(cls, cfg: Mapping[str, Any]) -> "DetectionConfig":
        """A config from OpenPCDet's ``DATA_CONFIG`` (or a whole model config holding one).

        Read: ``POINT_CLOUD_RANGE``, ``FOV_POINTS_ONLY``, ``DATA_AUGMENTOR`` (``AUG_CONFIG_LIST`` and
        ``DISABLE_AUG_LIST``, or the older bare list) with the entries ``gt_sampling``, ``random_world_flip``,
        ``random_world_rotation``, ``random_world_scaling``, and ``DATA_PROCESSOR`` with
        ``mask_points_and_boxes_outside_range`` and ``shuffle_points``. Ignored: dataset paths and splits,
        ``POINT_FEATURE_ENCODING`` (x, y, z, intensity), ``transform_points_to_voxels`` (the model
        voxelizes), gt sampling's ``DB_INFO_PATH`` (see ``gt_database``) and ``USE_ROAD_PLANE``. Keys absent
        keep the defaults; an augmentor or processor lidarops does not implement raises.

        Raises:
            ValueError: an unsupported augmentor, processor or option.
        """
        cfg = cfg.get("DATA_CONFIG", cfg)
        kw: dict[str, Any] = {}
        if "POINT_CLOUD_RANGE" in cfg:
            kw["point_cloud_range"] = tuple(cfg["POINT_CLOUD_RANGE"])
        if "FOV_POINTS_ONLY" in cfg:
            kw["fov_points_only"] = bool(cfg["FOV_POINTS_ONLY"])
        augmentor = cfg.get("DATA_AUGMENTOR")
        if augmentor is not None:
            if isinstance(augmentor, Mapping):
                entries, disabled = augmentor.get("AUG_CONFIG_LIST", []), set(augmentor.get("DISABLE_AUG_LIST", []))
            else:
                entries, disabled = augmentor, set()
            names = []
            for entry in entries:
                name = entry["NAME"]
                if name in disabled:
                    continue
                kw.update(_augmentor_options(name, entry))
                names.append(name)
            kw["augmentations"] = tuple(names)
        processors = cfg.get("DATA_PROCESSOR")
        if processors is not None:
            names = [entry["NAME"] for entry in processors]
            for entry in processors:
                if entry["NAME"] not in _PROCESSORS:
                    raise ValueError(f"DATA_PROCESSOR {entry['NAME']!r} is not supported (supported: {list(_PROCESSORS)})")
                if entry["NAME"] == "mask_points_and_boxes_outside_range":
                    kw["remove_outside_boxes"] = bool(entry.get("REMOVE_OUTSIDE_BOXES", True))
                    kw["use_center_to_filter"] = bool(entry.get("USE_CENTER_TO_FILTER", True))
                    kw["min_num_corners"] = int(entry.get("min_num_corners", 1))
                elif entry["NAME"] == "shuffle_points":
                    enabled = entry.get("SHUFFLE_ENABLED", {"train": True, "test": False})
                    kw["shuffle_train"], kw["shuffle_test"] = bool(enabled["train"]), bool(enabled["test"])
            kw["mask_outside_range"] = "mask_points_and_boxes_outside_range" in names
            if "shuffle_points" not in names:
                kw["shuffle_train"] = kw["shuffle_test"] = False
        return cls(**kw)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (for checkpoints and recipes)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))


def _augmentor_options(name: str, entry: Mapping[str, Any]) -> dict[str, Any]:
    if name == "gt_sampling":
        prepare = dict(entry.get("PREPARE", {}) or {})
        unknown = set(prepare) - {"filter_by_min_points", "filter_by_difficulty"}
        if unknown:
            raise ValueError(f"gt_sampling PREPARE {sorted(unknown)} is not supported")
        if entry.get("DATABASE_WITH_FAKELIDAR", False):
            raise ValueError("gt_sampling DATABASE_WITH_FAKELIDAR is not supported "
                             "(databases are in the LiDAR box convention)")
        if int(entry.get("NUM_POINT_FEATURES", 4)) != 4:
            raise ValueError(f"gt_sampling NUM_POINT_FEATURES must be 4 (x, y, z, intensity), "
                             f"got {entry['NUM_POINT_FEATURES']}")
        return {
            "sample_groups": _counts(entry.get("SAMPLE_GROUPS", []), "SAMPLE_GROUPS"),
            "min_points": _counts(prepare.get("filter_by_min_points", []), "filter_by_min_points"),
            "remove_difficulty": tuple(int(v) for v in prepare.get("filter_by_difficulty", [])),
            "remove_extra_width": tuple(entry.get("REMOVE_EXTRA_WIDTH", (0.0, 0.0, 0.0))),
            "limit_whole_scene": bool(entry.get("LIMIT_WHOLE_SCENE", False)),
        }
    if name == "random_world_flip":
        return {"flip_axes": tuple(entry["ALONG_AXIS_LIST"])}
    if name == "random_world_rotation":
        angle = entry["WORLD_ROT_ANGLE"]
        return {"rotation_range": tuple(angle) if isinstance(angle, (list, tuple)) else (-float(angle), float(angle))}
    if name == "random_world_scaling":
        return {"scale_range": tuple(entry["WORLD_SCALE_RANGE"])}
    if name == "random_point_dropout":
        return {"point_dropout_range": tuple(entry.get("DROP_RANGE", (0.0, 0.3)))}
    if name == "random_intensity":
        return {"intensity_scale_range": tuple(entry.get("SCALE_RANGE", (0.6, 1.4))),
                "intensity_jitter": float(entry.get("JITTER", 0.05)),
                "intensity_zero_range": tuple(entry.get("ZERO_RANGE", (0.0, 0.3)))}
    if name == "random_beam_drop":
        return {"beam_drop_prob": float(entry.get("PROB", 0.2)), "beam_bin_deg": float(entry.get("BIN_DEG", 0.42))}
    raise ValueError(f"augmentation {name!r} is not supported (supported: {list(AUGMENTATIONS)})")


# ---------------------------------------------------------------------------------------------
# processing and augmentation (NumPy; boxes are (M, 7 + C) x, y, z, dx, dy, dz, heading, ...)
# ---------------------------------------------------------------------------------------------
def drop_points(points: np.ndarray, p: float, rng: np.random.Generator) -> np.ndarray:
    """Each point kept with probability ``1 - p`` (order kept)."""
    return points[rng.random(points.shape[0]) >= p] if p > 0 else points


def perturb_intensity(points: np.ndarray, scale: float, jitter: float, zero: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Column 3 multiplied by ``scale``, plus Gaussian noise of ``jitter``, a share ``zero`` of the points set
    to 0, clipped to [0, 1] (a copy; the other columns untouched)."""
    out = points.copy()
    n = out.shape[0]
    value = out[:, 3].astype(np.float64) * scale + jitter * rng.standard_normal(n)
    value[rng.random(n) < zero] = 0.0
    out[:, 3] = np.clip(value, 0.0, 1.0)
    return out


def drop_alternate_beams(points: np.ndarray, bin_deg: float, parity: int) -> np.ndarray:
    """Keeps the points of every other beam, beams told apart by their elevation from the sensor (at the
    origin) in bins of ``bin_deg`` degrees; ``parity`` picks the even or the odd bins."""
    elevation = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
    return points[np.floor(elevation / bin_deg).astype(np.int64) % 2 == parity]


def mask_points_by_range(points: np.ndarray, point_cloud_range: Sequence[float]) -> np.ndarray:
    """OpenPCDet's ``mask_points_by_range``: ``x0 <= x <= x1`` and ``y0 <= y <= y1``.

    Like OpenPCDet, z is not checked (points outside ``z0..z1`` are left to the voxelizer) and both ends
    are closed (a point at ``x1`` falls outside the voxel grid, and the voxelizer drops it).

    Args:
        points (ndarray[N, >=2]): points.
        point_cloud_range (sequence of 6 float): ``x0, y0, z0, x1, y1, z1``.

    Returns:
        ndarray bool[N].
    """
    r = point_cloud_range
    x, y = points[:, 0], points[:, 1]
    return (x >= r[0]) & (x <= r[3]) & (y >= r[1]) & (y <= r[4])


def mask_boxes_outside_range(boxes: np.ndarray, point_cloud_range: Sequence[float], min_num_corners: int = 1,
                             use_center_to_filter: bool = True) -> np.ndarray:
    """OpenPCDet's ``mask_boxes_outside_range_numpy`` (its ``mask_points_and_boxes_outside_range`` passes
    ``USE_CENTER_TO_FILTER``, default True): boxes whose centre lies in the closed range in x, y and z; with
    ``use_center_to_filter=False``, boxes with at least ``min_num_corners`` of their eight corners in the
    closed range in x and y.

    Args:
        boxes (ndarray[M, >=7]): boxes.
        point_cloud_range (sequence of 6 float): ``x0, y0, z0, x1, y1, z1``.
        min_num_corners (int): corners required (corner rule only).
        use_center_to_filter (bool): the centre rule.

    Returns:
        ndarray bool[M].
    """
    r = np.asarray(point_cloud_range, dtype=np.float32)  # OpenPCDet's range is float32 (a centre on its end is in)
    boxes = np.asarray(boxes)[:, :7]
    if use_center_to_filter:
        centres = boxes[:, :3]
        return ((centres >= r[:3]) & (centres <= r[3:])).all(axis=1)
    corners = box_corners(boxes)[:, :, :2]  # (M, 8, 2)
    inside = ((corners >= r[:2]) & (corners <= r[3:5])).all(axis=2)
    return inside.sum(axis=1) >= min_num_corners


# ---------------------------------------------------------------------------------------------
# the dataset
# ---------------------------------------------------------------------------------------------
def _read_recipe(path: Path) -> dict:
    """The ``recipe.json`` a ``lidarops data synth`` folder carries: a JSON object (errors name the file)."""
    try:
        recipe = json.loads(read_text(path, "JSON"))
    except (json.JSONDecodeError, RecursionError) as e:
        raise ValueError(f"{path}: malformed JSON ({type(e).__name__}: {e})") from None
    if not isinstance(recipe, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(recipe).__name__}")
    return recipe


def _annos(labels: KittiLabels) -> dict[str, np.ndarray]:
    """The label file's fields (DontCare included) for evaluation; ``dimensions_hwl`` in the file's h, w, l."""
    annos = {
        "name": np.array(labels.names, dtype=str).reshape(-1),
        "truncated": np.asarray(labels.truncated, dtype=np.float64),  # float64, as KITTI's evaluator reads them
        "occluded": np.asarray(labels.occluded, dtype=np.int64),
        "alpha": np.asarray(labels.alpha, dtype=np.float64),
        "bbox": np.asarray(labels.bbox, dtype=np.float64).reshape(-1, 4),
        "dimensions_hwl": np.asarray(labels.dimensions, dtype=np.float64).reshape(-1, 3),
        "location": np.asarray(labels.location, dtype=np.float64).reshape(-1, 3),
        "rotation_y": np.asarray(labels.rotation_y, dtype=np.float64),
        "difficulty": kitti_difficulty(labels),
    }
    if labels.score is not None:
        annos["score"] = np.asarray(labels.score, dtype=np.float64)
    return annos


class KittiDetectionDataset(Dataset):
    """KITTI-format frames as OpenPCDet-style training or evaluation items (see the module docstring).

    Items are dicts:

    * ``points`` (ndarray float32[N, 4]): ``x, y, z, intensity``;
    * ``gt_boxes`` (ndarray float32[M, 8]): ``x, y, z, dx, dy, dz, heading, class id`` (1-based, the
      position in ``class_names`` + 1), LiDAR frame, z the box centre;
    * ``frame_id`` (str);
    * ``annos`` (dict of ndarray): every object of the label file, ``DontCare`` included, for evaluation:
      ``name``, ``truncated``, ``occluded``, ``alpha``, ``bbox``, ``dimensions_hwl`` (KITTI's h, w, l order,
      not OpenPCDet's l, h, w), ``location``, ``rotation_y``, ``difficulty`` (:func:`kitti_difficulty`);
    * ``calib`` (:class:`~lidarops.data.formats.kitti.KittiCalib`);
    * in training, ``augmentation`` (dict): what was drawn: ``gt_sampled`` (objects pasted), ``flip_x``,
      ``flip_y``, ``rotation`` (rad), ``scale``, ``resampled_from`` (the index asked for, when its frame
      had no box left and another was drawn; else absent).

    Args:
        root (str or Path): KITTI root (holding ``training/`` and ``ImageSets/``) or a split directory.
        split (str, sequence of str or None): an ``ImageSets`` name (``"train"``, ``"val"``; ``"test"``
            reads ``testing/``), a list of frame ids, or ``None`` for every scan.
        class_names (sequence of str): training classes, in class-id order.
        config (DetectionConfig, OpenPCDet DATA_CONFIG dict or None): processing; default pointpillar.yaml's.
        training (bool): augment, drop boxes outside the range, shuffle; else evaluation items.
        seed (int): base of every random draw (>= 0).
        gt_database (GtDatabase, path or None): objects for gt sampling (training only). ``None``: the file
            ``gt_database_<split>.npz`` next to ``ImageSets``, (re)built from this split's frames when missing,
            made from other frames or gathered with another margin than OpenPCDet's (kept in memory where the
            folder is read-only); for an id list, a database built in memory.
    """

    def __init__(self, root: str | Path, split: str | Sequence[str] | None = "train",
                 class_names: Sequence[str] = KITTI_CLASSES, config: "DetectionConfig | Mapping | None" = None,
                 training: bool = True, seed: int = 0, gt_database: "GtDatabase | str | Path | None" = None) -> None:
        if config is None:
            config = DetectionConfig()
        elif not isinstance(config, DetectionConfig):
            config = DetectionConfig.from_openpcdet(config)
        self.config = config
        self.class_names = tuple(class_names)
        if not self.class_names or len(set(self.class_names)) != len(self.class_names):
            raise ValueError(f"class_names must be distinct and not empty, got {list(class_names)}")
        self.training = bool(training)
        if int(seed) < 0:
            raise ValueError(f"seed must be >= 0, got {seed}")
        self.seed = int(seed)
        self.epoch = 0
        named = isinstance(split, str) or split is None
        kitti = KittiDataset(root, split="testing" if split == "test" else "training", image_set=split if named else None)
        self.split_dir = kitti.split_dir
        self.split = split if named else None
        self.ids = list(kitti.ids) if named else [str(i) for i in split]
        top = self.split_dir.parent if self.split_dir.name in ("training", "testing") else self.split_dir
        self.root = top
        recipe = top / "recipe.json"
        #: the ``lidarops data synth`` recipe of the folder (None for other folders)
        self.recipe = _read_recipe(recipe) if recipe.is_file() else None
        self.sampler: GtSampler | None = None
        if self.training and "gt_sampling" in config.augmentations and config.sample_groups:
            db = self._database(gt_database)
            self.sampler = GtSampler(db, config.sample_groups, config.min_points, self.class_names,
                                     remove_difficulty=config.remove_difficulty,
                                     remove_extra_width=config.remove_extra_width,
                                     limit_whole_scene=config.limit_whole_scene)

    def _database(self, gt_database: "GtDatabase | str | Path | None") -> GtDatabase:
        if isinstance(gt_database, GtDatabase):
            return gt_database
        if gt_database is not None:
            return GtDatabase.load(gt_database)
        if self.split is None or not isinstance(self.split, str):
            return build_gt_database(self, class_names=self.class_names)
        path = self.root / f"gt_database_{self.split}.npz"
        if path.is_file():
            db = GtDatabase.load(path)
            # built from these frames (for every object type), their points gathered as OpenPCDet does
            if list(db.source_ids) == self.ids and db.margin == BOX_MARGIN_XY:
                return db
        log.info("building the gt database of %s (%d frames) at %s", self.split_dir, len(self.ids), path)
        db = build_gt_database(self, class_names=None)
        try:
            db.save(path)
        except OSError as e:  # a read-only copy of KITTI: keep it in memory
            log.warning("could not save the gt database to %s (%s); pass gt_database=PATH to keep it", path, e)
        return db

    def set_epoch(self, epoch: int) -> None:
        """Sets the epoch that seeds the augmentations (call before creating each epoch's iterator)."""
        if int(epoch) < 0:
            raise ValueError(f"epoch must be >= 0, got {epoch}")
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.ids)

    def image_size(self, index: int) -> tuple[int, int]:
        """(width, height) of frame ``index``'s image: from ``image_2/<id>.png`` when present, else KITTI's."""
        return png_size(self.split_dir / "image_2" / f"{self.ids[index]}.png") or KITTI_IMAGE_SIZE

    def __getitem__(self, index: int) -> dict[str, Any]:
        index = int(index)
        if not 0 <= index < len(self):
            raise IndexError(f"item {index} out of range ({len(self)} frames)")
        first = index
        for _ in range(_MAX_RESAMPLES):
            rng = np.random.default_rng((self.seed, self.epoch, index))
            item = self._item(index, rng)
            if not self.training or item["gt_boxes"].shape[0] > 0:
                break
            index = int(rng.integers(len(self)))  # OpenPCDet: an item without boxes is replaced by a random one
        if index != first and self.training:
            item["augmentation"]["resampled_from"] = first
        return item

    def _item(self, index: int, rng: np.random.Generator) -> dict[str, Any]:
        cfg = self.config
        frame_id = self.ids[index]
        points = read_velodyne(self.split_dir / "velodyne" / f"{frame_id}.bin")
        calib = read_calib(self.split_dir / "calib" / f"{frame_id}.txt")
        labels = _frame_labels(self.split_dir, frame_id)
        if cfg.fov_points_only:
            points = points[kitti_fov_mask(points, calib, self.image_size(index))]
        care = labels.select(_care(labels))
        boxes = camera_to_lidar_boxes(care.location, care.dimensions, care.rotation_y, calib).astype(np.float32)
        names = np.array(care.names, dtype=str)
        item: dict[str, Any] = {"frame_id": frame_id, "annos": _annos(labels), "calib": calib}
        if self.training:
            points, boxes, names, item["augmentation"] = self._augment(points, boxes, names, rng)
        keep = np.isin(names, self.class_names)
        class_id = np.array([self.class_names.index(n) + 1 for n in names[keep]], dtype=np.float32)
        gt_boxes = np.concatenate([boxes[keep], class_id[:, None]], axis=1).astype(np.float32)
        if cfg.mask_outside_range:
            points = points[mask_points_by_range(points, cfg.point_cloud_range)]
            if self.training and cfg.remove_outside_boxes:
                gt_boxes = gt_boxes[mask_boxes_outside_range(gt_boxes, cfg.point_cloud_range, cfg.min_num_corners,
                                                             cfg.use_center_to_filter)]
        if cfg.shuffle_train if self.training else cfg.shuffle_test:
            points = points[rng.permutation(points.shape[0])]
        item["points"] = np.ascontiguousarray(points, dtype=np.float32)
        item["gt_boxes"] = gt_boxes
        return item

    def _augment(self, points: np.ndarray, boxes: np.ndarray, names: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        """OpenPCDet's ``DataAugmentor.forward``: the augmentations in config order, headings wrapped."""
        cfg = self.config
        info: dict[str, Any] = {"gt_sampled": 0, "flip_x": False, "flip_y": False, "rotation": 0.0, "scale": 1.0}
        for name in cfg.augmentations:
            if name == "gt_sampling" and self.sampler is not None:
                before = boxes.shape[0]
                points, boxes, names = self.sampler(points, boxes, names, rng)
                info["gt_sampled"] = int(boxes.shape[0] - before)
            elif name == "random_world_flip":
                for axis in cfg.flip_axes:
                    if rng.random() < 0.5:
                        points, boxes = (flip_along_x if axis == "x" else flip_along_y)(points, boxes)
                        info[f"flip_{axis}"] = True
            elif name == "random_world_rotation":
                info["rotation"] = float(rng.uniform(*cfg.rotation_range))
                points, boxes = rotate_world(points, boxes, info["rotation"])
            elif name == "random_world_scaling" and cfg.scale_range[1] - cfg.scale_range[0] >= 1e-3:  # OpenPCDet's test
                info["scale"] = float(rng.uniform(*cfg.scale_range))
                points, boxes = scale_world(points, boxes, info["scale"])
            elif name == "random_point_dropout":
                info["point_dropout"] = float(rng.uniform(*cfg.point_dropout_range))
                points = drop_points(points, info["point_dropout"], rng)
            elif name == "random_intensity":
                info["intensity_scale"] = float(rng.uniform(*cfg.intensity_scale_range))
                info["intensity_zero"] = float(rng.uniform(*cfg.intensity_zero_range))
                points = perturb_intensity(points, info["intensity_scale"], cfg.intensity_jitter, info["intensity_zero"],
                                           rng)
            elif name == "random_beam_drop":
                info["beam_drop"] = bool(rng.random() < cfg.beam_drop_prob)
                if info["beam_drop"]:
                    points = drop_alternate_beams(points, cfg.beam_bin_deg, int(rng.integers(2)))
        boxes = boxes.copy()
        boxes[:, 6] = wrap_angle(boxes[:, 6].astype(np.float64))
        return points, boxes, names, info

    def __repr__(self) -> str:
        mode = "training" if self.training else "evaluation"
        return (f"KittiDetectionDataset({str(self.split_dir)!r}, split={self.split!r}, {len(self)} frames, {mode}, "
                f"classes={list(self.class_names)})")


def train_val_datasets(root: str | Path, class_names: Sequence[str] = KITTI_CLASSES,
                       config: "DetectionConfig | Mapping | None" = None, seed: int = 0,
                       gt_database: "GtDatabase | str | Path | None" = None, train_split: str = "train",
                       val_split: str = "val") -> tuple[KittiDetectionDataset, KittiDetectionDataset]:
    """The training and evaluation datasets of a KITTI folder (``lidarops data synth`` output or real KITTI):
    ``ImageSets/<train_split>.txt`` augmented, ``ImageSets/<val_split>.txt`` for evaluation; the gt database
    comes from the training frames only. The folder's ``recipe.json`` (if any) is on ``.recipe``."""
    train = KittiDetectionDataset(root, train_split, class_names, config, training=True, seed=seed, gt_database=gt_database)
    val = KittiDetectionDataset(root, val_split, class_names, train.config, training=False, seed=seed)
    return train, val
