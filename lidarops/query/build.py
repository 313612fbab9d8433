"""Filling a frame index from frames: a source turns each frame into per-class counts and the counted
objects' BEV centres; :func:`build_index` loads the frames (in DataLoader workers when asked), counts them a
batch at a time and appends the counts a part at a time.

A source is any callable ``source(frames) -> list of (counts, centres)`` over a list of frames, with
``counts`` a ``{class: int}`` and ``centres`` a list of ``(class, x, y, score)``, and a ``classes`` list:

- :class:`LabelsSource`: the frames' own boxes (the ground truth);
- :class:`DetectorSource`: a detector used as a counter, its boxes above a score threshold;
- :class:`CounterSource`: a counting network (CounterNet), its heatmap peaks;
- any user model, in the same shape.

The model sources also split a call into ``submit`` (the copy to the device), ``run`` (the network, the
batch's counts gathered on the device) and ``finish`` (the batch's one read-back): :func:`build_index` runs
them three batches deep, so on CUDA the copies of the next and the previous batch run on a side stream
while the network works on the current one.

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

# (counts per class, centres (class, x, y, score)); a model selection adds the name of the model that counted
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


class _SideStream:
    """A CUDA stream beside the model's current one, for the copies between host and device, so that they run
    while the network computes; on the CPU every method is a no-op and the copies run in place."""

    def __init__(self, device):
        import torch

        self.device = device
        self.stream = torch.cuda.Stream(device) if device.type == "cuda" else None

    def enqueue(self):
        """The context whose work goes to the side stream."""
        import contextlib

        import torch

        return torch.cuda.stream(self.stream) if self.stream is not None else contextlib.nullcontext()

    def mark(self):
        """An event at the end of the work queued so far on the side stream (None on the CPU)."""
        import torch

        if self.stream is None:
            return None
        event = torch.cuda.Event()
        event.record(self.stream)
        return event

    def main_waits(self, event, tensor) -> None:
        """The current stream waits for ``event`` and then uses ``tensor`` (made on the side stream): the
        allocator must not reuse its memory before the current stream is done with it."""
        import torch

        if self.stream is not None:
            main = torch.cuda.current_stream(self.device)
            main.wait_event(event)
            tensor.record_stream(main)

    def side_waits(self, tensor) -> None:
        """The side stream waits for the work queued on the current stream and then reads ``tensor``."""
        import torch

        if self.stream is not None:
            self.stream.wait_stream(torch.cuda.current_stream(self.device))
            tensor.record_stream(self.stream)


@dataclass
class _Staged:
    """A batch between the steps of a model source: its points on the device, then its packed results on the
    host once their copy (``done``) has completed."""

    frames: int  # frames in the batch
    full: list[int]  # the frames holding points, in order
    lengths: list[int]  # the points of each of those frames
    points: Any = None  # Tensor[P, 5] on the device: the full frames' rows (index among them, x, y, z, intensity)
    done: Any = None  # CUDA event: the copy to the device, then the read-back, is complete (None on the CPU)
    host: Any = None  # Tensor[R] float64 (pinned on CUDA): the results read back, packed
    shapes: list = field(default_factory=list)  # the shapes of the tensors packed in ``host``
    meta: Any = None  # what the source needs besides them (rows per frame)


def _raise_bad_frames(flags: np.ndarray) -> None:
    """The eager call's check of the points' features (lidarops.models.pointpillars), which a graph ran on the
    device: ``flags`` per frame of the batch."""
    from lidarops.ops.pillars import MAX_ABS_INTENSITY
    from lidarops.ops.validation import value_checks_enabled

    if flags.any() and value_checks_enabled():
        raise ValueError(f"frame(s) {np.flatnonzero(flags).tolist()} of this batch: batch['points'][:, 4:] "
                         f"(intensity and other features) must be finite with |value| <= {MAX_ABS_INTENSITY:g}; "
                         "drop such points first (lidarops.stream.invalid_points gives the mask for intensity)")


class _ModelSource:
    """What the model-backed sources share: frames counted a batch at a time on the model's device, in three
    steps that :func:`build_index` overlaps across batches (calling the source runs them in a row):

    - :meth:`submit`: the frames' points copied to the device as one batch (on CUDA on a side stream, from the
      loader's pinned memory: the copy of the next batch runs while the network works on this one);
    - :meth:`run`: one batched ``predict`` under ``precision``, the source's results gathered on the device into
      one tensor (counts by one scatter over the batch), its copy to the host started on the side stream;
    - :meth:`finish`: waits for that copy (the batch's only read-back) and turns it into ``(counts, centres)``.

    A frame without points is predicted apart, as a batch of one empty frame (a batch's frames must each hold
    a point), once per call whatever the number of such frames.

    Args:
        precision: the network's arithmetic (:func:`lidarops.models.cuda_graph.precision_mode`, as
            ``benchmarks/bm_detector.py`` and ``GraphedPointPillars`` take it): ``"fp32"`` (float32, no TF32),
            ``"tf32"`` (TF32 matmuls and convolutions) or ``"fp16"`` (float16 autocast); None (default): torch's
            settings as they are (on CUDA, torch lets cuDNN's convolutions use TF32 by default). ``tf32`` and
            ``fp16`` are for CUDA: ``tf32`` changes nothing on the CPU and the CPU's float16 is far slower.

    ``stage_seconds`` adds up the host time of each step: ``to_device`` (:meth:`submit`), ``predict``
    (:meth:`run`: the network and its post-processing, whose host reads wait for the GPU) and ``read_back``
    (:meth:`finish`). Nothing is synchronised for the timing: what the side stream hides under the network
    is not counted.
    """

    needs_labels = False

    def __init__(self, model, precision: str | None = None):
        from lidarops.models.cuda_graph import PRECISIONS

        if precision is not None and precision not in PRECISIONS:
            raise QueryError(f"precision must be one of {', '.join(map(repr, PRECISIONS))} or None, got {precision!r}")
        self.model = model
        self.precision = precision
        self.classes = list(model.config.class_names)
        self.stage_seconds = {"to_device": 0.0, "predict": 0.0, "read_back": 0.0}
        self.pin_memory = next(model.parameters()).device.type == "cuda"  # asks build_index's loader to pin
        self._side: _SideStream | None = None
        self.graph = False  # each batch as one replayed CUDA graph (set by the sources that can)
        self.optimize = False  # the graph records a BatchNorm-folded, channels-last copy of the model
        self._graphed = None  # the graph, made at the first batch and again when it no longer fits
        self._pillars = 0  # the most pillar rows a batch has needed
        self._regraph = False  # a batch needed more rows than the graph holds
        self.pillar_step = 8192  # pillar rows are rounded up to a multiple of this
        self.eager_batches = 0  # batches counted eagerly because the graph could not hold them

    def _use_graph(self, graph: bool | None, capturable: bool, what: str, optimize: bool = False) -> None:
        if graph is not None and not isinstance(graph, bool):
            raise QueryError(f"graph must be True, False or None (on where it can run), got {graph!r}")
        if not isinstance(optimize, bool):
            raise QueryError(f"optimize must be True or False, got {optimize!r}")
        self.optimize = optimize
        if graph and not capturable:
            raise QueryError(f"graph=True needs {what} on a CUDA device, got {type(self.model).__name__} on "
                             f"{next(self.model.parameters()).device}")
        self.graph = capturable if graph is None else graph

    def _new_graph(self, capacity: int, batch: int, rows: int | None):
        raise NotImplementedError

    def _replay_staged(self, points, staged: _Staged):
        """A staged batch through the source's CUDA graph: each frame's points copied into the graph's padded
        input, one replay; ``(padded outputs, the frames' points)``.

        The graph is recorded for the largest batch and frame seen so far (frames rounded up to 32k points with a
        quarter more room) and, once a batch has shown how many pillars the frames make, with a quarter more
        pillar rows than the most seen (the pillar net then works on those rather than on every frame's
        capacity): a build records it a few times. A batch the graph cannot hold is counted again eagerly (the
        sources' ``_results``) and the next batch records a larger graph."""
        import torch

        most = max(staged.lengths, default=0)
        g = self._graphed
        step = self.pillar_step
        rows = None if not self._pillars else -(-(self._pillars + self._pillars // 4 + 1) // step) * step
        if g is None or g.batch_size < staged.frames or g.capacity < most or self._regraph or \
                (rows is not None and (g.max_pillars is None or g.max_pillars > rows + rows // 2)):
            capacity = -(-max(most + most // 4, g.capacity if g is not None else 0, 1) // 32768) * 32768
            batch = max(staged.frames, g.batch_size if g is not None else 1)
            if rows is not None:
                rows = min(rows, batch * min(self._max_voxels(), capacity))
            if g is not None:  # its outputs may still be read by queued work: let it finish before the memory goes
                torch.cuda.synchronize(points.device)
            self._graphed = g = None
            g = self._graphed = self._new_graph(capacity, batch, rows)
            self._regraph = False
        frames, row = [points[:0, 1:]] * staged.frames, 0
        for i, n in zip(staged.full, staged.lengths):
            frames[i] = points[row:row + n, 1:]
            row += n
        return g.replay(frames), frames

    def _max_voxels(self) -> int:
        return self.model.config.max_voxels_test

    def _eager_results(self, frames: list) -> list[Counted]:
        """``(counts, centres)`` of frames (device tensors of x, y, z, intensity) from the eager model, each frame
        alone, under ``precision``."""
        import torch

        from lidarops.models.cuda_graph import precision_mode

        with torch.inference_mode(), precision_mode(self.precision, "cuda",
                                                    autocast=next(self.model.parameters()).dtype != torch.float16):
            preds = [self._predict({"points": torch.nn.functional.pad(f, (1, 0)), "batch_size": 1})[0]
                     for f in frames]
            tensors, meta = self._gather(preds)
        return self._results([t.cpu().numpy() for t in tensors], meta)

    def _predict(self, batch: dict) -> list[dict]:
        """The model's predictions, one dict per frame (its ``predict``)."""
        return self.model.predict(batch)

    def _predict_staged(self, points, staged: _Staged) -> list[dict]:
        """The predictions of a staged batch's frames, in order: the full frames as one batch, the empty ones
        from one batch of one empty frame."""
        preds = self._predict({"points": points, "batch_size": len(staged.full)}) if staged.full else []
        if len(staged.full) < staged.frames:
            empty = self._predict({"points": points.new_zeros((0, 5)), "batch_size": 1})[0]
            by_frame = dict(zip(staged.full, preds))
            preds = [by_frame.get(i, empty) for i in range(staged.frames)]
        return preds

    def _gather(self, preds: list[dict]) -> tuple[list[Any], Any]:
        """The batch's predictions (one dict per frame, on the device) as tensors to read back and what
        :meth:`_results` needs besides them; nothing read to the host here."""
        raise NotImplementedError

    def _results(self, arrays: list[np.ndarray], meta: Any) -> list[Counted]:
        """``(counts, centres)`` per frame from :meth:`_gather`'s tensors, read back."""
        raise NotImplementedError

    def __call__(self, frames: Sequence[Any]) -> list[Counted]:
        return self.finish(self.run(self.submit(frames)))

    def submit(self, frames: Sequence[Any]) -> _Staged:
        """Starts the copy of the frames' points to the model's device, as one batch."""
        import torch

        t = time.perf_counter()
        device = next(self.model.parameters()).device
        if self._side is None or self._side.device != device:
            self._side = _SideStream(device)
        points = [f.points[:, :4].float() if isinstance(f.points, torch.Tensor)
                  else torch.from_numpy(np.ascontiguousarray(f.points[:, :4], np.float32)) for f in frames]
        full = [i for i, p in enumerate(points) if len(p)]
        with self._side.enqueue():
            batch = torch.empty((sum(len(points[i]) for i in full), 5), device=device)
            row = 0
            for j, i in enumerate(full):  # each frame as it is (pinned by the loader: asynchronous)
                n = len(points[i])
                batch[row:row + n, 0] = j
                batch[row:row + n, 1:].copy_(points[i], non_blocking=True)
                row += n
        staged = _Staged(len(frames), full, [len(points[i]) for i in full], batch, self._side.mark())
        self.stage_seconds["to_device"] += time.perf_counter() - t
        return staged

    def run(self, staged: _Staged) -> _Staged:
        """The network on a submitted batch, its results gathered on the device and their read-back started."""
        import torch

        from lidarops.models.cuda_graph import precision_mode

        t = time.perf_counter()
        points, staged.points = staged.points, None
        side = self._side
        side.main_waits(staged.done, points)
        weights = next(self.model.parameters())
        with torch.inference_mode(), precision_mode(self.precision, weights.device.type,
                                                    autocast=weights.dtype != torch.float16):
            preds = self._predict_staged(points, staged)
            if preds:
                tensors, staged.meta = self._gather(preds)
                staged.shapes = [tuple(x.shape) for x in tensors]
                packed = torch.cat([x.reshape(-1).double() for x in tensors])
                side.side_waits(packed)
                with side.enqueue():
                    staged.host = torch.empty(packed.shape, dtype=packed.dtype, pin_memory=side.stream is not None)
                    staged.host.copy_(packed, non_blocking=True)
                staged.done = side.mark()
        self.stage_seconds["predict"] += time.perf_counter() - t
        return staged

    def finish(self, staged: _Staged) -> list[Counted]:
        """Waits for a batch's read-back: ``(counts, centres)`` per frame."""
        t = time.perf_counter()
        if staged.host is None:  # no frames
            return []
        if staged.done is not None:
            staged.done.synchronize()
        flat, arrays = staged.host.numpy(), []
        for shape in staged.shapes:
            size = int(np.prod(shape))
            arrays.append(flat[:size].reshape(shape))
            flat = flat[size:]
        out = self._results(arrays, staged.meta)
        self.stage_seconds["read_back"] += time.perf_counter() - t
        return out


class DetectorSource(_ModelSource):
    """A detector as a counter: its detections scoring at least ``score_thresh``, per class, one batched
    ``predict`` per call (on the model's device), the counts of the whole batch made by one scatter on the device
    and read back with the centres in one copy; ``precision`` and ``stage_seconds`` as :class:`_ModelSource`'s.
    Labels are 1-based into the model's ``class_names`` (OpenPCDet's); others are not counted.

    ``graph``: run each batch as one replayed CUDA graph (:class:`~lidarops.models.cuda_graph.GraphedPointPillars`
    with ``batch_size``: voxelization to NMS without a host read or a launch per kernel); None (default): where it
    can, a PointPillars with the dense backbone on a CUDA device. The detections are the eager call's.
    ``optimize``: the graph records :func:`~lidarops.models.cuda_graph.inference_copy` of the model (BatchNorm
    folded, channels-last): faster, the scores round differently."""

    name = "detector"

    def __init__(self, model, score_thresh: float = 0.5, precision: str | None = None, graph: bool | None = None,
                 optimize: bool = False):
        if not 0 <= score_thresh <= 1:
            raise QueryError(f"score_thresh must be in [0, 1], got {score_thresh!r}")
        super().__init__(model, precision)
        self.score_thresh = float(score_thresh)
        from lidarops.models.pointpillars import PointPillars

        capturable = isinstance(model, PointPillars) and model.config.backbone_mode == "dense" and \
            next(model.parameters()).device.type == "cuda"
        self._use_graph(graph, capturable, "a PointPillars with backbone_mode='dense'", optimize)

    def _predict(self, batch: dict) -> list[dict]:
        """A PointPillars-style detector's detections through ``postprocess_padded``: the same rows as its
        ``predict``, each frame's padded to a fixed number with label 0 (not counted), and no host read per
        frame (``postprocess`` reads each frame's kept count back)."""
        from lidarops.models.postprocess import postprocess_padded
        from lidarops.models.pointpillars import PointPillars

        if not isinstance(self.model, PointPillars):
            return self.model.predict(batch)
        was_training = self.model.training
        self.model.eval()
        try:
            padded = postprocess_padded(*self.model.dense_head.decode(self.model(batch)), self.model.config)
        finally:
            self.model.train(was_training)
        return [{"boxes": padded["boxes"][b], "scores": padded["scores"][b], "labels": padded["labels"][b]}
                for b in range(padded["count"].shape[0])]

    def _predict_staged(self, points, staged: _Staged) -> list[dict]:
        """Through a CUDA graph of the whole batch (``graph``: :meth:`_replay_staged`), the padded outputs
        gathered where they lie."""
        if not self.graph:
            return super()._predict_staged(points, staged)
        out, frames = self._replay_staged(points, staged)
        return [{"boxes": out["boxes"][b], "scores": out["scores"][b], "labels": out["labels"][b],
                 "read": out["read"][b], "points": frames[b]} for b in range(staged.frames)]

    def _new_graph(self, capacity: int, batch: int, rows: int | None):
        from lidarops.models.cuda_graph import GraphedPointPillars

        return GraphedPointPillars(self.model, capacity, self.precision, batch, rows, self.optimize)

    def _gather(self, preds: list[dict]) -> tuple[list[Any], Any]:
        import torch

        classes = len(self.classes)
        scores = torch.cat([p["scores"] for p in preds])
        labels = torch.cat([p["labels"] for p in preds]).long()
        # the (frame, class) cell of each detection, frame by frame: index_add_ below (not bincount, which reads
        # its maximum back to the host on CUDA)
        cells = torch.cat([p["labels"].long() + (b * classes - 1) for b, p in enumerate(preds)])
        keep = (scores >= self.score_thresh) & (labels >= 1) & (labels <= classes)
        counts = torch.zeros(len(preds) * classes, dtype=torch.int64, device=scores.device)
        counts.index_add_(0, torch.where(keep, cells, 0), keep.long())
        xy = torch.cat([p["boxes"][:, :2] for p in preds]).double()  # float64 holds every float32/16 value
        rows = torch.stack([keep.double(), labels.double(), xy[:, 0], xy[:, 1], scores.double()], 1)
        tensors = [counts.view(len(preds), classes), rows]
        sizes = [len(p["scores"]) for p in preds]
        if "read" not in preds[0]:
            return tensors, sizes
        # the graph's value check of each frame and the batch's pillars, read back with the counts; the frames
        # kept for a batch that needed more pillar rows than the graph has
        tensors.append(torch.stack([p["read"] for p in preds]))
        return tensors, (sizes, [p["points"] for p in preds])

    def _results(self, arrays: list[np.ndarray], meta: Any) -> list[Counted]:
        counts, rows = arrays[:2]
        if len(arrays) > 2:  # through the graph: (count, bad, overflow, pillars) per frame
            read, (meta, frames) = arrays[2], meta
            _raise_bad_frames(read[:, 1])
            self._pillars = max(self._pillars, int(read[0, 3]))
            if read[0, 2]:  # more pillars than the graph's rows: this batch eagerly, a larger graph next
                self._regraph = True
                self.eager_batches += 1
                return self._eager_results(frames)
        out, start = [], 0
        for frame_counts, n in zip(counts.astype(np.int64).tolist(), meta):
            kept = rows[start:start + n]
            start += n
            centres = [(self.classes[int(label) - 1], x, y, score)
                       for _, label, x, y, score in kept[kept[:, 0] > 0].tolist()]
            out.append((dict(zip(self.classes, frame_counts)), centres))
        return out

class CounterSource(_ModelSource):
    """A counting network (:class:`lidarops.models.counternet.CounterNet`) as the source: its per-class counts
    and the BEV centres of its heatmap peaks, one batched ``predict`` per call and one read-back; ``precision``
    and ``stage_seconds`` as :class:`_ModelSource`'s.

    ``graph``: run each batch as one replayed CUDA graph (:class:`~lidarops.models.cuda_graph.GraphedCounterNet`:
    voxelization to the merged peaks without a host read); None (default): where it can, a CounterNet with the
    dense backbone on a CUDA device (a model selection counts eagerly). The counts are the eager call's, except
    where Otsu's threshold ties between two splits to within rounding (the graph's is computed on the device).
    ``optimize`` as :class:`DetectorSource`'s."""

    name = "counter"

    def __init__(self, model, precision: str | None = None, graph: bool | None = None, optimize: bool = False):
        super().__init__(model, precision)
        from lidarops.models.counternet import CounterNet

        capturable = isinstance(model, CounterNet) and model.config.floor_config().backbone_mode == "dense" and \
            next(model.parameters()).device.type == "cuda"
        self._use_graph(graph, capturable, "a CounterNet with backbone_mode='dense'", optimize)
        # peak rows per frame of the graph (the simulator's dense city frames hold 27 objects on average); doubled
        # when a frame holds more
        self.max_peaks = 256

    def _max_voxels(self) -> int:
        return self.model.config.floor_config().max_voxels_test

    def _new_graph(self, capacity: int, batch: int, rows: int | None):
        from lidarops.models.cuda_graph import GraphedCounterNet

        return GraphedCounterNet(self.model, capacity, self.precision, batch, rows, self.max_peaks,
                                 optimize=self.optimize)

    def _predict_staged(self, points, staged: _Staged) -> list[dict]:
        """Through a CUDA graph of the whole batch (``graph``: :meth:`_replay_staged`): every frame's padded
        peak rows, their number read back with the counts."""
        if not self.graph:
            return super()._predict_staged(points, staged)
        out, frames = self._replay_staged(points, staged)
        return [{"counts": out["counts"][b], "centres": out["centres"][b], "read": out["read"][b],
                 "peaks": out["peaks"][b], "points": frames[b]} for b in range(staged.frames)]

    def _gather(self, preds: list[dict]) -> tuple[list[Any], Any]:
        import torch

        tensors = [torch.stack([p["counts"] for p in preds]), torch.cat([p["centres"] for p in preds])]
        if "read" in preds[0]:  # the graph's padded rows: how many hold centres comes back with them
            tensors.append(torch.cat([torch.stack([p["read"] for p in preds]),
                                      torch.stack([p["peaks"] for p in preds])[:, None]], 1))
            return tensors, ([len(p["centres"]) for p in preds], [p["points"] for p in preds])
        # a model selection (SelectedCounter) names each frame's model: kept on the host, nothing to read back
        return tensors, ([len(p["centres"]) for p in preds], [p.get("model_name") for p in preds])

    def _results(self, arrays: list[np.ndarray], meta: Any) -> list[Counted]:
        counts, centres = arrays[:2]
        sizes, models = meta
        kept = sizes
        if len(arrays) > 2:  # through the graph: (centres, bad, redo, pillars, peaks) per frame
            read, frames = arrays[2], models
            models = [None] * len(sizes)
            _raise_bad_frames(read[:, 1])
            self._pillars = max(self._pillars, int(read[0, 3]))
            if read[:, 2].any():  # too few pillar or peak rows, or a merge not settled: this batch eagerly
                g = self._graphed
                if int(read[0, 3]) > (g.max_pillars or 0) or int(read[:, 4].max()) > g.max_peaks:
                    self._regraph = True
                    while self.max_peaks < int(read[:, 4].max()):
                        self.max_peaks *= 2
                self.eager_batches += 1
                return self._eager_results(frames)
            kept = read[:, 0].astype(np.int64).tolist()
        out, start = [], 0
        for frame_counts, n, k, model in zip(counts.tolist(), sizes, kept, models):
            rows = centres[start:start + k].tolist()
            start += n
            counted = (dict(zip(self.classes, (int(c) for c in frame_counts))),
                       [(self.classes[int(c)], x, y, score) for x, y, c, score in rows])
            out.append(counted if model is None else (*counted, model))
        return out

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


class _Pipeline:
    """Runs a source over batches of frames, results in order. A source with ``submit``, ``run`` and ``finish``
    (the model sources) is run three batches deep: batch k+1's copy to the device is started before the network
    runs on batch k, and batch k-1's read-back, started after its network, is taken after batch k's network,
    so on CUDA both copies run beside the network. Any other source is called on each batch as it comes."""

    def __init__(self, source):
        self.source = source
        self.staged = all(callable(getattr(source, step, None)) for step in ("submit", "run", "finish"))
        self.copying = self.reading = None  # (key, staged batch) in each step

    def push(self, key: Any, frames: list) -> list[tuple[Any, list[Counted]]]:
        """Hands in a batch (``key`` comes back with its results); returns the batches done, oldest first."""
        if not self.staged:
            return [(key, self.source(frames) if frames else [])]
        copying, self.copying = self.copying, (key, self.source.submit(frames))
        reading, self.reading = self.reading, copying and (copying[0], self.source.run(copying[1]))
        return [(reading[0], self.source.finish(reading[1]))] if reading else []

    def drain(self) -> list[tuple[Any, list[Counted]]]:
        """The batches still in flight, run to the end."""
        if not self.staged:
            return []
        copying, reading, self.copying, self.reading = self.copying, self.reading, None, None
        done = [(reading[0], self.source.finish(reading[1]))] if reading else []
        if copying:
            done.append((copying[0], self.source.finish(self.source.run(copying[1]))))
        return done


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
        if any(len(k) > 2 for k in part):  # the model that counted each frame (a model selection)
            counts["model"] = [k[2] if len(k) > 2 else None for k in part]
        for j, column in enumerate(("path", "sequence", "timestamp")):
            values = [extra[int(i)][j] for i in ids_]
            if any(v is not None for v in values):
                counts[column] = values if j < 2 else np.array([np.nan if v is None else v for v in values])
        rows = [(int(fid), c, x, y, s) for fid, counted in zip(ids_, part) for c, x, y, s in counted[1]]
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

    def take(done: list) -> None:
        """Queues counted batches for writing: ``done`` holds ``((frames, loaded), counted)``, ``frames`` a list
        of ``(frame id, facts)``, ``loaded`` the batch's size with its failed frames."""
        for (good, loaded), counted in done:
            if len(counted) != len(good):
                raise QueryError(f"source {name!r} returned {len(counted)} results for {len(good)} frames")
            for (fid, facts), result in zip(good, counted):
                pending_ids.append(fid)
                pending.append(result)
                extra[fid] = facts
            while len(pending_ids) >= part_frames:
                flush(part_frames)
            if progress is not None:
                progress(loaded)

    pipeline = _Pipeline(source)
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
        done = pipeline.push(([(fid, _frame_facts(frame)) for fid, frame in good], len(loaded)),
                             [frame for _, frame in good])
        report.stage_seconds["count"] += time.perf_counter() - t
        take(done)
        t = time.perf_counter()
    t = time.perf_counter()
    done = pipeline.drain()
    report.stage_seconds["count"] += time.perf_counter() - t
    take(done)
    flush(len(pending_ids))
    barrier()
    report.seconds = time.perf_counter() - start
    return report
