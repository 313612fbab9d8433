"""Object-level classification sets cut out of detection frames (NumPy only).

Like the KITTI classification set of the CAS-Net paper: the points inside each ground-truth box
become one sample labelled with the box's class; boxes with fewer than ``min_points`` points are
skipped; the train/test split is stratified by class *and* point count, so both halves see the same
mix of sparse and dense objects.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from lidarops.data._checks import read_npz
from lidarops.data.frame import CLASSES, Frame
from lidarops.data.geometry import points_in_boxes_mask

__all__ = ["ObjectSample", "ObjectSet", "extract_objects", "split_balanced", "canonicalize"]


@dataclass
class ObjectSample:
    """One object cloud.

    Attributes:
        points (ndarray float32[P, 4]): x, y, z, intensity (in the box frame if canonicalised).
        label (int): class index.
        box (ndarray float32[7]): the box in the frame's LiDAR frame.
        frame_index (int): frame it came from.
        object_id (int): track id (-1 unknown).
    """

    points: np.ndarray
    label: int
    box: np.ndarray
    frame_index: int = 0
    object_id: int = -1

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])


def canonicalize(points: np.ndarray, box: np.ndarray) -> np.ndarray:
    """Moves points into a box's frame: origin at the box centre, x along its heading.

    Args:
        points (ndarray[P, >=3]): points (extra columns kept).
        box (ndarray[7]): the box.

    Returns:
        ndarray float32[P, C].
    """
    out = np.array(points, dtype=np.float32, copy=True)
    c, s = np.cos(box[6]), np.sin(box[6])
    d = points[:, :3].astype(np.float64) - np.asarray(box[:3], dtype=np.float64)
    out[:, 0] = c * d[:, 0] + s * d[:, 1]
    out[:, 1] = -s * d[:, 0] + c * d[:, 1]
    out[:, 2] = d[:, 2]
    return out


def extract_objects(frames: Iterable[Frame], min_points: int = 10, canonical: bool = True, margin: float = 0.0,
                    classes: Sequence[str] | None = None) -> list[ObjectSample]:
    """Cuts the points inside every box of every frame.

    Args:
        frames (iterable of Frame): detection frames (e.g. a KittiDataset or SyntheticFrames).
        min_points (int): skip boxes with fewer points.
        canonical (bool): express each object in its box frame (centre at 0, heading along +x).
        margin (float): grow the boxes by this many metres when cutting.
        classes (sequence of str or None): keep only these class names.

    Returns:
        list[ObjectSample].
    """
    out: list[ObjectSample] = []
    for frame in frames:
        if frame.num_boxes == 0:
            continue
        mask = points_in_boxes_mask(frame.points, frame.boxes, margin=margin)
        for j in range(frame.num_boxes):
            label = int(frame.labels[j])
            if label < 0:
                continue
            if classes is not None and frame.class_names[label] not in classes:
                continue
            idx = np.flatnonzero(mask[:, j])
            if idx.size < min_points:
                continue
            pts = frame.points[idx]
            if canonical:
                pts = canonicalize(pts, frame.boxes[j])
            out.append(ObjectSample(pts.astype(np.float32), label, frame.boxes[j].copy(), frame.frame_index,
                                    int(frame.object_ids[j])))
    return out


def split_balanced(samples: Sequence[ObjectSample], test_fraction: float = 0.2, seed: int = 0,
                   bins: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Train/test split stratified by class and by point-count quantile.

    Within each class the samples are sorted into ``bins`` point-count quantile bins; from each bin
    a ``test_fraction`` share (rounded, at least one when the bin has two or more samples) goes to the
    test set at random.

    Args:
        samples (sequence of ObjectSample): objects.
        test_fraction (float): share of the test set, in (0, 1).
        seed (int): random seed.
        bins (int): point-count bins per class.

    Returns:
        train_index, test_index (ndarray int64).
    """
    if not 0.0 < test_fraction < 1.0:
        raise ValueError("test_fraction must be in (0, 1)")
    rng = np.random.default_rng(seed)
    labels = np.array([s.label for s in samples], dtype=np.int64)
    counts = np.array([s.num_points for s in samples], dtype=np.int64)
    test: list[int] = []
    for label in np.unique(labels):
        idx = np.flatnonzero(labels == label)
        order = idx[np.argsort(counts[idx], kind="stable")]
        for chunk in np.array_split(order, min(bins, len(order))):
            n_test = int(round(len(chunk) * test_fraction))
            if n_test == 0 and len(chunk) >= 2 and rng.random() < len(chunk) * test_fraction:
                n_test = 1
            test.extend(rng.choice(chunk, size=n_test, replace=False).tolist())
    test_index = np.array(sorted(test), dtype=np.int64)
    train_index = np.setdiff1d(np.arange(len(samples)), test_index).astype(np.int64)
    return train_index, test_index


@dataclass
class ObjectSet:
    """A saved classification set.

    Attributes:
        samples (list[ObjectSample]): the objects.
        class_names (tuple[str, ...]): class list.
        train_index, test_index (ndarray int64): the split.
    """

    samples: list[ObjectSample]
    class_names: tuple[str, ...] = CLASSES
    train_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    test_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @staticmethod
    def from_frames(frames: Iterable[Frame], min_points: int = 10, canonical: bool = True, test_fraction: float = 0.2,
                    seed: int = 0, class_names: Sequence[str] = CLASSES) -> "ObjectSet":
        """Extracts objects (:func:`extract_objects`) and splits them (:func:`split_balanced`)."""
        samples = extract_objects(frames, min_points=min_points, canonical=canonical)
        train, test = split_balanced(samples, test_fraction, seed) if samples else (np.zeros(0, np.int64),) * 2
        return ObjectSet(samples, tuple(class_names), train, test)

    def __len__(self) -> int:
        return len(self.samples)

    def save(self, path: str | Path) -> Path:
        """Saves as one ``.npz`` (points concatenated with offsets)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        sizes = np.array([s.num_points for s in self.samples], dtype=np.int64)
        points = np.concatenate([s.points for s in self.samples]) if self.samples else np.zeros((0, 4), np.float32)
        np.savez_compressed(
            path, points=points, sizes=sizes, labels=np.array([s.label for s in self.samples], np.int64),
            boxes=np.array([s.box for s in self.samples], np.float32).reshape(-1, 7),
            frame_index=np.array([s.frame_index for s in self.samples], np.int64),
            object_id=np.array([s.object_id for s in self.samples], np.int64),
            train_index=self.train_index, test_index=self.test_index, class_names=np.array(self.class_names),
        )
        return path

    @staticmethod
    def load(path: str | Path) -> "ObjectSet":
        """Loads a set written by :meth:`save`.

        Raises:
            FileNotFoundError: missing file.
            ValueError: not an object-set archive (a damaged or truncated ``.npz``, missing arrays, or
                arrays that do not describe the same objects); the file is named.
        """
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"object set not found: {path}")
        need = ("points", "sizes", "labels", "boxes", "frame_index", "object_id", "train_index", "test_index", "class_names")
        z = read_npz(path, need, "an object set")
        n = z["sizes"].shape[0] if z["sizes"].ndim == 1 else -1
        ints = ("sizes", "labels", "frame_index", "object_id", "train_index", "test_index")
        problem = None
        if n < 0 or any(z[k].ndim != 1 or z[k].dtype.kind not in "iu" for k in ints):
            problem = f"{', '.join(ints)} must be 1-D integer arrays"
        elif any(z[k].shape[0] != n for k in ("labels", "frame_index", "object_id")) or z["boxes"].shape != (n, 7):
            problem = f"sizes, labels, frame_index, object_id and boxes must describe the same {n} objects"
        elif z["points"].ndim != 2 or z["points"].dtype.kind != "f" or (z["sizes"] < 0).any() \
                or int(z["sizes"].sum()) != z["points"].shape[0]:
            problem = "the object sizes do not add up to the rows of points"
        elif any(((z[k] < 0) | (z[k] >= n)).any() for k in ("train_index", "test_index")):
            problem = f"train_index/test_index out of range [0, {n})"
        elif z["class_names"].ndim != 1 or (z["class_names"].size and z["class_names"].dtype.kind not in "US"):
            problem = "class_names must be a 1-D array of strings"
        if problem:
            raise ValueError(f"{path}: not an object set written by ObjectSet.save ({problem})")
        offsets = np.concatenate([[0], np.cumsum(z["sizes"])])
        samples = [ObjectSample(z["points"][offsets[i]:offsets[i + 1]], int(z["labels"][i]), z["boxes"][i],
                                int(z["frame_index"][i]), int(z["object_id"][i])) for i in range(n)]
        return ObjectSet(samples, tuple(str(c) for c in z["class_names"]), z["train_index"], z["test_index"])
