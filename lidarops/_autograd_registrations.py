"""Autograd formulas. Each backward is made of registered ops (gather / gather_backward), so it
works on every device, under torch.compile, and twice (double backward)."""
from __future__ import annotations

import torch

_ops = torch.ops.lidarops


# ---- gather: d x = scatter-add of d out ----

def _gather_setup(ctx, inputs, output):
    x, idx = inputs
    ctx.save_for_backward(idx)
    ctx.n = x.shape[1]


def _gather_backward(ctx, grad):
    (idx,) = ctx.saved_tensors
    if not ctx.needs_input_grad[0]:
        return None, None
    return _ops.gather_backward(grad.contiguous(), idx, ctx.n), None


torch.library.register_autograd("lidarops::gather", _gather_backward, setup_context=_gather_setup)


def _gather_bw_setup(ctx, inputs, output):
    grad, idx, n = inputs
    ctx.save_for_backward(idx)


def _gather_bw_backward(ctx, gg):
    (idx,) = ctx.saved_tensors
    return _ops.gather(gg.contiguous(), idx), None, None


torch.library.register_autograd("lidarops::gather_backward", _gather_bw_backward, setup_context=_gather_bw_setup)


# ---- knn / ball_query: dist2 = |q - p[idx]|^2 ----

def _neighbor_setup(ctx, inputs, output):
    query, points = inputs[0], inputs[1]
    _, idx = output
    ctx.save_for_backward(query, points, idx)
    ctx.mark_non_differentiable(idx)


def _neighbor_backward(ctx, grad_dist, _grad_idx):
    query, points, idx = ctx.saved_tensors
    B, M, K = idx.shape
    if grad_dist is None:
        return (None,) * 7
    flat = idx.reshape(B, M * K)
    ct = grad_dist.dtype
    neighbours = _ops.gather(points.to(ct).contiguous(), flat).reshape(B, M, K, 3)
    # padded entries (idx -1, dist2 +inf) carry no gradient
    g = torch.where(idx >= 0, grad_dist, torch.zeros((), dtype=ct, device=grad_dist.device))
    diff = query.to(ct).unsqueeze(2) - neighbours
    w = (2.0 * g).unsqueeze(-1) * diff
    grad_query = w.sum(2).to(query.dtype) if ctx.needs_input_grad[0] else None
    grad_points = None
    if ctx.needs_input_grad[1]:
        grad_points = _ops.gather_backward((-w).reshape(B, M * K, 3).contiguous(), flat, points.shape[1])
        grad_points = grad_points.to(points.dtype)
    return (grad_query, grad_points) + (None,) * 5


torch.library.register_autograd("lidarops::knn", _neighbor_backward, setup_context=_neighbor_setup)
torch.library.register_autograd("lidarops::ball_query", _neighbor_backward, setup_context=_neighbor_setup)
