"""A kernel map cached under an indice_key is reused only for the sites it was built on.

Before the check, a layer given the same key and the same number of *other* sites reused the old
map: the result came back on the old map's sites with wrong values. Each test below compares with
the dense reference (``Fs._conv_reference``) or asserts the ValueError that replaced that result.
"""
from __future__ import annotations

import pytest
import torch

from lidarops.sparse import SparseConvTensor
from lidarops.sparse import functional as Fs
from lidarops.sparse import nn as spnn
from helpers.devices import DEVICES
from helpers.sparse import assert_same_sites_and_features, linear_order, random_tensor, random_weight

SHAPE = (6, 7, 5)


def _with_dict(x: SparseConvTensor, indice_dict: dict, indices=None) -> SparseConvTensor:
    return SparseConvTensor(x.features, x.indices if indices is None else indices, x.spatial_shape, x.batch_size,
                            indice_dict=indice_dict)


def _check(y: SparseConvTensor, x: SparseConvTensor, w: torch.Tensor, kind: str, what: str, **kw) -> None:
    """y's sites and features against the dense reference, both in row-major order."""
    ref_i, ref_f = Fs._conv_reference(x, w, None, kind, **kw)
    order = linear_order(ref_i, y.spatial_shape)
    assert_same_sites_and_features(y.indices, y.features, ref_i[order], ref_f[order], y.spatial_shape, 1e-10, what)


def _check_subm(y: SparseConvTensor, x: SparseConvTensor, w: torch.Tensor, what: str) -> None:
    _check(y, x, w, "subm", what)


def test_other_sites_with_the_same_count_raise(device):
    x = random_tensor(1, SHAPE, 30, 3, seed=0, device=device)
    other = random_tensor(1, SHAPE, 30, 3, seed=5, device=device)  # 30 sites too, different ones
    assert other.indices.shape == x.indices.shape and not torch.equal(other.indices, x.indices)
    w = random_weight(4, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="subm1")
    with pytest.raises(ValueError, match=r"indice_key 'subm1' holds a kernel map of other sites.*own indice_key"):
        Fs.conv(_with_dict(other, y.indice_dict), w, None, "subm", indice_key="subm1")
    # the same for strided convolutions and max pooling (the map's input side)
    down = Fs.conv(x, w, None, "conv", stride=2, padding=1, indice_key="down1")
    with pytest.raises(ValueError, match="'down1' holds a kernel map of other sites"):
        Fs.conv(_with_dict(other, down.indice_dict), w, None, "conv", stride=2, padding=1, indice_key="down1")
    pooled = Fs.max_pool(x, 2, indice_key="pool1")
    with pytest.raises(ValueError, match="'pool1' holds a kernel map of other sites"):
        Fs.max_pool(_with_dict(other, pooled.indice_dict), 2, indice_key="pool1")
    # and without a key nothing is cached: the other sites get their own map and the right result
    _check_subm(Fs.conv(other, w, None, "subm"), other, w, "no key")


def test_inverse_checks_the_output_sites_it_inverts(device):
    x = random_tensor(1, SHAPE, 30, 3, seed=1, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    down = Fs.conv(x, w, None, "conv", stride=2, padding=1, indice_key="down")
    n = down.indices.shape[0]
    # as many sites as the strided output, on the same grid, but not those sites
    cells = torch.tensor(down.spatial_shape).prod().item()
    assert n < cells
    lin = torch.arange(cells - n, cells)
    coords = []
    for s in reversed(down.spatial_shape):
        coords.append(lin % s)
        lin = lin // s
    shifted = torch.stack([torch.zeros(n, dtype=torch.int64)] + coords[::-1], 1).to(torch.int32).to(device)
    assert not torch.equal(shifted, down.indices)
    moved = SparseConvTensor(down.features, shifted, down.spatial_shape, 1, indice_dict=down.indice_dict)
    with pytest.raises(ValueError, match="'down' holds a kernel map of other sites.*output sites of the convolution"):
        Fs.conv(moved, w, None, "inverse", indice_key="down")
    # its own output sites invert fine
    back = Fs.conv(down, w, None, "inverse", indice_key="down")
    _check(back, down, w, "inverse", "inverse", inverse_of=down.indice_dict["down"])


def test_the_maps_own_indices_reuse_without_comparing(device, monkeypatch):
    x = random_tensor(2, SHAPE, 25, 3, seed=2, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="subm1")
    km = y.indice_dict["subm1"]
    calls = []
    real_equal = torch.equal
    monkeypatch.setattr(torch, "equal", lambda a, b: calls.append(1) or real_equal(a, b))
    z = Fs.conv(y, w, None, "subm", indice_key="subm1")  # y.indices is the map's own tensor
    assert z.indice_dict["subm1"] is km and z.indices is km.indices
    again = Fs.conv(_with_dict(x, y.indice_dict), w, None, "subm", indice_key="subm1")  # same object, new tensor
    assert calls == []  # identity: no device comparison, so no host synchronisation on CUDA
    _check_subm(again, x, w, "reuse by identity")


def test_an_equal_copy_is_compared_once_then_remembered(device, monkeypatch):
    x = random_tensor(1, SHAPE, 30, 3, seed=3, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="subm1")
    copy = x.indices.clone()  # e.g. indices.to("cuda") made again for a new SparseConvTensor
    calls = []
    real_equal = torch.equal
    monkeypatch.setattr(torch, "equal", lambda a, b: calls.append(a is copy) or real_equal(a, b))
    for i in range(3):
        out = Fs.conv(_with_dict(x, y.indice_dict, copy), w, None, "subm", indice_key="subm1")
        _check_subm(out, x, w, f"equal copy, call {i}")
    assert sum(calls) == 1  # compared on the first call only
    copy.add_(0)  # a new version of the copy (its values could have changed): compared again
    Fs.conv(_with_dict(x, y.indice_dict, copy), w, None, "subm", indice_key="subm1")
    assert sum(calls) == 2


def test_indices_changed_in_place_after_the_map_raise(device):
    x = random_tensor(1, SHAPE, 30, 3, seed=4, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="subm1")
    free = [c for c in range(SHAPE[2]) if not ((x.indices[:, 1:3] == x.indices[0, 1:3]).all(1)
                                                 & (x.indices[:, 3] == c)).any()]
    x.indices[0, 3] = free[0]  # another site, still unique and inside the grid, same count
    with pytest.raises(ValueError, match="'subm1' were changed in place after the map was built"):
        Fs.conv(y, w, None, "subm", indice_key="subm1")
    # a fresh dict builds a new map on the new sites
    _check_subm(Fs.conv(_with_dict(x, {}), w, None, "subm", indice_key="subm1"), x, w, "fresh dict")


def test_network_forward_on_other_sites_raises(device):
    net = spnn.SparseSequential(
        spnn.SubMConv3d(3, 4, 3, indice_key="subm1"), torch.nn.ReLU(),
        spnn.SparseConv3d(4, 4, 3, stride=2, padding=1, indice_key="down1"),
        spnn.SubMConv3d(4, 4, 3, indice_key="subm2"),
        spnn.SparseInverseConv3d(4, 3, 3, indice_key="down1"),
    ).double().to(device).eval()
    x = random_tensor(1, SHAPE, 30, 3, seed=6, device=device)
    with torch.no_grad():
        out = net(x)
        maps = dict(out.indice_dict)
        # the cached forward on the same sites (the CUDA-graph recipe of docs/sparse.md) gives the same result
        again = net(_with_dict(x, maps, x.indices.clone()))
        assert torch.equal(again.indices, out.indices)
        torch.testing.assert_close(again.features, out.features, rtol=0, atol=0)
        other = random_tensor(1, SHAPE, 30, 3, seed=7, device=device)
        with pytest.raises(ValueError, match="'subm1' holds a kernel map of other sites"):
            net(_with_dict(other, maps))


def test_inference_tensors(device):
    with torch.inference_mode():  # inference tensors keep no version counter: identity and comparison only
        x = random_tensor(1, SHAPE, 30, 3, seed=8, device=device)
        w = random_weight(3, (3, 3, 3), 3, device=device)
        y = Fs.conv(x, w, None, "subm", indice_key="subm1")
        z = Fs.conv(y, w, None, "subm", indice_key="subm1")
        _check_subm(z, y, w, "inference mode")
        other = random_tensor(1, SHAPE, 30, 3, seed=9, device=device)
        with pytest.raises(ValueError, match="holds a kernel map of other sites"):
            Fs.conv(_with_dict(other, y.indice_dict), w, None, "subm", indice_key="subm1")


def test_compiled_forward_checks_too(device):
    x = random_tensor(1, SHAPE, 30, 3, seed=10, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="s")

    def layer(features, indices, maps):
        return Fs.conv(SparseConvTensor(features, indices, list(SHAPE), 1, indice_dict=maps), w, None, "subm",
                       indice_key="s").features

    torch._dynamo.reset()
    full = torch.compile(layer, fullgraph=True, backend="aot_eager")  # the map's own tensor: no graph break
    torch.testing.assert_close(full(x.features, x.indices, y.indice_dict), y.features)
    partial = torch.compile(layer, backend="aot_eager")  # another tensor: compared eagerly at a graph break
    torch.testing.assert_close(partial(x.features, x.indices.clone(), y.indice_dict), y.features)
    other = random_tensor(1, SHAPE, 30, 3, seed=11, device=device)
    with pytest.raises(ValueError, match="holds a kernel map of other sites"):
        partial(other.features, other.indices, y.indice_dict)


@pytest.mark.skipif(not any(p.values[0] == "cuda" and not p.marks for p in DEVICES),
                    reason="needs a GPU and lidarops built with CUDA kernels")
def test_cuda_graph_capture_of_an_unchecked_copy_raises():
    x = random_tensor(1, SHAPE, 30, 3, seed=12, device="cuda")
    w = random_weight(3, (3, 3, 3), 3, device="cuda")
    y = Fs.conv(x, w, None, "subm", indice_key="s")
    fresh = _with_dict(x, y.indice_dict, x.indices.clone())
    torch.cuda.synchronize()
    g = torch.cuda.CUDAGraph()
    with pytest.raises(ValueError, match="CUDA graph capture forbids"):
        with torch.no_grad(), torch.cuda.graph(g):
            Fs.conv(fresh, w, None, "subm", indice_key="s")
    # checked once outside the capture, the same tensor then captures and replays without a sync
    with torch.no_grad():
        Fs.conv(fresh, w, None, "subm", indice_key="s")
        torch.cuda.set_sync_debug_mode("error")
        try:
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g):
                out = Fs.conv(fresh, w, None, "subm", indice_key="s")
        finally:
            torch.cuda.set_sync_debug_mode("default")
        g.replay()
    torch.testing.assert_close(out.features, y.features)
    assert linear_order(out.indices, SHAPE).numel() == x.indices.shape[0]
