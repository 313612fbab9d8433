"""PointPillars inference replayed as one CUDA graph.

A frame's eager :meth:`PointPillars.predict` launches a few hundred kernels and reads back to the host
several times (the number of pillars, the boxes above the score threshold, the boxes NMS keeps); at
PointPillars' size the GPU then waits on the host. :class:`GraphedPointPillars` records the whole
inference once, for frames of up to ``capacity`` points, and replays it: padded voxelization
(``lidarops.voxelize(..., padded=True)``), the network, the decode and :func:`postprocess_padded`
(score threshold and rotated NMS with fixed-size outputs). The only host read is the number of boxes,
after the replay.

    graphed = GraphedPointPillars(model, capacity=150_000, precision="fp16")
    det = graphed(points)          # (P, 4) x, y, z, intensity on the model's device
    det["boxes"], det["scores"], det["labels"]

With ``batch_size=B`` one replay runs B frames (each voxelized on its own, the network and the
post-processing on the batch): ``graphed([p0, p1, ...])`` returns a list of such dicts, and
:meth:`GraphedPointPillars.replay` leaves the padded outputs on the device (the frame index's detector
source gathers its counts there).

The detections are :meth:`PointPillars.predict`'s (the same kernels in float32; fp16 / TF32 round like
their eager autocast runs). Only the dense backbone can be captured: the sparse one builds its kernel
maps with host reads.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence

import torch
from torch import Tensor

import lidarops
from lidarops.models.pointpillars import PointPillars, _check_batch
from lidarops.models.postprocess import postprocess_padded
from lidarops.ops.pillars import MAX_ABS_INTENSITY
from lidarops.ops.validation import check_tensor, describe, value_checks_enabled

__all__ = ["GraphedPointPillars", "PRECISIONS", "padded_inference"]

PRECISIONS = ("fp32", "tf32", "fp16")


@contextlib.contextmanager
def precision_mode(precision: str | None, device_type: str = "cuda", autocast: bool = True):
    """``"fp32"``: float32 without TF32; ``"tf32"``: TF32 matmuls and convolutions; ``"fp16"``: float16
    autocast (``autocast=False``: no autocast, for a model already converted with ``.half()``); None: torch's
    settings as they are."""
    if precision is None:
        yield
        return
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = precision == "tf32"
    ctx = torch.autocast(device_type=device_type, dtype=torch.float16) \
        if precision == "fp16" and autocast else contextlib.nullcontext()
    try:
        with ctx:
            yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def padded_inference(model: PointPillars, points: Tensor, max_pillars: int | None = None) -> dict[str, Tensor]:
    """:meth:`PointPillars.predict` on a batch of frames padded to one size, with outputs of sizes fixed by
    the shapes and nothing read back to the host: the body :class:`GraphedPointPillars` records, usable
    eagerly too (any device).

    The frames are voxelized by one call, stacked along z (frame b's points in the b-th slab of a pillar's
    height: the pillars are the per-frame ones, each frame keeping its own first ``max_voxels_test``), and the
    pillars of the whole batch are packed into ``max_pillars`` rows, frame after frame, so the pillar net and
    the scatter work on the pillars there are rather than on every frame's capacity.

    Args:
        model: an eval-mode PointPillars with ``backbone_mode="dense"``.
        points (Tensor[B, N, C]): frame b's points in ``points[b]``; rows outside the point range (the
            padding: x beyond it) are left out as voxelization leaves them out.
        max_pillars: pillar rows for the whole batch (default ``B * min(max_voxels_test, N)``, which always
            holds them). A batch with more pillars sets ``overflow``: its detections are then incomplete.

    Returns:
        dict of :func:`postprocess_padded`'s ``boxes (B, K, 7)``, ``scores``, ``labels``, ``count (B,)``;
        ``bad (B,)`` bool: frames whose features fail the eager call's value check; ``pillars`` (0-d int64):
        the rows the batch needs; ``overflow`` (0-d bool): more than ``max_pillars``.
    """
    from lidarops.ops.voxelize import voxel_grid_shape

    if not isinstance(model, PointPillars) or model.config.backbone_mode != "dense":
        raise ValueError(f"model must be a PointPillars with backbone_mode='dense', got {type(model).__name__}"
                         + (f" ({model.config.backbone_mode!r})" if isinstance(model, PointPillars) else ""))
    cfg = model.config
    check_tensor(points, "points")
    c = cfg.num_point_features
    if points.dim() != 3 or points.shape[2] < c or not points.is_floating_point() or points.shape[0] < 1:
        raise ValueError(f"points must be a floating (B >= 1, N, C >= {c}) tensor (frame b's x, y, z, intensity in "
                         f"points[b]), got {describe(points)}")
    param = next(model.parameters())
    if points.device != param.device:
        raise ValueError(f"points is on {points.device} but the model is on {param.device}")
    points = points.to(param.dtype)  # as predict does: the weights' dtype
    B, N, c = points.shape
    nz, ny, nx = voxel_grid_shape(cfg.voxel_size, cfg.point_cloud_range)
    if nz != 1:
        raise ValueError(f"padded_inference needs pillars (one voxel along z), got a grid of {nz} along z")
    per_frame = min(cfg.max_voxels_test, max(N, 1))
    if max_pillars is not None and (isinstance(max_pillars, bool) or not isinstance(max_pillars, int)
                                    or max_pillars < 1):
        raise ValueError(f"max_pillars must be an int >= 1 or None, got {max_pillars!r}")
    rows = B * min(per_frame, nx * ny) if max_pillars is None else max_pillars
    stage = torch.profiler.record_function  # ranges for benchmarks/profile/detector.py; nothing in a graph
    with stage("voxelize"):
        voxels, count, coords, needed = _batch_pillars(points, cfg, rows)
    with lidarops.validation(False):
        with stage("pfn"):
            x = model.vfe(voxels, count, coords)
        with stage("scatter"):
            x = model.map_to_bev(x, coords, B)
        with stage("backbone"):
            x = model.backbone_2d(x)
        with stage("head"):
            x = model.dense_head(x)
        with stage("decode"):
            x = model.dense_head.decode(x)
        with stage("postprocess"):
            out = postprocess_padded(*x, cfg)
    feats = points[:, :, 3:c]
    out["bad"] = ~(feats.abs() <= MAX_ABS_INTENSITY).flatten(1).all(1) if feats.shape[2] else \
        torch.zeros(B, dtype=torch.bool, device=points.device)
    out["pillars"] = needed
    out["overflow"] = needed > rows
    return out


def _batch_pillars(points: Tensor, cfg, rows: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pillars of a padded batch (:func:`padded_inference`) packed into ``rows`` rows: ``voxels (rows, P, C)``,
    ``num_points (rows,)``, ``coords (rows, 4)`` int32 (frame, 0, y, x; -1 for the rows left over) and the rows
    needed (0-d)."""
    from lidarops.ops.voxelize import voxel_assignment, voxel_grid_shape

    B, N, _ = points.shape
    vs, pr = [float(v) for v in cfg.voxel_size], [float(v) for v in cfg.point_cloud_range]
    _, ny, nx = voxel_grid_shape(vs, pr)
    per_frame = min(cfg.max_voxels_test, max(N, 1))
    flat = points.reshape(B * N, points.shape[2])[:, :cfg.num_point_features]
    # frame b's in-range points in the middle of the b-th slab; the op's own z test, in its float32
    # arithmetic (lidarops/voxelize.h); out-of-range z becomes NaN, which no slab holds
    xyz = flat[:, :3].float()
    z = xyz[:, 2]
    # (Python scalars: a CUDA graph capture refuses a copy from the host; float32 tensors keep float32 math)
    inside = (z >= pr[2]) & (z < pr[5]) & (torch.floor((z - pr[2]) / vs[2]) == 0)
    frame = torch.arange(B, device=points.device).repeat_interleave(N)
    slab = (frame.to(torch.float64) + 0.5) * vs[2] + pr[2]
    xyz = torch.cat([xyz[:, :2], torch.where(inside, slab, math.nan).to(torch.float32)[:, None]], 1)
    # every pillar of every frame gets a row here (16 bytes a row): none is dropped before the per-frame cap
    coords, nums, point_voxel, point_slot = voxel_assignment(
        xyz, vs, pr[:5] + [pr[2] + B * vs[2]], cfg.max_points_per_voxel, B * min(N, nx * ny) if N else 1)
    T = coords.shape[0]
    valid = coords[:, 0] >= 0
    owner = coords[:, 0].long().clamp(min=0)
    # rows come frame after frame (first seen, frames stacked in order): a row's rank within its frame
    held = torch.zeros(B, dtype=torch.int64, device=points.device).index_add_(0, owner, valid.long())
    start = torch.cumsum(held, 0) - held
    keep = valid & (torch.arange(T, device=points.device) - start[owner] < per_frame)
    new = torch.cumsum(keep.long(), 0) - 1
    needed = keep.sum()
    keep = keep & (new < rows)
    target = torch.where(keep, new, rows)  # row `rows`: a spare for everything not kept
    remap = torch.cat([target, target.new_full((1,), rows)])
    pv = remap[torch.where(point_voxel >= 0, point_voxel, T)]
    pv = torch.where(pv < rows, pv, -1)
    voxels = torch.ops.lidarops.voxelize_scatter(flat, pv, point_slot, rows, cfg.max_points_per_voxel)
    packed = torch.full((rows + 1, 4), -1, dtype=coords.dtype, device=points.device)
    packed.index_copy_(0, target, torch.cat([coords[:, :1], torch.zeros_like(coords[:, :1]), coords[:, 1:]], 1))
    count = torch.zeros(rows + 1, dtype=nums.dtype, device=points.device).index_copy_(0, target, nums)
    return voxels, count[:rows], packed[:rows], needed


class GraphedPointPillars:
    """A PointPillars model's inference on one frame, or on ``batch_size`` frames at once, as a replayed
    CUDA graph.

    Args:
        model (PointPillars): an eval-mode model on a CUDA device, ``backbone_mode="dense"``. Its
            weights are read by the graph at each replay (updating them in place is seen; replacing
            the parameter tensors is not).
        capacity (int): the most points a frame may have; memory and the voxelization's time grow with it.
        precision (str | None): ``"fp32"`` (default), ``"tf32"`` or ``"fp16"`` (float16 autocast), fixed at
            capture; None: torch's TF32 settings as they are at capture.
        batch_size (int): frames per replay (default 1): voxelized together (each keeping its own pillars),
            the network and the post-processing run on the batch.
        max_pillars (int | None): pillar rows of a replay, all frames together (:func:`padded_inference`);
            default ``batch_size * min(max_voxels_test, capacity)``, which always holds them. Fewer rows make
            the pillar net's work smaller; a replay whose frames need more is redone eagerly by a call (and
            reported by :meth:`replay`'s ``overflow``).

    Calling it with ``points (Tensor[P, C])`` (``C >= config.num_point_features``: x, y, z, intensity;
    more columns are ignored; ``P <= capacity``; the model's device) returns one dict of ``boxes (K, 7)``,
    ``scores (K,)``, ``labels (K,)`` (1-based into ``config.class_names``), as :meth:`PointPillars.predict`
    gives for that frame; with a list of up to ``batch_size`` such frames, a list of such dicts.
    :meth:`replay` leaves the padded outputs on the device, for callers that gather them there. The graph
    also checks the points' features as the eager call does; with ``lidarops.validation`` on (the default)
    a bad frame raises the eager call's ``ValueError`` (the flag comes back with the number of boxes: still
    one host read).
    """

    def __init__(self, model: PointPillars, capacity: int = 150_000, precision: str | None = "fp32",
                 batch_size: int = 1, max_pillars: int | None = None):
        if not isinstance(model, PointPillars):
            raise TypeError(f"model must be a PointPillars, got {type(model).__name__}")
        param = next(model.parameters())
        if param.device.type != "cuda":
            raise ValueError(f"GraphedPointPillars needs the model on a CUDA device, got {param.device}")
        cfg = model.config
        if cfg.backbone_mode != "dense":
            raise ValueError(f"GraphedPointPillars needs backbone_mode='dense', got {cfg.backbone_mode!r}: the sparse "
                             "backbone builds its kernel maps with host reads, which a CUDA graph cannot hold")
        for name, value in (("capacity", capacity), ("batch_size", batch_size)) + \
                (() if max_pillars is None else (("max_pillars", max_pillars),)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if precision is not None and precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS} or None, got {precision!r}")
        self.model, self.capacity, self.precision, self.batch_size = model.eval(), capacity, precision, batch_size
        self.max_pillars = max_pillars
        self.device, self.dtype = param.device, param.dtype
        c = cfg.num_point_features
        # rows past the frame: outside the point range, so voxelization leaves them out
        self._pad = torch.zeros(c, device=self.device, dtype=self.dtype)
        self._pad[0] = cfg.point_cloud_range[3] + 1000.0
        self._points = self._pad.expand(batch_size, capacity, c).clone()
        self._filled = [0] * batch_size  # rows holding each slot's last frame's points
        half_model = self.dtype == torch.float16

        def body():
            with torch.no_grad(), precision_mode(precision, autocast=not half_model):
                out = padded_inference(model, self._points, max_pillars)
                # the one host read: each frame's number of boxes and value check, the batch's pillars
                out["read"] = torch.stack([out["count"], out["bad"].to(torch.int64),
                                           out["overflow"].to(torch.int64).expand(batch_size),
                                           out["pillars"].expand(batch_size)], 1)
                return out

        with torch.cuda.device(self.device):
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):  # warm-up: cuDNN picks its algorithms, the allocator its blocks
                for _ in range(2):
                    body()
            torch.cuda.current_stream().wait_stream(side)
            self._graph = torch.cuda.CUDAGraph()
            # thread_local: a DataLoader's pin-memory thread allocating pinned buffers meanwhile (the index
            # build) must not invalidate this capture, as the default global mode lets it
            with torch.cuda.graph(self._graph, capture_error_mode="thread_local"):
                self._out = body()

    def _check(self, points: Tensor, name: str) -> None:
        check_tensor(points, name)
        c = self.model.config.num_point_features
        if points.dim() != 2 or points.shape[1] < c or not points.is_floating_point():
            raise ValueError(f"{name} must be a floating (P, C >= {c}) tensor (x, y, z, intensity), got {describe(points)}")
        if points.device != self.device:
            raise ValueError(f"{name} is on {points.device} but the model is on {self.device}")
        if points.shape[0] > self.capacity:
            raise ValueError(f"{name} has {points.shape[0]} rows, more than capacity={self.capacity}: build a "
                             "GraphedPointPillars with a larger capacity")

    def replay(self, frames: Sequence[Tensor]) -> dict[str, Tensor]:
        """Runs the graph on up to ``batch_size`` frames (each ``Tensor[P, C]`` as for a call) and returns its
        padded outputs on the device without reading anything back: ``boxes (B, K, 7)``, ``scores``,
        ``labels``, ``count (B,)``, ``bad (B,)``, ``pillars`` and ``overflow`` (0-d: the pillar rows the frames
        needed, more than ``max_pillars``: the detections are then incomplete) and ``read (B, 4)`` (count, bad,
        overflow, pillars), row b for frame b (rows past the frames given: empty frames). They are overwritten by the next replay: gather or copy them
        first (work queued on the current stream before the next replay is)."""
        if not isinstance(frames, (list, tuple)) or not 1 <= len(frames) <= self.batch_size:
            raise ValueError(f"frames must be a list of 1 to batch_size={self.batch_size} point tensors, "
                             f"got {type(frames).__name__}" + (f" of {len(frames)}" if isinstance(frames, (list, tuple))
                                                               else ""))
        for i, f in enumerate(frames):
            self._check(f, f"frames[{i}]")
        c = self.model.config.num_point_features
        for b in range(self.batch_size):
            p = frames[b].shape[0] if b < len(frames) else 0
            if p:
                self._points[b, :p].copy_(frames[b][:, :c])
            if self._filled[b] > p:  # the rows of a larger previous frame become padding again
                self._points[b, p:self._filled[b]].copy_(self._pad.expand(self._filled[b] - p, c))
            self._filled[b] = p
        self._graph.replay()
        return self._out

    def __call__(self, points: Tensor | Sequence[Tensor]) -> dict[str, Tensor] | list[dict[str, Tensor]]:
        one = isinstance(points, Tensor)
        if one:
            self._check(points, "points")
        frames = [points] if one else points
        out = self.replay(frames)
        reads = out["read"][:len(frames)].tolist()  # the one host read
        if reads[0][2]:  # more pillars than max_pillars: the eager call, frame by frame, in the graph's precision
            c = self.model.config.num_point_features
            with precision_mode(self.precision, autocast=self.dtype != torch.float16):
                dets = [self.model.predict({"points": torch.nn.functional.pad(f[:, :c], (1, 0)), "batch_size": 1})[0]
                        for f in frames]
            return dets[0] if one else dets
        if value_checks_enabled():
            for f, (_, bad, _, _) in zip(frames, reads):
                if bad:  # the eager call's check and message
                    _check_batch({"points": torch.nn.functional.pad(f[:, :self.model.config.num_point_features],
                                                                    (1, 0)), "batch_size": 1},
                                 self.model.config, False, self.dtype)
        dets = [{"boxes": out["boxes"][b, :k].clone(), "scores": out["scores"][b, :k].clone(),
                 "labels": out["labels"][b, :k].clone()} for b, (k, *_) in enumerate(reads)]
        return dets[0] if one else dets
