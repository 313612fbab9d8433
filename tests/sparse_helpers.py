"""Shared helpers of the sparse-convolution tests: devices, random sparse tensors, comparisons.

Random sites are drawn without replacement (unique by construction), rows are shuffled so that no
kernel relies on sorted input, and with batch 3 the middle sample has no sites at all.
"""
from __future__ import annotations

import math
import os

import pytest
import torch

from lidarops.sparse import SparseConvTensor


def _cuda_params() -> list:
    if not torch.cuda.is_available():
        return []
    try:
        from lidarops import extension
        ok = extension.cuda_available()
        why = extension.build_info().get("cuda_reason", "")
    except Exception as e:  # noqa: BLE001
        ok, why = False, str(e)
    if ok or os.environ.get("LIDAROPS_TEST_REQUIRE_CUDA", "0") == "1":
        return [pytest.param("cuda", id="cuda")]
    return [pytest.param("cuda", id="cuda", marks=pytest.mark.skip(reason=f"lidarops has no CUDA kernels ({why})"))]


DEVICES = [pytest.param("cpu", id="cpu")] + _cuda_params()

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
