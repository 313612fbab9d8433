"""GraphedSparseNet: a sparse network replayed as one CUDA graph while its sites stay the same.

Reference: the same network called eagerly on a new SparseConvTensor (no indice_dict) with the same sites and
features, which builds its maps afresh. Every call of a sequence compares with it, so a replay that reads a stale
input, stale maps or stale BatchNorm statistics fails. On CPU every call is eager (no graph); the counters say
which path ran.
"""
from __future__ import annotations

import pytest
import torch
from torch import nn

from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.sparse import GraphedSparseNet, SparseConvTensor
from lidarops.sparse import nn as spnn
from helpers.devices import requires_cuda
from helpers.sparse import TOL, random_sites

SHAPE = [24, 20]


class Branches(nn.Module):
    """Down path, an inverse convolution back up, a max pool and a transposed branch, with a dense output: the
    output carries none of the maps, so they must come from the recording."""

    def __init__(self, c=8, up_key="up"):
        super().__init__()
        bn = lambda n: nn.BatchNorm1d(n, eps=1e-3)  # noqa: E731
        self.down = spnn.SparseSequential(
            spnn.SubMConv2d(c, c, 3, bias=False, indice_key="s0"), bn(c), nn.ReLU(),
            spnn.SparseConv2d(c, 2 * c, 3, stride=2, padding=1, bias=False, indice_key="d0"), bn(2 * c), nn.ReLU(),
            spnn.SubMConv2d(2 * c, 2 * c, 3, bias=True, indice_key="s1"), bn(2 * c), nn.ReLU(),
            spnn.SubMConv2d(2 * c, 2 * c, 3, bias=False, indice_key="s1"))
        self.back = spnn.SparseSequential(spnn.SparseInverseConv2d(2 * c, c, 3, indice_key="d0"), bn(c), nn.ReLU(),
                                          spnn.SubMConv2d(c, c, 3, bias=False, indice_key="b0"))
        self.pool = spnn.SparseMaxPool2d(2, 2, indice_key="p0")
        self.up = spnn.SparseSequential(spnn.SparseConvTranspose2d(2 * c, c, 2, stride=2, bias=False,
                                                                   indice_key=up_key), bn(c), nn.ReLU())

    def forward(self, x):
        d = self.down(x)
        a = self.back(d).dense()
        b = self.up(self.pool(d)).dense()
        h, w = min(a.shape[2], b.shape[2]), min(a.shape[3], b.shape[3])
        return {"map": torch.cat([a[:, :, :h, :w], b[:, :, :h, :w]], 1), "sparse": d}


def _net(device, dtype=torch.float32, seed=0, **kw):
    torch.manual_seed(seed)
    net = Branches(**kw)
    for m in net.modules():  # statistics away from the identity, so a stale fold shows
        if isinstance(m, nn.BatchNorm1d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    return net.to(device=device, dtype=dtype).eval()


def _sites(seed, device, batch=2):
    return random_sites(batch, SHAPE, 60, seed, empty_middle=False).to(device)


def _x(indices, seed, dtype=torch.float32, c=8):
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(indices.shape[0], c, generator=g, dtype=torch.float64)
    return SparseConvTensor(f.to(device=indices.device, dtype=dtype), indices, SHAPE, 2)


def _assert_same_result(got, want, dtype, what):
    assert isinstance(got, dict) and got.keys() == want.keys(), what
    tol = TOL[dtype]
    ref = want["map"].double()
    scale = max(1.0, float(ref.abs().max()))
    assert float((got["map"].double() - ref).abs().max()) <= tol * scale, what
    assert torch.equal(got["sparse"].indices, want["sparse"].indices), what
    f_ref = want["sparse"].features.double()
    assert float((got["sparse"].features.double() - f_ref).abs().max()) <= tol * max(1.0, float(f_ref.abs().max())), what


def _eager(net, x):
    """The reference: a fresh tensor, no maps."""
    return net(SparseConvTensor(x.features.clone(), x.indices.clone(), x.spatial_shape, x.batch_size))


def test_every_call_equals_the_eager_network(device):
    net = _net(device)
    g = GraphedSparseNet(net)
    a, b = _sites(1, device), _sites(2, device)
    # (sites, features seed, the path on CUDA): same tensor, an equal copy, other sites, back again
    calls = [(a, 0, "eager"), (a, 1, "capture"), (a.clone(), 2, "replay"), (b, 3, "eager"), (a, 4, "replay"),
             (b, 5, "capture"), (b.clone(), 6, "replay"), (a, 7, "eager"), (a, 8, "capture")]
    cuda = device == "cuda"
    with torch.no_grad():
        for i, (sites, seed, path) in enumerate(calls):
            before = (g.replays, g.captures, g.eager_calls)
            x = _x(sites, seed)
            _assert_same_result(g(x), _eager(net, x), torch.float32, f"call {i}")
            after = (g.replays, g.captures, g.eager_calls)
            if not cuda:
                path = "eager"
            want = {"eager": (0, 0, 1), "capture": (1, 1, 0), "replay": (1, 0, 0)}[path]
            assert tuple(q - p for p, q in zip(before, after)) == want, f"call {i}: {before} -> {after}, want {path}"
    assert g.reason is None


def test_float64_and_inference_mode(device):
    net = _net(device, torch.float64, seed=3)
    g = GraphedSparseNet(net)
    a = _sites(4, device)
    with torch.inference_mode():
        for seed in range(3):
            x = _x(a, seed, torch.float64)
            _assert_same_result(g(x), _eager(net, x), torch.float64, f"inference mode, call {seed}")
    with torch.no_grad():  # the graph recorded in inference mode, called outside it
        x = _x(a, 9, torch.float64)
        _assert_same_result(g(x), _eager(net, x), torch.float64, "after inference mode")
    if device == "cuda":
        assert g.captures == 1 and g.replays == 3, g


@requires_cuda
def test_outputs_are_copies_unless_asked():
    net = _net("cuda")
    a = _sites(5, "cuda")
    with torch.no_grad():
        for clone in (True, False):
            g = GraphedSparseNet(net, clone_outputs=clone)
            for s in range(2):
                g(_x(a, s))
            first = g(_x(a, 10))
            kept = first["map"].clone()
            second = g(_x(a, 11))
            assert g.replays == 3, g  # the recording call replays too
            assert (first["map"].data_ptr() == second["map"].data_ptr()) is not clone
            if clone:
                assert torch.equal(first["map"], kept)
            else:  # the graph's own output, overwritten by the next replay
                assert not torch.equal(first["map"], kept)


def _graphed_after(net, sites, calls: int) -> GraphedSparseNet:
    """A GraphedSparseNet of ``net`` after ``calls`` calls on ``sites`` (features seeds 0, 1, ...)."""
    g = GraphedSparseNet(net)
    with torch.no_grad():
        for s in range(calls):
            g(_x(sites, s))
    return g


@requires_cuda
def test_changed_parameters_record_again():
    net = _net("cuda")
    a = _sites(6, "cuda")
    g = _graphed_after(net, a, 3)
    assert g.captures == 1
    with torch.no_grad():
        bn = net.down[1]
        bn.running_var.mul_(3.0)  # folded into the recorded scale: stale unless recorded again
        x = _x(a, 20)
        _assert_same_result(g(x), _eager(net, x), torch.float32, "after a BatchNorm change")
        net.down[0].weight.add_(0.5)
        x = _x(a, 21)
        _assert_same_result(g(x), _eager(net, x), torch.float32, "after a weight change")
    assert g.captures == 3, g


@requires_cuda
def test_autocast_and_tf32_are_part_of_the_key():
    net = _net("cuda")
    g = GraphedSparseNet(net)
    a = _sites(7, "cuda")
    old = torch.backends.cuda.matmul.allow_tf32
    try:
        with torch.no_grad():
            for s in range(3):
                with torch.autocast("cuda", dtype=torch.float16):
                    x = _x(a, s)
                    want = _eager(net, x)
                    got = g(x)
                assert got["map"].dtype == want["map"].dtype == torch.float16
                _assert_same_result(got, want, torch.float16, f"fp16 call {s}")
            assert g.captures == 1 and g.replays == 2
            x = _x(a, 5)
            _assert_same_result(g(x), _eager(net, x), torch.float32, "float32 after fp16")
            assert g.captures == 2, g  # the same sites: recorded again at once, on the same maps
            torch.backends.cuda.matmul.allow_tf32 = not old
            x = _x(a, 6)
            _assert_same_result(g(x), _eager(net, x), torch.float32, "TF32 flipped")
            assert g.captures == 3 and g.eager_calls == 1 and g.replays == 4, g
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old


def test_gradients_and_training_run_eagerly(device):
    net = _net(device)
    g = GraphedSparseNet(net)
    a = _sites(8, device)
    for s in range(3):  # gradients enabled, parameters requiring them
        out = g(_x(a, s))
        assert out["map"].requires_grad
    out["map"].sum().backward()
    assert net.down[0].weight.grad is not None
    net.train()
    with torch.no_grad():
        for s in range(3):
            g(_x(a, s))
    assert g.eager_calls == 6 and g.captures == g.replays == 0


def test_a_strided_map_without_a_key_stays_eager(device):
    net = _net(device)
    net.pool.indice_key = None  # the pooling map is built every call: a host read (its output count)
    g = GraphedSparseNet(net)
    a = _sites(9, device)
    with torch.no_grad():
        for s in range(4):
            x = _x(a, s)
            _assert_same_result(g(x), _eager(net, x), torch.float32, f"call {s}")
    assert g.captures == 0 and g.eager_calls == 4, g
    if device == "cuda":  # found by the first call's recording, before any capture is tried
        assert g.reason is not None and "pool layer without an indice_key" in g.reason, g
        assert "eager only" in repr(g)
        g.reset()
        assert g.reason is None


class _Reads(nn.Module):
    """A network that reads a value back to the host in its forward."""

    def __init__(self):
        super().__init__()
        self.net = _net("cuda")

    def forward(self, x):
        out = self.net(x)
        return {"map": out["map"] * float(x.features.abs().sum() > 0), "sparse": out["sparse"]}


@requires_cuda
def test_a_host_read_in_the_forward_stays_eager():
    """The capture is tried and fails (compute-sanitizer reports the failed capture's API errors: expected)."""
    net = _Reads().eval()
    g = GraphedSparseNet(net)
    a = _sites(14, "cuda")
    with torch.no_grad():
        for s in range(4):
            x = _x(a, s)
            _assert_same_result(g(x), _eager(net, x), torch.float32, f"call {s}")
    assert g.reason is not None and "cannot be recorded" in g.reason, g
    assert g.captures == 0 and g.eager_calls == 4, g


def test_one_key_on_two_sets_of_sites_is_refused_a_graph(device):
    net = _net(device, up_key="b0")  # the two branches each register "b0": the eager forward is right (the branches
    # fork the indice_dict), but no one dict can hold both maps
    g = GraphedSparseNet(net)
    a = _sites(10, device)
    with torch.no_grad():
        for s in range(3):
            x = _x(a, s)
            _assert_same_result(g(x), _eager(net, x), torch.float32, f"call {s}")
    if device == "cuda":
        assert g.reason is not None and "indice_key" in g.reason
    assert g.captures == 0


@requires_cuda
def test_sites_changed_in_place_run_eagerly():
    net = _net("cuda")
    g = GraphedSparseNet(net)
    a = _sites(11, "cuda")
    with torch.no_grad():
        for s in range(3):
            g(_x(a, s))
        a.copy_(_sites(12, "cuda"))  # the recorded tensor, changed in place: its maps are stale
        x = _x(a, 3)
        _assert_same_result(g(x), _eager(net, x), torch.float32, "after an in-place change")
    assert g.captures == 1 and g.replays == 2 and g.eager_calls == 2, g


def test_the_sparse_pointpillars_backbone(device):
    torch.manual_seed(0)
    bb = BaseBEVBackbone(16, layer_nums=(1, 2), layer_strides=(2, 2), num_filters=(16, 32),
                         upsample_strides=(1, 2), num_upsample_filters=(16, 16), mode="sparse").to(device).eval()
    g = GraphedSparseNet(bb)
    idx = random_sites(1, (32, 40), 150, 13).to(device)
    with torch.no_grad():
        for s in range(3):
            f = torch.randn(idx.shape[0], 16, generator=torch.Generator().manual_seed(s)).to(device)
            got = g(SparseConvTensor(f, idx, [32, 40], 1))
            want = bb(SparseConvTensor(f.clone(), idx.clone(), [32, 40], 1))
            assert torch.allclose(got, want, rtol=0, atol=TOL[torch.float32] * max(1.0, float(want.abs().max())))
    if device == "cuda":
        assert g.reason is None and g.captures == 1 and g.replays == 2, g


@requires_cuda
def test_a_recorded_graph_runs_every_map_with_its_row_order():
    # a replay costs no host time, so each map, also one a single layer runs on and an inverse one, carries its
    # order into the capture, which cannot make it
    g = _graphed_after(_net("cuda"), _sites(1, "cuda"), 2)
    assert g.captures == 1, g
    maps = g._graph[5].indice_dict
    assert {"s0", "d0", "s1", "b0", "p0", "up"} <= set(maps)
    for key, km in maps.items():
        assert km._order is not None, key
        assert torch.equal(km._order, torch.ops.lidarops.sparse_kernel_map_order(km.neighbors)), key
    assert maps["d0"]._inverse is not None and maps["d0"]._inverse._order is not None


@pytest.mark.parametrize("args,match", [((object(),), "net must be a torch.nn.Module"),
                                        ((nn.Identity(), "yes"), "clone_outputs must be True or False")])
def test_bad_arguments(args, match):
    with pytest.raises(ValueError, match=match):
        GraphedSparseNet(*args)


def test_bad_input():
    g = GraphedSparseNet(nn.Identity())
    with pytest.raises(ValueError, match="x must be a SparseConvTensor, got Tensor"):
        g(torch.zeros(3, 2))


def test_the_key_sees_every_parameter_and_buffer_change(device):
    """What decides a new recording (white box: on CPU no graph is recorded, but the key is the same code)."""
    net = _net(device)
    g = GraphedSparseNet(net)
    x = _x(_sites(15, device), 0)
    key = g._key(x)
    assert g._key(x) == key
    with torch.no_grad():
        net.down[1].running_var.mul_(2)  # in place
    assert g._key(x) != key
    key = g._key(x)
    net.up[0].weight = nn.Parameter(net.up[0].weight.detach().clone())  # replaced by another Parameter
    assert g._key(x) != key
    key = g._key(x)
    net.up[0].weight.data = net.up[0].weight.data.clone()  # the same Parameter, new memory
    assert g._key(x) != key
    key = g._key(x)
    net.down[3].bias = nn.Parameter(torch.zeros(16, device=device))  # a slot that held None
    assert g._key(x) != key
    key = g._key(x)
    with torch.autocast(device, dtype=torch.bfloat16):
        assert g._key(x) != key
    assert g._key(_x(_sites(15, device), 0, torch.float64)) != key
    with torch.inference_mode():
        net.down[1].running_mean = torch.zeros(8, device=device)  # an inference tensor: no version counter
    assert g._key(x) != key
    assert g._key(x) == g._key(x)
