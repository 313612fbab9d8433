"""CAS-Net (lidarops.models.casnet): shapes, hard mode as a true subset, the straight-through gradient, ball-query
padding that never leaks into features, ragged batches equal to the clouds alone, duplicates and their greedy
reassignment, segmenting, the sampler adapter and the loss."""
from __future__ import annotations

import math

import pytest
import torch

from lidarops.models.casnet import (CASNet, CASNetOutput, CASNetSampler, FeatureEmbedding, casnet_loss,
                                    count_duplicates, greedy_distinct_rows, matrix_sample, segment_and_sample)
from lidarops.models.casnet_losses import chamfer_distance, selection_cosine_loss
from lidarops.models.samplers import segment_shares, spatial_segments

from helpers.compare import assert_close_report
from helpers.devices import requires_cuda
from helpers.models import greedy_reference, randomize_bn


pytestmark = pytest.mark.usefixtures("one_thread")  # tiny tensors: OpenMP wake-ups cost more than the work

def tiny(num_out: int = 8, seed: int = 0, dtype=torch.float64, device="cpu", **kw) -> CASNet:
    """A small CAS-Net (k = 4, r = 0.5) with BatchNorm statistics far from the identity, in eval mode."""
    torch.manual_seed(seed)
    kw = {"k": 4, "radius": 0.5, **kw}
    net = CASNet(num_out, **kw)
    randomize_bn(net, seed)
    return net.to(device, dtype).eval()


def cloud(B: int, N: int, seed: int = 0, channels: int = 4, dtype=torch.float64, device="cpu") -> torch.Tensor:
    """(B, N, channels) points in [0, 1.5]^3 (neighbourhoods of a few points at r = 0.5) with extra channels."""
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(B, N, 3, generator=g, dtype=torch.float64) * 1.5
    extra = torch.rand(B, N, channels - 3, generator=g, dtype=torch.float64)
    return torch.cat([xyz, extra], -1).to(device, dtype)


def close(actual: torch.Tensor, expected, rtol: float = 1e-6, atol: float = 1e-6, what: str = "") -> None:
    """Within tolerance, reporting the largest difference and where (torch.testing's first call costs seconds)."""
    assert_close_report(actual, expected, rtol, atol, what or "values")


def rows_at(points: torch.Tensor, indices: torch.Tensor) -> torch.Tensor:
    return torch.stack([points[b, indices[b]] for b in range(points.shape[0])])


# ---- shapes and the true subset ----

def test_shapes_hard_and_soft(device):
    net = tiny(device=device)
    pts = cloud(2, 40, device=device)
    out = net(pts)
    assert isinstance(out, CASNetOutput) and out.mode == "hard"
    assert out.sampled.shape == (2, 8, 4) and out.sampled.dtype == pts.dtype
    assert out.sampled_xyz.shape == (2, 8, 3)
    assert out.indices.shape == (2, 8) and out.indices.dtype == torch.int64
    assert out.soft_matrix.shape == (2, 8, 40) and out.logits.shape == (2, 8, 40)
    close(out.soft_matrix.sum(-1), torch.ones(2, 8, dtype=pts.dtype, device=device))
    assert torch.equal(out.lengths, torch.tensor([40, 40], device=device))
    assert out.num_duplicates.shape == (2,)
    soft = net(pts, mode="soft")
    assert soft.indices is None and soft.num_duplicates is None and soft.sampled.shape == (2, 8, 4)
    close(soft.sampled, torch.bmm(soft.soft_matrix, pts))


def test_paper_layout():
    net = CASNet(16)
    assert (net.embedding.k, net.embedding.radius, net.embedding.neighbors) == (32, 2.0, "ball")
    assert len(net.attention) == 3
    assert net.head.layers[0].in_channels == 195 and net.head.layers[-2].out_channels == 16
    assert [type(m).__name__ for m in net.head.layers] == ["Conv1d", "BatchNorm1d", "Conv1d", "BatchNorm1d"]
    assert [type(m).__name__ for m in net.embedding.mlp] == ["Conv1d", "BatchNorm1d", "LeakyReLU"] * 2
    assert net.embedding.mlp[2].negative_slope == 0.2
    fast = CASNet.fast(16)
    assert len(fast.attention) == 1 and fast.embedding.k == 1 and fast.head.layers[0].in_channels == 67
    assert isinstance(CASNet(16, head_activation=True).head.layers[2], torch.nn.LeakyReLU)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("train", [False, True], ids=["eval", "train"])
def test_hard_mode_is_a_subset(device, dtype, train):
    net = tiny(device=device, dtype=torch.float32)
    net.train(train)
    pts = cloud(3, 50, seed=1, channels=5, dtype=dtype, device=device).requires_grad_(train)
    out = net(pts, torch.tensor([50, 31, 1], device=device))
    assert torch.equal(out.sampled, rows_at(pts, out.indices)), "hard rows must be the input rows, bit for bit"
    assert bool((out.indices[1] < 31).all()) and bool((out.indices[2] == 0).all())


def test_fast_variant_embeds_each_point_alone():
    """k = 1 nearest neighbour: every point's edge is [p, 0], whatever its neighbours."""
    torch.manual_seed(0)
    net = CASNet.fast(4).double().eval()
    randomize_bn(net, 1)
    xyz = cloud(1, 20, channels=3)
    emb = net.embedding(xyz, torch.tensor([20]))
    alone = net.embedding.mlp(torch.cat([xyz, torch.zeros_like(xyz)], -1).transpose(1, 2))
    close(emb, alone, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("training", [False, True], ids=["eval", "train"])
def test_fast_embedding_equals_the_searched_neighbourhoods(training):
    """k = 1 nearest neighbour skips the search: the same embedding (and BatchNorm statistics) as the searched
    neighbour, with duplicate points (whose nearest may be the twin) and a padded cloud."""
    emb = FeatureEmbedding(k=1, neighbors="knn").double()
    randomize_bn(emb, 3)
    twin = FeatureEmbedding(k=1, neighbors="knn").double()
    twin.load_state_dict(emb.state_dict())
    emb.train(training), twin.train(training)
    xyz = cloud(2, 30, channels=3)
    xyz[:, 20:] = xyz[:, :10]
    lengths = torch.tensor([30, 17])
    idx = twin.neighbour_indices(xyz, lengths)
    assert bool((idx[1, 17:] == -1).all()) and bool((idx[0, 20:, 0] != torch.arange(20, 30)).any()), \
        "some duplicate's nearest should be its twin, or the test proves less"
    close(emb(xyz, lengths), twin.embed(xyz, idx, idx >= 0), rtol=0, atol=0)
    for a, b in zip(emb.state_dict().values(), twin.state_dict().values()):
        close(a.double(), b.double(), rtol=1e-12, atol=1e-12)


# ---- the straight-through gradient ----

def _soft_backward_by_hand(logits, features, upstream):
    """d<upstream, S~ P>/d logits with S~ = softmax(logits): the softmax Jacobian applied to upstream P^T."""
    s = torch.softmax(logits, -1)
    ds = upstream @ features.transpose(1, 2)
    return s * (ds - (s * ds).sum(-1, keepdim=True))


@pytest.mark.parametrize("dedup", [False, True])
def test_straight_through_gradient_equals_soft(device, dedup):
    g = torch.Generator().manual_seed(0)
    logits = (torch.randn(2, 5, 12, generator=g, dtype=torch.float64) * 3).to(device)
    features = torch.randn(2, 12, 4, generator=g, dtype=torch.float64).to(device)
    upstream = torch.randn(2, 5, 4, generator=g, dtype=torch.float64).to(device)
    grads = {}
    for mode in ("hard", "soft"):
        lg = logits.clone().requires_grad_()
        ft = features.clone().requires_grad_()
        sampled, idx, _ = matrix_sample(lg, ft, mode=mode, dedup=dedup)
        sampled.backward(upstream)
        grads[mode] = (lg.grad, ft.grad, idx, sampled.detach())
    hard_logits, soft_logits = grads["hard"][0], grads["soft"][0]
    assert float(hard_logits.abs().max()) > 1e-3, "no gradient reached the logits through hard mode"
    close(hard_logits, soft_logits, rtol=1e-12, atol=1e-14)
    close(hard_logits, _soft_backward_by_hand(logits, features, upstream), rtol=1e-10,
                               atol=1e-12)
    # the features get the one-hot rows' S^T g in hard mode (S~^T g in soft mode)
    idx = grads["hard"][2]
    want = torch.zeros_like(features)
    for b in range(2):
        want[b].index_add_(0, idx[b], upstream[b])
    close(grads["hard"][1], want, rtol=0, atol=1e-14)
    assert torch.equal(grads["hard"][3], rows_at(features, idx))


def test_straight_through_through_the_model(device):
    """The same linear loss through the whole model: the gradient at the logits is the same in both modes."""
    net = tiny(device=device)
    net.train()  # batch statistics: the two forwards compute the same logits
    pts = cloud(2, 30, seed=2, device=device)
    upstream = torch.randn(2, 8, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).to(device)
    got = {}
    for mode in ("hard", "soft"):
        out = net(pts, mode=mode)
        got[mode] = torch.autograd.grad((out.sampled * upstream).sum(), out.logits)[0]
    assert float(got["hard"].abs().max()) > 0
    close(got["hard"], got["soft"], rtol=1e-12, atol=1e-14)
    out = net(pts)
    (out.sampled * upstream).sum().backward()
    assert net.head.layers[0].weight.grad is not None and float(net.head.layers[0].weight.grad.abs().max()) > 0
    assert float(net.embedding.mlp[0].weight.grad.abs().max()) > 0


# ---- ball-query padding ----

def _hand_cloud():
    """p0 has one neighbour within r = 1 besides itself (2 of k = 3 slots); p2..p5 are a row of four."""
    xyz = torch.tensor([[0.0, 0, 0], [0.5, 0, 0], [3.0, 0, 0], [3.2, 0, 0], [3.4, 0, 0], [3.6, 0, 0]],
                       dtype=torch.float64)
    return xyz.unsqueeze(0)


def _embedding(seed=0):
    torch.manual_seed(seed)
    emb = FeatureEmbedding(k=3, radius=1.0).double()
    randomize_bn(emb, seed)
    return emb.eval()


def test_padding_slots_are_not_points():
    emb = _embedding()
    xyz = _hand_cloud()
    with_nan = torch.cat([xyz, torch.full((1, 1, 3), math.nan, dtype=xyz.dtype)], 1)  # a padding row
    idx = emb.neighbour_indices(with_nan, torch.tensor([6]))
    assert idx[0, 0].tolist() == [0, 1, -1] and idx[0, 5].tolist() == [2, 3, 4] and idx[0, 6].tolist() == [-1] * 3
    out = emb(xyz, torch.tensor([6]))
    # by hand: the max over p0's two real edges [p0, pj - p0]
    p0 = xyz[0, 0]
    edges = torch.stack([torch.cat([p0, xyz[0, j] - p0]) for j in (0, 1)])  # (2, 6)
    want = emb.mlp(edges.t().unsqueeze(0)).amax(-1)[0]
    close(out[0, :, 0], want, rtol=1e-12, atol=1e-12)
    # the padded slot pointing at any coordinates (here a NaN row past the cloud, or the far p5) changes nothing
    valid = idx >= 0
    for fill in (6, 5):
        filled = torch.where(valid, idx, torch.full_like(idx, fill))
        got = emb.embed(with_nan, filled, valid)
        # equal to rounding: the padded slot's column changes the matmul's blocking
        close(got[..., :6], out, rtol=1e-13, atol=1e-13)
        assert bool((got[..., 6] == 0).all())  # no neighbour at all: the zero vector
    # treating the slot as a point would change p0's embedding: the check above can fail
    idx, valid = idx[:, :6], valid[:, :6]
    leaky = emb.embed(xyz, torch.where(valid, idx, torch.full_like(idx, 5)), torch.ones_like(valid))
    assert not torch.allclose(leaky[0, :, 0], out[0, :, 0])
    close(leaky[0, :, 2:], out[0, :, 2:], rtol=1e-12, atol=1e-12)  # full neighbourhoods agree


def test_padding_slots_stay_out_of_batchnorm_statistics():
    emb = _embedding().train()
    bn = emb.mlp[1]
    bn.reset_running_stats()
    xyz = _hand_cloud()
    idx = emb.neighbour_indices(xyz, torch.tensor([6]))
    emb(xyz, torch.tensor([6]))
    real = [(i, int(j)) for i in range(6) for j in idx[0, i] if j >= 0]
    assert len(real) == 2 + 2 + 3 * 4  # p0, p1: 2 each; p2..p5: 3 each (k = 3 of 4 in range)
    edges = torch.stack([torch.cat([xyz[0, i], xyz[0, j] - xyz[0, i]]) for i, j in real])
    h = emb.mlp[0](edges.t().unsqueeze(0))[0]  # (64, 16)
    close(bn.running_mean, bn.momentum * h.mean(1), rtol=1e-12, atol=1e-12)
    close(bn.running_var, (1 - bn.momentum) + bn.momentum * h.var(1, unbiased=True),
                               rtol=1e-12, atol=1e-12)


def test_knn_option_pads_short_clouds():
    torch.manual_seed(0)
    emb = FeatureEmbedding(k=5, neighbors="knn").double().eval()
    xyz = _hand_cloud()[:, :3]
    idx = emb.neighbour_indices(xyz, torch.tensor([3]))
    assert bool((idx[0, :, 3:] == -1).all())
    out = emb(xyz, torch.tensor([3]))
    short = FeatureEmbedding(k=3, neighbors="knn").double().eval()
    short.load_state_dict(emb.state_dict())
    close(out, short(xyz, torch.tensor([3])), rtol=1e-13, atol=1e-13)  # rounding: k changes the matmul's width


# ---- ragged batches: padded rows are not there ----

@pytest.mark.parametrize("mode", ["hard", "soft"])
def test_padded_cloud_equals_the_cloud_alone(device, mode):
    net = tiny(device=device)
    pts = cloud(2, 40, seed=3, device=device)
    alone = net(pts[:1, :27], mode=mode)
    padded = pts.clone()
    padded[0, 27:] = math.nan  # padding rows may hold anything
    out = net(padded, torch.tensor([27, 40], device=device), mode=mode)
    close(out.logits[:1, :, :27], alone.logits, rtol=1e-10, atol=1e-10)
    assert bool(torch.isinf(out.logits[0, :, 27:]).all()) and bool((out.soft_matrix[0, :, 27:] == 0).all())
    close(out.sampled[:1], alone.sampled, rtol=1e-10, atol=1e-10)
    if mode == "hard":
        assert torch.equal(out.indices[:1], alone.indices)


def test_padded_cloud_equals_the_cloud_alone_in_training(device):
    """Batch statistics too: every BatchNorm sees the real points only."""
    net = tiny(device=device).train()
    pts = cloud(1, 40, seed=4, device=device)
    alone = net(pts[:, :29])
    out = net(pts, torch.tensor([29], device=device))
    close(out.logits[:, :, :29], alone.logits, rtol=1e-9, atol=1e-9)
    assert torch.equal(out.indices, alone.indices)


# ---- duplicates and the greedy reassignment ----

def test_count_duplicates():
    idx = torch.tensor([[0, 1, 2, 3], [5, 5, 5, 1], [2, -1, -1, 2]])
    assert count_duplicates(idx).tolist() == [0, 2, 1]


def test_greedy_distinct_rows_by_hand():
    # rows 0 and 1 both prefer point 0; row 1 is surer, so row 0 takes its second choice
    scores = torch.tensor([[[0.9, 0.8, 0.1], [0.95, 0.0, 0.0], [0.0, 0.0, 0.5]]]).log()
    assert greedy_distinct_rows(scores).tolist() == [[1, 0, 2]]
    assert torch.argmax(scores, -1).tolist() == [[0, 0, 2]]


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("m, N, valid, spread", [(7, 9, 5, 0.5), (12, 50, 10, 0.5), (40, 90, 90, 0.01),
                                                 (40, 90, 60, 3.0)])
def test_greedy_distinct_rows_equals_the_sequential_greedy(seed, m, N, valid, spread):
    """Alike rows (small spread: many conflicts, candidate lists that must grow), clouds with fewer valid
    points than rows (some rows must repeat), rows that disagree."""
    g = torch.Generator().manual_seed(seed)
    base = torch.randn(2, 1, N, generator=g) * 2
    scores = torch.log_softmax(base + spread * torch.randn(2, m, N, generator=g), -1)
    mask = torch.ones(2, N, dtype=torch.bool)
    mask[1, valid:] = False
    got = greedy_distinct_rows(scores, mask)
    assert torch.equal(got, greedy_reference(scores, mask))
    assert got[0].unique().numel() == m
    assert got[1].unique().numel() == min(m, valid) and bool((got[1] < valid).all())


def test_dedup_in_the_model(device):
    net = tiny(num_out=16, device=device)
    pts = cloud(2, 40, seed=5, device=device)
    plain, dedup = net(pts), net(pts, dedup=True)
    assert int(plain.num_duplicates.sum()) > 0, "an untrained model should repeat picks (else this test is moot)"
    assert dedup.num_duplicates.tolist() == [0, 0]
    assert all(dedup.indices[b].unique().numel() == 16 for b in range(2))
    assert torch.equal(dedup.sampled, rows_at(pts, dedup.indices))
    # the greedy assignment of the rows' log-probabilities (not "uncontested rows keep their pick": a row that
    # lost its first choice may outbid one for its second)
    assert torch.equal(dedup.indices.cpu(), greedy_reference(torch.log_softmax(plain.logits, -1).cpu()))
    assert net.dedup is False and CASNet(4, dedup=True).dedup is True


# ---- segments and the sampler ----

def test_segment_and_sample_covers_every_segment(device):
    net = tiny(num_out=16, dtype=torch.float32, device=device)
    pts = cloud(1, 700, seed=6, dtype=torch.float32, device=device)[0] * 3
    segs = spatial_segments(pts, 64)
    assert len(segs) == 11
    for dedup in (False, True):
        idx = segment_and_sample(net, pts, ratio=4, dedup=dedup)
        assert idx.shape == (11 * 16,) and idx.dtype == torch.int64
        for i, seg in enumerate(segs):
            part = idx[16 * i:16 * (i + 1)]
            assert bool(torch.isin(part, seg).all()), f"segment {i}: picks outside the segment"
            if dedup:
                assert part.unique().numel() == 16
        if dedup:
            assert idx.unique().numel() == idx.numel()
    # exactly n / D samples: each segment its share, distinct
    idx = segment_and_sample(net, pts, ratio=4, num_samples=175, dedup=True)
    assert idx.numel() == 175 and idx.unique().numel() == 175
    shares = segment_shares([s.numel() for s in segs], 175, caps=[16] * len(segs))
    assert [int(torch.isin(idx, s).sum()) for s in segs] == shares
    # as many as the segments give: a segment's proportional share (176 * 64 / 700 > 16) is capped at m
    idx = segment_and_sample(net, pts, ratio=4, num_samples=176, dedup=True)
    assert idx.numel() == 176 and idx.unique().numel() == 176
    assert [int(torch.isin(idx, s).sum()) for s in segs] == [16] * len(segs)


def test_segment_and_sample_one_segment_equals_the_model():
    net = tiny(num_out=8)
    pts = cloud(1, 30, seed=7)
    idx = segment_and_sample(net, pts[0], ratio=4)
    assert torch.equal(idx, net(pts).indices[0])


def test_segment_and_sample_errors():
    net = tiny(num_out=8)
    pts = cloud(1, 30)[0]
    with pytest.raises(ValueError, match="ratio"):
        segment_and_sample(net, pts, ratio=2048)
    with pytest.raises(ValueError, match="ratio"):
        segment_and_sample(net, pts, ratio=0)
    with pytest.raises(ValueError, match="points"):
        segment_and_sample(net, pts.unsqueeze(0), ratio=2)
    with pytest.raises(ValueError, match="num_samples"):
        segment_and_sample(net, pts, ratio=2, num_samples=17)
    assert segment_and_sample(net, pts[:0], ratio=2).numel() == 0


def test_casnet_sampler(device):
    net = tiny(num_out=16, dtype=torch.float32, device=device)
    pts = cloud(2, 300, seed=8, dtype=torch.float32, device=device)
    sampler = CASNetSampler(net)
    idx = sampler(pts, 37, torch.tensor([300, 20], device=device))
    assert idx.shape == (2, 37)
    assert idx[0].unique().numel() == 37 and bool(((idx[0] >= 0) & (idx[0] < 300)).all())
    assert sorted(idx[1, :20].tolist()) == list(range(20)) and bool((idx[1, 20:] == -1).all())
    with pytest.raises(ValueError, match="m="):
        CASNetSampler(net, ratio=8)(pts, 100)
    with pytest.raises(ValueError, match="model"):
        CASNetSampler("net")
    with pytest.raises(ValueError, match="max_points"):
        CASNetSampler(net, max_points=8)


# ---- the loss ----

def test_casnet_loss():
    net = tiny(num_out=8).train()
    pts = cloud(2, 30, seed=9)
    lengths = torch.tensor([30, 21])
    out = net(pts, lengths)
    task = torch.tensor(0.25, dtype=torch.float64)
    losses = casnet_loss(out, pts, task, alpha=0.5, beta=2.0)
    cd = chamfer_distance(out.sampled_xyz, pts[..., :3], b_lengths=lengths)
    cos = selection_cosine_loss(out.soft_matrix)
    close(losses["loss"], 0.25 + 0.5 * cd + 2.0 * cos)
    close(losses["loss_chamfer"], cd)
    frob = casnet_loss(out, pts, task, cosine_form="frobenius")["loss_cosine"]
    close(frob, selection_cosine_loss(out.soft_matrix, form="frobenius"))
    losses["loss"].backward()
    assert float(net.embedding.mlp[0].weight.grad.abs().max()) > 0
    for kw, name in ((dict(alpha=-1.0), "alpha"), (dict(beta=math.nan), "beta"), (dict(beta=True), "beta")):
        with pytest.raises(ValueError, match=name):
            casnet_loss(out, pts, task, **kw)
    with pytest.raises(ValueError, match="task_loss"):
        casnet_loss(out, pts, torch.zeros(2))
    with pytest.raises(ValueError, match="points"):
        casnet_loss(out, pts[:, :20], task)
    with pytest.raises(ValueError, match="form"):
        casnet_loss(out, pts, task, cosine_form="sum")


# ---- argument checks ----

@pytest.mark.parametrize("args, name", [
    (("cloud",), "points"),
    ((torch.zeros(5, 3),), "points"),
    ((torch.zeros(1, 5, 2),), "points"),
    ((torch.zeros(1, 5, 3, dtype=torch.int32),), "points"),
    ((torch.zeros(0, 5, 3),), "points"),
    ((torch.zeros(1, 0, 3),), "points"),
    ((torch.zeros(1, 5, 3), torch.tensor([0])), "lengths"),
    ((torch.zeros(1, 5, 3), torch.tensor([6])), "lengths"),
    ((torch.zeros(1, 5, 3), torch.tensor([2, 3])), "lengths"),
    ((torch.zeros(1, 5, 3), torch.tensor([2.0])), "lengths"),
    ((torch.tensor([[[0.0, math.nan, 0.0]] * 5]),), "points"),
    ((torch.zeros(1, 5, 3), None, "medium"), "mode"),
    ((torch.zeros(1, 5, 3), None, None, "yes"), "dedup"),
])
def test_forward_errors(args, name):
    net = tiny(num_out=2, dtype=torch.float32)
    with pytest.raises(ValueError, match=name):
        net(*args)


@pytest.mark.parametrize("kw, name", [
    (dict(num_out=0), "num_out"), (dict(num_out=2.0), "num_out"), (dict(k=0), "k"), (dict(radius=0.0), "radius"),
    (dict(radius=math.inf), "radius"), (dict(neighbors="grid"), "neighbors"), (dict(num_oa_layers=0), "num_oa_layers"),
    (dict(temperature=0.0), "temperature"), (dict(temperature=math.nan), "temperature"), (dict(mode="x"), "mode"),
    (dict(dedup=1), "dedup"), (dict(chunk=0), "chunk"), (dict(channels=0), "channels"),
])
def test_constructor_errors(kw, name):
    kw = {"num_out": 4, **kw}
    with pytest.raises(ValueError, match=name):
        CASNet(**kw)


@requires_cuda
def test_points_on_another_device():
    with pytest.raises(ValueError, match="points"):
        tiny(num_out=2, device="cuda")(torch.zeros(1, 5, 3))


@requires_cuda
def test_cpu_cuda_parity():
    # float64: the same picks and the same matrix to rounding; float32: the matrix within float32's
    # accumulated rounding (three attention layers deep), the picks checked in float64 only (near-ties)
    net = tiny(num_out=16, dtype=torch.float64)
    pts = cloud(2, 200, seed=10, dtype=torch.float64) * 2
    lengths = torch.tensor([200, 150])
    cpu = net(pts, lengths, dedup=True)
    gpu = net.cuda()(pts.cuda(), lengths.cuda(), dedup=True)
    close(gpu.soft_matrix.cpu(), cpu.soft_matrix, rtol=1e-9, atol=1e-12)
    assert torch.equal(gpu.indices.cpu(), cpu.indices)
    idx_cpu = segment_and_sample(net.cpu(), pts[0], ratio=4, num_samples=50, dedup=True)
    idx_gpu = segment_and_sample(net.cuda(), pts[0].cuda(), ratio=4, num_samples=50, dedup=True)
    assert torch.equal(idx_gpu.cpu(), idx_cpu)
    net32 = tiny(num_out=16, dtype=torch.float32)
    cpu32 = net32(pts.float(), lengths).soft_matrix
    gpu32 = net32.cuda()(pts.float().cuda(), lengths.cuda()).soft_matrix.cpu()
    close(gpu32, cpu32, rtol=2e-3, atol=1e-5)
