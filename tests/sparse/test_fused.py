"""The fused inference convolution: ``sparse_conv_affine`` (a per-channel affine map and ReLU applied to
the convolution's float accumulator), its use by ``SparseSequential`` and the sparse PointPillars
backbone for conv -> BatchNorm (eval) -> ReLU, and the host-side shortcuts of eager inference.

References: the float64 product of the same (rounded) inputs on the CPU followed by the epilogue in
float64, and, for the networks, the same modules run unfused (with gradients enabled, which turns the
fusion off) or a hand-written BatchNorm.
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

import lidarops.compat.spconv as spconv
from lidarops.sparse import SparseConvTensor
from lidarops.sparse import nn as spnn
from lidarops.sparse import functional as Fs
from helpers.sparse import TOL, random_tensor, random_weight

ops = torch.ops.lidarops


def _reference(features, weight, nbr, scale, shift, relu):
    out = ops.sparse_conv(features.double().cpu(), weight.double().cpu(), nbr.cpu())
    if scale is not None:
        out = out * scale.double().cpu()
    if shift is not None:
        out = out + shift.double().cpu()
    return out.clamp_min(0) if relu else out


# kernel families on CUDA: (cin, cout) and dtype pick the general SIMT tiles (cin % 4 != 0), the
# float32 cp.async tiles, the tensor-core pipeline (cin a multiple of the vector) and the plain
# tensor-core kernel (float16 with cin % 8 != 0); every one runs on the CPU too
CASES = [(6, 10, torch.float32), (24, 100, torch.float32), (32, 64, torch.float16), (20, 48, torch.float16),
         (32, 40, torch.bfloat16), (16, 24, torch.float64), (64, 16, "tf32"), (48, 32, "3xtf32")]


@pytest.mark.parametrize("cin,cout,dtype", CASES, ids=[f"{a}-{b}-{c}".replace("torch.", "") for a, b, c in CASES])
@pytest.mark.parametrize("parts", ["scale+shift+relu", "shift+relu", "scale", "relu"])
def test_sparse_conv_affine_matches_float64(device, cin, cout, dtype, parts):
    if dtype in ("tf32", "3xtf32") and device == "cpu":
        pytest.skip("TF32 is a CUDA mode")
    algo = "3xtf32" if dtype == "3xtf32" else "auto"
    dt = torch.float32 if dtype in ("tf32", "3xtf32") else dtype
    x = random_tensor(2, (40, 40), 300, cin, seed=cin + cout, dtype=dt, device=device)
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    nbr = km.neighbors.clone()
    nbr[::7] = -1  # rows with no input: epi(0)
    w = (random_weight(cout, (3, 3), cin, seed=cout, dtype=dt, device=device) / 8).reshape(cout, 9, cin)
    g = torch.Generator().manual_seed(cin)
    scale = (torch.rand(cout, generator=g) + 0.5).to(device) if "scale" in parts else None
    shift = (torch.randn(cout, generator=g)).to(device) if "shift" in parts else None
    relu = "relu" in parts
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        torch.backends.cuda.matmul.allow_tf32 = dtype == "tf32"
        got = ops.sparse_conv_affine(x.features, w, nbr, km.order, scale, shift, relu, algo)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old
    ref = _reference(x.features, w, nbr, scale, shift, relu)
    assert got.dtype == dt and got.shape == ref.shape
    row0 = torch.zeros(cout, dtype=torch.float64)  # the epilogue of an empty sum
    if shift is not None:
        row0 = row0 + shift.double().cpu()
    if relu:
        row0 = row0.clamp_min(0)
    torch.testing.assert_close(got[::7].double().cpu(), row0.to(dt).double().expand(got[::7].shape[0], cout),
                               rtol=0, atol=0)
    tol = 5e-3 if dtype == "tf32" else TOL[dt]  # 3xTF32: float32's tolerance
    assert (got.double().cpu() - ref).abs().max().item() <= tol * max(1.0, ref.abs().max().item())
    if relu:
        assert (got >= 0).all()


def test_sparse_conv_affine_without_inputs_and_nan(device):
    w = torch.randn(5, 9, 4, device=device)
    nbr = torch.full((3, 9), -1, dtype=torch.int32, device=device)
    shift = torch.tensor([1.0, -2.0, 0.5, -0.1, 3.0], device=device)
    for n_in in (0, 6):
        x = torch.randn(n_in, 4, device=device)
        out = ops.sparse_conv_affine(x, w, nbr, None, None, shift, True)
        assert torch.equal(out.cpu(), shift.clamp_min(0).expand(3, 5).cpu())
        out = ops.sparse_conv_affine(x, w, nbr, None, torch.full((5,), 2.0, device=device), shift, False)
        assert torch.equal(out.cpu(), shift.expand(3, 5).cpu())
    # ReLU keeps NaN, as torch.relu
    x = torch.full((1, 4), float("nan"), device=device)
    out = ops.sparse_conv_affine(x, w, torch.zeros(1, 9, dtype=torch.int32, device=device), None, None, None, True)
    assert torch.isnan(out).all()


def test_sparse_conv_affine_checks_its_arguments(device):
    x = random_tensor(1, (8, 8), 20, 4, seed=1, dtype=torch.float32, device=device)
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    w = torch.randn(6, 9, 4, device=device)
    good = torch.ones(6, device=device)
    for bad, name in [(torch.ones(6, dtype=torch.float64, device=device), "scale"), (torch.ones(5, device=device), "scale"),
                      (torch.ones(6, 1, device=device), "scale")]:
        with pytest.raises(ValueError, match=name):
            ops.sparse_conv_affine(x.features, w, km.neighbors, None, bad, good, False)
        with pytest.raises(ValueError, match="shift"):
            ops.sparse_conv_affine(x.features, w, km.neighbors, None, good, bad, False)
    with pytest.raises(ValueError, match="scale"):
        Fs.conv(x, torch.randn(6, 3, 3, 4, device=device), None, "subm", scale=good.double())
    if device != "cpu":
        with pytest.raises(ValueError, match="scale is on cpu"):
            ops.sparse_conv_affine(x.features, w, km.neighbors, None, good.cpu(), None, False)


def test_opcheck_sparse_conv_affine(device):
    x = random_tensor(2, (6, 5), 10, 3, seed=0, dtype=torch.float32, device=device)
    km = Fs.build_kernel_map(x, "conv", 3, 2, 1, 1)
    w = random_weight(4, (9,), 3, dtype=torch.float32, device=device)
    s, b = torch.rand(4, device=device) + 0.5, torch.randn(4, device=device)
    torch.library.opcheck(ops.sparse_conv_affine, (x.features, w, km.neighbors, km.order, s, b, True))
    torch.library.opcheck(ops.sparse_conv_affine, (x.features, w, km.neighbors, None, None, None, False))


def test_functional_conv_epilogue_with_and_without_gradients(device):
    x = random_tensor(2, (20, 20), 80, 8, seed=3, dtype=torch.float32, device=device)
    w = random_weight(12, (3, 3), 8, seed=3, dtype=torch.float32, device=device) / 4
    bias = torch.randn(12, device=device)
    scale, shift = torch.rand(12, device=device) + 0.5, torch.randn(12, device=device)
    ref = Fs.conv(x, w, bias, "conv", 2, 1).features
    ref = torch.relu(ref * scale + shift)
    with torch.no_grad():  # fused kernel, the bias folded into the shift
        got = Fs.conv(x, w, bias, "conv", 2, 1, scale=scale, shift=shift, relu=True).features
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)
    wg = w.clone().requires_grad_()
    y = Fs.conv(x, wg, bias, "conv", 2, 1, scale=scale, shift=shift, relu=True).features  # differentiable path
    torch.testing.assert_close(y.detach(), ref, rtol=1e-5, atol=1e-5)
    y.sum().backward()
    assert wg.grad is not None and wg.grad.abs().sum() > 0


def _randomize_norms(net, seed=0):
    g = torch.Generator().manual_seed(seed)
    for m in net.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            C = m.num_features
            m.running_mean.copy_(torch.randn(C, generator=g))
            m.running_var.copy_(torch.rand(C, generator=g) + 0.3)
            if m.weight is not None:
                m.weight.data.copy_(torch.rand(C, generator=g) + 0.5)
                m.bias.data.copy_(torch.randn(C, generator=g))
    return net


def _net(cin):
    return spconv.SparseSequential(
        spconv.SubMConv2d(cin, 16, 3, bias=True, indice_key="s1"), nn.BatchNorm1d(16), nn.ReLU(),
        spconv.SparseConv2d(16, 32, 3, stride=2, padding=1, bias=False, indice_key="d1"), nn.BatchNorm1d(32),
        spconv.SubMConv2d(32, 32, 3, bias=False, indice_key="s2"), nn.BatchNorm1d(32, affine=False), nn.ReLU(),
        spconv.SparseInverseConv2d(32, 16, 3, indice_key="d1", bias=False), nn.BatchNorm1d(16), nn.ReLU(),
        spconv.SparseConvTranspose2d(16, 8, 2, stride=2, bias=True), spconv.SparseBatchNorm(8), spconv.SparseReLU(),
        spconv.SubMConv2d(8, 8, 1, bias=False), nn.BatchNorm1d(8), nn.ReLU())  # spconv's kernel-1 shortcut


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_sparse_sequential_fuses_eval_batchnorm_relu(device, dtype):
    if dtype == torch.float16 and device == "cpu":
        pytest.skip("float16 networks run on CUDA")
    net = _randomize_norms(_net(8)).to(device=device, dtype=dtype).eval()
    x = random_tensor(2, (30, 30), 150, 8, seed=5, dtype=dtype, device=device)
    ref = net(x)  # gradients enabled and parameters require them: no fusion
    calls = []
    orig = ops.sparse_conv_affine
    with torch.no_grad():
        try:  # count the fused launches: single layers, and SubM layers with a key as (one-layer) chains
            ops.sparse_conv_affine = lambda *a: calls.append(1) or orig(*a)  # noqa: E731
            got, chains = _count_chains(lambda: net(x))
        finally:
            ops.sparse_conv_affine = orig
    assert len(calls) == 3 and chains == [1, 1]  # every conv but the kernel-1 shortcut
    assert torch.equal(got.indices, ref.indices)
    tol = 1e-5 if dtype == torch.float32 else 2e-2
    torch.testing.assert_close(got.features, ref.features.detach(), rtol=tol, atol=tol)
    # an in-place change of a BatchNorm buffer reaches the cached affine map
    with torch.no_grad():
        net[1].running_var.mul_(4)
        again = net(x)
    ref2 = net(x)
    torch.testing.assert_close(again.features, ref2.features.detach(), rtol=tol, atol=tol)
    assert not torch.allclose(again.features, got.features)
    # so do a replaced BatchNorm parameter and a changed eps
    net[1].weight = nn.Parameter(net[1].weight.detach() * -2)
    net[4].eps = 0.5
    with torch.no_grad():
        third = net(x)
    ref3 = net(x)
    torch.testing.assert_close(third.features, ref3.features.detach(), rtol=tol, atol=tol)
    assert not torch.allclose(third.features, again.features)


def test_sparse_sequential_keeps_hooks_training_mode_and_float64(device):
    net = _randomize_norms(_net(8)).to(device)
    x = random_tensor(2, (30, 30), 150, 8, seed=6, dtype=torch.float32, device=device)
    seen = []
    net.eval()
    h = net[1].register_forward_hook(lambda m, i, o: seen.append(o.shape))
    with torch.no_grad():
        net(x)
    h.remove()
    assert len(seen) == 1  # the hooked BatchNorm ran as a module
    # training mode: batch statistics, never fused (running stats are updated)
    net.train()
    before = net[1].running_mean.clone()
    with torch.no_grad():
        net(x)
    assert not torch.equal(before, net[1].running_mean)
    # float64 keeps BatchNorm's own arithmetic
    net64 = _randomize_norms(_net(8)).to(device=device, dtype=torch.float64).eval()
    x64 = random_tensor(2, (30, 30), 150, 8, seed=6, dtype=torch.float64, device=device)
    with torch.no_grad():
        got = net64(x64)
    ref = net64(x64)
    assert (got.features - ref.features).abs().max() <= 1e-12


def test_pointpillars_sparse_backbone_fused_equals_unfused(device):
    from lidarops.models.bev_backbone import BaseBEVBackbone
    torch.manual_seed(0)
    bb = _randomize_norms(BaseBEVBackbone(in_channels=16, mode="sparse")).to(device).eval()
    x = random_tensor(1, (64, 64), 500, 16, seed=7, dtype=torch.float32, device=device)
    ref = bb(x)  # gradients: three steps per layer
    with torch.no_grad():
        got = bb(x)
        again = bb(x)  # cached weights and affine maps
    torch.testing.assert_close(got, ref.detach(), rtol=1e-5, atol=1e-5)
    assert torch.equal(got, again)
    with torch.no_grad():  # a weight changed in place reaches the cached sparse weight
        bb.blocks[0][1].weight.mul_(-1)  # the first block's strided conv
        changed = bb(x)
    torch.testing.assert_close(changed, bb(x).detach(), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(changed, got)


def test_fused_layers_with_a_parametrized_weight():
    """A layer whose weight is a parametrization (not in its parameter dict) is read as an attribute: fused or
    alone, the result is that of the parametrized weight."""
    import torch.nn.utils.parametrize as P

    from lidarops.sparse import nn as snn
    from helpers.sparse import random_tensor

    class Double(torch.nn.Module):
        def forward(self, w):
            return 2 * w

    torch.manual_seed(0)
    x = random_tensor(1, (9, 11), 25, 4, seed=3, device="cpu").replace_feature(torch.randn(25, 4))
    conv = snn.SubMConv2d(4, 5, 3, bias=True, indice_key="p")
    bn = torch.nn.BatchNorm1d(5).eval()
    bn.running_mean.uniform_(-1, 1)
    bn.running_var.uniform_(0.5, 2)
    plain = snn.SubMConv2d(4, 5, 3, bias=True, indice_key="p")
    with torch.no_grad():
        plain.weight.copy_(2 * conv.weight)
        plain.bias.copy_(conv.bias)
    P.register_parametrization(conv, "weight", Double())
    assert "weight" not in conv._parameters
    with torch.no_grad():
        want = torch.relu(bn(plain(x).features))
        got = snn.SparseSequential(conv, bn, torch.nn.ReLU())(x).features
        alone = conv(x).features
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(alone, plain(x).features, rtol=1e-6, atol=1e-6)


def _block(kind: str, bias: bool, relu: bool, cin=8, cout=12):
    torch.manual_seed(len(kind) + bias + 2 * relu)
    if kind == "subm":
        conv = spnn.SubMConv2d(cin, cout, 3, bias=bias, indice_key="s")
    else:
        conv = spnn.SparseConv2d(cin, cout, 3, stride=2, padding=1, bias=bias, indice_key="d")
    norm = _randomize_norms(nn.Sequential(nn.BatchNorm1d(cout, eps=1e-3)))[0]
    return spnn.SparseConvBNReLU(conv, norm, relu=relu)


def _unfused(block, x):
    """The three modules in turn, BatchNorm as the module itself."""
    y = block.conv(x)
    y = y.replace_feature(block.norm(y.features))
    return y.replace_feature(torch.relu(y.features)) if block.relu else y


@pytest.mark.parametrize("kind", ["subm", "conv"])
@pytest.mark.parametrize("bias,relu", [(False, True), (True, True), (True, False)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_sparse_conv_bn_relu_module_matches_its_parts(device, kind, bias, relu, dtype):
    if dtype == torch.float16 and device == "cpu":
        pytest.skip("float16 networks run on CUDA")
    block = _block(kind, bias, relu).to(device=device, dtype=dtype).eval()
    x = random_tensor(2, (30, 30), 150, 8, seed=11, dtype=dtype, device=device)
    calls = []
    orig = ops.sparse_conv_affine
    with torch.no_grad():
        try:
            ops.sparse_conv_affine = lambda *a: calls.append(1) or orig(*a)  # noqa: E731
            got = block(x)
        finally:
            ops.sparse_conv_affine = orig
        ref = _unfused(block, x)
    assert len(calls) == 1  # one fused convolution
    assert torch.equal(got.indices, ref.indices)
    tol = 1e-5 if dtype == torch.float32 else 2e-2
    torch.testing.assert_close(got.features, ref.features, rtol=tol, atol=tol)
    if relu:
        assert (got.features >= 0).all() and (ref.features < 0).sum() == 0
    else:
        assert (got.features < 0).any()  # a ReLU that should not be there would fail this


def test_sparse_conv_bn_relu_module_in_training_and_with_gradients(device):
    block = _block("subm", True, True).to(device)
    twin = _block("subm", True, True).to(device)
    twin.load_state_dict(block.state_dict())
    x = random_tensor(2, (30, 30), 150, 8, seed=12, dtype=torch.float32, device=device)
    block.train(), twin.train()
    got, ref = block(x), _unfused(twin, x)
    torch.testing.assert_close(got.features, ref.features)  # batch statistics
    torch.testing.assert_close(block.norm.running_mean, twin.norm.running_mean)  # and their update
    assert block.norm.num_batches_tracked.item() == 1
    got.features.sum().backward()
    assert block.conv.weight.grad is not None and block.norm.weight.grad is not None
    # eval with gradients: not fused (autograd needs the three steps), the parts' result
    block.eval(), twin.eval()
    torch.testing.assert_close(block(x).features, _unfused(twin, x).features)
    assert sorted(block.state_dict()) == sorted(["conv.weight", "conv.bias", "norm.weight", "norm.bias",
                                                 "norm.running_mean", "norm.running_var", "norm.num_batches_tracked"])


def test_sparse_conv_bn_relu_module_hooks_empty_input_and_arguments(device):
    block = _block("subm", False, True).to(device).eval()
    seen = []
    block.norm.register_forward_hook(lambda m, i, o: seen.append(1))
    x = random_tensor(2, (30, 30), 150, 8, seed=13, dtype=torch.float32, device=device)
    with torch.no_grad():
        block(x)
    assert seen == [1]  # a hooked part runs as a module
    empty = SparseConvTensor(torch.zeros(0, 8, device=device), torch.zeros(0, 3, dtype=torch.int32, device=device),
                             [30, 30], 2)
    block.train()
    assert block(empty).features.shape == (0, 12)
    with pytest.raises(ValueError, match="conv must be a sparse convolution"):
        spnn.SparseConvBNReLU(nn.Linear(2, 2), nn.BatchNorm1d(2))
    with pytest.raises(ValueError, match="norm must be a BatchNorm over conv's 12 output channels"):
        spnn.SparseConvBNReLU(spnn.SubMConv2d(8, 12, 3), nn.BatchNorm1d(8))
    with pytest.raises(ValueError, match="relu must be True or False"):
        spnn.SparseConvBNReLU(spnn.SubMConv2d(8, 12, 3), nn.BatchNorm1d(12), relu=1)


def _chain_net(cin=8):
    """Fused SubM layers sharing an indice_key (chained after the first), a strided layer, a second run, and a layer
    with its own key (not chained)."""
    return spconv.SparseSequential(
        spconv.SubMConv2d(cin, 16, 3, bias=False, indice_key="a"), nn.BatchNorm1d(16), nn.ReLU(),  # builds "a"
        spconv.SubMConv2d(16, 24, 3, bias=True, indice_key="a"), nn.BatchNorm1d(24), nn.ReLU(),  # chained ...
        spconv.SubMConv2d(24, 24, 3, bias=False, indice_key="a"), nn.BatchNorm1d(24),  # ... without a ReLU
        spconv.SparseConv2d(24, 32, 3, stride=2, padding=1, bias=False, indice_key="d"), nn.BatchNorm1d(32), nn.ReLU(),
        spconv.SubMConv2d(32, 32, 3, bias=False, indice_key="b"), nn.BatchNorm1d(32), nn.ReLU(),
        spconv.SubMConv2d(32, 32, 3, bias=True, indice_key="b"), nn.BatchNorm1d(32, affine=False), nn.ReLU(),
        spconv.SubMConv2d(32, 16, 3, bias=False, indice_key="c"), nn.BatchNorm1d(16), nn.ReLU())


def _count_chains(fn):
    """fn()'s result and the number of layers of each sparse_conv_affine_chain call it made."""
    calls, orig = [], ops.sparse_conv_affine_chain
    try:
        ops.sparse_conv_affine_chain = lambda *a: calls.append(len(a[1])) or orig(*a)  # noqa: E731
        return fn(), calls
    finally:
        ops.sparse_conv_affine_chain = orig


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_sparse_sequential_chains_subm_layers_sharing_a_map(device, dtype):
    if dtype == torch.float16 and device == "cpu":
        pytest.skip("float16 networks run on CUDA")
    torch.manual_seed(1)
    net = _randomize_norms(_chain_net(), seed=2).to(device=device, dtype=dtype).eval()
    x = random_tensor(2, (40, 40), 300, 8, seed=9, dtype=dtype, device=device)
    ref = net(x)  # gradients: every layer as three steps
    with torch.no_grad():
        got, calls = _count_chains(lambda: net(x))
    assert calls == [3, 2, 1]  # "a": its three layers, the map built first; "b": its two; "c" alone
    assert torch.equal(got.indices, ref.indices)
    tol = 1e-5 if dtype == torch.float32 else 2e-2
    torch.testing.assert_close(got.features, ref.features.detach(), rtol=tol, atol=tol)
    # the chain reads the current parameters: an in-place change of a chained layer's weight and BatchNorm
    with torch.no_grad():
        net[3].weight.mul_(-1)
        net[7].running_mean.add_(0.5)
        changed = net(x)
    torch.testing.assert_close(changed.features, net(x).features.detach(), rtol=tol, atol=tol)
    assert not torch.allclose(changed.features, got.features)


def test_subm_chain_stops_where_a_layer_cannot_join(device):
    torch.manual_seed(3)
    net = _randomize_norms(_chain_net(), seed=4).to(device).eval()
    x = random_tensor(1, (30, 30), 200, 8, seed=10, dtype=torch.float32, device=device)
    ref = net(x).features.detach()
    seen = []
    h = net[6].register_forward_hook(lambda m, i, o: seen.append(1))  # the third "a" layer runs as a module
    with torch.no_grad():
        got, calls = _count_chains(lambda: net(x))
    h.remove()
    assert seen == [1] and calls == [2, 2, 1]  # "a" stops before the hooked layer; "b"; "c"
    torch.testing.assert_close(got.features, ref, rtol=1e-5, atol=1e-5)
    with torch.no_grad(), torch.autocast(device, dtype=torch.bfloat16):  # autocast: layer by layer
        _, calls = _count_chains(lambda: net(x))
    assert calls == []
    net.train()
    with torch.no_grad():
        _, calls = _count_chains(lambda: net(x))
    assert calls == []
    # a layer with the wrong input channels is left to the layer path and its error
    bad = spconv.SparseSequential(spconv.SubMConv2d(8, 16, 3, indice_key="a"), nn.BatchNorm1d(16), nn.ReLU(),
                                  spconv.SubMConv2d(12, 16, 3, indice_key="a"), nn.BatchNorm1d(16)).to(device).eval()
    with torch.no_grad(), pytest.raises(ValueError, match="expects 12 input channels"):
        bad(x)
    # no sites: the chain's layers give (0, C)
    empty = SparseConvTensor(torch.zeros(0, 8, device=device), torch.zeros(0, 3, dtype=torch.int32, device=device),
                             [30, 30], 1)
    net.eval()
    with torch.no_grad():
        out, calls = _count_chains(lambda: spconv.SparseSequential(*list(net)[:8])(empty))
    assert out.features.shape == (0, 24) and calls == [3]


def test_sparse_conv_affine_chain_equals_its_layers(device):
    x = random_tensor(2, (40, 40), 300, 16, seed=11, dtype=torch.float32, device=device)
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    g = torch.Generator().manual_seed(5)
    chans = [16, 24, 32, 8]
    ws = [(torch.randn(co, 9, ci, generator=g) / 8).to(device) for ci, co in zip(chans, chans[1:])]
    scales = [(torch.rand(co, generator=g) + 0.5).to(device) for co in chans[1:]]
    shifts = [torch.randn(co, generator=g).to(device) for co in chans[1:]]
    relus = [True, False, True]
    got = ops.sparse_conv_affine_chain(x.features, ws, km.neighbors, km.order, scales, shifts, relus)
    step, ref = x.features, x.features.double().cpu()
    for w, s, b, r in zip(ws, scales, shifts, relus):
        step = ops.sparse_conv_affine(step, w, km.neighbors, km.order, s, b, r)
        ref = _reference(ref, w, km.neighbors, s, b, r)
    assert torch.equal(got, step)  # the same kernels in the same order
    assert (got.double().cpu() - ref).abs().max().item() <= 1e-4 * max(1.0, ref.abs().max().item())
    torch.library.opcheck(ops.sparse_conv_affine_chain, (x.features, ws, km.neighbors, km.order, scales, shifts, relus))


def test_sparse_conv_affine_chain_checks_its_arguments(device):
    x = random_tensor(1, (8, 8), 20, 4, seed=1, dtype=torch.float32, device=device)
    km = Fs.build_kernel_map(x, "subm", 3, 1, 1, 1)
    w1, w2 = torch.randn(6, 9, 4, device=device), torch.randn(5, 9, 6, device=device)
    s1, s2 = torch.ones(6, device=device), torch.ones(5, device=device)
    f, nbr = x.features, km.neighbors
    with pytest.raises(ValueError, match="weights must hold at least one"):
        ops.sparse_conv_affine_chain(f, [], nbr, None, [], [], [])
    with pytest.raises(ValueError, match="one entry per layer: weights has 2, scales 1"):
        ops.sparse_conv_affine_chain(f, [w1, w2], nbr, None, [s1], [s1, s2], [True, True])
    with pytest.raises(ValueError, match=r"weights\[1\] must be \(Cout, K, Cin = 6\) \(Cin: the channels of the "
                                         r"previous layer's output\), got shape \[5, 9, 5\]"):
        ops.sparse_conv_affine_chain(f, [w1, w2[..., :5]], nbr, None, [s1, s2], [s1, s2], [True, True])
    with pytest.raises(ValueError, match=r"kernel_map must be a submanifold map, \(N, K\) with N = 20"):
        ops.sparse_conv_affine_chain(f, [w1], nbr[:5], None, [s1], [s1], [False])
    with pytest.raises(ValueError, match=r"scale must be a float32 \(Cout,\) = \(5,\)"):  # the layer's own check
        ops.sparse_conv_affine_chain(f, [w1, w2], nbr, None, [s1, s1], [s1, s2], [True, True])
