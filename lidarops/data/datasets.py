"""PyTorch datasets with one interface whether the frames come from the simulator or from disk.

* :class:`DetectionDataset` -- frames as tensors with OpenPCDet's keys (``points``, ``gt_boxes`` with
  1-based class ids), batched by :func:`collate_batch` (the one collate of every detection dataset).
* :class:`ObjectDataset` -- object clouds ``(points, label)`` from detection frames or ModelNet40.
* :class:`StreamDataset` -- consecutive time slices ``{"points", "t"}`` of a simulator or of frames with
  per-point timestamps (e.g. a PandaSet sequence).

A *frame source* is anything with ``len()`` and integer indexing returning a
:class:`~lidarops.data.frame.Frame`: :class:`~lidarops.data.synthetic.SyntheticFrames`,
:class:`~lidarops.data.formats.KittiDataset`, :class:`~lidarops.data.formats.PandaSetSequence`, ...
Every dataset also accepts a path or a scenario name and opens it with
:func:`lidarops.data.formats.open_frames`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Protocol, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from lidarops._moved import warn_renamed
from lidarops.data._checks import integer, real
from lidarops.data.frame import Frame

__all__ = [
    "FrameSource",
    "as_frame_source",
    "DetectionDataset",
    "ObjectDataset",
    "StreamDataset",
    "collate_batch",
    "collate_detection",
    "collate_objects",
]


class FrameSource(Protocol):
    """Anything with ``len()`` and ``[i] -> Frame``."""

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Frame: ...


def as_frame_source(source: "FrameSource | str | Path", **kwargs) -> FrameSource:
    """A frame source from a source, a path or a scenario name (``"driving_city"``,
    ``"synthetic:drone_bridge"``); ``kwargs`` go to :func:`~lidarops.data.formats.open_frames`."""
    if isinstance(source, (str, Path)):
        from lidarops.data.formats import open_frames

        return open_frames(source, **kwargs)
    if kwargs:
        raise TypeError(f"options {sorted(kwargs)} only apply when the source is a path or a name")
    return source


class DetectionDataset(Dataset):
    """Detection frames of any frame source as tensors with OpenPCDet's keys (the batch dialect every
    lidarops model reads; :func:`collate_batch` batches them).

    Items are dicts with ``points (Tensor[N, 4])``, ``gt_boxes (Tensor[M, 8])`` (7 box values + the class
    id, 1-based into ``class_names``; boxes of other classes are left out, as OpenPCDet does),
    ``num_points_in_box (Tensor[M])``, ``frame_id`` (the frame's index in its source), and
    ``t (Tensor[N] float64)`` when the source has timestamps.

    Args:
        source: a frame source, a path or a scenario name.
        class_names (sequence of str or None): the classes kept, in label order; ``None``: the source's own
            class list (:data:`lidarops.data.CLASSES` for the simulator).
        min_points (int): drop boxes with fewer points.
        transform (callable or None): applied to the item dict.
        **source_options: see :func:`as_frame_source`.
    """

    def __init__(self, source, class_names: Sequence[str] | None = None, min_points: int = 0,
                 transform: Callable[[dict], dict] | None = None, **source_options) -> None:
        if isinstance(class_names, int) and not isinstance(class_names, bool):  # 0.1's DetectionDataset(src, min_points)
            raise TypeError("DetectionDataset's second argument is class_names; pass min_points= by keyword")
        self.source = as_frame_source(source, **source_options)
        self.class_names = None if class_names is None else tuple(str(n) for n in class_names)
        self.min_points = integer(min_points, "min_points", 0)
        self.transform = transform

    def __len__(self) -> int:
        return len(self.source)

    def __getitem__(self, i: int) -> dict[str, Any]:
        frame = self.source[i]
        if self.min_points > 0:
            frame = frame.filter_boxes(self.min_points)
        names = self.class_names if self.class_names is not None else tuple(frame.class_names)
        frame_names = [frame.class_names[k] if 0 <= k < len(frame.class_names) else None for k in frame.labels]
        class_id = np.array([names.index(n) + 1 if n in names else 0 for n in frame_names], dtype=np.float32)
        keep = class_id > 0
        gt_boxes = np.concatenate([frame.boxes[keep], class_id[keep, None]], axis=1).astype(np.float32)
        item = {
            "points": torch.from_numpy(frame.points),
            "gt_boxes": torch.from_numpy(gt_boxes),
            "num_points_in_box": torch.from_numpy(frame.num_points_in_box[keep]),
            "frame_id": frame.frame_index,
        }
        if frame.t is not None:
            item["t"] = torch.from_numpy(frame.t)
        return self.transform(item) if self.transform else item


def collate_batch(items: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
    """Batches detection items as OpenPCDet's ``collate_batch`` (the one collate of every detection dataset).

    Args:
        items: dicts with ``points`` (N, C) and ``gt_boxes`` (M, 8) as NumPy arrays or tensors, and any
            other keys.

    Returns:
        dict: ``points`` (Tensor float32[sum N, 1 + C]: frame index in the batch, then the point's columns),
        ``gt_boxes`` (Tensor float32[B, M_max, 8], zero padded: class id 0 marks padding), ``batch_size``
        (int), ``t`` (Tensor float64[sum N]) when every item has it; any other item key (``frame_id``,
        ``annos``, ``calib`` ...) becomes a list with one entry per frame.
    """
    items = list(items)
    batch_size = len(items)

    def array(x) -> np.ndarray:
        return x.numpy() if isinstance(x, torch.Tensor) else np.asarray(x)

    pts = [array(it["points"]) for it in items]
    width = pts[0].shape[1] if pts else 4
    points = [np.concatenate([np.full((p.shape[0], 1), b, np.float32), p.astype(np.float32, copy=False)], axis=1)
              for b, p in enumerate(pts)]
    boxes = [array(it["gt_boxes"]) for it in items]
    m = max([g.shape[0] for g in boxes] + [0])
    gt_boxes = np.zeros((batch_size, m, boxes[0].shape[1] if boxes else 8), dtype=np.float32)
    for b, g in enumerate(boxes):
        gt_boxes[b, :g.shape[0]] = g
    out: dict[str, Any] = {
        "points": torch.from_numpy(np.concatenate(points) if points else np.zeros((0, 1 + width), np.float32)),
        "gt_boxes": torch.from_numpy(gt_boxes),
        "batch_size": batch_size,
    }
    if items and all("t" in it for it in items):
        out["t"] = torch.from_numpy(np.concatenate([array(it["t"]).astype(np.float64, copy=False) for it in items]))
    for key in dict.fromkeys(k for it in items for k in it):
        if key not in out:
            out[key] = [it.get(key) for it in items]
    return out


def collate_detection(batch: Sequence[dict]) -> dict[str, Any]:
    """The batch format of lidarops 0.1 (``batch_index``, ``boxes``, 0-based ``labels``); deprecated: use
    :func:`collate_batch`, whose keys every model reads."""
    warn_renamed("lidarops.data.datasets.collate_detection", "lidarops.data.collate_batch (OpenPCDet's keys)")
    out = collate_batch(batch)
    gt = out.pop("gt_boxes")
    n = torch.tensor([int((g[:, 7] > 0).sum()) for g in gt], dtype=torch.int64) if gt.shape[1] else \
        torch.zeros(len(gt), dtype=torch.int64)
    out["batch_index"] = out["points"][:, 0].long()
    out["points"] = out["points"][:, 1:]
    out["boxes"], out["labels"], out["num_boxes"] = gt[..., :7], gt[..., 7].long() - 1, n
    out["frame_index"] = out.pop("frame_id")
    return out


class ObjectDataset(Dataset):
    """Object clouds ``(points Tensor[P, C], label)``.

    Backed by detection frames (the points inside each box, see
    :func:`lidarops.data.objects.extract_objects`), by a saved :class:`~lidarops.data.objects.ObjectSet`
    (``.npz``), or by ModelNet40 (``.h5`` file or directory).

    Args:
        source: frame source / path / scenario name, an ``ObjectSet`` or its ``.npz`` path, or a
            ModelNet40 ``.h5`` path or directory.
        split (str or None): ``"train"``, ``"test"`` or ``None`` (all).  For frame sources the split is
            :func:`~lidarops.data.objects.split_balanced` with ``test_fraction`` and ``seed``; for
            ModelNet40 directories it picks the ``ply_data_<split>*.h5`` files.
        num_points (int or None): resample every cloud to this many points (random choice, with
            replacement when it has fewer), so items can be stacked.
        min_points (int): skip objects with fewer points (frame sources).
        canonical (bool): objects in their box frame (frame sources).
        test_fraction (float), seed (int): split parameters.
        **source_options: options for opening a path (e.g. ``num_frames`` for synthetic).
    """

    def __init__(self, source, split: str | None = None, num_points: int | None = None, min_points: int = 10,
                 canonical: bool = True, test_fraction: float = 0.2, seed: int = 0, **source_options) -> None:
        from lidarops.data.objects import ObjectSet

        self.num_points = None if num_points is None else integer(num_points, "num_points", 1)
        min_points, seed = integer(min_points, "min_points", 0), integer(seed, "seed", 0)
        self.seed = seed
        self._rng = np.random.default_rng(seed)
        text = str(source) if isinstance(source, (str, Path)) else ""
        if isinstance(source, ObjectSet) or text.endswith(".npz"):
            objset = source if isinstance(source, ObjectSet) else ObjectSet.load(text)
            self._from_objset(objset, split)
        elif text.endswith((".h5", ".hdf5")) or (text and Path(text).is_dir() and any(Path(text).glob("ply_data_*.h5"))):
            from lidarops.data.formats.modelnet import ModelNet40

            mn = ModelNet40(text, split=split or "train")
            self.clouds = [p for p in mn.points]
            self.labels = [int(v) for v in mn.labels]
            self.class_names = mn.class_names
        else:
            frames = as_frame_source(source, **source_options)
            objset = ObjectSet.from_frames((frames[i] for i in range(len(frames))), min_points=min_points,
                                           canonical=canonical, test_fraction=test_fraction, seed=seed)
            self._from_objset(objset, split)

    def _from_objset(self, objset, split: str | None) -> None:
        if split is None:
            index = np.arange(len(objset))
        elif split in ("train", "test"):
            index = objset.train_index if split == "train" else objset.test_index
        else:
            raise ValueError("split must be 'train', 'test' or None")
        self.clouds = [objset.samples[i].points for i in index]
        self.labels = [objset.samples[i].label for i in index]
        self.class_names = objset.class_names

    def __len__(self) -> int:
        return len(self.clouds)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, int]:
        pts = self.clouds[i]
        if self.num_points is not None and pts.shape[0] != self.num_points:
            rng = np.random.default_rng((self.seed, i))
            choice = rng.choice(pts.shape[0], size=self.num_points, replace=pts.shape[0] < self.num_points)
            pts = pts[choice]
        return torch.from_numpy(np.ascontiguousarray(pts, dtype=np.float32)), int(self.labels[i])


def collate_objects(batch: Sequence[tuple[torch.Tensor, int]]) -> dict[str, torch.Tensor]:
    """Batches object clouds of varying size: ``points (Tensor[sum P, C])``, ``batch_index``, ``labels (Tensor[B])``."""
    return {
        "points": torch.cat([p for p, _ in batch]),
        "batch_index": torch.cat([torch.full((p.shape[0],), i, dtype=torch.int64) for i, (p, _) in enumerate(batch)]),
        "labels": torch.tensor([label for _, label in batch], dtype=torch.int64),
    }


class StreamDataset(Dataset):
    """Consecutive time slices of a point stream: item ``i`` holds the points with
    ``t0 + i * slice_duration <= t < t0 + (i + 1) * slice_duration``.

    Items are dicts ``{"points": Tensor[n, 4], "t": Tensor[n] float64, "t0": float, "t1": float}``.

    Args:
        source: a :class:`~lidarops.data.synthetic.Simulator` (any span), or a frame source / path /
            scenario name whose frames carry per-point ``t`` (the slices then cover the frames' time span).
        slice_duration (float): seconds per slice (10 ms by default, as the streaming SSCATeR consumes).
        t0 (float or None): start time (default 0 for a simulator, the first timestamp otherwise).
        num_slices (int or None): number of slices (default: one frame period for a simulator; the whole
            span of the frames otherwise).
        **source_options: options for opening a path or name.
    """

    def __init__(self, source, slice_duration: float = 0.01, t0: float | None = None, num_slices: int | None = None,
                 **source_options) -> None:
        from lidarops.data.synthetic import Simulator

        slice_duration = self.slice_duration = real(slice_duration, "slice_duration", 0, lo_open=True, unit=" s")
        if t0 is not None:
            t0 = real(t0, "t0", unit=" s")
        if num_slices is not None:
            num_slices = integer(num_slices, "num_slices", 0)
        if isinstance(source, Simulator):
            self.simulator = source
            self.t0 = 0.0 if t0 is None else real(t0, "t0", 0, unit=" s (a simulator starts at 0)")
            n = num_slices if num_slices is not None else int(round(source.frame_period / slice_duration))
            self.num_slices = int(n)
            self._points = self._t = None
        else:
            frames = as_frame_source(source, **source_options)
            self.simulator = None
            pts, ts = [], []
            for i in range(len(frames)):
                f = frames[i]
                if f.t is None:
                    raise ValueError(f"frame {i} of {source!r} has no per-point timestamps; a stream needs them")
                pts.append(f.points)
                ts.append(f.t)
            points = np.concatenate(pts) if pts else np.zeros((0, 4), np.float32)
            t = np.concatenate(ts) if ts else np.zeros(0)
            order = np.argsort(t, kind="stable")
            self._points, self._t = points[order], t[order]
            self.t0 = float(self._t[0]) if t0 is None and self._t.size else float(t0 or 0.0)
            span = (float(self._t[-1]) - self.t0) if self._t.size else 0.0
            self.num_slices = int(num_slices) if num_slices is not None else int(np.floor(span / slice_duration)) + 1

    def __len__(self) -> int:
        return self.num_slices

    def span(self, i: int) -> tuple[float, float]:
        """Time span ``[t0, t1)`` of slice ``i``."""
        return self.t0 + i * self.slice_duration, self.t0 + (i + 1) * self.slice_duration

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not 0 <= i < self.num_slices:
            raise IndexError(f"slice {i} out of range ({self.num_slices} slices)")
        a, b = self.span(i)
        if self.simulator is not None:
            points, t = self.simulator.stream(a, b)
        else:
            lo, hi = np.searchsorted(self._t, [a, b], side="left")
            points, t = self._points[lo:hi], self._t[lo:hi]
        return {"points": torch.from_numpy(np.ascontiguousarray(points)), "t": torch.from_numpy(np.ascontiguousarray(t)),
                "t0": a, "t1": b}
