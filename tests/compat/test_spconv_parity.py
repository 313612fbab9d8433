"""lidarops.compat.spconv against spconv 2.3.8 itself (GPU machine, with the spconv bundle installed):
the same state_dict and input give the same output sites (as sets) and features (to float tolerance)
for every kind, in 2D and 3D, the kernel-size-1 shortcut included. Skipped where spconv is absent.
"""
from __future__ import annotations

import pytest
import torch

import lidarops.compat.spconv as lspconv
from helpers.devices import CUDA_OK
from helpers.sparse import linear_order, random_sites

spconv = pytest.importorskip("spconv.pytorch", reason="spconv 2.x is not installed (pip install spconv-cu120 or a spconv wheel for your CUDA)")
pytestmark = pytest.mark.skipif(not CUDA_OK, reason="needs a GPU and lidarops built with CUDA kernels")

SHAPES = {2: [40, 36], 3: [12, 40, 36]}


def _input(sp, D, channels, dtype, seed=0):
    idx = random_sites(2, SHAPES[D], 200 if D == 2 else 400, seed, empty_middle=False).cuda()
    g = torch.Generator().manual_seed(seed)
    feats = torch.randn(idx.shape[0], channels, generator=g).to(device="cuda", dtype=dtype)
    return sp.SparseConvTensor(feats, idx, SHAPES[D], 2)


def _compare(ours, theirs, shape, tol, what):
    assert list(ours.spatial_shape) == list(theirs.spatial_shape), f"{what}: grids differ"
    a, b = linear_order(ours.indices, shape), linear_order(theirs.indices, shape)
    ia, ib = ours.indices.long().cpu()[a], theirs.indices.long().cpu()[b]
    assert torch.equal(ia, ib), f"{what}: output sites differ ({ia.shape[0]} vs {ib.shape[0]})"
    fa, fb = ours.features.double().cpu()[a], theirs.features.double().cpu()[b]
    scale = max(1.0, fb.abs().max().item()) if fb.numel() else 1.0
    diff = (fa - fb).abs().max().item() if fb.numel() else 0.0
    assert diff <= tol * scale, f"{what}: max |diff| {diff:.3e} (scale {scale:.3g})"


def _layers(D, kind, k, s, p, cin, cout):
    name = {("subm", 2): "SubMConv2d", ("subm", 3): "SubMConv3d", ("conv", 2): "SparseConv2d",
            ("conv", 3): "SparseConv3d", ("transposed", 2): "SparseConvTranspose2d",
            ("transposed", 3): "SparseConvTranspose3d"}[(kind, D)]
    kw = {} if kind == "subm" else {"stride": s, "padding": p}
    return (getattr(spconv, name)(cin, cout, k, bias=True, indice_key="k", **kw),
            getattr(lspconv, name)(cin, cout, k, bias=True, indice_key="k", **kw))


@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("kind,k,s,p", [("subm", 3, 1, 1), ("subm", 1, 1, 0), ("conv", 3, 2, 1), ("conv", 2, 2, 0),
                                        ("conv", 1, 1, 0), ("conv", 1, 2, 0), ("transposed", 2, 2, 0),
                                        ("transposed", 3, 1, 1)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16], ids=["f32", "f16"])
def test_layer_matches_spconv(D, kind, k, s, p, dtype):
    theirs_layer, ours_layer = _layers(D, kind, k, s, p, 16, 32)
    theirs_layer = theirs_layer.cuda().to(dtype)
    ours_layer = ours_layer.cuda().to(dtype)
    ours_layer.load_state_dict(theirs_layer.state_dict())  # spconv's state_dict loads unchanged
    x_theirs = _input(spconv, D, 16, dtype)
    x_ours = lspconv.SparseConvTensor(x_theirs.features, x_theirs.indices, SHAPES[D], 2)
    with torch.no_grad():
        y_theirs = theirs_layer(x_theirs)
        y_ours = ours_layer(x_ours)
    tol = 1e-4 if dtype == torch.float32 else 5e-3
    _compare(y_ours, y_theirs, y_theirs.spatial_shape, tol, f"{kind} k{k} s{s} p{p} {D}D {dtype}")


@pytest.mark.parametrize("D", [2, 3])
def test_inverse_and_max_pool_match_spconv(D):
    Conv = spconv.SparseConv2d if D == 2 else spconv.SparseConv3d
    Inv = spconv.SparseInverseConv2d if D == 2 else spconv.SparseInverseConv3d
    LConv = lspconv.SparseConv2d if D == 2 else lspconv.SparseConv3d
    LInv = lspconv.SparseInverseConv2d if D == 2 else lspconv.SparseInverseConv3d
    Pool = spconv.SparseMaxPool2d if D == 2 else spconv.SparseMaxPool3d
    LPool = lspconv.SparseMaxPool2d if D == 2 else lspconv.SparseMaxPool3d
    theirs = spconv.SparseSequential(Conv(16, 32, 3, 2, 1, indice_key="down"), Inv(32, 8, 3, indice_key="down")).cuda()
    ours = lspconv.SparseSequential(LConv(16, 32, 3, 2, 1, indice_key="down"), LInv(32, 8, 3, indice_key="down")).cuda()
    ours.load_state_dict(theirs.state_dict())
    x_theirs = _input(spconv, D, 16, torch.float32, seed=1)
    x_ours = lspconv.SparseConvTensor(x_theirs.features, x_theirs.indices, SHAPES[D], 2)
    with torch.no_grad():
        _compare(ours(x_ours), theirs(x_theirs), SHAPES[D], 1e-4, f"inverse conv {D}D")
        _compare(LPool(2, 2)(x_ours), Pool(2, 2)(x_theirs), [n // 2 for n in SHAPES[D]], 0.0,
                 f"max pool {D}D")
