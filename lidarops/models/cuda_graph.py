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

The detections are :meth:`PointPillars.predict`'s (the same kernels in float32; fp16 / TF32 round like
their eager autocast runs). Only the dense backbone can be captured: the sparse one builds its kernel
maps with host reads.
"""
from __future__ import annotations

import contextlib

import torch
from torch import Tensor

import lidarops
from lidarops.models.pointpillars import PointPillars, _check_batch
from lidarops.models.postprocess import postprocess_padded
from lidarops.ops.pillars import MAX_ABS_INTENSITY
from lidarops.ops.validation import check_tensor, describe, value_checks_enabled

__all__ = ["GraphedPointPillars", "PRECISIONS"]

PRECISIONS = ("fp32", "tf32", "fp16")


@contextlib.contextmanager
def precision_mode(precision: str, device_type: str = "cuda", autocast: bool = True):
    """``"fp32"``: float32 without TF32; ``"tf32"``: TF32 matmuls and convolutions; ``"fp16"``: float16
    autocast (``autocast=False``: no autocast, for a model already converted with ``.half()``)."""
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


class GraphedPointPillars:
    """A PointPillars model's inference on one frame as a replayed CUDA graph.

    Args:
        model (PointPillars): an eval-mode model on a CUDA device, ``backbone_mode="dense"``. Its
            weights are read by the graph at each replay (updating them in place is seen; replacing
            the parameter tensors is not).
        capacity (int): the most points a frame may have; memory and the voxelization's time grow with it.
        precision (str): ``"fp32"`` (default), ``"tf32"`` or ``"fp16"`` (float16 autocast), fixed at capture.

    Calling it with ``points (Tensor[P, C])`` (``C >= config.num_point_features``: x, y, z, intensity;
    more columns are ignored; ``P <= capacity``; the model's device) returns one dict of ``boxes (K, 7)``,
    ``scores (K,)``, ``labels (K,)`` (1-based into ``config.class_names``), as :meth:`PointPillars.predict`
    gives for that frame. The graph also checks the points' features as the eager call does; with
    ``lidarops.validation`` on (the default) a bad frame raises the eager call's ``ValueError`` (the flag
    comes back with the number of boxes: still one host read).
    """

    def __init__(self, model: PointPillars, capacity: int = 150_000, precision: str = "fp32"):
        if not isinstance(model, PointPillars):
            raise TypeError(f"model must be a PointPillars, got {type(model).__name__}")
        param = next(model.parameters())
        if param.device.type != "cuda":
            raise ValueError(f"GraphedPointPillars needs the model on a CUDA device, got {param.device}")
        cfg = model.config
        if cfg.backbone_mode != "dense":
            raise ValueError(f"GraphedPointPillars needs backbone_mode='dense', got {cfg.backbone_mode!r}: the sparse "
                             "backbone builds its kernel maps with host reads, which a CUDA graph cannot hold")
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"capacity must be an int >= 1, got {capacity!r}")
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.model, self.capacity, self.precision = model.eval(), capacity, precision
        self.device, self.dtype = param.device, param.dtype
        c = cfg.num_point_features
        # rows past the frame: outside the point range, so voxelization leaves them out
        self._pad = torch.zeros(c, device=self.device, dtype=self.dtype)
        self._pad[0] = cfg.point_cloud_range[3] + 1000.0
        self._points = self._pad.expand(capacity, c).clone()
        self._filled = 0  # rows holding the last frame's points
        half_model = self.dtype == torch.float16
        # a frame cannot have more pillars than points: the padded tensors need no more rows
        max_voxels = min(cfg.max_voxels_test, capacity)

        def body():
            from lidarops.ops.voxelize import voxelize

            with torch.no_grad(), precision_mode(precision, autocast=not half_model), lidarops.validation(False):
                v, co, n = voxelize(self._points, cfg.voxel_size, cfg.point_cloud_range, cfg.max_points_per_voxel,
                                    max_voxels, overflow="drop", padded=True)
                coords = torch.cat([(co[:, :1] >= 0).to(co.dtype) - 1, co], 1)  # frame 0; padding rows -1
                out = postprocess_padded(*model.dense_head.decode(model.network(v, n, coords, 1)), cfg)
                # the eager call's value check, read back with the number of boxes
                feats = self._points[:, 3:c]
                bad = ~(feats.abs() <= MAX_ABS_INTENSITY).all() if feats.shape[1] else torch.zeros((), dtype=torch.bool,
                                                                                                   device=self.device)
                out["read"] = torch.stack([out["count"][0], bad.to(torch.int64)])
                return out

        with torch.cuda.device(self.device):
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):  # warm-up: cuDNN picks its algorithms, the allocator its blocks
                for _ in range(2):
                    body()
            torch.cuda.current_stream().wait_stream(side)
            self._graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self._graph):
                self._out = body()

    def __call__(self, points: Tensor) -> dict[str, Tensor]:
        check_tensor(points, "points")
        c = self.model.config.num_point_features
        if points.dim() != 2 or points.shape[1] < c or not points.is_floating_point():
            raise ValueError(f"points must be a floating (P, C >= {c}) tensor (x, y, z, intensity), got {describe(points)}")
        if points.device != self.device:
            raise ValueError(f"points is on {points.device} but the model is on {self.device}")
        if points.shape[0] > self.capacity:
            raise ValueError(f"points has {points.shape[0]} rows, more than capacity={self.capacity}: build a "
                             "GraphedPointPillars with a larger capacity")
        p = points.shape[0]
        self._points[:p].copy_(points[:, :c])
        if self._filled > p:  # the rows of a larger previous frame become padding again
            self._points[p:self._filled].copy_(self._pad.expand(self._filled - p, c))
        self._filled = p
        self._graph.replay()
        k, bad = self._out["read"].tolist()  # the one host read
        if bad and value_checks_enabled():  # the eager call's check and message
            _check_batch({"points": torch.nn.functional.pad(points[:, :c], (1, 0)), "batch_size": 1},
                         self.model.config, False, self.dtype)
        return {"boxes": self._out["boxes"][0, :k].clone(), "scores": self._out["scores"][0, :k].clone(),
                "labels": self._out["labels"][0, :k].clone()}
