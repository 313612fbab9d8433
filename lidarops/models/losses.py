"""Losses shared by the models' heads, element-wise (each head weights and reduces them): focal
classification, smooth L1 regression with OpenPCDet's sine heading difference.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

__all__ = ["sigmoid_focal_loss", "smooth_l1", "add_sin_difference"]


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Element-wise sigmoid focal loss (Lin et al. 2017; OpenPCDet's ``SigmoidFocalClassificationLoss``
    before weighting, torchvision's ``sigmoid_focal_loss(reduction="none")``)."""
    p = torch.sigmoid(logits)
    alpha_weight = targets * alpha + (1 - targets) * (1 - alpha)
    pt = targets * (1 - p) + (1 - targets) * p
    bce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    return alpha_weight * pt.pow(gamma) * bce


def smooth_l1(diff: Tensor, beta: float) -> Tensor:
    a = diff.abs()
    return torch.where(a < beta, 0.5 * a * a / beta, a - 0.5 * beta) if beta >= 1e-5 else a


def add_sin_difference(pred: Tensor, target: Tensor, dim: int = 6) -> tuple[Tensor, Tensor]:
    """OpenPCDet's ``add_sin_difference``: sin(a - b) = sin a cos b - cos a sin b, split between the two."""
    p = torch.sin(pred[..., dim:dim + 1]) * torch.cos(target[..., dim:dim + 1])
    t = torch.cos(pred[..., dim:dim + 1]) * torch.sin(target[..., dim:dim + 1])
    return (torch.cat([pred[..., :dim], p, pred[..., dim + 1:]], -1),
            torch.cat([target[..., :dim], t, target[..., dim + 1:]], -1))
