"""lidarops.sparse: SparseConvTensor, nn modules, SparseSequential, state_dicts.

Networks are checked end to end against a dense emulator (tests/helpers/sparse.py, emulate: every layer
by F.convNd / F.conv_transposeNd / F.max_poolNd on the dense tensor, read at the output sites).
"""
from __future__ import annotations

from collections import OrderedDict

import pytest
import torch
from torch import nn

from lidarops import sparse
from lidarops.sparse import SparseConvTensor
from lidarops.sparse import nn as spnn
from helpers.sparse import assert_same_sites_and_features, emulate, linear_order, random_tensor


def _compare_tensors(y, ref, tol=1e-10, what="network"):
    order = linear_order(ref.indices, ref.spatial_shape)
    assert y.spatial_shape == list(ref.spatial_shape), f"{what}: grid {y.spatial_shape} vs {ref.spatial_shape}"
    assert_same_sites_and_features(y.indices, y.features, ref.indices[order], ref.features[order], y.spatial_shape,
                                   tol, what)


def test_dense_from_dense_round_trip(device):
    x = random_tensor(3, (5, 6, 4), 20, 3, seed=1, device=device)
    d = x.dense()
    assert d.shape == (3, 3, 5, 6, 4)
    assert torch.equal(x.dense(channels_first=False).permute(0, 4, 1, 2, 3), d)
    idx = x.indices.long()
    torch.testing.assert_close(d.permute(0, 2, 3, 4, 1)[tuple(idx.unbind(1))], x.features)
    assert d.abs().sum(1).gt(0).sum() == x.indices.shape[0]
    y = SparseConvTensor.from_dense(d, channels_first=True)
    order = linear_order(x.indices, x.spatial_shape)
    assert torch.equal(y.indices, x.indices[order]) and torch.equal(y.features, x.features[order])
    z = SparseConvTensor.from_dense(x.dense(channels_first=False))
    assert torch.equal(z.indices, y.indices) and z.spatial_shape == [5, 6, 4] and z.batch_size == 3
    assert x.spatial_size == 120 and x.ndim == 3
    import numpy as np
    z = SparseConvTensor(x.features, x.indices, np.array([5, 6, 4]), np.int64(3))  # OpenPCDet passes numpy
    assert z.spatial_shape == [5, 6, 4] and z.batch_size == 3 and isinstance(z.batch_size, int)


def test_dense_is_differentiable_and_checks_sites(device):
    x = random_tensor(1, (4, 4), 5, 2, seed=0, device=device)
    f = x.features.clone().requires_grad_()
    x.replace_feature(f).dense().sum().backward()
    assert torch.equal(f.grad, torch.ones_like(f))
    bad = SparseConvTensor(x.features, x.indices + 10, [4, 4], 1)
    with pytest.raises(ValueError, match=r"indices lie outside batch_size 1 / spatial_shape \[4, 4\]"):
        bad.dense()


_DENSE_SHAPES = {1: (50,), 2: (13, 11), 3: (7, 9, 6), 4: (3, 4, 5, 3)}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16],
                         ids=["f64", "f32", "f16", "bf16"])
@pytest.mark.parametrize("D,batch,C", [(1, 2, 5), (2, 3, 40), (3, 1, 33), (4, 2, 3)])
def test_sparse_to_dense_op_and_its_adjoint(device, dtype, D, batch, C):
    """The registered dense-map op against index_put (exact: both copy), with more than one 32 x 32 tile
    of rows and of channels, shuffled rows, an empty middle sample (batch 3), a row outside the grid
    (skipped) and no rows at all; sparse_from_dense reads the sites back (zeros for the outside row)."""
    ops = torch.ops.lidarops
    shape = _DENSE_SHAPES[D]
    x = random_tensor(batch, shape, 40, C, seed=D + C, dtype=dtype, device=device)
    idx = x.indices
    ref = x.features.new_zeros([batch, *shape, C])
    ref[tuple(idx.long().unbind(1))] = x.features
    ref = ref.movedim(-1, 1)
    got = ops.sparse_to_dense(x.features, idx, batch, list(shape))
    assert got.shape == ref.shape and got.dtype == dtype and got.is_contiguous()
    assert torch.equal(got, ref)
    assert torch.equal(ops.sparse_from_dense(got, idx), x.features)
    dense = torch.randn(ref.shape, dtype=torch.float64).to(device=device, dtype=dtype)
    assert torch.equal(ops.sparse_from_dense(dense, idx), dense.movedim(1, -1)[tuple(idx.long().unbind(1))])
    outside = idx[:1].clone()
    outside[0, 1] = shape[0]  # one past the grid
    idx2, f2 = torch.cat([idx, outside]), torch.cat([x.features, x.features[:1] + 1])
    assert torch.equal(ops.sparse_to_dense(f2, idx2, batch, list(shape)), ref)
    back = ops.sparse_from_dense(ref, idx2)
    assert torch.equal(back[:-1], x.features) and torch.equal(back[-1], torch.zeros_like(back[-1]))
    empty = ops.sparse_to_dense(x.features[:0], idx[:0], batch, list(shape))
    assert empty.shape == ref.shape and not empty.any()


def test_sparse_to_dense_gradients_and_errors(device):
    ops = torch.ops.lidarops
    x = random_tensor(2, (5, 4), 6, 3, seed=4, device=device)
    f = x.features.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: ops.sparse_to_dense(t, x.indices, 2, [5, 4]), (f,))
    assert torch.autograd.gradgradcheck(lambda t: ops.sparse_to_dense(t, x.indices, 2, [5, 4]), (f,))
    d = torch.randn(2, 3, 5, 4, dtype=torch.float64, device=device, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: ops.sparse_from_dense(t, x.indices), (d,))
    assert torch.autograd.gradgradcheck(lambda t: ops.sparse_from_dense(t, x.indices), (d,))
    with pytest.raises(ValueError, match="indices must be int32"):
        ops.sparse_to_dense(x.features, x.indices.long(), 2, [5, 4])
    n = x.indices.shape[0]
    with pytest.raises(ValueError, match=f"indices has {n} rows but features has {n + 1}"):
        ops.sparse_to_dense(torch.cat([x.features, x.features[:1]]), x.indices, 2, [5, 4])
    with pytest.raises(ValueError, match=r"indices must be \(N, 4\) for D = 3"):
        ops.sparse_to_dense(x.features, x.indices, 2, [5, 4, 2])
    with pytest.raises(ValueError, match="features must be floating point"):
        ops.sparse_to_dense(x.indices[:, :1].expand(-1, 3).contiguous(), x.indices, 2, [5, 4])
    with pytest.raises(ValueError, match=r"dense must be \(B, C, \*spatial\)"):
        ops.sparse_from_dense(torch.zeros(3, 4, device=device), x.indices)


def test_dense_check_is_cached_per_indices_version_and_shape(device):
    # dense() checks an indices tensor once (no host sync on the next calls), but again after an
    # in-place change of the indices or with another spatial_shape / batch_size
    x = random_tensor(1, (4, 4), 5, 2, seed=0, device=device)
    idx = x.indices.clone()
    SparseConvTensor(x.features, idx, [4, 4], 1).dense()
    idx[0, 1] = 7  # in place: the cached check must not hide it
    with pytest.raises(ValueError, match=r"indices lie outside batch_size 1 / spatial_shape \[4, 4\]"):
        SparseConvTensor(x.features, idx, [4, 4], 1).dense()
    idx[0, 1] = 3
    SparseConvTensor(x.features, idx, [4, 4], 1).dense()
    with pytest.raises(ValueError, match=r"indices lie outside batch_size 1 / spatial_shape \[3, 4\]"):
        SparseConvTensor(x.features, idx, [3, 4], 1).dense()
    with torch.inference_mode():  # inference tensors keep no version counter: checked every call
        inf_idx = idx.clone()
        y = SparseConvTensor(x.features, inf_idx, [4, 4], 1)
        assert torch.equal(y.dense(), SparseConvTensor(x.features, idx, [4, 4], 1).dense())
        inf_idx[0, 1] = 7
        with pytest.raises(ValueError, match=r"indices lie outside batch_size 1 / spatial_shape \[4, 4\]"):
            y.dense()


def test_replace_feature_add_and_setter(device):
    x = random_tensor(1, (4, 4), 5, 2, seed=0, device=device)
    x.indice_dict["k"] = "cached"
    y = x.replace_feature(x.features * 2)
    assert y.indices is x.indices and y.indice_dict is x.indice_dict
    torch.testing.assert_close((x + y).features, x.features * 3)
    torch.testing.assert_close((x.features + y).features, x.features * 3)
    torch.testing.assert_close(x.minus().features, -x.features)
    y.features = torch.zeros_like(x.features)  # allowed (older spconv code assigns features)
    with pytest.raises(ValueError, match=r"features must be \(N, C\) with N = 5"):
        y.features = torch.zeros(4, 2, device=device)


@pytest.mark.parametrize("D", [2, 3])
def test_modules_match_dense_emulation(device, D):
    shape = (12, 10) if D == 2 else (8, 9, 7)
    x = random_tensor(3, shape, 30, 4, seed=D, device=device)
    Sub = spnn.SubMConv2d if D == 2 else spnn.SubMConv3d
    Conv = spnn.SparseConv2d if D == 2 else spnn.SparseConv3d
    ConvT = spnn.SparseConvTranspose2d if D == 2 else spnn.SparseConvTranspose3d
    Inv = spnn.SparseInverseConv2d if D == 2 else spnn.SparseInverseConv3d
    Pool = spnn.SparseMaxPool2d if D == 2 else spnn.SparseMaxPool3d
    net = spnn.SparseSequential(
        Sub(4, 8, 3, indice_key="subm1"), nn.BatchNorm1d(8), nn.ReLU(),
        Sub(8, 8, 3, indice_key="subm1"),
        Conv(8, 16, 3, stride=2, padding=1, indice_key="down1"), nn.ReLU(),
        Sub(16, 16, 3, dilation=2, indice_key="subm2"),
        Inv(16, 8, 3, indice_key="down1"), nn.Linear(8, 6),
        Pool(2, indice_key="pool1"),
        ConvT(6, 5, 2, stride=2, indice_key="up1"),
        Conv(5, 4, 1, bias=False),
    ).double().to(device).eval()
    y = net(x)
    ref = emulate(net, x)
    _compare_tensors(y, ref, what=f"{D}D module network")
    # the submanifold layers with one key share one kernel map
    assert y.indice_dict["subm1"].kind == "subm"
    assert set(y.indice_dict) == {"subm1", "down1", "subm2", "pool1", "up1"}


def test_sparse_sequential_feature_modules_and_empty_input(device):
    net = spnn.SparseSequential(OrderedDict([
        ("conv", spnn.SubMConv3d(3, 4, 3, indice_key="s")), ("bn", nn.BatchNorm1d(4)), ("relu", nn.ReLU()),
        ("lin", nn.Linear(4, 2)), ("dense", spnn.ToDense()), ("pool", nn.AdaptiveMaxPool3d(1))])).to(device)
    assert len(net) == 6 and isinstance(net[0], spnn.SubMConv3d) and isinstance(net[-1], nn.AdaptiveMaxPool3d)
    x = random_tensor(2, (5, 5, 5), 10, 3, seed=0, dtype=torch.float32, device=device)
    out = net(x)
    assert out.shape == (2, 2, 1, 1, 1)
    empty = SparseConvTensor(torch.zeros(0, 3, device=device), torch.zeros(0, 4, dtype=torch.int32, device=device),
                             [5, 5, 5], 2)
    net.train()
    out = net(empty)  # BatchNorm is skipped on a tensor without sites; the Linear still maps 4 -> 2 channels
    assert out.shape == (2, 2, 1, 1, 1)
    seq = spnn.SparseSequential(a=nn.ReLU())
    seq.add(nn.Identity())
    assert list(seq._modules) == ["a", "1"]


def test_module_arguments_are_checked():
    with pytest.raises(ValueError, match="submanifold convolution has stride 1"):
        spnn.SubMConv3d(3, 4, 3, stride=2)
    with pytest.raises(ValueError, match="kernel_size must have 3 entries"):
        spnn.SparseConv3d(3, 4, (3, 3))
    with pytest.raises(ValueError, match="in_channels must be a positive int"):
        spnn.SparseConv2d(0, 4, 3)
    with pytest.raises(ValueError, match="needs the indice_key"):
        spnn.SparseInverseConv3d(3, 4, 3, indice_key=None)
    with pytest.raises(ValueError, match="bias must be True or False"):
        spnn.SubMConv2d(3, 4, 3, bias="no")
    with pytest.raises(ValueError, match="indice_key must be a str or None"):
        spnn.SubMConv2d(3, 4, 3, indice_key=1)
    conv = spnn.SubMConv2d(3, 4, 3)
    x = random_tensor(1, (4, 4), 3, 5, seed=0, dtype=torch.float32)
    with pytest.raises(ValueError, match="expects 3 input channels"):
        conv(x)
    with pytest.raises(ValueError, match="takes a SparseConvTensor"):
        conv(torch.zeros(3, 3))


def test_weight_layout_and_state_dict_round_trip():
    m = spnn.SparseConv3d(4, 8, (3, 2, 1), stride=2, bias=True)
    assert m.weight.shape == (8, 3, 2, 1, 4)
    m2 = spnn.SparseConv3d(4, 8, (3, 2, 1), stride=2, bias=True)
    m2.load_state_dict(m.state_dict())
    x = random_tensor(1, (6, 6, 6), 20, 4, seed=2, dtype=torch.float32)
    torch.testing.assert_close(m(x).features, m2(x).features, rtol=0, atol=0)
    # a spconv 2.x state_dict (weight [Cout, *k, Cin]) loads unchanged
    sd = {"weight": torch.randn(8, 3, 2, 1, 4), "bias": torch.randn(8)}
    m.load_state_dict(sd)
    assert torch.equal(m.weight, sd["weight"])


def test_kernel_size_one_uses_documented_layout(device):
    x = random_tensor(2, (5, 5, 5), 10, 4, seed=3, device=device)
    m = spnn.SubMConv3d(4, 6, 1, bias=False).double().to(device)
    y = m(x)
    torch.testing.assert_close(y.features, x.features @ m.weight.reshape(6, 4).t())
    m2 = spnn.SparseConv3d(4, 6, 1, bias=False).double().to(device)
    m2.weight.data.copy_(m.weight)
    y2 = m2(x)
    order = linear_order(x.indices, x.spatial_shape)
    torch.testing.assert_close(y2.features, y.features[order])


def test_training_step_reduces_loss(device):
    torch.manual_seed(0)
    net = spnn.SparseSequential(spnn.SubMConv2d(3, 8, 3, indice_key="a"), nn.BatchNorm1d(8), nn.ReLU(),
                                spnn.SparseConv2d(8, 8, 3, stride=2, padding=1), nn.ReLU(),
                                spnn.SparseConvTranspose2d(8, 3, 2, stride=2)).to(device)
    x = random_tensor(2, (16, 16), 40, 3, seed=0, dtype=torch.float32, device=device)
    opt = torch.optim.SGD(net.parameters(), lr=0.05)
    losses = []
    for _ in range(5):
        opt.zero_grad()
        loss = net(x).dense().pow(2).mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0]
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_public_namespace():
    for name in ("SparseConvTensor", "SubMConv2d", "SubMConv3d", "SparseConv2d", "SparseConv3d",
                 "SparseConvTranspose2d", "SparseConvTranspose3d", "SparseInverseConv2d", "SparseInverseConv3d",
                 "SparseMaxPool2d", "SparseMaxPool3d", "SparseSequential", "ToDense", "build_kernel_map", "conv"):
        assert hasattr(sparse, name), name
