"""Small models of the model, SSCATeR and stream tests: a reduced BEV backbone with BatchNorm statistics far
from the identity."""
from __future__ import annotations

import torch

from lidarops.models.bev_backbone import BaseBEVBackbone


def randomize_bn(module: torch.nn.Module, seed: int, negative_bias: float = 0.0) -> None:
    """Running statistics and affine parameters far from the identity; a negative bias makes many
    pre-activations negative (ReLU zeros)."""
    g = torch.Generator().manual_seed(seed)
    for m in module.modules():
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
            n = m.num_features
            m.running_mean.copy_(torch.rand(n, generator=g) - 0.5)
            m.running_var.copy_(torch.rand(n, generator=g) * 1.5 + 0.5)
            m.weight.data.copy_(torch.rand(n, generator=g) + 0.5)
            m.bias.data.copy_(torch.rand(n, generator=g) * 0.6 - 0.3 - negative_bias)


def small_backbone(cin=8, seed=0, negative_bias=0.0, dtype=torch.float64):
    """A three-block :class:`BaseBEVBackbone` (1/2/2 layers, 8/12/16 filters), randomized BatchNorm, eval mode."""
    torch.manual_seed(seed)
    bb = BaseBEVBackbone(cin, (1, 2, 2), (2, 2, 2), (8, 12, 16), (1, 2, 4), (6, 6, 6))
    randomize_bn(bb, seed, negative_bias)
    return bb.eval().to(dtype)
