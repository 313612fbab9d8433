"""Fake kernels and autograd formulas of the sparse convolution ops (``torch.ops.lidarops.sparse_*``).

The autograd formulas of the ops a network calls in every forward (``sparse_conv``, ``sparse_to_dense``,
``sparse_from_dense``) are C++ kernels instead (``csrc/ops/autograd``), for their host time.

Imported by :mod:`lidarops.sparse.functional` after :func:`lidarops.extension.load`. Every backward is
made of registered ops, so it runs on every device, under ``torch.compile``, and twice (the
convolution is bilinear in features and weight: its second derivatives are convolutions again).
"""
from __future__ import annotations

import torch

_ops = torch.ops.lidarops


# ---- fake kernels -------------------------------------------------------------------------------

@torch.library.register_fake("lidarops::sparse_conv_out_indices")
def _out_indices_fake(indices, batch_size, spatial_shape, out_spatial_shape, kernel_size, stride, padding,
                      dilation, transposed=False, method=0, validate=True, checked=False):
    # The number of output sites depends on the data.
    m = torch.library.get_ctx().new_dynamic_size()
    return indices.new_empty((m, indices.shape[1]))


@torch.library.register_fake("lidarops::sparse_kernel_map")
def _kernel_map_fake(indices, out_indices, batch_size, spatial_shape, kernel_size, stride, padding, dilation,
                     transposed=False, validate=True, method=0):
    kvol = 1
    for k in kernel_size:
        kvol *= k
    return out_indices.new_empty((out_indices.shape[0], kvol), dtype=torch.int32)


@torch.library.register_fake("lidarops::sparse_kernel_map_transpose")
def _kernel_map_transpose_fake(kernel_map, n_in):
    return kernel_map.new_empty((n_in, kernel_map.shape[1]))


@torch.library.register_fake("lidarops::sparse_kernel_map_order")
def _kernel_map_order_fake(kernel_map):
    return kernel_map.new_empty((kernel_map.shape[0],))


@torch.library.register_fake("lidarops::sparse_conv")
def _conv_fake(features, weight, kernel_map, order=None, algo="auto", splits=0):
    torch._check(weight.shape[1] == kernel_map.shape[1], lambda: "weight and kernel_map disagree on K")
    torch._check(weight.shape[2] == features.shape[1], lambda: "weight and features disagree on Cin")
    return features.new_empty((kernel_map.shape[0], weight.shape[0]))


@torch.library.register_fake("lidarops::sparse_conv_affine")
def _conv_affine_fake(features, weight, kernel_map, order=None, scale=None, shift=None, relu=False, algo="auto",
                      splits=0):
    return _conv_fake(features, weight, kernel_map, order)


@torch.library.register_fake("lidarops::sparse_conv_weight_grad")
def _conv_weight_grad_fake(features, grad_out, kernel_map):
    return features.new_empty((grad_out.shape[1], kernel_map.shape[1], features.shape[1]))


@torch.library.register_fake("lidarops::sparse_max_pool")
def _max_pool_fake(features, kernel_map):
    shape = (kernel_map.shape[0], features.shape[1])
    return features.new_empty(shape), features.new_empty(shape, dtype=torch.int64)


@torch.library.register_fake("lidarops::sparse_max_pool_backward")
def _max_pool_backward_fake(grad, argmax, kernel_map_t):
    return grad.new_empty((kernel_map_t.shape[0], grad.shape[1]))


@torch.library.register_fake("lidarops::sparse_to_dense")
def _to_dense_fake(features, indices, batch_size, spatial_shape):
    return features.new_empty([batch_size, features.shape[1], *spatial_shape])


@torch.library.register_fake("lidarops::sparse_from_dense")
def _from_dense_fake(dense, indices):
    return dense.new_empty((indices.shape[0], dense.shape[1]))


# ---- autograd -----------------------------------------------------------------------------------
# sparse_conv's formula is a C++ autograd kernel (csrc/ops/autograd/sparse_conv_kernel.cpp): a Python
# one cost every call of the op 10-20 us of host time, gradients or not (docs/sparse.md, session 14).

def _transpose_weight(w):
    return w.permute(2, 1, 0).contiguous()


# sparse_conv_weight_grad(x, g, map)[co, k, ci] = sum_o g[o, co] x[map[o, k], ci]: bilinear in (x, g).
#   d x = sparse_conv(g, H^T, map^T),  d g = sparse_conv(x, H, map)   for an incoming gradient H.

def _wgrad_setup(ctx, inputs, output):
    features, grad_out, kernel_map = inputs
    ctx.save_for_backward(features, grad_out, kernel_map)


def _wgrad_backward(ctx, h):
    features, grad_out, kernel_map = ctx.saved_tensors
    h = h.contiguous()
    d_x = d_g = None
    if ctx.needs_input_grad[0]:
        kernel_map_t = _ops.sparse_kernel_map_transpose(kernel_map, features.shape[0])
        d_x = _ops.sparse_conv(grad_out.contiguous(), _transpose_weight(h), kernel_map_t)
    if ctx.needs_input_grad[1]:
        d_g = _ops.sparse_conv(features, h, kernel_map)
    return d_x, d_g, None


torch.library.register_autograd("lidarops::sparse_conv_weight_grad", _wgrad_backward, setup_context=_wgrad_setup)


# sparse_max_pool: the gradient goes to the selected input row of each (output row, channel).

def _pool_setup(ctx, inputs, output):
    features, kernel_map = inputs
    _, argmax = output
    ctx.save_for_backward(argmax, kernel_map)
    ctx.n_in = features.shape[0]
    ctx.mark_non_differentiable(argmax)


def _pool_backward(ctx, grad, _grad_argmax):
    argmax, kernel_map = ctx.saved_tensors
    if grad is None or not ctx.needs_input_grad[0]:
        return None, None
    kernel_map_t = _ops.sparse_kernel_map_transpose(kernel_map, ctx.n_in)
    return _ops.sparse_max_pool_backward(grad.contiguous(), argmax, kernel_map_t), None


torch.library.register_autograd("lidarops::sparse_max_pool", _pool_backward, setup_context=_pool_setup)


def _pool_bw_setup(ctx, inputs, output):
    grad, argmax, kernel_map_t = inputs
    ctx.save_for_backward(argmax)


def _pool_bw_backward(ctx, gg):
    (argmax,) = ctx.saved_tensors
    # The adjoint of the scatter is a gather at the selected rows (zero where none was selected).
    safe = argmax.clamp_min(0)
    picked = torch.gather(gg, 0, safe) if gg.shape[0] else gg.new_zeros(argmax.shape)
    return torch.where(argmax >= 0, picked, torch.zeros_like(picked)), None, None


torch.library.register_autograd("lidarops::sparse_max_pool_backward", _pool_bw_backward, setup_context=_pool_bw_setup)

# sparse_to_dense and sparse_from_dense: C++ autograd kernels (csrc/ops/autograd/sparse_dense_kernel.cpp),
# for the same reason as sparse_conv.
