"""Inference-time weights: 1x1 convolutions with the BatchNorm after them folded in, as ``(W, b)`` pairs for
``F.linear`` on row-major features ``(..., C)``, kept per module and dtype and rebuilt when a source tensor
changes (an optimiser step, ``load_state_dict``, ``.to()``). Eval mode only: BatchNorm's running statistics are
what is folded. CAS-Net's inference path (:meth:`lidarops.models.casnet.CASNet.pick`) uses them: one launch per
layer instead of a convolution, a BatchNorm and, under autocast, the weights' casts."""
from __future__ import annotations

import itertools
from typing import Callable, Optional

import torch
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_weights

__all__ = ["conv_bn", "cached", "compute_dtype"]


def conv_bn(conv: nn.Conv1d, bn: Optional[nn.BatchNorm1d] = None) -> tuple[Tensor, Tensor]:
    """``(W (out, in), b (out,))`` with ``F.linear(x, W, b) == bn(conv(x))`` in eval mode (kernel size 1)."""
    if conv.kernel_size != (1,) or conv.groups != 1:
        raise ValueError(f"conv_bn folds 1x1 convolutions without groups, got {conv}")
    w, b = conv.weight.detach(), None if conv.bias is None else conv.bias.detach()
    if bn is not None:
        if bn.running_mean is None or bn.running_var is None:
            raise ValueError(f"{bn} keeps no running statistics: nothing to fold")
        ones = torch.ones_like(bn.running_var)
        w, b = fuse_conv_bn_weights(w, b, bn.running_mean, bn.running_var, bn.eps,
                                    ones if bn.weight is None else bn.weight.detach(),
                                    ones * 0 if bn.bias is None else bn.bias.detach())
        w, b = w.detach(), b.detach()
    if b is None:
        b = w.new_zeros(w.shape[0])
    return w[:, :, 0], b


def compute_dtype(like: Tensor) -> torch.dtype:
    """The dtype a layer computes in for an input like ``like``: autocast's on its device, else its own."""
    kind = like.device.type
    return torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else like.dtype


def cached(module: nn.Module, name: str, dtype: torch.dtype, build: Callable[[], tuple[Tensor, ...]]
           ) -> tuple[Tensor, ...]:
    """``build()``'s tensors in ``dtype``, cached on ``module`` until one of its parameters or buffers changes
    (its storage or its in-place version)."""
    stamp = tuple((t.data_ptr(), t._version) for t in itertools.chain(module.parameters(), module.buffers()))
    store = module.__dict__.setdefault("_folded_cache", {})
    hit = store.get((name, dtype))
    if hit is not None and hit[0] == stamp:
        return hit[1]
    with torch.no_grad():
        tensors = tuple(t.to(dtype).contiguous() for t in build())
    store[(name, dtype)] = (stamp, tensors)
    return tensors
