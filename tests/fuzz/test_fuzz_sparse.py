"""Fuzz: sparse convolution and pooling (lidarops.sparse) against the dense float64 references
(``Fs._conv_reference``, ``Fs._max_pool_reference``: F.convNd / F.conv_transposeNd / F.max_poolNd on
``x.dense()``, read at the output sites).

Sites may be duplicated or outside the grid or the batch: then the kernel-map construction must
raise a ValueError naming the indices; otherwise the result must be the reference's.
"""
from __future__ import annotations

import copy

import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.sparse import SparseConvTensor
from lidarops.sparse import functional as Fs
from .fuzzing import Sites, assert_clear_error, assert_close, assert_no_error, assert_same, fuzz, outcome, sparse_sites


def _tensor(s: Sites, device: str) -> SparseConvTensor:
    return SparseConvTensor(s.features.to(device), s.indices.to(device), s.spatial_shape, s.batch_size)


def _row_major(indices: torch.Tensor, features: torch.Tensor, shape) -> tuple:
    idx = indices.long().cpu()
    key = idx[:, 0]
    for d, n in enumerate(shape):
        key = key * n + idx[:, d + 1]
    order = torch.argsort(key)
    return idx[order], features.detach().cpu()[order]


def _compare(y: SparseConvTensor, ref_i: torch.Tensor, ref_f: torch.Tensor, what: str) -> None:
    got_i, got_f = _row_major(y.indices, y.features, y.spatial_shape)
    want_i, want_f = _row_major(ref_i, ref_f, y.spatial_shape)
    assert_same(got_i, want_i, what + " sites")
    scale = max(1.0, float(want_f.abs().max())) if want_f.numel() else 1.0
    assert_close(got_f, want_f, rtol=0, atol=1e-10 * scale, what=what + " features")


def _geometry(data, D: int, kind: str) -> dict:
    k = data.draw(st.lists(st.integers(1, 3), min_size=D, max_size=D), "kernel")
    g = {"kernel": k, "dilation": data.draw(st.integers(1, 2), "dilation")}
    if kind in ("conv", "transposed", "pool"):
        g["stride"] = data.draw(st.integers(1, 3), "stride")
        g["padding"] = data.draw(st.integers(0, 1), "padding")
    if kind == "transposed" and data.draw(st.booleans(), "kernel = stride"):  # upsampling: disjoint blocks
        g.update(kernel=[g["stride"]] * D, dilation=1, padding=0)
    return g


@fuzz
@given(data=st.data())
def test_conv(device, data):
    s = data.draw(sparse_sites(), "sites")
    D = len(s.spatial_shape)
    kind = data.draw(st.sampled_from(["subm", "conv", "transposed"]), "kind")
    g = _geometry(data, D, kind)
    cin, cout = s.features.shape[1], data.draw(st.integers(1, 3), "Cout")
    w = torch.tensor(data.draw(st.lists(st.floats(-2, 2, width=32), min_size=cout * cin * _prod(g["kernel"]),
                                        max_size=cout * cin * _prod(g["kernel"]))),
                     dtype=torch.float64).reshape(cout, *g["kernel"], cin)
    bias = torch.linspace(-1, 1, cout, dtype=torch.float64) if data.draw(st.booleans(), "bias") else None
    what = f"conv({kind}, {g}, {tuple(s.indices.shape)} sites on {s.spatial_shape} x batch {s.batch_size})"
    x = _tensor(s, device)
    args = dict(stride=g.get("stride", 1), padding=g.get("padding", 0), dilation=g["dilation"])
    res, err = outcome(Fs.conv, x, w.to(device), None if bias is None else bias.to(device), kind,
                       method=data.draw(st.sampled_from(["auto", "dense", "hash"]), "method"), **args)
    if s.indices.shape[0] and not (s.in_range() and s.unique()):
        if kind == "subm" and _prod(g["kernel"]) == 1 and err is None:
            # documented: a 1x1 submanifold convolution reads no site (a matrix product per row), so
            # it builds no kernel map and checks no site; the next layer that reads them does
            want = s.features @ w.reshape(cout, cin).t() + (0 if bias is None else bias)
            return assert_close(res.features, want, rtol=0, atol=1e-12 * max(1.0, float(want.abs().max())),
                                what=what)
        if err is None and res.indices.shape[0] == 0:
            # duplicates are found while pairing sites with outputs: with no site reaching an output
            # (a strided 1x1 kernel on odd sites) there is nothing to pair, and the result is right
            # for any sites: no output
            uniq = Sites(torch.unique(s.indices.clamp_min(0), dim=0), None, s.spatial_shape, s.batch_size)
            reach = Fs._conv_reference(_tensor(Sites(uniq.indices, torch.zeros(uniq.indices.shape[0], cin,
                                                     dtype=torch.float64), s.spatial_shape, s.batch_size), "cpu"),
                                       w, None, kind, **args) if uniq.in_range() else None
            if reach is not None and reach[0].shape[0] == 0:
                return
        if err is not None and ("leaves no output site" in str(err) or "empty output grid" in str(err)):
            return assert_clear_error(err, ValueError, ["kernel", "convolution"], what)  # checked first
        return assert_clear_error(err, ValueError, ["indices"], what)
    if err is not None and ("leaves no output site" in str(err) or "empty output grid" in str(err)):
        return assert_clear_error(err, ValueError, ["kernel", "convolution"], what)
    assert_no_error(err, what)
    ref_i, ref_f = Fs._conv_reference(_tensor(s, "cpu"), w, bias, kind, **args)
    _compare(res, ref_i, ref_f, what)


@fuzz
@given(data=st.data())
def test_conv_without_validation_skips_rows_outside_the_grid(device, data):
    """Under lidarops.validation(False) a layer checks no site: rows outside the batch or grid are skipped
    (the result is the layer's on the other rows), never read out of bounds; then a second layer on the
    sites the first made (which it does not check) is the reference's."""
    from lidarops.ops.validation import validation
    s = data.draw(sparse_sites(), "sites")
    assume(s.unique())  # of duplicates "one wins" may differ between devices
    D = len(s.spatial_shape)
    kind = data.draw(st.sampled_from(["subm", "conv", "transposed"]), "kind")
    g = _geometry(data, D, kind)
    cin = s.features.shape[1]
    w = torch.linspace(-1, 1, 2 * cin * _prod(g["kernel"]), dtype=torch.float64).reshape(2, *g["kernel"], cin)
    args = dict(stride=g.get("stride", 1), padding=g.get("padding", 0), dilation=g["dilation"])
    bound = torch.tensor([s.batch_size] + s.spatial_shape)
    keep = ((s.indices >= 0) & (s.indices < bound)).all(1)
    good = Sites(s.indices[keep], s.features[keep], s.spatial_shape, s.batch_size)
    what = f"conv({kind}, {g}) under validation(False), {int((~keep).sum())} of {keep.numel()} rows outside"
    with validation(False):
        res, err = outcome(Fs.conv, _tensor(s, device), w.to(device), None, kind, **args)
    if err is not None and ("leaves no output site" in str(err) or "empty output grid" in str(err)):
        return assert_clear_error(err, ValueError, ["kernel", "convolution"], what)
    assert_no_error(err, what)
    if kind == "subm":  # the output keeps every input row; the rows inside the grid are the reference's
        ref_i, ref_f = Fs._conv_reference(_tensor(good, "cpu"), w, None, kind, **args)
        _compare(SparseConvTensor(res.features[keep.to(device)], res.indices[keep.to(device)], s.spatial_shape,
                                  s.batch_size), ref_i, ref_f, what)
        return
    ref_i, ref_f = Fs._conv_reference(_tensor(good, "cpu"), w, None, kind, **args)
    _compare(res, ref_i, ref_f, what)
    if res.indices.shape[0]:
        w2 = torch.linspace(1, -1, 2 * 2 * 3 ** D, dtype=torch.float64).reshape(2, *([3] * D), 2)
        made = Fs.conv(res, w2.to(device), None, "subm")
        ref2 = Fs._conv_reference(SparseConvTensor(res.features.cpu(), res.indices.cpu(), res.spatial_shape,
                                                   res.batch_size), w2, None, "subm")
        _compare(made, *ref2, what + ", then SubM on the made sites")


@fuzz
@given(data=st.data())
def test_conv_under_autocast(device, data):
    """Inside torch.autocast (bfloat16): float32 or bfloat16 features with float32 weights run in bfloat16 and give
    the convolution of the inputs cast by hand; float64 features are left alone, so float32 weights with them stay
    a clear error naming the weight."""
    s = data.draw(sparse_sites(), "sites")
    assume(s.in_range() and s.unique())
    D = len(s.spatial_shape)
    kind = data.draw(st.sampled_from(["subm", "conv", "transposed"]), "kind")
    g = _geometry(data, D, kind)
    cin, cout = s.features.shape[1], data.draw(st.integers(1, 3), "Cout")
    w = torch.linspace(-1, 1, cout * cin * _prod(g["kernel"])).reshape(cout, *g["kernel"], cin).to(device)
    bias = torch.linspace(-1, 1, cout, device=device) if data.draw(st.booleans(), "bias") else None
    feats = data.draw(st.sampled_from([torch.float32, torch.bfloat16, torch.float64]), "features dtype")
    x = SparseConvTensor(s.features.to(device, feats), s.indices.to(device), s.spatial_shape, s.batch_size)
    args = dict(stride=g.get("stride", 1), padding=g.get("padding", 0), dilation=g["dilation"])
    what = f"conv({kind}, {g}) of {feats} features under bfloat16 autocast"
    with torch.autocast(torch.device(device).type, dtype=torch.bfloat16):
        res, err = outcome(Fs.conv, x, w, bias, kind, **args)
    if err is not None and ("leaves no output site" in str(err) or "empty output grid" in str(err)):
        return assert_clear_error(err, ValueError, ["kernel", "convolution"], what)
    if feats == torch.float64:
        return assert_clear_error(err, ValueError, ["weight"], what)
    assert_no_error(err, what)
    assert res.features.dtype == torch.bfloat16, what
    want = Fs.conv(x.replace_feature(x.features.bfloat16()), w.bfloat16(), None if bias is None else bias.bfloat16(),
                   kind, **args)
    assert_same(res.indices, want.indices, what + " sites")
    assert_same(res.features, want.features, what + " features")


@fuzz
@given(data=st.data())
def test_max_pool(device, data):
    s = data.draw(sparse_sites(), "sites")
    D = len(s.spatial_shape)
    k = data.draw(st.lists(st.integers(1, 3), min_size=D, max_size=D), "kernel")
    stride = data.draw(st.none() | st.integers(1, 3), "stride")
    padding = data.draw(st.integers(0, 1), "padding")
    what = f"max_pool(kernel {k}, stride {stride}, padding {padding}, {tuple(s.indices.shape)} sites on {s.spatial_shape})"
    res, err = outcome(Fs.max_pool, _tensor(s, device), k, stride, padding)
    if err is not None and "leaves no output site" in str(err):  # checked before the sites
        return assert_clear_error(err, ValueError, ["kernel"], what)
    if s.indices.shape[0] and not (s.in_range() and s.unique()):
        if err is not None and padding * 2 > min(k):
            return assert_clear_error(err, ValueError, ["padding", "kernel", "indices"], what)
        return assert_clear_error(err, ValueError, ["indices"], what)
    if err is not None and padding * 2 > min(k):  # PyTorch's own rule, which the reference follows
        return assert_clear_error(err, ValueError, ["padding", "kernel"], what)
    assert_no_error(err, what)
    if padding * 2 > min(k):
        return  # F.max_poolNd refuses this geometry: no reference
    ref_i, ref_f = Fs._max_pool_reference(_tensor(s, "cpu"), k, stride, padding)
    _compare(res, ref_i, ref_f, what)


@fuzz
@given(data=st.data())
def test_dense_and_indice_key_reuse(device, data):
    """dense() checks the sites; a cached kernel map is reused only for its own sites."""
    s = data.draw(sparse_sites(D=2), "sites")
    other = data.draw(sparse_sites(D=2, channels=s.features.shape[1]), "other sites")
    x = _tensor(s, device)
    res, err = outcome(x.dense)
    if s.indices.shape[0] and not (s.in_range() and s.unique()):  # a dense map would keep one of two rows
        return assert_clear_error(err, ValueError, ["indices"], "dense()")
    assert_no_error(err, "dense()")
    if not s.indices.shape[0]:
        return
    w = torch.ones(2, 3, 3, s.features.shape[1], dtype=torch.float64, device=device)
    y = Fs.conv(x, w, None, "subm", indice_key="k")
    shape_ok = other.spatial_shape == s.spatial_shape and other.batch_size == s.batch_size
    if not (shape_ok and other.in_range() and other.unique()):
        return
    z = SparseConvTensor(other.features.to(device), other.indices.to(device), other.spatial_shape, other.batch_size,
                         indice_dict=y.indice_dict)
    what = f"reuse of indice_key 'k' by {tuple(other.indices.shape)} sites (map built on {tuple(s.indices.shape)})"
    res, err = outcome(Fs.conv, z, w, None, "subm", indice_key="k")
    if other.indices.shape != s.indices.shape:
        return assert_clear_error(err, ValueError, ["indice_key"], what)
    if not torch.equal(other.indices, s.indices):
        return assert_clear_error(err, ValueError, ["indice_key"], what)
    assert_no_error(err, what)
    ref_i, ref_f = Fs._conv_reference(_tensor(other, "cpu"), w.cpu(), None, "subm")
    _compare(res, ref_i, ref_f, what)


def _prod(v) -> int:
    out = 1
    for e in v:
        out *= e
    return out


@fuzz
@given(data=st.data())
def test_graphed_sparse_net_equals_the_network(device, data):
    """GraphedSparseNet over a sequence of calls on two sets of sites (the same tensors, equal copies, bad sites):
    every result is the eager network's on a fresh tensor, and bad sites get the network's own error."""
    from lidarops.sparse import GraphedSparseNet
    from lidarops.sparse import nn as spnn

    first = data.draw(sparse_sites(D=2, channels=2), "sites")
    second = data.draw(sparse_sites(D=2, channels=2), "other sites")
    torch.manual_seed(data.draw(st.integers(0, 3), "weights"))
    k = data.draw(st.integers(1, 3), "kernel")
    net = spnn.SparseSequential(
        spnn.SubMConv2d(2, 3, 3, indice_key="s"), torch.nn.ReLU(),
        spnn.SparseConv2d(3, 3, k, stride=data.draw(st.integers(1, 2), "stride"), indice_key="d"),
        spnn.SparseInverseConv2d(3, 2, k, indice_key="d")).double().to(device).eval()
    g = GraphedSparseNet(net)
    sets = [(first, first.indices.to(device)), (second, second.indices.to(device))]
    with torch.inference_mode() if data.draw(st.booleans(), "inference mode") else torch.no_grad():
        for call in range(data.draw(st.integers(1, 5), "calls")):
            s, idx = sets[data.draw(st.integers(0, 1), f"sites of call {call}")]
            if data.draw(st.booleans(), f"a copy at call {call}"):
                idx = idx.clone()
            f = torch.randn(idx.shape[0], 2, dtype=torch.float64, device=device)
            what = f"call {call}: {tuple(idx.shape)} sites on {s.spatial_shape} x batch {s.batch_size}"
            res, err = outcome(g, SparseConvTensor(f, idx, s.spatial_shape, s.batch_size))
            want, want_err = outcome(net, SparseConvTensor(f.clone(), idx.clone(), s.spatial_shape, s.batch_size))
            if s.indices.shape[0] and not (s.in_range() and s.unique()):
                assert_clear_error(err, ValueError, ["indices"], what)
            if want_err is not None:  # bad sites, or a grid too small for the kernel: the network's own error
                assert type(err) is type(want_err) and str(err) == str(want_err), f"{what}: {err!r} vs {want_err!r}"
                continue
            assert_no_error(err, what)
            assert_same(res.indices.cpu(), want.indices.cpu(), what + " sites")
            assert_close(res.features.cpu(), want.features.cpu(), rtol=0, atol=1e-12, what=what + " features")
    assert g.reason is None, g  # every map has an indice_key: the forward can always be recorded


@fuzz
@given(data=st.data())
def test_sparse_conv_bn_relu_equals_its_parts_in_float64(device, data):
    """SparseConvBNReLU in float32 (fused in eval mode without gradients, three steps otherwise) against the same
    parameters run as conv -> BatchNorm -> ReLU in float64; bad sites get the convolution's own error."""
    from lidarops.sparse import nn as spnn

    s = data.draw(sparse_sites(D=2), "sites")
    cin = s.features.shape[1]
    kind = data.draw(st.sampled_from(["subm", "conv"]), "kind")
    bias, relu, train = (data.draw(st.booleans(), n) for n in ("bias", "relu", "training"))
    torch.manual_seed(data.draw(st.integers(0, 3), "weights"))
    conv = spnn.SubMConv2d(cin, 3, 3, bias=bias) if kind == "subm" else \
        spnn.SparseConv2d(cin, 3, 2, stride=data.draw(st.integers(1, 2), "stride"), bias=bias)
    norm = torch.nn.BatchNorm1d(3)
    with torch.no_grad():
        norm.running_mean.uniform_(-1, 1)
        norm.running_var.uniform_(0.5, 2)
        norm.weight.uniform_(-2, 2)
        norm.bias.uniform_(-1, 1)
    block = spnn.SparseConvBNReLU(conv, norm, relu).to(device).train(train)
    twin = spnn.SparseConvBNReLU(copy.deepcopy(conv), copy.deepcopy(norm), relu).double().to(device).train(train)
    what = f"SparseConvBNReLU({kind}, bias={bias}, relu={relu}, training={train}) on {tuple(s.indices.shape)} sites"
    _float32_equals_float64_twin(block, twin, s, device, 2e-4, what)


def _float32_equals_float64_twin(net, twin, s: Sites, device: str, atol: float, what: str) -> None:
    """``net`` on the sites in float32 against ``twin`` (its float64 copy) without gradients: the same error, or the
    same sites and features within ``atol`` (relative to the largest feature)."""
    x = SparseConvTensor(s.features.float().to(device), s.indices.to(device), s.spatial_shape, s.batch_size)
    with torch.no_grad():
        res, err = outcome(net, x)
        want, want_err = outcome(twin, _tensor(s, device))
    if want_err is not None:
        assert type(err) is type(want_err) and str(err) == str(want_err), f"{what}: {err!r} vs {want_err!r}"
        return
    assert_no_error(err, what)
    assert_same(res.indices.cpu(), want.indices.cpu(), what + " sites")
    scale = max(1.0, float(want.features.abs().max())) if want.features.numel() else 1.0
    assert_close(res.features.double().cpu(), want.features.cpu(), rtol=0, atol=atol * scale, what=what + " features")


@fuzz
@given(data=st.data())
def test_subm_layers_sharing_a_map_chained_equal_float64(device, data):
    """SparseSequential of fused SubM layers sharing an indice_key (one op call after the first, in float32 eval
    without gradients) against the same modules in float64 (layer by layer); bad sites get the same error."""
    from lidarops.sparse import nn as spnn

    s = data.draw(sparse_sites(D=2), "sites")
    chans = [s.features.shape[1]] + data.draw(st.lists(st.integers(1, 9), min_size=2, max_size=4), "channels")
    relus = data.draw(st.lists(st.booleans(), min_size=len(chans) - 1, max_size=len(chans) - 1), "relus")
    k = data.draw(st.sampled_from([3, 5]), "kernel")
    torch.manual_seed(data.draw(st.integers(0, 3), "weights"))
    layers = []
    for ci, co, relu in zip(chans, chans[1:], relus):
        norm = torch.nn.BatchNorm1d(co)
        with torch.no_grad():
            norm.running_mean.uniform_(-1, 1)
            norm.running_var.uniform_(0.5, 2)
        layers += [spnn.SubMConv2d(ci, co, k, bias=data.draw(st.booleans(), "bias"), indice_key="k"), norm]
        layers += [torch.nn.ReLU()] if relu else []
    net = spnn.SparseSequential(*layers).to(device).eval()
    twin = copy.deepcopy(net).double()
    what = f"{len(chans) - 1} SubM layers {chans}, kernel {k}, ReLUs {relus} on {tuple(s.indices.shape)} sites"
    _float32_equals_float64_twin(net, twin, s, device, 5e-4, what)
