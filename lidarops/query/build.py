"""Filling a frame index from frames: a source turns each frame into per-class counts and the counted
objects' BEV centres; :func:`build_index` runs it chunk by chunk and appends each chunk as a part.

A source is any callable ``source(frames) -> list of (counts, centres)`` over a list of frames, with
``counts`` a ``{class: int}`` and ``centres`` a list of ``(class, x, y, score)``:

- :class:`LabelsSource`: the frames' own boxes (the ground truth);
- :class:`DetectorSource`: a detector used as a counter, its boxes above a score threshold.

Resumable and idempotent: a build started again on the same index skips the frames its source already
holds (one part per chunk is written to a temporary name and renamed), so a build killed midway and run
again ends with every frame once.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from lidarops.query.index import FrameIndex, QueryError

__all__ = ["LabelsSource", "DetectorSource", "build_index"]

Counted = tuple[dict[str, int], list[tuple[str, float, float, float]]]


class LabelsSource:
    """Counts from the frames' labelled boxes (``Frame.boxes``, ``Frame.labels``, ``Frame.class_names``)."""

    name = "labels"

    def __init__(self, classes: Sequence[str]):
        self.classes = list(classes)

    def __call__(self, frames: Sequence[Any]) -> list[Counted]:
        out = []
        for frame in frames:
            names = [frame.class_names[i] if 0 <= i < len(frame.class_names) else None for i in frame.labels.tolist()]
            counts = {c: 0 for c in self.classes}
            centres = []
            for name, box in zip(names, np.asarray(frame.boxes, np.float64)):
                if name in counts:
                    counts[name] += 1
                    centres.append((name, float(box[0]), float(box[1]), 1.0))
            out.append((counts, centres))
        return out


class DetectorSource:
    """A detector as a counter: its detections scoring at least ``score_thresh``, per class, in one batched
    ``predict`` per chunk (on the model's device)."""

    name = "detector"

    def __init__(self, model, score_thresh: float = 0.5):
        if not 0 <= score_thresh <= 1:
            raise QueryError(f"score_thresh must be in [0, 1], got {score_thresh!r}")
        self.model = model
        self.score_thresh = float(score_thresh)
        self.classes = list(model.config.class_names)

    def __call__(self, frames: Sequence[Any]) -> list[Counted]:
        import torch

        device = next(self.model.parameters()).device
        points = [torch.from_numpy(np.asarray(f.points[:, :4], np.float32)) for f in frames]
        batch_points = torch.cat([torch.cat([torch.full((len(p), 1), float(i)), p], 1) for i, p in enumerate(points)])
        preds = self.model.predict({"points": batch_points.to(device), "batch_size": len(frames)})
        out = []
        for pred in preds:
            keep = pred["scores"] >= self.score_thresh
            boxes, labels, scores = pred["boxes"][keep].cpu(), pred["labels"][keep].cpu(), pred["scores"][keep].cpu()
            counts = {c: 0 for c in self.classes}
            centres = []
            for box, label, score in zip(boxes.tolist(), labels.tolist(), scores.tolist()):
                name = self.classes[label - 1]  # 1-based, as OpenPCDet
                counts[name] += 1
                centres.append((name, box[0], box[1], score))
            out.append((counts, centres))
        return out


def build_index(root: "str | Path", frames: Iterable[tuple[int, Any]], source: Callable[[Sequence[Any]], list[Counted]],
                source_name: str | None = None, classes: Sequence[str] | None = None, chunk: int = 64,
                progress: Callable[[int], None] | None = None) -> dict[str, int]:
    """Counts ``frames`` (``(frame_id, Frame)`` pairs) with ``source`` into the index at ``root`` (made when
    absent), a part per ``chunk`` frames; frames the source already holds are skipped.

    Returns:
        ``{"indexed": n, "skipped": k}``: frames counted now, frames the index already held.
    """
    if chunk < 1:
        raise QueryError(f"chunk must be >= 1, got {chunk}")
    name = source_name or getattr(source, "name", None) or "labels"
    classes = list(classes or getattr(source, "classes"))
    root = Path(root)
    index = FrameIndex.open(root) if (root / "index.json").exists() else None
    if index is not None:
        missing = [c for c in classes if c not in index.classes]
        if missing:
            raise QueryError(f"the index at {root} holds the classes {index.classes}; this source counts {missing} too")
    held = set(index.sql("SELECT frame_id FROM counts WHERE source = ?", [name])["frame_id"].tolist()) \
        if index is not None and name in index.sources else set()
    done = skipped = 0
    pending: list[tuple[int, Any]] = []

    def flush() -> None:
        nonlocal index, done
        if not pending:
            return
        counted = source([f for _, f in pending])
        ids = np.array([fid for fid, _ in pending], np.int64)
        counts = {"frame_id": ids, **{c: np.array([k[0].get(c, 0) for k in counted], np.int64) for c in classes}}
        rows = [(int(fid), c, x, y, s) for fid, (_, cs) in zip(ids, counted) for c, x, y, s in cs]
        centres = {"frame_id": np.array([r[0] for r in rows], np.int64), "class": [r[1] for r in rows],
                   "x": np.array([r[2] for r in rows]), "y": np.array([r[3] for r in rows]),
                   "score": np.array([r[4] for r in rows])}
        if index is None:
            index = FrameIndex.create(root, counts, centres=centres, source=name, classes=classes)
        else:
            index.append(counts, centres=centres, source=name)
        done += len(pending)
        if progress is not None:
            progress(len(pending))
        pending.clear()

    for fid, frame in frames:
        fid = int(fid)
        if fid in held:
            skipped += 1
            if progress is not None:
                progress(1)
            continue
        held.add(fid)
        pending.append((fid, frame))
        if len(pending) >= chunk:
            flush()
    flush()
    return {"indexed": done, "skipped": skipped}
