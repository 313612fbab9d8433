"""Shared helpers of the sparse-convolution tests (tests/sparse/, tests/compat/, tests/sscater/): random sparse
tensors, comparisons, a dense emulator of sparse networks.

Random sites are drawn without replacement (unique by construction), rows are shuffled so that no
kernel relies on sorted input, and with batch 3 the middle sample has no sites at all.
"""
from __future__ import annotations

import math

import torch

from lidarops.sparse import SparseConvTensor

# max |got - ref| <= tol * max(1, max |ref|): float32 and half types are accumulated in float32
TOL = {torch.float64: 1e-10, torch.float32: 2e-5, torch.float16: 4e-3, torch.bfloat16: 3e-2}


def random_sites(batch: int, shape, per_sample: int, seed: int, empty_middle: bool = True) -> torch.Tensor:
    """(N, 1 + D) int32 unique sites, rows shuffled; with batch >= 3 the sample 1 is empty."""
    g = torch.Generator().manual_seed(seed)
    cells = math.prod(shape)
    rows = []
    for b in range(batch):
        n = 0 if (empty_middle and batch >= 3 and b == 1) else min(per_sample, cells)
        lin = torch.randperm(cells, generator=g)[:n]
        coords = []
        for s in reversed(shape):
            coords.append(lin % s)
            lin = lin // s
        coords = torch.stack([torch.full((n,), b, dtype=torch.int64)] + coords[::-1], 1)
        rows.append(coords)
    idx = torch.cat(rows) if rows else torch.zeros(0, 1 + len(shape), dtype=torch.int64)
    perm = torch.randperm(idx.shape[0], generator=g)
    return idx[perm].to(torch.int32)


def random_tensor(batch: int, shape, per_sample: int, channels: int, seed: int = 0, dtype=torch.float64,
                  device="cpu") -> SparseConvTensor:
    idx = random_sites(batch, shape, per_sample, seed)
    g = torch.Generator().manual_seed(seed + 7)
    feats = torch.randn(idx.shape[0], channels, generator=g, dtype=torch.float64)
    return SparseConvTensor(feats.to(device=device, dtype=dtype), idx.to(device), list(shape), batch)


def random_weight(cout: int, ksize, cin: int, seed: int = 0, dtype=torch.float64, device="cpu") -> torch.Tensor:
    g = torch.Generator().manual_seed(seed + 11)
    return torch.randn(cout, *ksize, cin, generator=g, dtype=torch.float64).to(device=device, dtype=dtype)


def linear_order(indices: torch.Tensor, shape) -> torch.Tensor:
    """Permutation sorting rows by (batch, row-major coordinates)."""
    idx = indices.long().cpu()
    key = idx[:, 0]
    for d, s in enumerate(shape):
        key = key * s + idx[:, d + 1]
    return torch.argsort(key)


def assert_same_sites_and_features(indices: torch.Tensor, features: torch.Tensor, ref_indices: torch.Tensor,
                                   ref_features: torch.Tensor, shape, tol: float, what: str) -> None:
    """Sites equal as sets (ref in row-major order), features within tol * max(1, max|ref|)."""
    order = linear_order(indices, shape)
    got_i = indices.long().cpu()[order]
    ref_i = ref_indices.long().cpu()
    assert got_i.shape == ref_i.shape, (f"{what}: {got_i.shape[0]} output sites, reference has {ref_i.shape[0]}")
    if not torch.equal(got_i, ref_i):
        got_set = {tuple(r) for r in got_i.tolist()}
        ref_set = {tuple(r) for r in ref_i.tolist()}
        raise AssertionError(f"{what}: site sets differ; extra {sorted(got_set - ref_set)[:5]}, "
                             f"missing {sorted(ref_set - got_set)[:5]}")
    got_f = features.detach().double().cpu()[order]
    ref_f = ref_features.detach().double().cpu()
    assert got_f.shape == ref_f.shape, f"{what}: features {tuple(got_f.shape)} vs {tuple(ref_f.shape)}"
    if got_f.numel() == 0:
        return
    scale = max(1.0, ref_f.abs().max().item())
    diff = (got_f - ref_f).abs()
    worst = diff.max().item()
    if not worst <= tol * scale:
        w = tuple(torch.nonzero(diff == diff.max())[0].tolist())
        raise AssertionError(f"{what}: max |diff| {worst:.3e} > {tol:.1e} x {scale:.3g}; worst at row {w[0]} "
                             f"(site {got_i[w[0]].tolist()}), channel {w[1]}: got {got_f[w].item()!r}, "
                             f"expected {ref_f[w].item()!r}")


# ---- a dense emulator of sparse networks (independent of the kernels, used by nn / compat tests) ----

class _Geometry:
    """What an inverse convolution needs to know about the convolution it inverts."""

    def __init__(self, indices, spatial_shape, out_spatial_shape, stride, padding, dilation):
        self.indices, self.spatial_shape, self.out_spatial_shape = indices, tuple(spatial_shape), tuple(out_spatial_shape)
        self.stride, self.padding, self.dilation = stride, padding, dilation


def emulate(module, x: SparseConvTensor, registry: dict | None = None):
    """Run a network of lidarops.sparse.nn / compat.spconv modules with the dense references of
    lidarops.sparse.functional (F.convNd on x.dense() per layer), returning a SparseConvTensor (sites in
    reference order) or a dense tensor after ToDense. nn.Module children other than sparse ones act on
    features, as in SparseSequential."""
    from torch import nn as tnn

    from lidarops.sparse import functional as Fs
    from lidarops.sparse import nn as spnn

    registry = {} if registry is None else registry
    if isinstance(module, spnn.SparseSequential):
        for m in module:
            x = emulate(m, x, registry)
        return x
    if isinstance(module, spnn.ToDense):
        return x.dense()
    if isinstance(module, spnn.SparseConvolution):
        w, b = module.weight, module.bias
        if getattr(module, "conv1x1", False):  # compat face: spconv 2.3.8's kernel-size-1 product
            f = x.features @ w.reshape(module.in_channels, module.out_channels)
            y = SparseConvTensor(f + b if b is not None else f, x.indices, x.spatial_shape, x.batch_size)
            y.spatial_shape = module._spconv_out_shape(x.spatial_shape)
            return y
        kind = module.kind
        if kind == "inverse":
            geo = registry[module.indice_key]
            sites, feats = Fs._conv_reference(x, w, b, "inverse", inverse_of=geo)
            return SparseConvTensor(feats, sites.int(), list(geo.spatial_shape), x.batch_size)
        s, p, d = module.stride, module.padding, module.dilation
        sites, feats = Fs._conv_reference(x, w, b, kind, s, p, d, module.output_padding)
        if kind == "subm":
            shape = x.spatial_shape
        elif kind == "transposed":
            out_shape = module._out_spatial_shape(x)
            shape = list(out_shape) if out_shape is not None else list(
                Fs.conv_transpose_output_shape(x.spatial_shape, module.kernel_size, s, p, d, module.output_padding))
            keep = (sites[:, 1:] < torch.tensor(shape, device=sites.device)).all(1)
            sites, feats = sites[keep], feats[keep]
        else:
            shape = list(Fs.conv_output_shape(x.spatial_shape, module.kernel_size, s, p, d))
        if module.indice_key is not None and kind != "subm" and module.indice_key not in registry:
            registry[module.indice_key] = _Geometry(x.indices, x.spatial_shape, shape, s, p, d)
        return SparseConvTensor(feats, sites.int(), shape, x.batch_size)
    if isinstance(module, spnn.SparseMaxPool):
        sites, feats = Fs._max_pool_reference(x, module.kernel_size, module.stride, module.padding, module.dilation)
        shape = list(Fs.conv_output_shape(x.spatial_shape, module.kernel_size, module.stride, module.padding,
                                          module.dilation))
        return SparseConvTensor(feats, sites.int(), shape, x.batch_size)
    if isinstance(x, SparseConvTensor):
        if x.features.shape[0] == 0 and isinstance(module, tnn.modules.batchnorm._BatchNorm):
            return x
        return x.replace_feature(module(x.features))
    return module(x)
