"""Fake kernels of the SSCATeR ops (``torch.ops.lidarops.sscater_*``); imported by
:func:`lidarops.extension.load`. The ops mutate their state arguments and have no autograd: SSCATeR is
an inference-time method (the streaming backbone runs in eval mode)."""
from __future__ import annotations

import torch


@torch.library.register_fake("lidarops::sscater_scatter_")
def _scatter_fake(acc, sites, delta, weight, stride, padding, transposed, out_active=None):
    return sites.new_empty((sites.shape[0] * weight.shape[1] * weight.shape[2],), dtype=torch.int64)


@torch.library.register_fake("lidarops::sscater_finalize_")
def _finalize_fake(acc, out, active, sites, scale, shift):
    m, C = sites.shape[0], acc.shape[2]
    return sites.new_empty((m,), dtype=torch.bool), acc.new_empty((m, C))
