"""PointPillars, the detector (Lang et al., CVPR 2019), as OpenPCDet's ``pointpillar.yaml`` builds it.
Read it top to bottom: the batch's points are voxelized into pillars on the device, then

- ``vfe``: :class:`~lidarops.models.pillar_vfe.PillarVFE`, 10 features per point, a PointNet layer, the
  max over each pillar's slots;
- ``map_to_bev``: :class:`~lidarops.models.map_to_bev.PointPillarScatter`, pillar features into a dense
  (B, C, ny, nx) pseudo-image;
- ``backbone_2d``: :class:`~lidarops.models.bev_backbone.BaseBEVBackbone`, dense (cuDNN, OpenPCDet's
  layout) or sparse (:mod:`lidarops.sparse`) with the same parameters;
- ``dense_head``: :class:`~lidarops.models.anchor_head.AnchorHeadSingle`, class scores, box residuals and
  direction bins over the anchors, with its losses and decoding;
- :meth:`PointPillars.postprocess`: score threshold, top-k and rotated NMS
  (:mod:`lidarops.models.postprocess`); :class:`~lidarops.models.cuda_graph.GraphedPointPillars` replays
  the whole inference as one CUDA graph.

Module and parameter names, shapes and the anchor order are OpenPCDet's, so an OpenPCDet PointPillars
checkpoint (``checkpoint["model_state"]``) loads with ``strict=True`` and gives the same boxes.
"""
from __future__ import annotations

import contextlib
import contextvars
import math
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops import checkpoint
from lidarops._moved import moved_attributes
from lidarops.checkpoint import CheckpointError, model_record, model_state, read_checkpoint
from lidarops.config import ConfigError
from lidarops.models.base import PredictMixin, as_model_config, placed
from lidarops.models.anchor_head import AnchorHeadSingle
from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.models.config import PointPillarsConfig
from lidarops.models.map_to_bev import PointPillarScatter
from lidarops.models.pillar_vfe import PillarVFE
from lidarops.models.postprocess import _postprocess_rows, postprocess
from lidarops.ops.pillars import MAX_ABS_INTENSITY
from lidarops.ops.validation import (check_positive_int, check_tensor, describe, run_value_checks,
                                      value_checks_enabled)

__all__ = ["PointPillars", "CheckpointMismatchError", "PREDICT_CPU_COPY", "PREDICT_CUDA_GRAPH", "eager_predict",
           "voxelize_frames"]

# predict() on CUDA (dense backbone) replays the whole inference as one CUDA graph from the second call with frames
# of a size (lidarops.models.cuda_graph.graphed_predict): eager, it launches a few hundred kernels and reads sizes
# back to the host several times, and at PointPillars' size the GPU waits on the host. The same detections.
PREDICT_CUDA_GRAPH = True
# predict() on the CPU (dense backbone) runs an inference copy of the model, BatchNorm and padding folded into the
# convolutions and the maps channels-last (lidarops.models.cuda_graph.copy_predict): about half the time, the same
# detections up to float rounding. False (or eager_predict()) runs the model itself.
PREDICT_CPU_COPY = True
_EAGER_PREDICT = contextvars.ContextVar("lidarops_eager_predict", default=False)


@contextlib.contextmanager
def eager_predict():
    """``PointPillars.predict`` runs the model itself, eagerly, inside this context (no CUDA graph, no inference
    copy on the CPU), whatever :data:`PREDICT_CUDA_GRAPH` and :data:`PREDICT_CPU_COPY` say."""
    token = _EAGER_PREDICT.set(True)
    try:
        yield
    finally:
        _EAGER_PREDICT.reset(token)

# lidarops 0.1's lidarops.models.pointpillars held the backbone and SSCATeR's pillar net: those names moved
__getattr__ = moved_attributes(__name__, {
    "PointPillarsBackbone": ("lidarops.models.bev_backbone", "BaseBEVBackbone"),
    "BackboneLayer": "lidarops.models.bev_backbone",
    "backbone_layers": "lidarops.models.bev_backbone",
    "scatter_to_bev": "lidarops.models.map_to_bev",
    "PillarFeatureNet": "lidarops.models.sscater_pointpillars",
})

#: A state dict that does not fit the model's config (the message lists the keys that differ), or a file
#: that is not a readable checkpoint: :class:`lidarops.checkpoint.CheckpointError` under its 0.1 name.
CheckpointMismatchError = CheckpointError


class PointPillars(PredictMixin, nn.Module):
    """The PointPillars detector.

    Args:
        config (PointPillarsConfig | Mapping | str | Path): a typed config, a dict of its fields, an
            OpenPCDet-schema dict (with ``MODEL``), or a YAML path (OpenPCDet's ``pointpillar.yaml`` or a
            lidarops config).

    Batch (OpenPCDet's keys): ``points (Tensor[P, 1 + C])`` with the frame's index in the batch in
    column 0 then x, y, z, intensity; ``batch_size`` (int); in training ``gt_boxes (Tensor[B, M, 8])``
    (7 box values + class id, 1-based into ``class_names``, 0 = padding).

    ``forward(batch)`` returns the losses in training mode (``loss``, ``loss_cls``, ``loss_box``,
    ``loss_dir``) and the raw head outputs in eval mode; :meth:`postprocess` turns those into
    per-frame boxes, :meth:`predict` does both.
    """

    def __init__(self, config: "PointPillarsConfig | Mapping | str | Path" = None):
        super().__init__()
        cfg = self.config = as_model_config(config, PointPillarsConfig)
        self.vfe = PillarVFE(cfg.num_point_features, cfg.voxel_size, cfg.point_cloud_range, cfg.vfe_num_filters,
                             cfg.with_distance, cfg.use_absolute_xyz, cfg.use_norm)
        self.map_to_bev = PointPillarScatter(self.vfe.out_channels, cfg.grid_size)
        self.backbone_2d = BaseBEVBackbone(self.vfe.out_channels, cfg.layer_nums, cfg.layer_strides, cfg.num_filters,
                                           cfg.upsample_strides, cfg.num_upsample_filters, mode=cfg.backbone_mode)
        self.dense_head = AnchorHeadSingle(cfg, self.backbone_2d.out_channels)
        self.register_buffer("global_step", torch.zeros(1, dtype=torch.long))  # OpenPCDet's Detector3DTemplate

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config: "PointPillarsConfig | Mapping | str | Path") -> "PointPillars":
        """A model with freshly initialised weights from a config (see the class docstring)."""
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: "PointPillarsConfig | Mapping | str | Path | None" = None,
                        map_location: "str | torch.device" = "cpu", check_finite: bool = True) -> "PointPillars":
        """A model with weights from a lidarops checkpoint (it carries its config) or an OpenPCDet one
        (``model_state``; give its ``config``). A state dict that does not fit, or (with ``check_finite``)
        holds NaN or infinite values, raises :class:`~lidarops.checkpoint.CheckpointError` naming the keys."""
        ckpt = read_checkpoint(path, map_location)
        record = model_record(ckpt, str(path))
        if record.model_class not in (None, cls.__name__):
            raise CheckpointError(f"{path} holds a {record.model_class}, not a {cls.__name__}: load it with "
                                  "lidarops.models.load_model(path)")
        if config is None:
            config = record.config
            if config is None:
                raise ConfigError(f"{path} carries no model config (an OpenPCDet checkpoint?): pass config=...")
        try:
            model = cls(config)
        except ConfigError as e:
            where = "the config given" if record.config is None or config is not record.config else "its model_config"
            raise ConfigError(f"{path}: {where}: {e}") from None
        model.load_weights(model_state(ckpt, str(path)), source=str(path), check_finite=check_finite)
        return placed(model, map_location)

    def load_weights(self, state_dict: Mapping[str, Tensor], source: str = "state dict",
                     check_finite: bool = True) -> None:
        """``load_state_dict(strict=True)`` after checking keys and shapes, with one error naming every
        missing, unexpected or differently shaped key; with ``check_finite`` (the default) NaN or infinite
        values are refused too, naming the tensors (:func:`lidarops.checkpoint.check_finite`)."""
        own = self.state_dict()
        missing = [k for k in own if k not in state_dict]
        unexpected = [k for k in state_dict if k not in own]
        shapes = [f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(own[k].shape)}"
                  for k in own if k in state_dict and tuple(state_dict[k].shape) != tuple(own[k].shape)]
        if missing or unexpected or shapes:
            parts = []
            for title, items in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", shapes)):
                if items:
                    parts.append(f"{title} ({len(items)}): " + ", ".join(items[:8]) + (" ..." if len(items) > 8 else ""))
            raise CheckpointMismatchError(f"{source} does not fit this PointPillars config "
                                          f"(classes {self.config.class_names}): " + "; ".join(parts))
        if check_finite:
            checkpoint.check_finite(state_dict, source)
        self.load_state_dict({k: v.to(own[k].dtype) for k, v in state_dict.items()}, strict=True)

    # ---------------------------------------------------------------- the network
    def voxelize(self, points: Tensor, batch_size: int) -> tuple[Tensor, Tensor, Tensor]:
        """Pillars of every frame: ``voxels (V, N, C)``, ``num_points (V,)``, ``coords (V, 4)`` int32 =
        (batch, z, y, x); pillars beyond the config's max voxels (train / test) are dropped."""
        return voxelize_frames(points, batch_size, self.config, self.training)

    def network(self, voxels: Tensor, num_points: Tensor, coords: Tensor, batch_size: int) -> dict[str, Tensor]:
        """Pillars -> raw head outputs (the part ``torch.export`` takes)."""
        features = self.vfe(voxels, num_points, coords)
        if self.config.backbone_mode == "dense":
            bev = self.backbone_2d(self.map_to_bev(features, coords, batch_size))
        else:
            from lidarops.sparse import SparseConvTensor

            nx, ny, _ = self.config.grid_size
            x = SparseConvTensor(features, coords[:, [0, 2, 3]].int().contiguous(), [ny, nx], batch_size)
            bev = self.backbone_2d(x)
        return self.dense_head(bev)

    def forward(self, batch: Mapping[str, Any]) -> dict[str, Tensor]:
        weights = self.vfe.pfn_layers[0].linear.weight.dtype
        points, batch_size = _check_batch(batch, self.config, self.training, weights)
        raw = self.network(*self.voxelize(points, batch_size), batch_size)
        if not self.training:
            return raw
        return self.dense_head.loss(raw, batch["gt_boxes"])

    def postprocess(self, raw: Mapping[str, Tensor], batch: Mapping[str, Any] | None = None) -> list[dict]:
        """Per-frame detections (see :func:`postprocess`) from the raw outputs of ``forward`` in eval mode."""
        head = self.dense_head
        if raw["cls_preds"].is_cuda:  # every anchor decoded in a few launches, once for the whole batch
            return postprocess(*head.decode(raw), self.config)
        # on the CPU only the anchors the score threshold keeps are decoded (decoding every anchor costs more than
        # the rest of the post-processing); each anchor's box depends on its own row alone
        B = raw["cls_preds"].shape[0]
        return _postprocess_rows(raw["cls_preds"].view(B, -1, head.num_class).float(),
                                 lambda b, anchors: head._decode_rows(raw, b, anchors), self.config)

    def _predict_replayed(self, batch: Mapping[str, Any]) -> list[dict] | None:
        # cheap tests first: the graph module is imported only when a graph or the inference copy may run
        points = batch.get("points") if isinstance(batch, Mapping) else None
        if not (isinstance(points, Tensor) and self.config.backbone_mode == "dense" and not _EAGER_PREDICT.get()):
            return None
        if points.is_cuda and PREDICT_CUDA_GRAPH:
            from lidarops.models.cuda_graph import graphed_predict

            return graphed_predict(self, batch)
        return _predict_on_cpu_copy(self, batch)


def _predict_on_cpu_copy(model: nn.Module, batch: Mapping[str, Any]) -> list[dict] | None:
    """``model.predict(batch)`` through the model's inference copy (:data:`PREDICT_CPU_COPY`), or None where the
    model itself runs (the switch off, inside :func:`eager_predict`, or what :func:`copy_predict` leaves to it: a
    batch or model off the CPU). For models on PointPillars' dense floor."""
    if not PREDICT_CPU_COPY or _EAGER_PREDICT.get():
        return None
    from lidarops.models.cuda_graph import copy_predict

    return copy_predict(model, batch)


def voxelize_frames(points: Tensor, batch_size: int, cfg: PointPillarsConfig,
                    training: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The pillars of every frame of an OpenPCDet batch (``points (P, 1 + C)``, frame index first), with the
    config's capacities (train or test): ``voxels (V, N, C)``, ``num_points (V,)``, ``coords (V, 4)`` int32 =
    (batch, z, y, x). The same as voxelizing each frame on its own and concatenating, frame by frame."""
    from lidarops.ops.voxelize import voxelize

    max_voxels = cfg.max_voxels_train if training else cfg.max_voxels_test
    if batch_size > 1:
        stacked = _voxelize_stacked(points, batch_size, cfg, max_voxels)
        if stacked is not None:
            return stacked
    frame = points[:, 0].long()
    voxels, nums, coords = [], [], []
    for b in range(batch_size):
        pts = points[frame == b, 1:1 + cfg.num_point_features]
        v, c, n = voxelize(pts, cfg.voxel_size, cfg.point_cloud_range, cfg.max_points_per_voxel, max_voxels,
                           overflow="drop")
        voxels.append(v)
        nums.append(n)
        coords.append(F.pad(c, (1, 0), value=b))
    return torch.cat(voxels), torch.cat(nums), torch.cat(coords)


def _voxelize_stacked(points: Tensor, batch_size: int, cfg: PointPillarsConfig,
                      max_voxels: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """:func:`voxelize_frames` in one call of the op instead of one per frame (each reads counts back to the
    host): pillars span the whole z range, so the frames are stacked along z, frame b's points placed in
    the middle of the b-th slab and their own z put back afterwards. None where that would not give the
    per-frame result: not pillars, a dtype whose z could not hold the slabs exactly, a frame over
    ``max_voxels`` (the per-frame call drops its last pillars)."""
    from lidarops.ops.voxelize import voxelize

    if points.dtype not in (torch.float32, torch.float64):
        return None
    vs, pr = list(cfg.voxel_size), list(cfg.point_cloud_range)
    if round((pr[5] - pr[2]) / vs[2]) != 1:
        return None
    order = torch.argsort(points[:, 0], stable=True)  # frame by frame, each frame's points in their order
    pts = points[order]
    frame = pts[:, 0].long()
    feats = pts[:, 1:1 + cfg.num_point_features]
    z = feats[:, 2]
    # the op's own test of z, in its arithmetic (lidarops/voxelize.h): lo <= z < hi and floor((z - lo) / size) == 0
    lo, hi, size = (torch.tensor(v, dtype=z.dtype, device=z.device) for v in (pr[2], pr[5], vs[2]))
    inside = (z >= lo) & (z < hi) & (torch.floor((z - lo) / size) == 0)
    slab = pr[2] + (frame.to(torch.float64) + 0.5) * vs[2]
    stacked = feats.clone()
    stacked[:, 2] = torch.where(inside, slab, math.nan).to(z.dtype)
    res = voxelize(stacked, vs, pr[:5] + [pr[2] + batch_size * vs[2]], cfg.max_points_per_voxel,
                   batch_size * max_voxels, overflow="drop")
    voxels, coords, nums = res
    per_frame = torch.zeros(batch_size, dtype=torch.int64, device=coords.device)
    per_frame.index_add_(0, coords[:, 0].long(), torch.ones_like(coords[:, 0], dtype=torch.int64))
    if bool((per_frame > max_voxels).any()):
        return None
    # each stored point's own z back in its slot; the points not stored write to one spare slot
    V, P = voxels.shape[:2]
    info = res.info
    slot = torch.where(info.point_slot >= 0, info.point_voxel * P + info.point_slot, V * P)
    column = torch.zeros(V * P + 1, dtype=voxels.dtype, device=voxels.device)
    column[slot] = z
    voxels[:, :, 2] = column[:-1].view(V, P)
    coords = torch.cat([coords[:, :1], torch.zeros_like(coords[:, :1]), coords[:, 1:]], 1)
    return voxels, nums, coords


def _check_batch(batch: Mapping[str, Any], cfg: PointPillarsConfig, training: bool,
                 dtype: torch.dtype = torch.float32) -> tuple[Tensor, int]:
    if not isinstance(batch, Mapping) or "points" not in batch:
        raise ValueError("batch must be a dict with 'points' (P, 1 + C) and 'batch_size' (OpenPCDet's keys)")
    points = batch["points"]
    check_tensor(points, "batch['points']")
    c = cfg.num_point_features
    if points.dim() != 2 or points.shape[1] < 1 + c or not points.is_floating_point():
        raise ValueError(f"batch['points'] must be a floating (P, 1 + {c}) tensor (frame index, x, y, z, "
                         f"intensity), got {describe(points)}")
    batch_size = check_positive_int(batch.get("batch_size"), "batch['batch_size']")  # ints, NumPy ints; not 1.0
    # every frame of a batch holds a point (an empty scan is a batch of its own): refused before anything is
    # allocated, since each frame costs a whole pseudo-image
    if batch_size > max(points.shape[0], 1):
        raise ValueError(f"batch['batch_size']={batch_size} but batch['points'] holds {points.shape[0]} point(s): "
                         "every frame of a batch needs at least one point (an empty scan is a batch of its own, "
                         "batch_size=1)")
    if points.dtype != dtype:  # the weights' dtype: float32 (OpenPCDet's), float16 after model.half()
        points = points.to(dtype)
    checks = []
    if value_checks_enabled() and points.shape[0]:
        frame, feats = points[:, 0], points[:, 4:1 + c]
        # a point of another frame (or of none) would be silently left out of every frame
        bad_frame = ~((frame >= 0) & (frame < batch_size) & (frame == frame.round()))
        checks.append((bad_frame.any(), lambda: _bad_rows_message(
            bad_frame, points[:, 0], f"batch['points'][:, 0] (frame index) must be an integer in [0, {batch_size})")))
        if batch_size > 1:
            per_frame = torch.bincount(frame.long().clamp(0, batch_size - 1), minlength=batch_size)
            empty = per_frame == 0
            checks.append((empty.any(), lambda: f"batch['points'][:, 0] names no point of frame(s) "
                           f"{torch.nonzero(empty).flatten()[:8].tolist()} of batch['batch_size']={batch_size}: every "
                           "frame of a batch needs at least one point (an empty scan is a batch of its own)"))
        if feats.shape[1]:
            # non-finite x, y, z fall outside the point range (left out, as voxelize does); other
            # features would enter a pillar and turn its features, then every box near it, into NaN
            bad_feat = ~(feats.abs() <= MAX_ABS_INTENSITY).all(1)
            checks.append((bad_feat.any(), lambda: _bad_rows_message(
                bad_feat, feats, f"batch['points'][:, 4:] (intensity and other features) must be finite with "
                f"|value| <= {MAX_ABS_INTENSITY:g}; drop such points first (lidarops.stream.invalid_points gives the "
                "mask for intensity)")))
    if training:
        gt = batch.get("gt_boxes")
        check_tensor(gt, "batch['gt_boxes']")
        if gt.dim() != 3 or gt.shape[0] != batch_size or gt.shape[2] != 8:
            raise ValueError(f"batch['gt_boxes'] must be (batch_size={batch_size}, M, 8) (box, class id), "
                             f"got {describe(gt)}")
        if value_checks_enabled() and gt.numel():
            real = gt[..., 7] != 0  # class 0 rows are padding
            box = gt[..., :7]
            bad_box = real & ~(torch.isfinite(box).all(-1) & (box[..., 3:6] > 0).all(-1))
            checks.append((bad_box.any(), lambda: _bad_rows_message(
                bad_box.reshape(-1), gt.reshape(-1, 8), "batch['gt_boxes'] rows with a class must hold finite boxes "
                "with sizes dx, dy, dz > 0")))
    run_value_checks(checks)
    return points, batch_size


def _bad_rows_message(bad: Tensor, values: Tensor, expected: str) -> str:
    rows = torch.nonzero(bad).flatten()
    return (f"{expected}; {rows.numel()} row(s) are not, first row {int(rows[0])}: "
            f"{values[int(rows[0])].tolist()}")
