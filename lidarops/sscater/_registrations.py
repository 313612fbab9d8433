"""Fake kernels of the SSCATeR ops (``torch.ops.lidarops.sscater_*``, schemas in csrc/ops/sscater.cpp;
wrappers in :mod:`lidarops.sscater.ops`); imported by
:func:`lidarops.extension.load`. The ops mutate their state arguments and have no autograd: SSCATeR is
an inference-time method (the streaming backbone runs in eval mode), so there is no autograd formula,
Python or C++ (``csrc/ops/autograd``)."""
from __future__ import annotations

import torch


@torch.library.register_fake("lidarops::sscater_scatter_")
def _scatter_fake(acc, sites, delta, weight, stride, padding, transposed, out_active=None, count=None,
                  channel_sparse=0.85):
    return sites.new_empty((sites.shape[0] * weight.shape[1] * weight.shape[2],), dtype=torch.int64)


@torch.library.register_fake("lidarops::sscater_finalize_")
def _finalize_fake(acc, out, active, sites, scale, shift):
    m, C = sites.shape[0], acc.shape[2]
    return sites.new_empty((m,), dtype=torch.bool), acc.new_empty((m, C))


# ---- the fused layer step: every output is padded to a bound known from the input shapes ----

@torch.library.register_fake("lidarops::sscater_cover_update_")
def _cover_update_fake(cover, active, stamp, value, added, removed, kh, kw, stride, padding):
    rows = min((added.shape[0] + removed.shape[0]) * kh * kw, cover.shape[0] * cover.shape[1])
    return added.new_empty((rows, 2)), added.new_empty((rows, 2)), added.new_empty((2,), dtype=torch.int64)


@torch.library.register_fake("lidarops::sscater_children_")
def _children_fake(active, added, removed, kh, kw, stride, padding):
    return added.new_empty((added.shape[0] * kh * kw, 2)), removed.new_empty((removed.shape[0] * kh * kw, 2))


@torch.library.register_fake("lidarops::sscater_gather_")
def _gather_fake(acc, input, weight, sites, stride, padding, count=None):
    return None


@torch.library.register_fake("lidarops::sscater_touch_")
def _touch_fake(stamp, acc, value, targets, added, removed):
    rows = min(targets.shape[0] + added.shape[0] + removed.shape[0], stamp.shape[0] * stamp.shape[1])
    return added.new_empty((rows, 2)), targets.new_empty((1,))


@torch.library.register_fake("lidarops::sscater_finalize_compact_")
def _finalize_compact_fake(acc, out, active, cand, count, stamp, status_value, scale, shift):
    rows = cand.shape[0]
    return cand.new_empty((rows, 2)), acc.new_empty((rows, acc.shape[2])), count.new_empty((3,))


@torch.library.register_fake("lidarops::sscater_dense_finalize_")
def _dense_finalize_fake(y, acc, out, scale, shift, active=None, out_nchw=None):
    return None
