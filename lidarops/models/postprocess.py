"""Detections from decoded anchors (OpenPCDet's ``post_processing``): score threshold, top-k and rotated
BEV NMS (:func:`lidarops.nms_bev`), per frame (:func:`postprocess`) or with outputs of a size fixed by
the shapes for CUDA graphs (:func:`postprocess_padded`). Labels are 1-based into the config's
``class_names``.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
from torch import Tensor

from lidarops.models.config import PointPillarsConfig

__all__ = ["postprocess", "postprocess_padded"]


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
    return _postprocess_rows(cls_logits, lambda b, anchors: boxes[b, anchors], cfg)


def _postprocess_rows(cls_logits: Tensor, boxes_of: Callable[[int, Tensor], Tensor],
                      cfg: PointPillarsConfig) -> list[dict[str, Tensor]]:
    """:func:`postprocess` with the boxes decoded on demand: ``boxes_of(b, anchors)`` gives frame ``b``'s boxes
    ``(len(anchors), 7)`` of the anchors at those indices, asked only for the anchors the score threshold keeps
    (on the CPU, decoding every anchor costs more than the rest of the post-processing)."""
    from lidarops.ops.boxes import batched_nms_bev, nms_bev

    pre, post = _limits(cfg)
    out = []
    for b in range(cls_logits.shape[0]):
        scores_all = torch.sigmoid(cls_logits[b])
        if not cfg.multi_classes_nms:
            scores, labels = scores_all.max(dim=-1)
            keep = torch.nonzero(scores >= cfg.score_thresh).squeeze(1)
            boxes, scores, labels = boxes_of(b, keep), scores[keep], labels[keep]
            sel = nms_bev(boxes, scores, cfg.nms_thresh, pre_max=pre, post_max=post)
            out.append({"boxes": boxes[sel], "scores": scores[sel], "labels": labels[sel] + 1})
            continue
        anchor, label = torch.nonzero(scores_all >= cfg.score_thresh, as_tuple=True)
        boxes, scores = boxes_of(b, anchor), scores_all[anchor, label]
        sel = batched_nms_bev(boxes, scores, label, cfg.nms_thresh, pre_max=pre, post_max=post)
        out.append({"boxes": boxes[sel], "scores": scores[sel], "labels": label[sel] + 1})
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
    from lidarops.ops.boxes import nms_bev, nms_bev_frames

    pre, post = _limits(cfg)
    B, A, C = cls_logits.shape
    if not cfg.multi_classes_nms:  # all frames in one NMS call: its launches are shared, not made per frame
        scores, labels = torch.sigmoid(cls_logits).max(dim=-1)  # (B, A)
        keep, count = nms_bev_frames(boxes, scores, cfg.nms_thresh, pre_max=pre, post_max=post,
                                     score_threshold=cfg.score_thresh)
        anchor = keep.clamp(min=0)
        valid = torch.arange(anchor.shape[1], device=anchor.device) < count[:, None]
        return {"boxes": torch.where(valid[..., None], boxes.gather(1, anchor[..., None].expand(-1, -1, 7)), 0),
                "scores": torch.where(valid, scores.gather(1, anchor), 0),
                "labels": torch.where(valid, labels.gather(1, anchor) + 1, 0), "count": count}
    out: dict[str, list] = {"boxes": [], "scores": [], "labels": [], "count": []}
    for b in range(B):
        scores_all = torch.sigmoid(cls_logits[b])
        # per class: a padded NMS per class, merged by score
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


def _limits(cfg: PointPillarsConfig) -> tuple[int | None, int | None]:
    """``nms_pre_maxsize`` and ``nms_post_maxsize`` as the NMS ops take them: -1 (no limit) is None."""
    return (cfg.nms_pre_maxsize if cfg.nms_pre_maxsize >= 0 else None,
            cfg.nms_post_maxsize if cfg.nms_post_maxsize >= 0 else None)
