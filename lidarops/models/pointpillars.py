"""PointPillars, the detector (Lang et al., CVPR 2019), as OpenPCDet's ``pointpillar.yaml`` builds it:
voxelization into pillars -> PillarVFE -> scatter to a pseudo-image -> BaseBEVBackbone -> anchor head
-> decode -> rotated NMS. Read it top to bottom:

- :class:`PillarVFE` (``vfe``): 10 features per point (x, y, z, intensity, offsets to the pillar's
  mean, offsets to the pillar centre), Linear -> BatchNorm -> ReLU, max over the pillar's slots.
- :class:`PointPillarScatter` (``map_to_bev``): pillar features into a dense (B, C, ny, nx) map.
- :class:`~lidarops.models.pointpillars.PointPillarsBackbone` (``backbone_2d``): dense (cuDNN, the
  OpenPCDet layout) or sparse (lidarops.sparse) with the same parameters.
- :class:`AnchorHeadSingle` (``dense_head``): 1x1 convolutions ``conv_cls``, ``conv_box``,
  ``conv_dir_cls`` over the anchors of :mod:`lidarops.models.boxes`; focal, smooth-L1 (sine of the
  heading difference) and direction losses; decoding.
- :func:`postprocess`: score threshold, top-k, class-agnostic (or per-class) rotated NMS
  (``lidarops.nms_bev``); :func:`postprocess_padded` the same with fixed-size outputs, for CUDA graphs
  (:class:`~lidarops.models.graph.GraphedPointPillars`).

Module and parameter names, shapes and the anchor order are OpenPCDet's, so an OpenPCDet PointPillars
checkpoint (``checkpoint["model_state"]``) loads with ``strict=True`` and gives the same boxes. Like
OpenPCDet, the VFE lets a pillar's empty slots (zero features) take part in BatchNorm's statistics and
in the max: that is what its checkpoints were trained with.
"""
from __future__ import annotations

import math
import operator
from pathlib import Path
from typing import Any, Mapping

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops.models.boxes import (
    AnchorGenerator,
    AxisAlignedTargetAssigner,
    ResidualCoder,
    decode_direction,
    flatten_anchors,
    get_direction_target,
)
from lidarops.models.config import ConfigError, PointPillarsConfig, load_config
from lidarops.models.pointpillars import PointPillarsBackbone
from lidarops.stream.pillars import MAX_ABS_INTENSITY
from lidarops.ops.validation import check_tensor, describe, run_value_checks, value_checks_enabled

__all__ = ["PointPillars", "PillarVFE", "PFNLayer", "PointPillarScatter", "AnchorHeadSingle", "postprocess",
           "postprocess_padded", "CheckpointMismatchError", "sigmoid_focal_loss"]


class CheckpointMismatchError(ValueError):
    """A state dict that does not fit the model's config; the message lists the keys that differ."""


# ---------------------------------------------------------------------------------------------
# pillar feature net
# ---------------------------------------------------------------------------------------------
class PFNLayer(nn.Module):
    """Linear -> BatchNorm1d -> ReLU on every slot of every pillar, then the max over the slots
    (concatenated back to each slot when this is not the last layer, as in OpenPCDet)."""

    def __init__(self, in_channels: int, out_channels: int, use_norm: bool = True, last_layer: bool = False):
        super().__init__()
        self.last_vfe = last_layer
        self.use_norm = use_norm
        if not last_layer:
            out_channels //= 2
        self.linear = nn.Linear(in_channels, out_channels, bias=not use_norm)
        if use_norm:
            self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, x: Tensor) -> Tensor:
        V, N, _ = x.shape
        if self.last_vfe and not self.training and self.use_norm and V * N:
            return self._folded_max(x)
        x = self.linear(x)
        if self.use_norm:  # statistics over every slot of every pillar, as BatchNorm1d over (V, C, N)
            x = self.norm(x.reshape(V * N, -1)).view(V, N, -1) if V * N else x
        x = F.relu(x)
        x_max = x.amax(dim=1, keepdim=True) if N else x.new_zeros(V, 1, x.shape[2])
        if self.last_vfe:
            return x_max
        return torch.cat([x, x_max.expand(-1, N, -1)], dim=2)

    def _folded_max(self, x: Tensor) -> Tensor:
        """Inference of the last layer: BatchNorm's running statistics folded into the linear map, and
        the max over the slots before the ReLU (they commute): one GEMM and one reduction instead of
        four passes over every slot's features."""
        norm = self.norm
        scale = norm.weight * torch.rsqrt(norm.running_var + norm.eps)
        weight = self.linear.weight * scale[:, None]
        bias = norm.bias - norm.running_mean * scale
        return F.relu(F.linear(x, weight, bias).amax(dim=1, keepdim=True))


class PillarVFE(nn.Module):
    """OpenPCDet's ``PillarVFE``.

    Args:
        num_point_features (int): features per point (x, y, z, intensity: 4).
        voxel_size (Sequence[float]), point_cloud_range (Sequence[float]): the pillar grid.
        num_filters (Sequence[int]): PFN layer widths ([64]).
        with_distance (bool): add the point's distance to the sensor as a feature.
        use_absolute_xyz (bool): keep x, y, z among the features (else only the other point features).
        use_norm (bool): BatchNorm in the PFN layers.

    Shape:
        ``forward(voxels (V, N, C), num_points (V,), coords (V, 4) = (batch, z, y, x))`` ->
        ``(V, num_filters[-1])``.
    """

    def __init__(self, num_point_features: int, voxel_size, point_cloud_range, num_filters=(64,),
                 with_distance: bool = False, use_absolute_xyz: bool = True, use_norm: bool = True):
        super().__init__()
        self.use_absolute_xyz, self.with_distance = use_absolute_xyz, with_distance
        c_in = num_point_features + 6 if use_absolute_xyz else num_point_features + 3
        c_in += 1 if with_distance else 0
        self.num_point_features = num_point_features
        filters = [c_in] + [int(f) for f in num_filters]
        self.pfn_layers = nn.ModuleList(
            PFNLayer(filters[i], filters[i + 1], use_norm, last_layer=i == len(filters) - 2)
            for i in range(len(filters) - 1))
        self.out_channels = filters[-1]
        vs, pr = [float(v) for v in voxel_size], [float(v) for v in point_cloud_range]
        # buffers, not Python lists: no host-to-device copy per call (CUDA-graph capturable); not saved
        self.register_buffer("voxel_size", torch.tensor(vs), persistent=False)
        self.register_buffer("centre_offset", torch.tensor([vs[i] / 2 + pr[i] for i in range(3)]), persistent=False)

    def forward(self, voxels: Tensor, num_points: Tensor, coords: Tensor) -> Tensor:
        V, N, _ = voxels.shape
        xyz = voxels[:, :, :3]
        count = num_points.to(voxels.dtype).clamp_min(1).view(-1, 1, 1)
        f_cluster = xyz - xyz.sum(dim=1, keepdim=True) / count
        # pillar centres from (z, y, x) indices: columns 3, 2, 1 of coords are x, y, z (a flip, not a
        # list index: that would copy an index tensor from the host, which a CUDA graph capture refuses)
        centre = coords[:, 1:].flip(1).to(voxels.dtype) * self.voxel_size.to(voxels.dtype) \
            + self.centre_offset.to(voxels.dtype)
        f_center = xyz - centre[:, None, :]
        parts = [voxels if self.use_absolute_xyz else voxels[:, :, 3:], f_cluster, f_center]
        if self.with_distance:
            parts.append(torch.linalg.vector_norm(xyz, dim=2, keepdim=True))
        features = torch.cat(parts, dim=-1)
        slot = torch.arange(N, device=voxels.device)
        features = features * (slot[None, :] < num_points[:, None]).to(features.dtype)[..., None]
        for pfn in self.pfn_layers:
            features = pfn(features)
        return features.squeeze(1)


class PointPillarScatter(nn.Module):
    """Scatter of pillar features into the dense pseudo-image (OpenPCDet's ``PointPillarScatter``).

    Shape: ``forward(features (V, C), coords (V, 4) = (batch, z, y, x), batch_size)`` -> (B, C, ny, nx).
    Rows whose coords are negative (the padding of ``voxelize(..., padded=True)``) are left out without
    reading anything back to the host, so the scatter can run inside a CUDA graph.
    """

    def __init__(self, num_bev_features: int, grid_size):
        super().__init__()
        self.num_bev_features = int(num_bev_features)
        self.nx, self.ny, self.nz = (int(v) for v in grid_size)

    def forward(self, features: Tensor, coords: Tensor, batch_size: int) -> Tensor:
        c = coords.long()
        cells = batch_size * self.ny * self.nx
        flat = (c[:, 0] * self.ny + c[:, 2]) * self.nx + c[:, 3]
        # padding goes to one spare row (a full_like, not a Python scalar: nothing copied from the host)
        flat = torch.where((c >= 0).all(1), flat, torch.full_like(flat, cells))
        canvas = features.new_zeros(cells + 1, self.num_bev_features)
        canvas.index_copy_(0, flat, features)
        return canvas[:cells].view(batch_size, self.ny, self.nx, -1).permute(0, 3, 1, 2).contiguous()


# ---------------------------------------------------------------------------------------------
# anchor head and losses
# ---------------------------------------------------------------------------------------------
def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Element-wise sigmoid focal loss (Lin et al. 2017; OpenPCDet's ``SigmoidFocalClassificationLoss``
    before weighting, torchvision's ``sigmoid_focal_loss(reduction="none")``)."""
    p = torch.sigmoid(logits)
    alpha_weight = targets * alpha + (1 - targets) * (1 - alpha)
    pt = targets * (1 - p) + (1 - targets) * p
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    return alpha_weight * pt.pow(gamma) * bce


def _smooth_l1(diff: Tensor, beta: float) -> Tensor:
    a = diff.abs()
    return torch.where(a < beta, 0.5 * a * a / beta, a - 0.5 * beta) if beta >= 1e-5 else a


def _sin_difference(pred: Tensor, target: Tensor, dim: int = 6) -> tuple[Tensor, Tensor]:
    """OpenPCDet's ``add_sin_difference``: sin(a - b) = sin a cos b - cos a sin b, split between the two."""
    p = torch.sin(pred[..., dim:dim + 1]) * torch.cos(target[..., dim:dim + 1])
    t = torch.cos(pred[..., dim:dim + 1]) * torch.sin(target[..., dim:dim + 1])
    return (torch.cat([pred[..., :dim], p, pred[..., dim + 1:]], -1),
            torch.cat([target[..., :dim], t, target[..., dim + 1:]], -1))


class AnchorHeadSingle(nn.Module):
    """OpenPCDet's ``AnchorHeadSingle``: one 1x1 convolution each for class scores, box residuals and
    direction bins over every anchor of every class at every feature-map location.

    Shape:
        ``forward(features (B, C, H, W))`` -> dict ``cls_preds (B, H, W, A*K)``, ``box_preds (B, H, W, A*7)``,
        ``dir_cls_preds (B, H, W, A*bins)`` (A anchors per location, K classes); flattened with
        ``view(B, -1, K)`` their rows follow the anchors' (z, y, x, class, size, rotation) order.
    """

    def __init__(self, cfg: PointPillarsConfig, input_channels: int):
        super().__init__()
        self.cfg = cfg
        self.num_class = cfg.num_class
        self.box_coder = ResidualCoder(7)
        gen = AnchorGenerator(cfg.point_cloud_range, cfg.anchor_generator_config)
        anchors, per_location = gen.generate_anchors(gen.feature_map_sizes(cfg.grid_size))
        self.num_anchors_per_location = int(sum(per_location))
        for i, a in enumerate(anchors):  # not in the state dict (OpenPCDet does not save them)
            self.register_buffer(f"anchors_{i}", a, persistent=False)
        self._num_anchor_sets = len(anchors)
        flat, _ = flatten_anchors(anchors)
        self.register_buffer("anchors_flat", flat, persistent=False)
        self.target_assigner = AxisAlignedTargetAssigner(cfg.anchor_generator_config, cfg.class_names, self.box_coder,
                                                         norm_by_num_examples=cfg.norm_by_num_examples)
        a = self.num_anchors_per_location
        self.conv_cls = nn.Conv2d(input_channels, a * self.num_class, kernel_size=1)
        self.conv_box = nn.Conv2d(input_channels, a * self.box_coder.code_size, kernel_size=1)
        self.conv_dir_cls = (nn.Conv2d(input_channels, a * cfg.num_dir_bins, kernel_size=1)
                             if cfg.use_direction_classifier else None)
        prior = 0.01  # focal-loss prior: every anchor starts at score 0.01
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - prior) / prior))
        nn.init.normal_(self.conv_box.weight, mean=0.0, std=0.001)

    @property
    def anchors(self) -> list[Tensor]:
        return [getattr(self, f"anchors_{i}") for i in range(self._num_anchor_sets)]

    def forward(self, features: Tensor) -> dict[str, Tensor]:
        out = {"cls_preds": self.conv_cls(features).permute(0, 2, 3, 1).contiguous(),
               "box_preds": self.conv_box(features).permute(0, 2, 3, 1).contiguous()}
        if self.conv_dir_cls is not None:
            out["dir_cls_preds"] = self.conv_dir_cls(features).permute(0, 2, 3, 1).contiguous()
        expected = self.anchors_flat.shape[0]
        got = out["cls_preds"].shape[1] * out["cls_preds"].shape[2] * self.num_anchors_per_location
        if got != expected:
            raise ValueError(f"the feature map {tuple(features.shape[2:])} does not match the anchors "
                             f"({expected} for the config's grid); check POINT_CLOUD_RANGE / VOXEL_SIZE")
        return out

    def loss(self, preds: Mapping[str, Tensor], gt_boxes: Tensor) -> dict[str, Tensor]:
        """OpenPCDet's ``AnchorHeadTemplate.get_loss``: per-frame normalised by the number of positive
        anchors, summed over anchors, averaged over the frames of the batch."""
        cfg = self.cfg
        targets = self.target_assigner.assign_targets(self.anchors, gt_boxes.to(self.anchors_flat.dtype))
        labels = targets["box_cls_labels"]  # (B, A): -1 ignored, 0 background, k class
        B = labels.shape[0]
        positives, negatives = labels > 0, labels == 0
        normalizer = positives.sum(1, keepdim=True).to(preds["cls_preds"].dtype).clamp_min(1.0)
        cls_weights = (negatives | positives).to(normalizer.dtype) / normalizer
        one_hot = F.one_hot(labels.clamp_min(0), self.num_class + 1)[..., 1:].to(normalizer.dtype)
        cls_preds = preds["cls_preds"].view(B, -1, self.num_class).float()
        loss_cls = (sigmoid_focal_loss(cls_preds, one_hot) * cls_weights[..., None]).sum() / B * cfg.cls_weight
        box_preds = preds["box_preds"].view(B, -1, self.box_coder.code_size).float()
        reg_targets = targets["box_reg_targets"]
        reg_weights = positives.to(normalizer.dtype) / normalizer
        p, t = _sin_difference(box_preds, reg_targets)
        t = torch.where(torch.isnan(t), p, t)
        code_weights = box_preds.new_tensor(cfg.code_weights)
        loss_box = (_smooth_l1((p - t) * code_weights, 1.0 / 9.0) * reg_weights[..., None]).sum() / B * cfg.loc_weight
        out = {"loss_cls": loss_cls, "loss_box": loss_box}
        total = loss_cls + loss_box
        if self.conv_dir_cls is not None:
            anchors = self.anchors_flat[None].expand(B, -1, -1)
            dir_targets = get_direction_target(anchors, reg_targets, one_hot=False, dir_offset=cfg.dir_offset,
                                               num_bins=cfg.num_dir_bins)
            logits = preds["dir_cls_preds"].view(B, -1, cfg.num_dir_bins).float()
            weights = positives.to(normalizer.dtype) / normalizer
            ce = F.cross_entropy(logits.reshape(-1, cfg.num_dir_bins), dir_targets.reshape(-1), reduction="none")
            loss_dir = (ce.view(B, -1) * weights).sum() / B * cfg.dir_weight
            out["loss_dir"] = loss_dir
            total = total + loss_dir
        out["loss"] = total
        out["num_positives"] = positives.sum().to(normalizer.dtype) / B
        return out

    def decode(self, preds: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Scores (logits, (B, A, K)) and boxes (B, A, 7) of every anchor (OpenPCDet's
        ``generate_predicted_boxes``)."""
        cfg = self.cfg
        B = preds["cls_preds"].shape[0]
        cls = preds["cls_preds"].view(B, -1, self.num_class).float()
        boxes = self.box_coder.decode(preds["box_preds"].view(B, -1, self.box_coder.code_size).float(),
                                      self.anchors_flat[None].float())  # float32 also in a .half() model
        if self.conv_dir_cls is not None:
            dir_labels = preds["dir_cls_preds"].view(B, -1, cfg.num_dir_bins).argmax(dim=-1)
            heading = decode_direction(boxes[..., 6], dir_labels, cfg.dir_offset, cfg.dir_limit_offset,
                                       cfg.num_dir_bins)
            boxes = torch.cat([boxes[..., :6], heading[..., None], boxes[..., 7:]], dim=-1)
        return cls, boxes


def postprocess(cls_logits: Tensor, boxes: Tensor, cfg: PointPillarsConfig) -> list[dict[str, Tensor]]:
    """Per-frame detections from decoded anchors (OpenPCDet's ``post_processing``).

    Class-agnostic (``multi_classes_nms: False``, PointPillars' setting): each anchor's best class and
    its sigmoid score; scores >= ``score_thresh``; the ``nms_pre_maxsize`` best; rotated BEV NMS at
    ``nms_thresh`` (strictly greater suppresses); at most ``nms_post_maxsize`` kept. Per class: the same
    on each class's own scores, then all classes together.

    Args:
        cls_logits (Tensor[B, A, K]), boxes (Tensor[B, A, 7]): from :meth:`AnchorHeadSingle.decode`.

    Returns:
        list of B dicts: ``boxes (K, 7)``, ``scores (K,)``, ``labels (K,)`` int64 (1-based into
        ``cfg.class_names``), in descending score order.
    """
    from lidarops.ops.boxes import batched_nms_bev, nms_bev

    out = []
    for b in range(cls_logits.shape[0]):
        scores_all = torch.sigmoid(cls_logits[b])
        if not cfg.multi_classes_nms:
            scores, labels = scores_all.max(dim=-1)
            keep = torch.nonzero(scores >= cfg.score_thresh).squeeze(1)
            sel = keep[nms_bev(boxes[b, keep], scores[keep], cfg.nms_thresh, pre_max=cfg.nms_pre_maxsize,
                               post_max=cfg.nms_post_maxsize)]
            out.append({"boxes": boxes[b, sel], "scores": scores[sel], "labels": labels[sel] + 1})
            continue
        anchor, label = torch.nonzero(scores_all >= cfg.score_thresh, as_tuple=True)
        scores = scores_all[anchor, label]
        sel = batched_nms_bev(boxes[b, anchor], scores, label, cfg.nms_thresh, pre_max=cfg.nms_pre_maxsize,
                              post_max=cfg.nms_post_maxsize)
        out.append({"boxes": boxes[b, anchor[sel]], "scores": scores[sel], "labels": label[sel] + 1})
    return out


def postprocess_padded(cls_logits: Tensor, boxes: Tensor, cfg: PointPillarsConfig) -> dict[str, Tensor]:
    """:func:`postprocess` with outputs of a size fixed by the shapes and nothing read back to the host,
    so it can run inside a CUDA graph (:class:`~lidarops.models.graph.GraphedPointPillars`) or a
    ``torch.compile`` graph without dynamic sizes.

    The score threshold becomes part of the NMS (``lidarops.nms_bev(..., score_threshold=, padded=True)``):
    the ``nms_pre_maxsize`` best of all anchors, NMS among those scoring at least ``score_thresh``. That
    keeps the boxes :func:`postprocess` keeps, in its order: an anchor below the threshold sorts after
    every anchor above it, so it is never among the first ``nms_pre_maxsize`` above-threshold ones
    either. Per-class NMS runs one padded NMS per class and merges the classes by score (ties: lower
    anchor, then lower class, as :func:`postprocess`'s order).

    Returns:
        dict: ``boxes (B, K, 7)``, ``scores (B, K)``, ``labels (B, K)`` int64 and ``count (B,)`` int64:
        frame b's detections are its first ``count[b]`` rows (zeros after them), the rows
        :func:`postprocess` returns. ``K = min(anchors, nms_pre_maxsize, nms_post_maxsize)``, times the
        number of classes with ``multi_classes_nms``.
    """
    from lidarops.ops.boxes import nms_bev

    pre = cfg.nms_pre_maxsize if cfg.nms_pre_maxsize >= 0 else None
    post = cfg.nms_post_maxsize if cfg.nms_post_maxsize >= 0 else None
    B, A, C = cls_logits.shape
    out: dict[str, list] = {"boxes": [], "scores": [], "labels": [], "count": []}
    for b in range(B):
        scores_all = torch.sigmoid(cls_logits[b])
        if not cfg.multi_classes_nms:
            scores, labels = scores_all.max(dim=-1)
            keep, count = nms_bev(boxes[b], scores, cfg.nms_thresh, pre_max=pre, post_max=post,
                                  score_threshold=cfg.score_thresh, padded=True)
            anchor = keep.clamp(min=0)
            label = labels[anchor]
        else:
            kept = [nms_bev(boxes[b], scores_all[:, c], cfg.nms_thresh, pre_max=pre, post_max=post,
                            score_threshold=cfg.score_thresh, padded=True) for c in range(C)]
            keep = torch.stack([k for k, _ in kept])  # (C, Kc)
            counts = torch.stack([n for _, n in kept])
            valid = torch.arange(keep.shape[1], device=keep.device) < counts[:, None]
            label = torch.arange(C, device=keep.device)[:, None].expand_as(keep)
            # merge: by score, then by (anchor, class), the padding last
            flat = torch.where(valid, keep * C + label, A * C).reshape(-1)
            by_index = torch.sort(flat, stable=True).indices
            key = torch.where(valid.reshape(-1), scores_all[keep.clamp(min=0), label].reshape(-1).float(),
                              -math.inf)[by_index]
            sel = by_index[torch.sort(key, stable=True, descending=True).indices]
            anchor, label, count = keep.clamp(min=0).reshape(-1)[sel], label.reshape(-1)[sel], counts.sum()
        valid = torch.arange(anchor.shape[0], device=anchor.device) < count
        out["boxes"].append(torch.where(valid[:, None], boxes[b, anchor], 0))
        out["scores"].append(torch.where(valid, scores_all[anchor, label], 0))
        out["labels"].append(torch.where(valid, label + 1, 0))
        out["count"].append(count)
    return {k: torch.stack(v) for k, v in out.items()}


# ---------------------------------------------------------------------------------------------
# the detector
# ---------------------------------------------------------------------------------------------
class PointPillars(nn.Module):
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
        cfg = self.config = _as_config(config)
        self.vfe = PillarVFE(cfg.num_point_features, cfg.voxel_size, cfg.point_cloud_range, cfg.vfe_num_filters,
                             cfg.with_distance, cfg.use_absolute_xyz, cfg.use_norm)
        self.map_to_bev = PointPillarScatter(self.vfe.out_channels, cfg.grid_size)
        self.backbone_2d = PointPillarsBackbone(self.vfe.out_channels, cfg.layer_nums, cfg.layer_strides,
                                                cfg.num_filters, cfg.upsample_strides, cfg.num_upsample_filters,
                                                mode=cfg.backbone_mode)
        self.dense_head = AnchorHeadSingle(cfg, self.backbone_2d.out_channels)
        self.register_buffer("global_step", torch.zeros(1, dtype=torch.long))  # OpenPCDet's Detector3DTemplate

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config: "PointPillarsConfig | Mapping | str | Path") -> "PointPillars":
        """A model with freshly initialised weights from a config (see the class docstring)."""
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config: "PointPillarsConfig | Mapping | str | Path | None" = None,
                        map_location: "str | torch.device" = "cpu") -> "PointPillars":
        """A model with weights from a lidarops checkpoint (it carries its config) or an OpenPCDet one
        (``model_state``; give its ``config``). A state dict that does not fit raises
        :class:`CheckpointMismatchError` naming the keys."""
        ckpt = read_checkpoint(path, map_location)
        if not isinstance(ckpt, Mapping):
            raise CheckpointMismatchError(f"{path}: not a checkpoint (a {type(ckpt).__name__})")
        if config is None:
            config = ckpt.get("model_config")
            if config is None:
                raise ConfigError(f"{path} carries no model config (an OpenPCDet checkpoint?): pass config=...")
        model = cls(config)
        state = ckpt.get("model_state", ckpt.get("state_dict", ckpt.get("model")))
        if not isinstance(state, Mapping):
            raise CheckpointMismatchError(f"{path}: no model_state / state_dict in the checkpoint "
                                          f"(keys: {sorted(ckpt)[:8]})")
        model.load_weights(state, source=str(path))
        return model

    def load_weights(self, state_dict: Mapping[str, Tensor], source: str = "state dict") -> None:
        """``load_state_dict(strict=True)`` after checking keys and shapes, with one error naming every
        missing, unexpected or differently shaped key."""
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
        self.load_state_dict({k: v.to(own[k].dtype) for k, v in state_dict.items()}, strict=True)

    # ---------------------------------------------------------------- the network
    def voxelize(self, points: Tensor, batch_size: int) -> tuple[Tensor, Tensor, Tensor]:
        """Pillars of every frame: ``voxels (V, N, C)``, ``num_points (V,)``, ``coords (V, 4)`` int32 =
        (batch, z, y, x); pillars beyond the config's max voxels (train / test) are dropped."""
        from lidarops.ops.voxelize import voxelize

        cfg = self.config
        max_voxels = cfg.max_voxels_train if self.training else cfg.max_voxels_test
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
        return postprocess(*self.dense_head.decode(raw), self.config)

    @torch.no_grad()
    def predict(self, batch: Mapping[str, Any]) -> list[dict]:
        """Eval-mode forward and post-processing: one dict of ``boxes``, ``scores``, ``labels`` per frame."""
        was_training = self.training
        self.eval()
        try:
            return self.postprocess(self(batch), batch)
        finally:
            self.train(was_training)


def read_checkpoint(path: "str | Path", map_location: "str | torch.device" = "cpu") -> Any:
    """``torch.load`` of a checkpoint with ``weights_only=True`` (a pickle can run code; lidarops' and
    OpenPCDet's checkpoints hold only tensors and plain values).

    Raises:
        FileNotFoundError: no such file.
        CheckpointMismatchError: the file is not a readable checkpoint (truncated, not a torch file, or
            holding objects ``weights_only`` refuses); the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} not found")
    try:
        return torch.load(str(path), map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001  (torch.load raises many types for a damaged or foreign file)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise CheckpointMismatchError(
            f"{path}: not a readable checkpoint ({type(e).__name__}: {first[:200]}); if it is a checkpoint you "
            "trust that holds other objects, load it with torch.load(..., weights_only=False) and pass its "
            "state dict to model.load_weights") from None


def _as_config(config) -> PointPillarsConfig:
    if config is None:
        return PointPillarsConfig()
    if isinstance(config, PointPillarsConfig):
        return config
    if isinstance(config, (str, Path)):
        return PointPillarsConfig.from_openpcdet(load_config(config))
    if isinstance(config, Mapping):
        return PointPillarsConfig.from_openpcdet(config) if "MODEL" in config else PointPillarsConfig.from_dict(config)
    raise ConfigError(f"config must be a PointPillarsConfig, a dict or a YAML path, got {type(config).__name__}")


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
    batch_size = batch.get("batch_size")
    if isinstance(batch_size, Tensor) and batch_size.numel() == 1 and not batch_size.is_floating_point():
        batch_size = int(batch_size)
    try:
        if isinstance(batch_size, bool):
            raise TypeError
        batch_size = operator.index(batch_size)  # ints and NumPy ints; not 1.0
    except TypeError:
        raise ValueError(f"batch['batch_size'] must be a positive int, got {batch_size!r}") from None
    if batch_size < 1:
        raise ValueError(f"batch['batch_size'] must be a positive int, got {batch_size!r}")
    if points.dtype != dtype:  # the weights' dtype: float32 (OpenPCDet's), float16 after model.half()
        points = points.to(dtype)
    checks = []
    if value_checks_enabled() and points.shape[0]:
        frame, feats = points[:, 0], points[:, 4:1 + c]
        # a point of another frame (or of none) would be silently left out of every frame
        bad_frame = ~((frame >= 0) & (frame < batch_size) & (frame == frame.round()))
        checks.append((bad_frame.any(), lambda: _bad_rows_message(
            bad_frame, points[:, 0], f"batch['points'][:, 0] (frame index) must be an integer in [0, {batch_size})")))
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
