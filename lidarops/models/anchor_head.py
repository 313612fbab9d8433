"""PointPillars' detection head (``dense_head``), OpenPCDet's ``AnchorHeadSingle``: 1x1 convolutions for
class scores, box residuals and direction bins over the anchors of :mod:`lidarops.models.anchors`; its
losses (focal, smooth L1 of the sine heading difference, direction cross-entropy) and the decoding of
every anchor's box. Turning decoded anchors into detections is :mod:`lidarops.models.postprocess`.
"""
from __future__ import annotations

import math
from typing import Mapping

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops.models.anchors import (
    AnchorGenerator,
    AxisAlignedTargetAssigner,
    ResidualCoder,
    decode_direction,
    flatten_anchors,
    get_direction_target,
)
from lidarops.models.config import PointPillarsConfig
from lidarops.models.losses import add_sin_difference, sigmoid_focal_loss, smooth_l1

__all__ = ["AnchorHeadSingle", "safe_regression"]


def safe_regression(anchors: Tensor) -> float:
    """The largest ``|box regression|`` (every column of the head's ``box_preds``) for which each anchor's decoded
    box is one the box ops accept (:func:`lidarops.ops.boxes.unsupported_boxes`: centre, size and heading in range),
    with a factor 2 to spare and at most 10; 0 where no such bound holds (anchors of size 0, non-finite). A CUDA
    graph's post-processing checks the raw regressions against it instead of decoding every anchor."""
    from lidarops.ops.boxes import MAX_ABS_BOX_CENTRE, MAX_BOX_SIZE, MIN_BOX_SIZE

    a = anchors.detach().double().cpu()
    if a.dim() != 2 or a.shape[0] == 0 or a.shape[1] < 7 or not bool(torch.isfinite(a).all()):
        return 0.0
    sizes = a[:, 3:6]
    if float(sizes.min()) <= 0:
        return 0.0
    # x, y move by t * diagonal, z by t * dz, sizes scale by exp(t); headings stay near the anchors' (finite)
    reach = max(float(torch.sqrt(a[:, 3] ** 2 + a[:, 4] ** 2).max()), float(sizes[:, 2].max()))
    t = min(10.0, math.log(MAX_BOX_SIZE / (2 * float(sizes.max()))), math.log(float(sizes.min()) / (2 * MIN_BOX_SIZE)),
            (MAX_ABS_BOX_CENTRE / 2 - float(a[:, :3].abs().max())) / reach)
    return float(math.floor(t)) if t >= 1 else 0.0


class AnchorHeadSingle(nn.Module):
    """OpenPCDet's ``AnchorHeadSingle``: one 1x1 convolution each for class scores, box residuals and
    direction bins over every anchor of every class at every feature-map location.

    Shape:
        ``forward(features (B, C, H, W))`` -> dict ``cls_preds (B, H, W, A*K)``, ``box_preds (B, H, W, A*7)``,
        ``dir_cls_preds (B, H, W, A*bins)`` (A anchors per location, K classes); flattened with
        ``view(B, -1, K)`` their rows follow the anchors' (y, x, class, z, size, rotation) order.
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
        self.safe_regression = safe_regression(flat)
        self.target_assigner = AxisAlignedTargetAssigner(cfg.anchor_generator_config, cfg.class_names, self.box_coder,
                                                         norm_by_num_examples=cfg.norm_by_num_examples,
                                                         match_height=cfg.match_height)
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
        return self._check_grid(out)

    def _check_grid(self, out: dict[str, Tensor]) -> dict[str, Tensor]:
        """``out``, if its (B, H, W, ...) maps hold one set of anchors per site of the config's grid."""
        expected = self.anchors_flat.shape[0]
        got = out["cls_preds"].shape[1] * out["cls_preds"].shape[2] * self.num_anchors_per_location
        if got != expected:
            raise ValueError(f"the feature map {tuple(out['cls_preds'].shape[1:3])} does not match the anchors "
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
        p, t = add_sin_difference(box_preds, reg_targets)
        t = torch.where(torch.isnan(t), p, t)
        code_weights = box_preds.new_tensor(cfg.code_weights)
        loss_box = (smooth_l1((p - t) * code_weights, 1.0 / 9.0) * reg_weights[..., None]).sum() / B * cfg.loc_weight
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

    def decode(self, preds: Mapping[str, Tensor], anchors: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Scores (logits, (B, A, K)) and boxes (B, A, 7) of every anchor (OpenPCDet's
        ``generate_predicted_boxes``); with ``anchors (B, A', 7)``, of those anchors only, ``preds`` then holding
        their rows (``(B, A', K)``, ``(B, A', code_size)``, ``(B, A', bins)``)."""
        cfg = self.cfg
        B = preds["cls_preds"].shape[0]
        cls = preds["cls_preds"].view(B, -1, self.num_class).float()
        boxes = self.box_coder.decode(preds["box_preds"].view(B, -1, self.box_coder.code_size).float(),
                                      (self.anchors_flat[None] if anchors is None else anchors).float())
        # (float32 also in a .half() model)
        if self.conv_dir_cls is not None:
            dir_labels = preds["dir_cls_preds"].view(B, -1, cfg.num_dir_bins).argmax(dim=-1)
            heading = decode_direction(boxes[..., 6], dir_labels, cfg.dir_offset, cfg.dir_limit_offset,
                                       cfg.num_dir_bins)
            if boxes.requires_grad and torch.is_grad_enabled():
                boxes = torch.cat([boxes[..., :6], heading[..., None], boxes[..., 7:]], dim=-1)
            else:  # the decoder's own new tensor: the heading column written in place, not a copy of all seven
                boxes[..., 6] = heading
        return cls, boxes

    def _decode_rows(self, preds: Mapping[str, Tensor], b: int, anchors: Tensor) -> Tensor:
        """The boxes ``(n, 7)`` :meth:`decode` gives frame ``b``'s anchors at the indices ``anchors (n,)``, decoding
        only those."""
        A = self.anchors_flat.shape[0]
        keys = ("cls_preds", "box_preds") + (("dir_cls_preds",) if self.conv_dir_cls is not None else ())
        rows = {k: preds[k][b].reshape(A, -1)[anchors][None] for k in keys}
        return self.decode(rows, self.anchors_flat[anchors][None])[1][0]
