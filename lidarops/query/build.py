"""Filling a frame index from frames: a source turns each frame into per-class counts and the counted
objects' BEV centres; :func:`build_index` loads the frames (in DataLoader workers when asked), counts them a
batch at a time and appends the counts a part at a time.

A source is any callable ``source(frames) -> list of (counts, centres)`` over a list of frames, with
``counts`` a ``{class: int}`` and ``centres`` a list of ``(class, x, y, score)``, and a ``classes`` list:

- :class:`LabelsSource`: the frames' own boxes (the ground truth);
- :class:`DetectorSource`: a detector used as a counter, its boxes above a score threshold;
- :class:`CounterSource`: a counting network (CounterNet), its heatmap peaks;
- any user model, in the same shape.

Resumable and idempotent: a part is written to a temporary name and renamed, and a build started again on
the same index skips the frames its source already holds, so a build killed midway and run again ends with
every frame once. Under ``torchrun`` each rank counts its share of the frames and writes its own parts
(named by rank); the index is their union.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from lidarops.query.index import FrameIndex, QueryError

__all__ = ["LabelsSource", "DetectorSource", "CounterSource", "build_index", "BuildReport", "FrameError", "Scan"]

Counted = tuple[dict[str, int], list[tuple[str, float, float, float]]]


class FrameError(ValueError):
    """A frame that cannot be counted (an unreadable scan, labels asked for and missing): the message
    names the frame and its file."""


@dataclass
class Scan:
    """A frame as a counter needs it: its points, as a tensor (so that DataLoader workers hand it over in
    shared memory instead of pickling it), and the file it came from."""

    points: Any  # torch.Tensor (N, 4) float32
    source: str = ""
    frame_index: int = 0
    timestamp: float | None = None
    meta: dict = field(default_factory=dict)

    def pin_memory(self) -> "Scan":
        """What a DataLoader with ``pin_memory=True`` calls: the points in page-locked memory, so that the
        copy to the GPU is asynchronous and fast."""
        return Scan(self.points.pin_memory(), self.source, self.frame_index, self.timestamp, self.meta)


class LabelsSource:
    """Counts from the frames' labelled boxes (``Frame.boxes``, ``Frame.labels``, ``Frame.class_names``).

    Args:
        classes: the classes counted.
        region: ``(x0, y0, x1, y1)`` metres: count only boxes centred inside (``x0 <= x < x1``,
            ``y0 <= y < y1``), e.g. a detector's range, so that the truth counts what a counter can see;
            None: everywhere.
        min_points: count only boxes holding at least this many points (``Frame.num_points_in_box``);
            a box no ray reached cannot be counted from the point cloud.
    """

    name = "labels"
    needs_labels = True

    def __init__(self, classes: Sequence[str], region: Sequence[float] | None = None, min_points: int = 0):
        self.classes = list(classes)
        if region is not None:
            region = tuple(float(v) for v in region)
            if len(region) != 4 or not (region[0] < region[2] and region[1] < region[3]):
                raise QueryError(f"region must be (x0, y0, x1, y1) with x0 < x1 and y0 < y1, got {region}")
        if isinstance(min_points, bool) or not isinstance(min_points, int) or min_points < 0:
            raise QueryError(f"min_points must be an integer >= 0, got {min_points!r}")
        self.region, self.min_points = region, min_points

    def __call__(self, frames: Sequence[Any]) -> list[Counted]:
        out = []
        for frame in frames:
            names = [frame.class_names[i] if 0 <= i < len(frame.class_names) else None for i in frame.labels.tolist()]
            boxes = np.asarray(frame.boxes, np.float64).reshape(-1, 7)
            keep = np.ones(len(boxes), bool)
            if self.region is not None:
                x0, y0, x1, y1 = self.region
                keep &= (boxes[:, 0] >= x0) & (boxes[:, 0] < x1) & (boxes[:, 1] >= y0) & (boxes[:, 1] < y1)
            if self.min_points:
                keep &= np.asarray(frame.num_points_in_box).reshape(-1) >= self.min_points
            counts = {c: 0 for c in self.classes}
            centres = []
            for name, box, kept in zip(names, boxes, keep):
                if name in counts and kept:
                    counts[name] += 1
                    centres.append((name, float(box[0]), float(box[1]), 1.0))
            out.append((counts, centres))
        return out


class _ModelSource:
    """What the model-backed sources share: the frames batched on the model's device, one ``predict`` per call,
    each frame's prediction turned into ``(counts, centres)`` by :meth:`counted`.

    ``stage_seconds`` adds up where the time went: ``to_device`` (batching the points and the copy),
    ``predict`` (the network and its post-processing, synchronised on CUDA) and ``read_back``.
    """

    needs_labels = False

    def __init__(self, model):
        self.model = model
        self.classes = list(model.config.class_names)
        self.stage_seconds = {"to_device": 0.0, "predict": 0.0, "read_back": 0.0}
        self.pin_memory = next(model.parameters()).device.type == "cuda"  # asks build_index's loader to pin

    def counted(self, pred: dict) -> Counted:
        raise NotImplementedError

    def __call__(self, frames: Sequence[Any]) -> list[Counted]:
        import torch

        device = next(self.model.parameters()).device
        sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
        t0 = time.perf_counter()
        points = [f.points[:, :4].float() if isinstance(f.points, torch.Tensor)
                  else torch.from_numpy(np.ascontiguousarray(f.points[:, :4], np.float32)) for f in frames]
        # each frame to the device as it is (pinned by the loader: asynchronous), batched there
        points = [p.to(device, non_blocking=p.is_pinned()) for p in points]
        batch_points = torch.cat([torch.cat([torch.full((len(p), 1), float(i), device=device), p], 1)
                                  for i, p in enumerate(points)])
        sync()
        t1 = time.perf_counter()
        with torch.inference_mode():
            preds = self.model.predict({"points": batch_points, "batch_size": len(frames)})
        sync()
        t2 = time.perf_counter()
        out = [self.counted(pred) for pred in preds]
        t3 = time.perf_counter()
        self.stage_seconds["to_device"] += t1 - t0
        self.stage_seconds["predict"] += t2 - t1
        self.stage_seconds["read_back"] += t3 - t2
        return out


class DetectorSource(_ModelSource):
    """A detector as a counter: its detections scoring at least ``score_thresh``, per class, one batched
    ``predict`` per call (on the model's device); ``stage_seconds`` as :class:`CounterSource`'s."""

    name = "detector"

    def __init__(self, model, score_thresh: float = 0.5):
        if not 0 <= score_thresh <= 1:
            raise QueryError(f"score_thresh must be in [0, 1], got {score_thresh!r}")
        super().__init__(model)
        self.score_thresh = float(score_thresh)

    def counted(self, pred: dict) -> Counted:
        keep = pred["scores"] >= self.score_thresh
        boxes, labels, scores = pred["boxes"][keep].cpu(), pred["labels"][keep].cpu(), pred["scores"][keep].cpu()
        counts = {c: 0 for c in self.classes}
        centres = []
        for box, label, score in zip(boxes.tolist(), labels.tolist(), scores.tolist()):
            name = self.classes[label - 1]  # 1-based, as OpenPCDet
            counts[name] += 1
            centres.append((name, box[0], box[1], score))
        return counts, centres


class CounterSource(_ModelSource):
    """A counting network (:class:`lidarops.models.counternet.CounterNet`) as the source: its per-class counts
    and the BEV centres of its heatmap peaks, one batched ``predict`` per call."""

    name = "counter"

    def counted(self, pred: dict) -> Counted:
        counts = dict(zip(self.classes, (int(n) for n in pred["counts"].cpu().tolist())))
        centres = [(self.classes[int(c)], x, y, score) for x, y, c, score in pred["centres"].cpu().tolist()]
        return counts, centres


@dataclass
class BuildReport:
    """What one :func:`build_index` call did (this process's share under ``torchrun``)."""

    indexed: int = 0
    skipped: int = 0  # frames the index already held
    failed: list[tuple[int, str]] = field(default_factory=list)  # (frame id, why) of frames left out
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)  # load (waiting for frames), count, write

    @property
    def frames_per_second(self) -> float:
        return self.indexed / self.seconds if self.seconds > 0 else 0.0

    def shares(self) -> str:
        """``load 12 %, count 80 %, write 8 %``: each stage's share of the wall time."""
        return ", ".join(f"{k} {100 * v / self.seconds:.0f} %" for k, v in self.stage_seconds.items()) \
            if self.seconds > 0 else ""


class _Loading:
    """The frames still to count, as a torch Dataset: each item is ``(frame id, Frame or the error)``, so
    that a bad file reaches the main process as a named error instead of ending a worker."""

    def __init__(self, ids: Sequence[int], load: Callable[[int], Any]):
        self.ids, self.load = list(ids), load

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int):
        fid = self.ids[i]
        try:
            return fid, self.load(fid)
        except FrameError as e:
            return fid, e
        except (OSError, ValueError) as e:  # an unreadable or malformed file
            return fid, FrameError(f"frame {fid}: {e}")


def _batches(loading: _Loading, batch: int, workers: int, pin: bool):
    if workers <= 0:
        for start in range(0, len(loading), batch):
            yield [loading[i] for i in range(start, min(start + batch, len(loading)))]
        return
    from torch.utils.data import DataLoader

    yield from DataLoader(loading, batch_size=batch, num_workers=workers, collate_fn=list,
                          prefetch_factor=4, persistent_workers=False, pin_memory=pin)


def _frame_facts(frame) -> tuple:
    """(path of its scan file, sequence, timestamp) of a frame, each None where unknown."""
    src = getattr(frame, "source", None)
    path = str(Path(src).resolve()) if isinstance(src, str) and src.endswith(".bin") else None
    meta = getattr(frame, "meta", None) or {}
    sequence = meta.get("sequence")
    stamp = getattr(frame, "timestamp", None)
    return path, None if sequence is None else str(sequence), None if stamp is None else float(stamp)


def _distributed() -> tuple[int, int, Callable[[], None]]:
    """(rank, world size, barrier) of the torch.distributed group if one is up, else one process."""
    try:
        import torch.distributed as dist
    except ImportError:  # a torch built without it
        return 0, 1, lambda: None
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        return dist.get_rank(), dist.get_world_size(), dist.barrier
    return 0, 1, lambda: None


def build_index(root: "str | Path", ids: Sequence[int], load: Callable[[int], Any],
                source: Callable[[Sequence[Any]], list[Counted]], source_name: str | None = None,
                classes: Sequence[str] | None = None, batch: int = 8, part_frames: int = 1024, workers: int = 0,
                on_error: str = "raise", progress: Callable[[int], None] | None = None) -> BuildReport:
    """Counts the frames ``ids`` (``load(frame_id)`` gives each frame) with ``source`` into the index at
    ``root`` (made when absent); frames the source already holds are skipped.

    Args:
        ids: frame ids (integers, unique).
        load: ``frame_id -> Frame``; in ``workers`` DataLoader processes when ``workers > 0``. Raise
            :class:`FrameError` (or ``OSError`` / ``ValueError``) for a frame that cannot be read.
        source: the counter, ``frames -> [(counts, centres), ...]``, called on ``batch`` frames at a time.
        part_frames: frames per Parquet part: what a killed build loses at most.
        on_error: ``"raise"`` (default): the first unreadable frame stops the build with its name;
            ``"skip"``: it is left out, counted and listed in the report (a build run again retries it).
        progress: called with the number of frames done (counted, skipped or failed) as they go.

    Under ``torchrun`` (a torch.distributed group of several processes) every rank calls this with the same
    ``ids``: rank 0 makes the index, each rank counts every ``world``-th frame still missing and writes its
    own parts. The report is this rank's.
    """
    for what, value in (("batch", batch), ("part_frames", part_frames)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise QueryError(f"{what} must be an integer >= 1, got {value!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        raise QueryError(f"workers must be an integer >= 0, got {workers!r}")
    if on_error not in ("raise", "skip"):
        raise QueryError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    name = source_name or getattr(source, "name", None) or "labels"
    classes = list(classes or getattr(source, "classes"))
    ids = np.asarray(list(ids), dtype=np.int64).reshape(-1) if len(ids) else np.zeros(0, np.int64)
    uniq, times = np.unique(ids, return_counts=True)
    if (times > 1).any():
        raise QueryError(f"ids holds duplicates, e.g. {uniq[times > 1][:5].tolist()}")
    root = Path(root)
    rank, world, barrier = _distributed()
    if rank == 0:
        index = FrameIndex.open(root) if (root / "index.json").exists() else FrameIndex.create(root, classes=classes)
        missing = [c for c in classes if c not in index.classes]
        if missing:
            raise QueryError(f"the index at {root} holds the classes {index.classes}; this source counts {missing} too")
        if name not in index.sources:
            index.add_source(name, centres=True)
    barrier()
    index = FrameIndex.open(root)
    held = index.held_frames(name)
    todo = ids[~np.isin(ids, held)]
    mine = todo[rank::world]
    report = BuildReport(skipped=int(len(ids) - len(todo)),
                         stage_seconds={"load": 0.0, "count": 0.0, "write": 0.0})
    if progress is not None and rank == 0 and report.skipped:
        progress(report.skipped)
    writer = f"r{rank:03d}" if world > 1 else ""
    pending_ids: list[int] = []
    pending: list[Counted] = []
    start = time.perf_counter()

    def flush(n: int) -> None:
        """Writes the first ``n`` pending frames as one part."""
        if not pending:
            return
        t = time.perf_counter()
        ids_ = np.array(pending_ids[:n], np.int64)
        part = pending[:n]
        counts = {"frame_id": ids_, **{c: np.array([k[0].get(c, 0) for k in part], np.int64) for c in classes}}
        for j, column in enumerate(("path", "sequence", "timestamp")):
            values = [extra[int(i)][j] for i in ids_]
            if any(v is not None for v in values):
                counts[column] = values if j < 2 else np.array([np.nan if v is None else v for v in values])
        rows = [(int(fid), c, x, y, s) for fid, (_, cs) in zip(ids_, part) for c, x, y, s in cs]
        centres = {"frame_id": np.array([r[0] for r in rows], np.int64), "class": [r[1] for r in rows],
                   "x": np.array([r[2] for r in rows], np.float64), "y": np.array([r[3] for r in rows], np.float64),
                   "score": np.array([r[4] for r in rows], np.float64)}
        index._write(counts, centres, name, writer=writer, check_held=False)
        report.indexed += len(ids_)
        for fid in ids_.tolist():
            del extra[fid]
        del pending_ids[:n], pending[:n]
        report.stage_seconds["write"] += time.perf_counter() - t

    extra: dict[int, tuple] = {}  # frame id -> (path, sequence, timestamp)
    t = time.perf_counter()
    pin = bool(getattr(source, "pin_memory", False))
    for loaded in _batches(_Loading(mine.tolist(), load), batch, workers, pin):
        report.stage_seconds["load"] += time.perf_counter() - t
        good = []
        for fid, frame in loaded:
            if isinstance(frame, Exception):
                if on_error == "raise":
                    raise frame
                report.failed.append((int(fid), str(frame)))
            else:
                good.append((int(fid), frame))
        t = time.perf_counter()
        counted = source([f for _, f in good]) if good else []
        if len(counted) != len(good):
            raise QueryError(f"source {name!r} returned {len(counted)} results for {len(good)} frames")
        report.stage_seconds["count"] += time.perf_counter() - t
        for (fid, frame), result in zip(good, counted):
            pending_ids.append(fid)
            pending.append(result)
            extra[fid] = _frame_facts(frame)
        while len(pending_ids) >= part_frames:
            flush(part_frames)
        if progress is not None:
            progress(len(loaded))
        t = time.perf_counter()
    flush(len(pending_ids))
    barrier()
    report.seconds = time.perf_counter() - start
    return report
