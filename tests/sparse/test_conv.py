"""Sparse convolution against dense PyTorch: kernel maps, each kind of convolution, max pooling,
gradients, registered-op checks, empty and bad inputs.

References are independent of the kernels: dense ``F.convNd`` / ``F.conv_transposeNd`` /
``F.max_poolNd`` on ``x.dense()`` (float64), read at the output sites, and a pure-Python dictionary
lookup for kernel maps. Output sites are compared as sets.
"""
from __future__ import annotations

import itertools
import math

import pytest
import torch

from lidarops.sparse import SparseConvTensor
from lidarops.sparse import functional as Fs
from lidarops.sparse import nn as spnn
from helpers.devices import CUDA_OK, requires_cuda
from helpers.sparse import (TOL, assert_same_sites_and_features, linear_order, random_sites, random_tensor,
                            random_weight)

ops = torch.ops.lidarops
SHAPES = {2: (13, 11), 3: (7, 9, 6)}
PER_SAMPLE = {2: 30, 3: 40}
GEOMETRY = list(itertools.product((1, 2, 3), (1, 2, 3), (0, 1), (1, 2)))  # kernel, stride, padding, dilation


def _id(k, s, p, d):
    return f"k{k}s{s}p{p}d{d}"


# ================================================================================================
# Kernel maps
# ================================================================================================

def _python_kernel_map(indices, out_indices, shape, k, s, p, d, transposed):
    """Dictionary lookup, one (output, offset) at a time."""
    D = len(shape)
    table = {tuple(r): i for i, r in enumerate(indices.tolist())}
    offsets = list(itertools.product(*[range(kk) for kk in k]))
    out = torch.full((out_indices.shape[0], len(offsets)), -1, dtype=torch.int32)
    for o, row in enumerate(out_indices.tolist()):
        b, q = row[0], row[1:]
        for t, off in enumerate(offsets):
            pin = []
            for i in range(D):
                if transposed:
                    v = q[i] + p[i] - off[i] * d[i]
                    if v % s[i]:
                        break
                    v //= s[i]
                else:
                    v = q[i] * s[i] - p[i] + off[i] * d[i]
                if not 0 <= v < shape[i]:
                    break
                pin.append(v)
            else:
                out[o, t] = table.get((b, *pin), -1)
    return out


@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("transposed", [False, True], ids=["conv", "transposed"])
@pytest.mark.parametrize("k,s,p,d", [(3, 1, 1, 1), (3, 2, 1, 1), (2, 2, 0, 1), (3, 1, 0, 2), (3, 3, 1, 1)])
def test_kernel_map_matches_python_lookup_both_tables(device, D, transposed, k, s, p, d):
    shape = SHAPES[D]
    x = random_tensor(3, shape, PER_SAMPLE[D], 2, seed=k * 10 + s, device=device)
    kk, ss, pp, dd = (k,) * D, (s,) * D, (p,) * D, (d,) * D
    if transposed:
        out_shape = Fs.conv_transpose_output_shape(shape, kk, ss, pp, dd)
    else:
        out_shape = Fs.conv_output_shape(shape, kk, ss, pp, dd)
    results = {}
    for method in ("dense", "hash", "auto"):
        out_idx = Fs.conv_out_indices(x.indices, 3, shape, out_shape, kk, ss, pp, dd, transposed, method=method)
        nbr = Fs.kernel_map(x.indices, out_idx, 3, shape, kk, ss, pp, dd, transposed, method=method)
        results[method] = (out_idx.cpu(), nbr.cpu())
    for method in ("hash", "auto"):
        assert torch.equal(results[method][0], results["dense"][0]), f"out indices differ for method {method}"
        assert torch.equal(results[method][1], results["dense"][1]), f"kernel maps differ for method {method}"
    out_idx, nbr = results["dense"]
    # output sites sorted by linear index, unique
    assert torch.equal(linear_order(out_idx, out_shape), torch.arange(out_idx.shape[0]))
    expected = _python_kernel_map(x.indices.cpu(), out_idx, shape, kk, ss, pp, dd, transposed)
    assert torch.equal(nbr, expected)
    # every output site is fed by at least one input (that is what makes it an output site)
    assert bool((nbr >= 0).any(1).all())


@pytest.mark.parametrize("D", [2, 3])
def test_kernel_map_transpose_and_subset(device, D):
    shape = SHAPES[D]
    x = random_tensor(1, shape, PER_SAMPLE[D], 2, seed=3, device=device)
    km = Fs.build_kernel_map(x, "conv", 3, 2, 1, 1)
    nbr, nbr_t = km.neighbors.cpu(), km.neighbors_t.cpu()
    assert nbr_t.shape == (x.indices.shape[0], 3 ** D)
    expected = torch.full_like(nbr_t, -1)
    for o, t in (nbr >= 0).nonzero().tolist():
        expected[nbr[o, t], t] = o
    assert torch.equal(nbr_t, expected)
    # a map restricted to some output sites is those rows of the full map
    rows = torch.tensor([0, 3, 5, km.out_indices.shape[0] - 1])
    sub = Fs.kernel_map(x.indices, km.out_indices[rows.to(device)].contiguous(), 1, shape, 3, 2, 1, 1)
    assert torch.equal(sub.cpu(), nbr[rows])


# K = 9 and 27 sort 32-bit keys on CUDA, K = 49 64-bit ones (the sort covers the mask's K bits only)
@pytest.mark.parametrize("shape,k", [(SHAPES[2], 3), ((5, 6, 7), 3), ((12, 11), 7)], ids=["2d-k3", "3d-k3", "2d-k7"])
def test_kernel_map_order_groups_rows_by_offset_mask(device, shape, k):
    x = random_tensor(2, shape, 40, 3, seed=8, device=device)
    km = Fs.build_kernel_map(x, "subm", k)
    K = km.kernel_volume
    order = ops.sparse_kernel_map_order(km.neighbors).cpu().long()
    nbr = km.neighbors.cpu()
    assert torch.equal(torch.sort(order).values, torch.arange(nbr.shape[0]))
    masks = ((nbr >= 0).long() << torch.arange(K)).sum(1)
    m = masks[order]
    assert bool((m[1:] >= m[:-1]).all())  # ascending masks
    same = m[1:] == m[:-1]
    assert bool((order[1:][same] > order[:-1][same]).all())  # stable
    assert len(set(masks.tolist())) > 3  # rows with different masks: the test sorts something
    # the order changes nothing but the speed
    w = random_weight(4, (k,) * x.ndim, 3, device=device)
    a = ops.sparse_conv(x.features, w.reshape(4, K, 3), km.neighbors)
    b = ops.sparse_conv(x.features, w.reshape(4, K, 3), km.neighbors, ops.sparse_kernel_map_order(km.neighbors))
    torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("from_call", [2, 3])
def test_layer_order_from_its_call_on(device, from_call, monkeypatch):
    # a map's first layer calls run without the row order (on CUDA it would cost more launches than it saves an
    # eager forward); the ORDER_FROM_CALL-th layer call on the same map makes it once and uses it, as every later
    # call does; the layers' results are those with the order
    from lidarops.sparse import tensor as sparse_tensor
    monkeypatch.setattr(sparse_tensor, "ORDER_FROM_CALL", from_call)
    x = random_tensor(2, SHAPES[2], 60, 8, seed=21, dtype=torch.float32, device=device)
    layers = [spnn.SubMConv2d(8, 8, 3, bias=False, indice_key="s").to(device) for _ in range(from_call + 1)]
    with torch.no_grad():
        ys, y = [], x
        for i, layer in enumerate(layers, 1):
            y = layer(y)
            ys.append(y)
            km = y.indice_dict["s"]
            assert (km._order is not None) == (device == "cuda" and i >= from_call), i  # CPU: never
        if device == "cuda":
            assert torch.equal(km._order, ops.sparse_kernel_map_order(km.neighbors))
        ref = x.features
        for layer, y in zip(layers, ys):
            ref = ops.sparse_conv(ref, layer.weight.reshape(8, 9, 8), km.neighbors, km.order)
            torch.testing.assert_close(y.features, ref, rtol=1e-5, atol=1e-5)


@requires_cuda
def test_layer_order_not_made_while_capturing():
    # the order made inside a capture would be an output of the graph, unwritten until a replay
    x = random_tensor(1, SHAPES[2], 60, 8, seed=22, dtype=torch.float32, device="cuda")
    conv = spnn.SubMConv2d(8, 8, 3, bias=False, indice_key="s").cuda()
    with torch.no_grad():
        y = conv(x)  # the map, built eagerly; its first layer
        km = y.indice_dict["s"]
        graph = torch.cuda.CUDAGraph()
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side), torch.cuda.graph(graph):
            z = conv(y)
        torch.cuda.current_stream().wait_stream(side)
        assert km._order is None
        graph.replay()
        torch.cuda.synchronize()
        ref = ops.sparse_conv(y.features, conv.weight.reshape(8, 9, 8), km.neighbors)
    torch.testing.assert_close(z.features, ref, rtol=1e-5, atol=1e-5)


# ================================================================================================
# Convolutions against dense PyTorch (float64)
# ================================================================================================

@pytest.mark.parametrize("batch", [1, 3])
@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("k,s,p,d", GEOMETRY, ids=[_id(*g) for g in GEOMETRY])
def test_regular_conv_matches_dense(device, D, batch, k, s, p, d):
    shape = SHAPES[D]
    x = random_tensor(batch, shape, PER_SAMPLE[D], 3, seed=k + 3 * s + 7 * p, device=device)
    w = random_weight(4, (k,) * D, 3, seed=d, device=device)
    bias = torch.randn(4, dtype=torch.float64, device=device)
    y = Fs.conv(x, w, bias, "conv", stride=s, padding=p, dilation=d)
    assert y.spatial_shape == list(Fs.conv_output_shape(shape, k, s, p, d))
    ref_i, ref_f = Fs._conv_reference(x, w, bias, "conv", s, p, d)
    assert_same_sites_and_features(y.indices, y.features, ref_i, ref_f, y.spatial_shape, TOL[torch.float64],
                                   "regular conv")


@pytest.mark.parametrize("batch", [1, 3])
@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("k,s,p,d", GEOMETRY, ids=[_id(*g) for g in GEOMETRY])
def test_transposed_conv_matches_dense(device, D, batch, k, s, p, d):
    shape = tuple(max(2, n // 2) for n in SHAPES[D])
    x = random_tensor(batch, shape, PER_SAMPLE[D] // 3, 3, seed=k + 5 * s + p, device=device)
    w = random_weight(2, (k,) * D, 3, seed=d + 1, device=device)
    y = Fs.conv(x, w, None, "transposed", stride=s, padding=p, dilation=d)
    assert y.spatial_shape == list(Fs.conv_transpose_output_shape(shape, k, s, p, d))
    ref_i, ref_f = Fs._conv_reference(x, w, None, "transposed", s, p, d)
    assert_same_sites_and_features(y.indices, y.features, ref_i, ref_f, y.spatial_shape, TOL[torch.float64],
                                   "transposed conv")


@pytest.mark.parametrize("D", [2, 3])
def test_transposed_conv_output_padding(device, D):
    shape = tuple(max(2, n // 2) for n in SHAPES[D])
    x = random_tensor(2, shape, 10, 3, seed=1, device=device)
    w = random_weight(2, (3,) * D, 3, device=device)
    y = Fs.conv(x, w, None, "transposed", stride=2, padding=1, output_padding=1)
    ref_i, ref_f = Fs._conv_reference(x, w, None, "transposed", 2, 1, 1, output_padding=1)
    assert_same_sites_and_features(y.indices, y.features, ref_i, ref_f, y.spatial_shape, TOL[torch.float64],
                                   "transposed conv, output_padding 1")


@pytest.mark.parametrize("batch", [1, 3])
@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("k", [1, 2, 3])
@pytest.mark.parametrize("d", [1, 2])
def test_submanifold_conv_matches_dense(device, D, batch, k, d):
    shape = SHAPES[D]
    x = random_tensor(batch, shape, PER_SAMPLE[D], 3, seed=k + d, device=device)
    w = random_weight(5, (k,) * D, 3, seed=k, device=device)
    bias = torch.randn(5, dtype=torch.float64, device=device)
    y = Fs.conv(x, w, bias, "subm", dilation=d)
    assert y.indices is x.indices and y.spatial_shape == x.spatial_shape
    ref_i, ref_f = Fs._conv_reference(x, w, bias, "subm", dilation=d)
    assert_same_sites_and_features(y.indices, y.features, ref_i[linear_order(ref_i, shape)],
                                   ref_f[linear_order(ref_i, shape)], shape, TOL[torch.float64], "submanifold conv")


@pytest.mark.parametrize("batch", [1, 3])
@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("k,s,p,d", [g for g in GEOMETRY if g[0] > 1 or g[1] > 1],
                         ids=[_id(*g) for g in GEOMETRY if g[0] > 1 or g[1] > 1])
def test_inverse_conv_returns_to_input_sites(device, D, batch, k, s, p, d):
    shape = SHAPES[D]
    x = random_tensor(batch, shape, PER_SAMPLE[D], 3, seed=2 * k + s, device=device)
    w_down = random_weight(4, (k,) * D, 3, seed=1, device=device)
    w_up = random_weight(2, (k,) * D, 4, seed=2, device=device)
    y = Fs.conv(x, w_down, None, "conv", stride=s, padding=p, dilation=d, indice_key="down")
    z = Fs.conv(y, w_up, None, "inverse", indice_key="down")
    assert torch.equal(z.indices.cpu(), x.indices.cpu()), "inverse conv must return to the input rows, in order"
    assert z.spatial_shape == x.spatial_shape
    ref_i, ref_f = Fs._conv_reference(y, w_up, None, "inverse", inverse_of=y.indice_dict["down"])
    order = linear_order(ref_i, shape)
    assert_same_sites_and_features(z.indices, z.features, ref_i[order], ref_f[order], shape, TOL[torch.float64],
                                   "inverse conv")


@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("k,s,p,d", [(2, 2, 0, 1), (3, 2, 1, 1), (3, 1, 1, 1), (2, 1, 1, 2), (3, 3, 1, 1)])
@pytest.mark.parametrize("batch", [1, 3])
def test_max_pool_matches_dense(device, D, k, s, p, d, batch):
    shape = SHAPES[D]
    x = random_tensor(batch, shape, PER_SAMPLE[D], 4, seed=k + s, device=device)
    x = x.replace_feature(x.features - 3.0)  # mostly negative: absent sites must not count as zeros
    y = Fs.max_pool(x, k, s, p, d)
    ref_i, ref_f = Fs._max_pool_reference(x, k, s, p, d)
    assert_same_sites_and_features(y.indices, y.features, ref_i, ref_f, y.spatial_shape, 0.0, "max pool")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16], ids=["f32", "f16", "bf16"])
@pytest.mark.parametrize("kind", ["subm", "conv", "transposed"])
def test_low_precision_matches_float64_reference(device, dtype, kind):
    D, shape = 3, SHAPES[3]
    x = random_tensor(2, shape, 60, 16, seed=5, dtype=dtype, device=device)
    w = random_weight(16, (3, 3, 3), 16, seed=6, dtype=dtype, device=device)
    w = w / 8
    y = Fs.conv(x, w, None, kind, stride=2 if kind != "subm" else 1, padding=1)
    assert y.features.dtype == dtype
    x64 = SparseConvTensor(x.features.double(), x.indices, shape, 2)
    ref_i, ref_f = Fs._conv_reference(x64, w.double(), None, kind, 2 if kind != "subm" else 1, 1)
    if kind == "subm":
        order = linear_order(ref_i, shape)
        ref_i, ref_f = ref_i[order], ref_f[order]
    assert_same_sites_and_features(y.indices, y.features, ref_i, ref_f, y.spatial_shape, TOL[dtype], f"{kind} {dtype}")


@pytest.mark.parametrize("amp", [torch.float16, torch.bfloat16], ids=["f16", "bf16"])
@pytest.mark.parametrize("features_dtype", [torch.float32, torch.bfloat16, torch.float64], ids=["f32", "bf16", "f64"])
def test_autocast_runs_in_the_autocast_dtype(device, amp, features_dtype):
    """Under torch.autocast a layer runs in the autocast dtype, as F.conv2d does: float32 weights with
    features of either precision, the same numbers as casting both by hand, gradients back to the
    float32 weight; float64 stays float64 (and its mismatch with float32 weights stays an error)."""
    if device == "cpu" and amp == torch.float16 and features_dtype != torch.float64:
        pytest.skip("CPU autocast to float16 is slow and adds nothing to the bfloat16 case")
    x = random_tensor(2, SHAPES[2], 40, 8, seed=11, dtype=features_dtype, device=device)
    w = (random_weight(12, (3, 3), 8, seed=12, dtype=torch.float32, device=device) / 8).requires_grad_()
    b = torch.randn(12, device=device)
    with torch.autocast(device, dtype=amp):
        if features_dtype == torch.float64:
            with pytest.raises(ValueError, match="must match the features"):
                Fs.conv(x, w, b, "subm")
            y64 = Fs.conv(x, w.detach().double(), b.double(), "subm")
            assert y64.features.dtype == torch.float64
            return
        y = Fs.conv(x, w, b, "conv", stride=2, padding=1)
    assert y.features.dtype == amp
    xa = x.replace_feature(x.features.to(amp))
    want = Fs.conv(xa, w.detach().to(amp), b.to(amp), "conv", stride=2, padding=1)
    assert torch.equal(y.indices, want.indices)
    assert torch.equal(y.features, want.features)
    y.features.float().sum().backward()
    assert w.grad is not None and w.grad.dtype == torch.float32 and w.grad.abs().sum() > 0


def test_noncontiguous_features_and_weight(device):
    x = random_tensor(2, SHAPES[2], 30, 6, seed=9, device=device)
    wide = torch.randn(x.features.shape[0], 12, dtype=torch.float64, device=device)
    wide[:, ::2] = x.features
    xs = x.replace_feature(wide[:, ::2])
    assert not xs.features.is_contiguous()
    w = random_weight(4, (3, 3), 6, device=device)
    w_nc = w.permute(3, 1, 2, 0).contiguous().permute(3, 1, 2, 0)
    assert not w_nc.is_contiguous()
    y1 = Fs.conv(x, w, None, "conv", stride=2, padding=1)
    y2 = Fs.conv(xs, w_nc, None, "conv", stride=2, padding=1)
    assert torch.equal(y1.indices, y2.indices)
    torch.testing.assert_close(y1.features, y2.features, rtol=0, atol=1e-12)


# ================================================================================================
# Gradients
# ================================================================================================

@pytest.mark.parametrize("kind", ["subm", "conv", "transposed", "inverse"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradcheck_conv(device, kind, seed):
    D, shape = 2, (6, 5)
    x = random_tensor(2, shape, 8, 3, seed=seed, device=device)
    if kind == "inverse":
        x = Fs.conv(x, random_weight(3, (3, 3), 3, seed=seed, device=device), None, "conv", stride=2, padding=1,
                    indice_key="k")
    w = random_weight(2, (3, 3), 3, seed=seed, device=device).requires_grad_()
    b = torch.randn(2, dtype=torch.float64, device=device, requires_grad=True)
    f = x.features.detach().clone().requires_grad_()

    def fn(feats, weight, bias):
        return Fs.conv(x.replace_feature(feats), weight, bias, kind, stride=2, padding=1, indice_key="k").features

    assert torch.autograd.gradcheck(fn, (f, w, b))
    assert torch.autograd.gradgradcheck(fn, (f, w, b))


@pytest.mark.parametrize("seed", [0, 1])
def test_gradcheck_max_pool(device, seed):
    x = random_tensor(2, (6, 5), 12, 3, seed=seed, device=device)
    f = x.features.detach().clone().requires_grad_()
    fn = lambda feats: Fs.max_pool(x.replace_feature(feats), 3, 2, 1).features  # noqa: E731
    assert torch.autograd.gradcheck(fn, (f,))
    assert torch.autograd.gradgradcheck(fn, (f,))


def test_conv_gradients_match_dense_autograd(device):
    D, shape = 3, SHAPES[3]
    x = random_tensor(2, shape, 40, 3, seed=4, device=device)
    w = random_weight(4, (3, 3, 3), 3, seed=4, device=device)
    f1, w1 = x.features.clone().requires_grad_(), w.clone().requires_grad_()
    y = Fs.conv(x.replace_feature(f1), w1, None, "conv", stride=2, padding=1)
    g = torch.randn_like(y.features)
    (y.features * g).sum().backward()
    f2, w2 = x.features.clone().requires_grad_(), w.clone().requires_grad_()
    ref_i, ref_f = Fs._conv_reference(x.replace_feature(f2), w2, None, "conv", 2, 1, 1)
    order = linear_order(y.indices, y.spatial_shape)
    (ref_f * g[order]).sum().backward()
    torch.testing.assert_close(f1.grad, f2.grad, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(w1.grad, w2.grad, rtol=1e-10, atol=1e-10)


# ================================================================================================
# Registered-op checks, torch.compile
# ================================================================================================

def _map_conv_reference(features, weight, kernel_map):
    """out[o] = sum_k weight[:, k, :] @ features[kernel_map[o, k]], in plain PyTorch (-1: no input)."""
    padded = torch.cat([features, features.new_zeros(1, features.shape[1])])
    rows = torch.where(kernel_map >= 0, kernel_map.long(), features.shape[0])
    return torch.einsum("okc,dkc->od", padded[rows], weight)


def _op_args(device):
    x = random_tensor(2, (6, 5), 10, 3, seed=0, device=device)
    km = Fs.build_kernel_map(x, "conv", 3, 2, 1, 1)
    return x, km


def test_opcheck_all_sparse_ops(device):
    x, km = _op_args(device)
    shape, K = x.spatial_shape, km.neighbors.shape[1]
    w = random_weight(4, (K,), 3, device=device).requires_grad_()
    f = x.features.clone().requires_grad_()
    g = torch.randn(km.out_indices.shape[0], 4, dtype=torch.float64, device=device)
    checks = [
        (ops.sparse_kernel_map, (x.indices, km.out_indices, 2, shape, [3, 3], [2, 2], [1, 1], [1, 1], False, True, 0)),
        (ops.sparse_kernel_map_transpose, (km.neighbors, x.indices.shape[0])),
        (ops.sparse_kernel_map_order, (km.neighbors,)),
        (ops.sparse_conv, (f, w, km.neighbors)),
        (ops.sparse_conv, (f, w, km.neighbors, ops.sparse_kernel_map_order(km.neighbors))),
        (ops.sparse_conv, (f, w, km.neighbors, None, "mma_sync", 2)),
        (ops.sparse_conv_weight_grad, (f, g.requires_grad_(), km.neighbors)),
        (ops.sparse_max_pool, (f, km.neighbors)),
        (ops.sparse_to_dense, (f, x.indices, 2, shape)),
        (ops.sparse_from_dense, (x.dense().requires_grad_(), x.indices)),
    ]
    out, arg = ops.sparse_max_pool(x.features, km.neighbors)
    checks.append((ops.sparse_max_pool_backward, (g[:, :3].contiguous(), arg, km.neighbors_t)))
    for op, args in checks:
        torch.library.opcheck(op, args)
    # data-dependent output size: the dynamic-shape AOT test does not apply
    torch.library.opcheck(ops.sparse_conv_out_indices,
                          (x.indices, 2, shape, list(km.out_spatial_shape), [3, 3], [2, 2], [1, 1], [1, 1], False, 0),
                          test_utils=("test_schema", "test_faketensor"))


def test_compile_fullgraph_sparse_conv(device):
    x, km = _op_args(device)
    w = random_weight(4, (9,), 3, device=device)

    @torch.compile(fullgraph=True, backend="aot_eager")
    def f(feats, weight, nbr):
        return torch.relu(ops.sparse_conv(feats, weight, nbr)) * 2.0

    torch.testing.assert_close(f(x.features, w, km.neighbors), torch.relu(ops.sparse_conv(x.features, w, km.neighbors)) * 2.0)


def test_compile_fullgraph_sparse_conv_backward(device):
    """The C++ autograd kernel traced by AOTAutograd gives the eager gradients, which match the reference."""
    x, km = _op_args(device)
    w = random_weight(4, (3, 3), 3, device=device).reshape(4, 9, 3)
    feats = x.features.detach()
    g = torch.randn(km.neighbors.shape[0], 4, dtype=torch.float64, generator=torch.Generator().manual_seed(3)).to(device)

    def loss(fn, f, ww):
        f, ww = f.clone().requires_grad_(), ww.clone().requires_grad_()
        (fn(f, ww) * g).sum().backward()
        return f.grad, ww.grad

    compiled = torch.compile(lambda f, ww: torch.relu(ops.sparse_conv(f, ww, km.neighbors)), fullgraph=True,
                             backend="aot_eager")
    got = loss(compiled, feats, w)
    want = loss(lambda f, ww: torch.relu(_map_conv_reference(f, ww, km.neighbors)), feats, w)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)


def test_compile_dynamic_shapes_through_cpp_autograd(device):
    """Point clouds change size every frame: with dynamic shapes, the C++ autograd kernels of sparse_conv,
    sparse_to_dense and sparse_from_dense trace and give the reference gradients for two sizes."""
    @torch.compile(fullgraph=True, backend="aot_eager", dynamic=True)
    def f(feats, weight, nbr, indices):
        dense = ops.sparse_to_dense(ops.sparse_conv(feats, weight, nbr), indices, 2, [3, 3])
        return ops.sparse_from_dense(dense * dense, indices)

    def reference(feats, weight, nbr, indices):
        out = _map_conv_reference(feats, weight, nbr)
        return out * out  # to_dense then from_dense at the same (unique) sites is the identity

    for per_sample in (6, 9):
        x = random_tensor(2, (6, 5), per_sample, 3, seed=per_sample, device=device)
        km = Fs.build_kernel_map(x, "conv", 3, 2, 1, 1)
        w = random_weight(4, (9,), 3, device=device)
        out_idx = km.out_indices
        grads = []
        for fn in (f, reference):
            feats, weight = x.features.clone().requires_grad_(), w.clone().requires_grad_()
            fn(feats, weight, km.neighbors, out_idx).sum().backward()
            grads.append((feats.grad, weight.grad))
        for a, b in zip(*grads):
            torch.testing.assert_close(a, b)


# ================================================================================================
# Empty and bad inputs
# ================================================================================================

@pytest.mark.parametrize("D", [2, 3])
def test_empty_tensor_every_kind(device, D):
    shape = SHAPES[D]
    x = SparseConvTensor(torch.zeros(0, 3, dtype=torch.float64, device=device, requires_grad=True),
                         torch.zeros(0, D + 1, dtype=torch.int32, device=device), shape, 2)
    w = random_weight(4, (3,) * D, 3, device=device).requires_grad_()
    for kind in ("subm", "conv", "transposed"):
        y = Fs.conv(x, w, None, kind, stride=2 if kind != "subm" else 1, padding=1, indice_key="k" + kind)
        assert y.features.shape == (0, 4) and y.indices.shape == (0, D + 1)
        y.features.sum().backward()
        assert w.grad is not None and bool((w.grad == 0).all())
        assert y.dense().shape == (2, 4, *y.spatial_shape)
    y = Fs.conv(x, w, None, "conv", stride=2, padding=1, indice_key="down")
    z = Fs.conv(y.replace_feature(y.features.new_zeros(0, 3)), w, None, "inverse", indice_key="down")
    assert z.features.shape == (0, 4)
    p = Fs.max_pool(x, 2)
    assert p.features.shape == (0, 3)


def test_duplicate_coordinates_raise(device):
    idx = torch.tensor([[0, 1, 2], [0, 3, 3], [1, 1, 2], [0, 1, 2]], dtype=torch.int32, device=device)
    x = SparseConvTensor(torch.randn(4, 2, device=device), idx, [5, 5], 2)
    w = torch.randn(3, 3, 3, 2, device=device)
    for method in ("dense", "hash"):
        with pytest.raises(ValueError, match=r"indices rows 0 and 3 both hold .*\(0, 1, 2\).*unique"):
            Fs.conv(x, w, None, "subm", method=method)
        with pytest.raises(ValueError, match=r"rows 0 and 3"):
            Fs.conv(x, w, None, "conv", stride=2, method=method)


@pytest.mark.parametrize("bad_row,what", [([0, 5, 1], "coordinate = shape"), ([0, -1, 1], "negative"),
                                          ([2, 1, 1], "batch = batch_size"), ([-1, 1, 1], "negative batch")])
def test_out_of_range_coordinates_raise(device, bad_row, what):
    idx = torch.tensor([[0, 1, 2], bad_row, [1, 0, 0]], dtype=torch.int32, device=device)
    x = SparseConvTensor(torch.randn(3, 2, device=device), idx, [5, 4], 2)
    w = torch.randn(3, 3, 3, 2, device=device)
    for kind in ("subm", "conv", "transposed"):
        with pytest.raises(ValueError, match=r"indices row 1 .* lies outside batch_size 2 / spatial_shape \[5, 4\]"):
            Fs.conv(x, w, None, kind, stride=1 if kind == "subm" else 2)


def test_bad_arguments_raise(device):
    idx = torch.tensor([[0, 1, 2], [0, 3, 3]], dtype=torch.int32, device=device)
    f = torch.randn(2, 2, device=device)
    with pytest.raises(ValueError, match="indices must be an integer tensor"):
        SparseConvTensor(f, idx.float(), [5, 5], 1)
    assert SparseConvTensor(f, idx.long(), [5, 5], 1).indices.dtype == torch.int32  # range-checked, then converted
    with pytest.raises(ValueError, match=r"indices must be \(N, 1 \+ D\)"):
        SparseConvTensor(f, idx[:, 0], [5, 5], 1)
    with pytest.raises(ValueError, match="spatial_shape must hold 2 positive ints"):
        SparseConvTensor(f, idx, [5, 5, 5], 1)
    with pytest.raises(ValueError, match=r"features must be \(N, C\) with N = 2"):
        SparseConvTensor(f[:1], idx, [5, 5], 1)
    x = SparseConvTensor(f, idx, [5, 5], 1)
    with pytest.raises(ValueError, match="features must be floating point"):
        Fs.conv(x.replace_feature(f.long()), torch.randn(3, 3, 3, 2, device=device).long(), kind="subm")
    with pytest.raises(ValueError, match=r"weight .* must match the features"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device, dtype=torch.float64), kind="subm")
    with pytest.raises(ValueError, match=r"weight must be \(Cout, \*kernel \(2 dims\), Cin = 2\)"):
        Fs.conv(x, torch.randn(3, 3, 3, 4, device=device), kind="subm")
    with pytest.raises(ValueError, match="kind must be one of"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device), kind="dilated")
    with pytest.raises(ValueError, match="method must be one of"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device), kind="conv", method="tree")
    with pytest.raises(ValueError, match="stride entries must be >= 1"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device), kind="conv", stride=0)
    with pytest.raises(ValueError, match="leaves no output site"):
        Fs.conv(x, torch.randn(3, 7, 7, 2, device=device), kind="conv")
    with pytest.raises(ValueError, match="needs the indice_key"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device), kind="inverse")
    with pytest.raises(ValueError, match="'nope' is not in this tensor's indice_dict"):
        Fs.conv(x, torch.randn(3, 3, 3, 2, device=device), kind="inverse", indice_key="nope")
    nbr = torch.tensor([[0, 5]], dtype=torch.int32, device=device)
    with pytest.raises(ValueError, match=r"neighbors must lie in \[-1, 2\)"):
        Fs.sparse_conv(f, torch.randn(3, 2, 2, device=device), nbr)
    with pytest.raises(ValueError, match="neighbors must be an \\(N_out, K\\) int32"):
        Fs.sparse_conv(f, torch.randn(3, 2, 2, device=device), nbr.long())
    # the raw ops validate too (ValueError from C++)
    with pytest.raises(ValueError, match="kernel_map must be \\(N_out, K\\) int32"):
        ops.sparse_conv(f, torch.randn(3, 2, 2, device=device), nbr.long())
    with pytest.raises(ValueError, match="weight expects Cin = 3"):
        ops.sparse_conv(f, torch.randn(3, 2, 3, device=device), nbr.clamp_max(1))


def test_bad_algo_raises(device):
    x = random_tensor(1, (8, 8), 20, 2, seed=0, dtype=torch.float32, device=device)
    w = torch.randn(3, 3, 3, 2, device=device)
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    w3 = w.reshape(3, 9, 2)
    allowed = r"algo must be one of \('auto', 'mma_sync', 'wgmma_2blocks', 'wgmma_3blocks', '3xtf32'\), got 'fast'"
    with pytest.raises(ValueError, match=allowed):
        Fs.conv(x, w, kind="subm", algo="fast")
    with pytest.raises(ValueError, match=allowed):
        Fs.sparse_conv(x.features, w3, km.neighbors, algo="fast")
    with pytest.raises(ValueError, match=allowed):
        spnn.SubMConv2d(2, 3, 3, algo="fast")
    with pytest.raises(ValueError, match="algo must be one of"):
        spnn.SparseConv2d(2, 3, 3, algo=None)
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match=r"splits must be an int >= 0 \(0: chosen per layer\), got"):
            Fs.sparse_conv(x.features, w3, km.neighbors, splits=bad)
    # the raw ops check them on every device (ValueError from C++), after the tensors
    with pytest.raises(ValueError, match="algo must be one of 'auto', 'mma_sync', 'wgmma_2blocks', 'wgmma_3blocks', "
                                         "'3xtf32', got 'fast'"):
        ops.sparse_conv(x.features, w3, km.neighbors, None, "fast")
    with pytest.raises(ValueError, match=r"splits must be >= 0 \(0: chosen per layer\), got -1"):
        ops.sparse_conv_affine(x.features, w3, km.neighbors, None, None, None, False, "auto", -1)
    with pytest.raises(ValueError, match="weight expects Cin = 1"):
        ops.sparse_conv(x.features, w3[:, :, :1].contiguous(), km.neighbors, None, "fast")


@pytest.mark.parametrize("algo", Fs.CONV_ALGOS)
def test_every_algo_gives_the_same_convolution(device, algo):
    """Every kernel choice (and forced offset splits) computes the same sums: bit for bit on the CPU,
    which has one algorithm; to float32's tolerance on CUDA (TF32 is off, so "3xtf32" picks the 3xTF32
    kernel there). The modules pass their ``algo`` on, and the features gradient (a convolution over the
    transposed map) takes it too."""
    x = random_tensor(2, (40, 40), 300, 32, seed=4, dtype=torch.float32, device=device)
    w = (random_weight(48, (3, 3), 32, seed=4, dtype=torch.float32, device=device) / 8)
    ref = Fs.conv(x, w, None, "subm")
    scale = max(1.0, ref.features.abs().max().item())
    exact = device == "cpu"
    for splits in (0, 2):
        km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
        got = Fs.sparse_conv(x.features, w, km.neighbors, km.order, algo=algo, splits=splits)
        diff = (got.double() - ref.features.double()).abs().max().item()
        assert diff == 0 if exact else diff <= 2e-5 * scale, (splits, diff)
    layer = spnn.SubMConv2d(32, 48, 3, bias=False, algo=algo).to(device)
    assert layer.algo == algo and ("algo=" in repr(layer)) == (algo != "auto")
    with torch.no_grad():
        layer.weight.copy_(w)
    f = x.features.clone().requires_grad_()
    y = layer(x.replace_feature(f))
    diff = (y.features.double() - ref.features.double()).abs().max().item()
    assert diff == 0 if exact else diff <= 2e-5 * scale
    y.features.square().sum().backward()
    f_ref = x.features.clone().requires_grad_()
    Fs.conv(x.replace_feature(f_ref), w, None, "subm").features.square().sum().backward()
    gscale = max(1.0, f_ref.grad.abs().max().item())
    gdiff = (f.grad - f_ref.grad).abs().max().item()
    assert gdiff == 0 if exact else gdiff <= 1e-4 * gscale


def test_indice_key_reuse_rules(device):
    x = random_tensor(1, SHAPES[3], 40, 3, seed=0, device=device)
    w = random_weight(3, (3, 3, 3), 3, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="subm1")
    km = y.indice_dict["subm1"]
    assert "subm1" not in x.indice_dict  # the output gets a new dict, as in spconv
    z = Fs.conv(y, w, None, "subm", indice_key="subm1")
    assert z.indice_dict["subm1"] is km  # reused, not rebuilt
    with pytest.raises(ValueError, match="indice_key 'subm1' holds the kernel map of a subm layer"):
        Fs.conv(z, random_weight(3, (5, 5, 5), 3, device=device), None, "subm", indice_key="subm1")
    with pytest.raises(ValueError, match="does not fit this conv layer"):
        Fs.conv(z, w, None, "conv", stride=2, indice_key="subm1")
    down = Fs.conv(z, w, None, "conv", stride=2, padding=1, indice_key="down")
    with pytest.raises(ValueError, match="inverse convolution has kernel"):
        Fs.conv(down, random_weight(3, (2, 2, 2), 3, device=device), None, "inverse", indice_key="down")
    with pytest.raises(ValueError, match="holds a subm kernel map"):
        Fs.conv(down, w, None, "inverse", indice_key="subm1")


# ================================================================================================
# CUDA: parity with CPU, TF32
# ================================================================================================

_cuda = pytest.mark.skipif(not CUDA_OK, reason="needs a GPU and lidarops built with CUDA kernels")


@_cuda
@pytest.mark.parametrize("D", [2, 3])
@pytest.mark.parametrize("method", ["dense", "hash"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16],
                         ids=["f64", "f32", "f16", "bf16"])
def test_cpu_cuda_parity(D, method, dtype):
    shape = SHAPES[D]
    x = random_tensor(3, shape, PER_SAMPLE[D], 32, seed=12, dtype=dtype)
    w = random_weight(48, (3,) * D, 32, seed=12, dtype=dtype) / 16
    xc = SparseConvTensor(x.features.cuda(), x.indices.cuda(), shape, 3)
    for kind in ("subm", "conv", "transposed"):
        s = 1 if kind == "subm" else 2
        a = Fs.conv(x, w, None, kind, stride=s, padding=1, method=method)
        b = Fs.conv(xc, w.cuda(), None, kind, stride=s, padding=1, method=method)
        assert torch.equal(a.indices, b.indices.cpu()), f"{kind}: output sites differ between CPU and CUDA"
        km_a = Fs.build_kernel_map(x, kind, 3, s, 1, 1, method=method)
        km_b = Fs.build_kernel_map(xc, kind, 3, s, 1, 1, method=method)
        assert torch.equal(km_a.neighbors, km_b.neighbors.cpu()), f"{kind}: kernel maps differ"
        scale = max(1.0, a.features.double().abs().max().item())
        diff = (a.features.double() - b.features.double().cpu()).abs().max().item()
        assert diff <= 2 * TOL[dtype] * scale, f"{kind} {dtype}: CPU/CUDA max |diff| {diff:.3e}"
        pa, _ = ops.sparse_max_pool(x.features, km_a.neighbors)
        pb, _ = ops.sparse_max_pool(xc.features, km_b.neighbors)
        assert torch.equal(pa, pb.cpu())
    g = torch.randn(a.features.shape, dtype=torch.float64).to(dtype)
    wa = ops.sparse_conv_weight_grad(x.features, g, km_a.neighbors)
    wb = ops.sparse_conv_weight_grad(xc.features, g.cuda(), km_b.neighbors)
    scale = max(1.0, wa.double().abs().max().item())
    assert (wa.double() - wb.double().cpu()).abs().max().item() <= 2 * TOL[dtype] * scale


@_cuda
@pytest.mark.parametrize("cin,cout,D,ksize,sites,ordered", [
    (32, 8, 2, 3, 3000, True),       # 64 x 16 tiles (Cout <= 16), cp.async pipeline
    (20, 32, 2, 3, 3000, False),     # 64 x 32 tiles; Cin not a multiple of the 32-channel step
    (64, 64, 2, 3, 5000, True),      # 64 x 64 tiles
    (64, 100, 2, 3, 40000, True),    # many blocks; Cout not a multiple of the tile (or of 4)
    (16, 64, 3, 3, 4000, True),      # K = 27 (3D)
    (4, 10, 2, 1, 500, True),        # K = 1, one 4-channel copy per row
    (8, 16, 2, 7, 2000, True),       # K = 49 > 32: the general SIMT kernel
    (6, 12, 2, 3, 2000, True),       # Cin not a multiple of 4: the general SIMT kernel
])
def test_cuda_float32_tiles_match_float64(cin, cout, D, ksize, sites, ordered):
    """Every float32 CUDA tile configuration (and the fallbacks around it) against the float64 CPU
    product on the same kernel map, with and without the mask order; rows with no input stay 0."""
    shape = (400, 400) if D == 2 else (40, 40, 40)
    x = random_tensor(2, shape, sites // 2, cin, seed=sites + cin, dtype=torch.float32, device="cuda")
    km = Fs.build_kernel_map(x, "subm", ksize, 1, ksize // 2, 1)
    nbr = km.neighbors.clone()
    nbr[::7] = -1  # rows with no input at all
    w = random_weight(cout, (ksize,) * D, cin, seed=cin, dtype=torch.float32, device="cuda").reshape(cout, -1, cin)
    ref = ops.sparse_conv(x.features.double().cpu(), w.double().cpu(), nbr.cpu())
    order = ops.sparse_kernel_map_order(nbr) if ordered else None
    got = ops.sparse_conv(x.features, w, nbr, order).double().cpu()
    assert got.shape == ref.shape
    assert torch.all(got[::7] == 0)
    scale = max(1.0, ref.abs().max().item())
    assert (got - ref).abs().max().item() <= 2e-5 * scale


@_cuda
@pytest.mark.parametrize("mma", ["auto", "mma_sync", "wgmma_2blocks"])
@pytest.mark.parametrize("dtype", ["f16", "bf16", "tf32", "3xtf32"])
@pytest.mark.parametrize("cin,cout,D,sites", [(24, 100, 2, 20000), (64, 64, 2, 3000), (16, 32, 3, 4000),
                                              (32, 16, 2, 3000), (40, 17, 2, 5000), (128, 128, 2, 8000),
                                              (128, 128, 2, 2000), (32, 256, 2, 16000), (128, 72, 3, 3000)])
def test_cuda_tensor_core_pipeline_matches_float64(mma, dtype, cin, cout, D, sites):
    """The cp.async-fed tensor-core kernels (float16, bfloat16, TF32, and float32 as 3xTF32) against the
    float64 product of the same (rounded) inputs: several blocks, Cout not a multiple of the tile (and
    odd), Cin not a multiple of the 128-byte step, rows with no input. ``mma_sync`` forces the mma.sync
    kernel, which then takes every tile shape on a 132-multiprocessor GPU: 32 x 64 (20000 rows of 100
    channels, 8000 of 128), 64 x 64 (16000 rows of 256 channels), and 64 rows by 32 or 16 columns
    (Cout <= 32; 2000 rows of 128 channels). ``auto`` on an sm_90a build on a Hopper GPU gives the
    layers with Cout > 64 to the wgmma kernel (64 x 128 tiles in TF32, 64 x 64 in 16 bits; 72 columns:
    a partial second tile, K = 27), the others as ``mma_sync``. ``wgmma_2blocks`` is ``auto`` with the
    TF32 64 x 128 tiles in the configuration of layers with a full wave of them (two blocks per
    multiprocessor, four stages, one wgmma group in flight across steps). 3xTF32 (always on mma.sync)
    must be as accurate as float32."""
    algo = "3xtf32" if dtype == "3xtf32" else mma
    shape = (400, 400) if D == 2 else (40, 40, 40)
    dt = {"f16": torch.float16, "bf16": torch.bfloat16, "tf32": torch.float32, "3xtf32": torch.float32}[dtype]
    x = random_tensor(2, shape, sites // 2, cin, seed=sites + cin, dtype=dt, device="cuda")
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    nbr = km.neighbors.clone()
    nbr[::7] = -1
    w = (random_weight(cout, (3,) * D, cin, seed=cin, dtype=dt, device="cuda") / 8).reshape(cout, -1, cin)
    ref = ops.sparse_conv(x.features.double().cpu(), w.double().cpu(), nbr.cpu())
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = dtype == "tf32"
        got = ops.sparse_conv(x.features, w, nbr, ops.sparse_kernel_map_order(nbr), algo).double().cpu()
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    assert torch.all(got[::7] == 0)
    scale = max(1.0, ref.abs().max().item())
    tol = {"f16": 4e-3, "bf16": 3e-2, "tf32": 5e-3, "3xtf32": 2e-5}[dtype]
    assert (got - ref).abs().max().item() <= tol * scale


@_cuda
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32], ids=["f16", "bf16", "tf32"])
def test_cuda_hopper_builds_use_wgmma(dtype):
    """On a compute capability 9.0 GPU with an sm_90a build (setup.py builds 9.0 as 9.0a), tensor-core
    layers with Cout > 64 launch the wgmma kernel, and algo="mma_sync" the mma.sync kernel: the
    Hopper path cannot go dead unnoticed. The two give the same answer to the tolerance of the type."""
    import json
    from pathlib import Path
    import lidarops
    info = json.loads((Path(lidarops.__file__).parent / "_build_info.json").read_text())
    if torch.cuda.get_device_capability() != (9, 0) or "9.0a" not in info["arch_list"].split(";"):
        pytest.skip(f"needs compute capability 9.0 and an sm_90a build (arch list {info['arch_list']})")
    x = random_tensor(2, (200, 200), 3000, 128, seed=5, dtype=dtype, device="cuda")
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    w = (random_weight(128, (3, 3), 128, seed=5, dtype=dtype, device="cuda") / 8).reshape(128, -1, 128)
    order = ops.sparse_kernel_map_order(km.neighbors)

    def kernels(algo):
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA], acc_events=True) as prof:
            y = ops.sparse_conv(x.features, w, km.neighbors, order, algo)
            torch.cuda.synchronize()
        names = {e.name for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA}
        if not names:  # no kernel at all: CUPTI is unavailable (compute-sanitizer, another profiler)
            pytest.skip("the CUDA profiler records no kernels here")
        return y, {n for n in names if "conv_fwd" in n}

    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = True
        y_wg, names_wg = kernels("auto")
        y_sync, names_sync = kernels("mma_sync")
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    assert any("conv_fwd_wgmma_kernel" in n for n in names_wg), names_wg
    assert names_sync and all("conv_fwd_mma_kernel" in n for n in names_sync), names_sync
    scale = y_sync.double().abs().max().item()
    tol = {torch.float16: 4e-3, torch.bfloat16: 3e-2, torch.float32: 5e-3}[dtype]
    assert (y_wg.double() - y_sync.double()).abs().max().item() <= tol * scale


_SPLIT_ALGOS = {"fp32": torch.float32, "tf32": torch.float32, "3xtf32": torch.float32, "f16": torch.float16,
                "bf16": torch.bfloat16}


@_cuda
@pytest.mark.parametrize("precision", list(_SPLIT_ALGOS))
@pytest.mark.parametrize("splits", [0, 1, 2, 3, 9])
@pytest.mark.parametrize("cin,cout,D,sites", [(128, 128, 2, 1200), (32, 64, 3, 3000)])
def test_cuda_offset_splits_match_float64(precision, splits, cin, cout, D, sites):
    """Offset splits (split-K over the kernel offsets, for layers with too few tiles to fill the GPU)
    against the float64 product followed by the epilogue: the automatic choice (splits=0; on an H100 it
    splits the 2D layer's float32 kernels), forced 1, 2, 3 and 9 (more splits than most tiles have offsets:
    empty splits add zeros), 2D and 3D (K = 27), every pipelined kernel (FFMA tiles, TF32, 3xTF32,
    float16, bfloat16), with the fused scale, shift and ReLU applied once after the splits are added,
    and rows with no input at epi(0) exactly. Two calls give the same bits."""
    algo = "3xtf32" if precision == "3xtf32" else "auto"
    dt = _SPLIT_ALGOS[precision]
    shape = (48, 48) if D == 2 else (40, 40, 40)
    x = random_tensor(2, shape, sites // 2, cin, seed=sites + cin, dtype=dt, device="cuda")
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    nbr = km.neighbors.clone()
    nbr[::7] = -1
    w = (random_weight(cout, (3,) * D, cin, seed=cin, dtype=dt, device="cuda") / 8).reshape(cout, -1, cin)
    g = torch.Generator().manual_seed(cout)
    scale = (torch.rand(cout, generator=g) + 0.5).cuda()
    shift = torch.randn(cout, generator=g).cuda()
    ref = ops.sparse_conv(x.features.double().cpu(), w.double().cpu(), nbr.cpu())
    ref = (ref * scale.double().cpu() + shift.double().cpu()).clamp_min(0)
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = precision == "tf32"
        order = ops.sparse_kernel_map_order(nbr)
        got = ops.sparse_conv_affine(x.features, w, nbr, order, scale, shift, True, algo, splits)
        again = ops.sparse_conv_affine(x.features, w, nbr, order, scale, shift, True, algo, splits)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    assert got.dtype == dt and torch.equal(got, again)
    got = got.double().cpu()
    empty = shift.double().cpu().clamp_min(0).to(dt).double()
    assert torch.equal(got[::7], empty.expand(got[::7].shape[0], cout))
    tol = {"fp32": 2e-5, "tf32": 5e-3, "3xtf32": 2e-5, "f16": 4e-3, "bf16": 3e-2}[precision]
    assert (got - ref).abs().max().item() <= tol * max(1.0, ref.abs().max().item())


_NONFINITE = ([pytest.param("cpu", a, id=f"cpu-{a}") for a in ("f64", "f32", "f16", "bf16")]
              + [pytest.param("cuda", a, id=f"cuda-{a}", marks=_cuda)
                 for a in ("f64", "f32", "tf32", "3xtf32", "f16", "bf16")])


@pytest.mark.parametrize("dev,precision", _NONFINITE)
def test_conv_propagates_nan_and_inf(dev, precision):
    """Non-finite inputs against the dense float64 reference: NaN inputs (CUDA's own bit pattern
    0x7fff..., whose low bits a TF32 rounding by integer addition would carry into the sign, and a
    negative NaN) give NaN wherever their window reaches, a +inf input with positive weights gives
    +inf, every other output stays finite. The experimental 3xTF32 mode may give NaN where float32
    gives inf (it also multiplies inf by each weight's small part, which can be 0)."""
    dt = {"f64": torch.float64, "f32": torch.float32, "tf32": torch.float32, "3xtf32": torch.float32,
          "f16": torch.float16, "bf16": torch.bfloat16}[precision]
    bits, nan = {torch.float64: (torch.int64, 0x7FFFFFFFFFFFFFFF), torch.float32: (torch.int32, 0x7FFFFFFF),
                 torch.float16: (torch.int16, 0x7FFF), torch.bfloat16: (torch.int16, 0x7FFF)}[dt]
    shape = (40, 36)
    x = random_tensor(2, shape, 150, 40, seed=21)
    feats = x.features.to(dt)
    feats.view(bits)[3] = nan
    feats.view(bits)[50] = -1  # every bit set: a negative NaN
    feats[100] = float("inf")
    w = ((random_weight(24, (3, 3), 40, seed=21).abs() + 0.05) / 8).to(dt)  # positive: inf stays +inf
    xd = SparseConvTensor(feats.to(dev), x.indices.to(dev), list(shape), 2)
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = precision == "tf32"
        y = Fs.conv(xd, w.to(dev), None, "subm", algo="3xtf32" if precision == "3xtf32" else "auto")
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    got = y.features.double().cpu()[linear_order(y.indices, shape)]
    ref_i, ref = Fs._conv_reference(SparseConvTensor(feats.double(), x.indices, list(shape), 2), w.double(), None,
                                    "subm")
    ref = ref[linear_order(ref_i, shape)]
    inf = float("inf")
    assert ref.isnan().any() and (ref == inf).any() and ref.isfinite().any(), "the data must hold all three"
    assert got[ref.isfinite()].isfinite().all(), "finite outputs must stay finite"
    assert got[ref.isnan()].isnan().all(), "NaN must propagate"
    if precision == "3xtf32":
        assert not got[ref == inf].isfinite().any()
    else:
        assert (got[ref == inf] == inf).all(), "+inf must stay +inf"


@_cuda
def test_tf32_follows_torch_matmul_setting():
    x = random_tensor(2, SHAPES[3], 60, 32, seed=3, dtype=torch.float32, device="cuda")
    w = random_weight(32, (3, 3, 3), 32, seed=3, dtype=torch.float32, device="cuda") / 16
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = False
        exact = Fs.conv(x, w, None, "subm")
        torch.backends.cuda.matmul.allow_tf32 = True
        fast = Fs.conv(x, w, None, "subm")
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    x64 = SparseConvTensor(x.features.double(), x.indices, x.spatial_shape, 2)
    ref = Fs.conv(x64, w.double(), None, "subm").features.float()
    scale = ref.abs().max().item()
    assert (exact.features - ref).abs().max().item() <= 2e-5 * max(1.0, scale)
    assert (fast.features - ref).abs().max().item() <= 5e-3 * max(1.0, scale)
