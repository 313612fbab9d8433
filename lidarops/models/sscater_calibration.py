"""Seeded PointPillars fronts for SSCATeR, and the BatchNorm calibration that gives their random
weights a trained network's ReLU sparsity: one home for the ``lidarops stream`` CLI
(:mod:`lidarops.cli.stream`), ``benchmarks/bm_sscater.py`` and the profiles in ``benchmarks/profile/``.

No trained checkpoint exists for the 9-feature pillar net, so the weights are seeded random ones and
every BatchNorm is set so that, on a calibration window, a chosen share of each layer's pre-activations
is negative: which sites change from step to step, and so the work SSCATeR saves, depends on that share.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor
from torch.nn import functional as F

__all__ = ["build_model", "layer_labels", "calibrate_relu_zeros", "relu_zero_shares", "calibrate_on_window"]


def build_model(small: bool, seed: int, dtype: torch.dtype, device) -> tuple:
    """Seeded random PointPillars front: (pfn, backbone), in eval mode, on ``device`` in ``dtype``.

    Args:
        small (bool): PFN 16 channels and backbone channels (16, 32, 64) with 32 channels per upsampling
            branch (output 96 channels), for quick CPU runs; otherwise PointPillars' sizes (64; (64, 128,
            256); 3 x 128 = 384 output channels). The layout (3/5/5 convolutions, strides 2/2/2,
            upsampling 1/2/4) is PointPillars' in both cases.
    """
    from lidarops.models.bev_backbone import BaseBEVBackbone
    from lidarops.models.sscater_pointpillars import PillarFeatureNet
    torch.manual_seed(seed)
    if small:
        pfn = PillarFeatureNet(9, 16)
        backbone = BaseBEVBackbone(16, (3, 5, 5), (2, 2, 2), (16, 32, 64), (1, 2, 4), (32, 32, 32))
    else:
        pfn = PillarFeatureNet(9, 64)
        backbone = BaseBEVBackbone()
    return pfn.eval().to(device, dtype), backbone.eval().to(device, dtype)


def layer_labels(backbone) -> dict[str, str]:
    """Readable names of the backbone's layers, keyed by DeltaBackbone's names (``block0.down0``,
    ``block0.subm1``, ..., ``up0``): ``"block 1 conv 1 (3x3, stride 2)"``, ``"block 1 conv 2 (3x3)"``,
    ``"upsampling of block 1 (x1)"``. Blocks and convolutions are counted from 1."""
    from lidarops.models.bev_backbone import backbone_layers
    labels, n_conv, in_block = {}, 0, {}
    for layer in backbone_layers(backbone):
        k = "x".join(str(v) for v in layer.conv.kernel_size)
        if layer.kind == "up":
            labels[f"up{layer.block}"] = f"upsampling of block {layer.block + 1} (x{layer.stride})"
            continue
        j = in_block[layer.block] = in_block.get(layer.block, 0) + 1
        stride = f", stride {layer.stride}" if layer.stride != 1 else ""
        labels[f"block{layer.block}.{layer.kind}{n_conv}"] = f"block {layer.block + 1} conv {j} ({k}{stride})"
        n_conv += 1
    return labels


def _sparse_pass(pfn, backbone, pillars, shape,
                 on_preactivation: Callable[[str, torch.nn.Module, Tensor], None]) -> None:
    """The sparse network (PFN + ``backbone(mode="sparse")``) on ``pillars``, calling
    ``on_preactivation(name, norm, x)`` with each BatchNorm's input features ``x (Tensor[n, C])`` (active
    sites or points only) before the BatchNorm and ReLU are applied; the callback may change the norm."""
    from lidarops.models.bev_backbone import _norm_relu, backbone_layers
    from lidarops.sparse import SparseConvTensor
    from lidarops.sparse import functional as Fs

    feats, num = pillars.features.to(pfn.linear.weight.dtype), pillars.num_points.long()
    mask = torch.arange(feats.shape[1], device=feats.device) < num[:, None]
    on_preactivation("pfn", pfn.norm, pfn.linear(feats[mask]))
    x = SparseConvTensor(pfn(pillars), pillars.coords, list(shape), 1)
    block_out, n_conv = {}, 0
    for layer in backbone_layers(backbone):
        if layer.kind == "down":
            y = Fs.conv(x, layer.sparse_weight(), None, "conv", stride=layer.stride, padding=1)
        elif layer.kind == "subm":
            y = Fs.conv(x, layer.sparse_weight(), None, "subm", indice_key=f"subm{layer.block}")
        else:
            y = Fs.conv(block_out[layer.block], layer.sparse_weight(), None, "transposed", stride=layer.stride)
        # DeltaBackbone's layer names
        name = f"up{layer.block}" if layer.kind == "up" else f"block{layer.block}.{layer.kind}{n_conv}"
        n_conv += layer.kind != "up"
        on_preactivation(name, layer.norm, y.features)
        y = _norm_relu(y, layer)
        if layer.kind != "up":
            x = block_out[layer.block] = y


@torch.no_grad()
def calibrate_relu_zeros(pfn, backbone, pillars, shape, share: float) -> None:
    """Sets every BatchNorm (running statistics, weight 1, bias 0) so that, on ``pillars``, each channel's
    pre-activation is standardised and its ``share`` quantile sits at 0: about ``share`` of the ReLU
    outputs are zero. Layers are calibrated in order, each on the output of the calibrated layers before it.

    Args:
        pillars (Pillars): e.g. ``pillarize`` of the first window.
        shape ((H, W)): the pillar grid.
        share (float): in [0, 1).
    """
    if not 0.0 <= share < 1.0:
        raise ValueError(f"share must be in [0, 1), got {share}")

    def set_norm(name, norm, x):
        if x.shape[0] == 0:
            return
        k = min(x.shape[0] - 1, max(0, round(share * (x.shape[0] - 1))))
        q = x.sort(dim=0).values[k]
        var = x.var(dim=0, unbiased=False) if x.shape[0] > 1 else torch.ones_like(q)
        norm.running_mean.copy_(q)
        norm.running_var.copy_(torch.where(var > 1e-12, var, torch.ones_like(var)))
        norm.weight.fill_(1.0)
        norm.bias.fill_(0.0)

    _sparse_pass(pfn, backbone, pillars, shape, set_norm)


@torch.no_grad()
def relu_zero_shares(pfn, backbone, pillars, shape) -> dict[str, float]:
    """Share of zero ReLU outputs per layer (PFN: over the real points; backbone: over active sites)."""
    shares = {}

    def measure(name, norm, x):
        if x.shape[0]:
            y = F.batch_norm(x, norm.running_mean, norm.running_var, norm.weight, norm.bias, False, 0.0, norm.eps)
            shares[name] = float((y <= 0).double().mean())

    _sparse_pass(pfn, backbone, pillars, shape, measure)
    return shares


def calibrate_on_window(model, share: float) -> dict[str, float]:
    """:func:`calibrate_relu_zeros` of a :class:`~lidarops.models.SSCATeRPointPillars` on the window its
    stream holds now (e.g. after the first 100 ms of steps), then ``model.reset(reload=True)`` (the window
    is emptied and the new weights are read). Returns :func:`relu_zero_shares` on that window."""
    pillars = model.stream.pillars()
    shape = model.grid.shape
    calibrate_relu_zeros(model.pfn, model.backbone, pillars, shape, share)
    shares = relu_zero_shares(model.pfn, model.backbone, pillars, shape)
    model.reset(reload=True)
    return shares
