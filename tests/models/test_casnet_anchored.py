"""CAS-Net's anchored head (lidarops.models.casnet.AnchoredHead, ours): the logits against a float64 re-statement
(farthest point samples, brute-force nearest candidates, the formula), an untrained head equal to farthest point
sampling, any number of rows, padding, the straight-through gradient, distinct picks on sparse rows, segments
and the whole-cloud sampler, the config keys."""
from __future__ import annotations

import copy
import math

import pytest
import torch

import lidarops
from lidarops.config import ConfigError
from lidarops.models.casnet import AnchoredHead, CASNet, CASNetSampler, greedy_distinct_rows, segment_and_sample
from lidarops.models.casnet_pointnet import CASNetPointNetConfig, casnet_of
from lidarops.models.samplers import segment_shares, spatial_segments

from helpers.compare import assert_close_report
from helpers.devices import requires_cuda
from helpers.models import greedy_reference, randomize_bn

pytestmark = pytest.mark.usefixtures("one_thread")


def anchored(num_out: int = 8, seed: int = 0, trained: bool = True, device="cpu", **kw) -> CASNet:
    """A small anchored CAS-Net in float64, eval mode; ``trained``: its zero-initialised layers drawn at random
    (so that the feature terms matter), BatchNorm statistics far from the identity."""
    torch.manual_seed(seed)
    net = CASNet(num_out, k=4, radius=0.5, head="anchored", **{"candidates": 5, **kw})
    randomize_bn(net, seed)
    if trained:
        with torch.no_grad():
            for layer in (net.head.key, net.head.score):
                layer.weight.normal_(0, 0.5)
                layer.bias.normal_(0, 0.5)
            net.head.log_scale.fill_(0.3)
    return net.to(device, torch.float64).eval()


def cloud(B: int, N: int, seed: int = 0, device="cpu") -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(B, N, 3, generator=g, dtype=torch.float64) * 1.5
    return torch.cat([xyz, torch.rand(B, N, 1, generator=g, dtype=torch.float64)], -1).to(device)


def reference_logits(net: CASNet, points: torch.Tensor, n: int, m: int) -> torch.Tensor:
    """The anchored head's logits (m, N) for the first ``n`` points of one cloud, restated in float64: the
    anchors by lidarops.fps (its own tests hold it to a reference), the candidates by sorting all distances."""
    head = net.head
    xyz = points[:n, :3]
    with torch.no_grad():
        x = net.embedding(xyz.unsqueeze(0), torch.tensor([n]))
        feats = []
        for layer in net.attention:
            x = layer(x)
            feats.append(x)
        z = head.hidden(torch.cat(feats + [xyz.t().unsqueeze(0)], 1))[0]  # (hidden, n)
        q, k, u = head.query.weight[:, :, 0] @ z + head.query.bias[:, None], \
            head.key.weight[:, :, 0] @ z + head.key.bias[:, None], head.score.weight[0, :, 0] @ z + head.score.bias
    anchors = lidarops.fps(xyz.unsqueeze(0), m)[0]
    anchors = torch.where(anchors >= 0, anchors, anchors[torch.arange(m) % n])
    K = min(head.candidates, n)
    d2_all = ((xyz[anchors][:, None, :] - xyz[None]) ** 2).sum(-1)  # (m, n)
    cand = torch.sort(d2_all, dim=1, stable=True).indices[:, :K]
    d2 = d2_all.gather(1, cand)
    scale = d2.mean() * head.log_scale.exp()
    out = torch.full((m, points.shape[0]), -math.inf, dtype=torch.float64)
    for i in range(m):
        for c in range(K):
            j = int(cand[i, c])
            out[i, j] = -d2[i, c] / scale + float(q[:, anchors[i]] @ k[:, j]) / math.sqrt(head.qk_channels) + u[j]
    return out / net.temperature


@pytest.mark.parametrize("m", [3, 8, 13])
def test_logits_equal_the_restated_formula(m):
    net = anchored(seed=1)
    pts = cloud(1, 40, seed=2)
    out = net(pts, num_out=m)
    assert out.logits.shape == (1, m, 40)
    assert_close_report(out.logits[0], reference_logits(net, pts[0], 40, m), 1e-10, 1e-10, "anchored logits")
    # every pick is one of its row's candidates, the softmax's argmax among them
    finite = torch.isfinite(out.logits[0])
    assert (finite.sum(1) == net.head.candidates).all()
    assert finite.gather(1, out.indices[0].unsqueeze(1)).all()


def test_untrained_head_is_farthest_point_sampling(device):
    torch.manual_seed(0)
    net = CASNet(16, k=4, radius=0.5, head="anchored").to(device).eval()
    pts = cloud(2, 90, seed=3, device=device).float()
    lengths = torch.tensor([90, 41], device=device)
    out = net(pts, lengths)
    expected = lidarops.fps(pts[..., :3], 16, lengths)
    assert torch.equal(out.indices, expected)
    assert int(out.num_duplicates.sum()) == 0
    # the same in training mode (batch statistics do not change an untrained head's picks)
    assert torch.equal(net.train()(pts, lengths).indices, expected)


def test_rows_are_free_and_short_clouds_repeat_their_anchors():
    net = anchored()
    pts = cloud(2, 30, seed=4)
    lengths = torch.tensor([30, 6])
    for m in (1, 7, 25):
        out = net(pts, lengths, num_out=m)
        assert out.indices.shape == (2, m) and out.soft_matrix.shape == (2, m, 30)
        assert bool((out.indices[1] < 6).all())
        assert torch.allclose(out.soft_matrix.sum(-1), torch.ones(2, m, dtype=torch.float64))
    out = net(pts, lengths, num_out=9)  # the short cloud's rows past 6 reuse anchors 0, 1, 2
    assert torch.equal(out.indices[1, 6:9], out.indices[1, :3])


def test_padded_cloud_equals_the_cloud_alone():
    net = anchored(seed=5)
    pts = cloud(2, 50, seed=6)
    pts[1, 33:] = float("nan")
    out = net(pts, torch.tensor([50, 33]), num_out=10)
    alone = net(pts[1:, :33], num_out=10)
    assert torch.equal(out.indices[1], alone.indices[0])
    assert_close_report(out.logits[1, :, :33], alone.logits[0], 1e-10, 1e-10, "padded logits")
    assert bool(torch.isinf(out.logits[1, :, 33:]).all()) and bool((out.soft_matrix[1, :, 33:] == 0).all())


def test_straight_through_gradient_reaches_the_head_and_the_output_is_a_subset():
    net = anchored(seed=7).train()
    pts = cloud(2, 60, seed=8)
    out = net(pts, num_out=12)
    for b in range(2):
        assert torch.equal(out.sampled[b], pts[b, out.indices[b]])
    upstream = torch.randn_like(out.sampled)
    (out.sampled * upstream).sum().backward()
    for name in ("key.weight", "score.weight", "query.weight", "log_scale"):
        g = dict(net.head.named_parameters())[name].grad
        assert g is not None and bool(g.abs().sum() > 0), name
    # the logits' gradient is soft mode's: upstream @ features^T through the softmax
    net.zero_grad()
    out = net(pts, num_out=12)
    logits = out.logits
    g_hard = torch.autograd.grad((out.sampled * upstream).sum(), logits, retain_graph=True)[0]
    soft = torch.softmax(logits, -1)
    g_soft = torch.autograd.grad((torch.bmm(soft, pts) * upstream).sum(), logits)[0]
    assert_close_report(g_hard, g_soft, 1e-10, 1e-10, "straight-through gradient")


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("m", [15, 30])
def test_distinct_picks_on_sparse_rows_equal_the_greedy(seed, m):
    net = anchored(seed=seed, candidates=3)
    pts = cloud(2, 40, seed=10 + seed)
    out = net(pts, num_out=m)
    scores = torch.log_softmax(out.logits.detach(), -1)
    got = greedy_distinct_rows(scores)
    expected = greedy_reference(scores)
    assert torch.equal(got, expected)
    assert torch.equal(net(pts, num_out=m, dedup=True).indices, got)
    assert torch.equal(net.pick(pts, num_out=m, dedup=True), got)


def test_distinct_picks_serve_every_row_when_rows_see_few_points():
    # four rows of three candidates each, all preferring point 0: every row still gets its own point
    inf = math.inf
    scores = torch.tensor([[[-1.0, -2.0, -3.0, -inf, -inf, -inf],
                            [-1.5, -inf, -2.5, -3.5, -inf, -inf],
                            [-1.2, -inf, -inf, -2.2, -3.2, -inf],
                            [-1.1, -inf, -inf, -inf, -2.1, -3.1]]])
    got = greedy_distinct_rows(scores)
    assert got.tolist() == [[0, 2, 3, 4]] and torch.equal(got, greedy_reference(scores))


@pytest.mark.parametrize("regime", ["random", "duplicates"])
def test_pick_equals_the_forward_picks(regime):
    net = anchored(seed=8, candidates=4)
    pts = cloud(3, 50, seed=16)
    if regime == "duplicates":  # ties everywhere: every point twice
        pts[:, 25:] = pts[:, :25]
    lengths = torch.tensor([50, 31, 9])
    for dedup in (False, True):
        for m in (5, 12):
            want = net(pts, lengths, num_out=m, dedup=dedup).indices
            assert torch.equal(net.pick(pts, lengths, num_out=m, dedup=dedup), want), (dedup, m)
    matrix = CASNet(6, k=4, radius=0.5).double().eval()
    assert torch.equal(matrix.pick(pts), matrix(pts).indices)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=requires_cuda)])
@pytest.mark.parametrize("fast", [False, True], ids=["ball", "fast"])
def test_inference_rows_equal_the_modules(fast, device):
    """pick's path on CUDA for full clouds in eval mode (rows, BatchNorm folded, packed head terms) against the
    modules': the embedding, the features, the head's terms, the logits and the picks."""
    torch.manual_seed(3)
    net = (CASNet.fast(8, head="anchored", candidates=5) if fast else
           CASNet(8, k=4, radius=0.5, num_oa_layers=2, head="anchored", candidates=5))
    randomize_bn(net, 3)
    with torch.no_grad():
        for layer in (net.head.key, net.head.score):
            layer.weight.normal_(0, 0.5)
            layer.bias.normal_(0, 0.5)
    net = net.to(device, torch.float64).eval()
    pts = cloud(2, 60, seed=21, device=device)
    xyz, lengths = pts[..., :3], torch.tensor([60, 60], device=device)
    assert_close_report(net.embedding.rows(xyz, lengths), net.embedding(xyz, lengths).transpose(1, 2), 1e-12, 1e-12,
                        "embedding rows")
    feats = net._attend_rows(xyz, lengths)
    assert_close_report(feats, net._attend(xyz, lengths, None).transpose(1, 2), 1e-11, 1e-12, "features")
    packed = net.head.project_rows(feats)
    q, k, u = net.head.project(feats.transpose(1, 2))
    assert_close_report(packed, torch.cat([q, k, u], -1), 1e-11, 1e-12, "packed terms")
    found = net.head.search(xyz, lengths, 12)
    want = net.head.logits((q, k, u), found)[0]
    assert_close_report(net.head.logits(packed, found, padded=False)[0], want, 1e-11, 1e-12, "logits")
    for dedup in (False, True):
        assert torch.equal(net.pick(pts, num_out=12, dedup=dedup), net(pts, num_out=12, dedup=dedup).indices)


def test_segments_keep_each_segments_first_anchors():
    torch.manual_seed(0)
    net = CASNet(16, k=4, radius=0.5, head="anchored").double().eval()
    pts = cloud(1, 200, seed=12)[0]
    got = segment_and_sample(net, pts, ratio=4, num_samples=37)
    segs = spatial_segments(pts, 64)
    shares = segment_shares([s.numel() for s in segs], 37, caps=[s.numel() for s in segs])
    expected = torch.cat([seg[lidarops.fps(pts[seg][None, :, :3], share)[0]]
                          for seg, share in zip(segs, shares) if share])
    assert torch.equal(got, expected)


def test_whole_cloud_sampler():
    torch.manual_seed(0)
    net = CASNet(16, k=4, radius=0.5, head="anchored").double().eval()
    pts = cloud(2, 120, seed=13)
    lengths = torch.tensor([120, 70])
    idx = CASNetSampler(net, whole=True)(pts, 30, lengths)
    assert torch.equal(idx, lidarops.fps(pts[..., :3], 30, lengths))
    trained = anchored(seed=3)
    idx = CASNetSampler(trained, whole=True)(pts, 30, lengths)
    assert all(idx[b].unique().numel() == 30 for b in range(2))
    with pytest.raises(ValueError, match="head='anchored'"):
        CASNetSampler(CASNet(8, k=4), whole=True)


def test_errors():
    with pytest.raises(ValueError, match="head must be one of"):
        CASNet(8, head="rows")
    with pytest.raises(ValueError, match="candidates"):
        CASNet(8, head="anchored", candidates=0)
    with pytest.raises(ValueError, match="num_out=5.*fixed"):
        CASNet(8, k=4)(cloud(1, 20).float(), num_out=5)
    with pytest.raises(ValueError, match="num_out"):
        anchored()(cloud(1, 20), num_out=0)
    assert isinstance(AnchoredHead(10).candidates, int)


def test_config_keys():
    cfg = CASNetPointNetConfig(head="anchored", candidates=7, task_checkpoint=None)
    net = casnet_of(cfg)
    assert net.head_kind == "anchored" and net.head.candidates == 7
    assert casnet_of(CASNetPointNetConfig(task_checkpoint=None)).head_kind == "matrix"
    with pytest.raises(ConfigError, match="MODEL.HEAD"):
        CASNetPointNetConfig(head="rows", task_checkpoint=None)
    with pytest.raises(ConfigError, match="MODEL.CANDIDATES"):
        CASNetPointNetConfig(candidates=0, task_checkpoint=None)


def test_save_and_load_keep_the_head(tmp_path):
    net = anchored(seed=2)
    path = net.save(tmp_path / "a.pth")
    back = CASNet.from_checkpoint(path).double().eval()
    pts = cloud(1, 40, seed=1)
    assert back.head_kind == "anchored" and torch.equal(back(pts, num_out=9).indices, net(pts, num_out=9).indices)


@requires_cuda
def test_cpu_cuda_parity():
    net = anchored(seed=4)
    pts = cloud(2, 300, seed=14)
    lengths = torch.tensor([300, 170])
    cpu = net(pts, lengths, num_out=40, dedup=True)
    gpu = net.to("cuda")(pts.cuda(), lengths.cuda(), num_out=40, dedup=True)
    assert torch.equal(gpu.indices.cpu(), cpu.indices)
    finite = torch.isfinite(cpu.logits)
    assert torch.equal(torch.isfinite(gpu.logits).cpu(), finite)
    assert_close_report(gpu.logits.cpu()[finite], cpu.logits[finite], 1e-9, 1e-9, "anchored logits, CUDA")
    whole = CASNetSampler(net, whole=True)(pts.cuda(), 50, lengths.cuda())
    assert torch.equal(whole.cpu(), CASNetSampler(net.cpu(), whole=True)(pts, 50, lengths))


@requires_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32-fused"])
def test_cuda_pick_equals_cpu_pick(dtype):
    """pick on CUDA (anchors and candidates on a second stream beside the features, distinct picks by the
    device's greedy) gives the CPU's picks; float32 with the fused attention (log-sum-exps from the kernel)."""
    chunk = "fused" if dtype == torch.float32 else "auto"
    net = anchored(seed=9, chunk=chunk, candidates=8).to(dtype)
    gpu = copy.deepcopy(net).cuda()
    pts = cloud(2, 2500, seed=19).to(dtype)
    lengths = torch.tensor([2500, 1700])

    def agree(got, want, what):
        if dtype == torch.float64:
            assert torch.equal(got, want), what
        else:  # float32 rounding may flip a near tie: nearly all picks agree
            assert float((got == want).double().mean()) > 0.99, what

    for dedup in (False, True):
        for m in (300, 900):
            want = net.pick(pts, lengths, num_out=m, dedup=dedup)
            got = gpu.pick(pts.cuda(), lengths.cuda(), num_out=m, dedup=dedup).cpu()
            agree(got, want, (dedup, m))
            if dedup:
                for b, n in enumerate(lengths.tolist()):
                    assert got[b].unique().numel() == min(m, n)
    # no lengths: the path without host reads for them
    agree(gpu.pick(pts[:1].cuda(), num_out=500, dedup=True).cpu(), net.pick(pts[:1], num_out=500, dedup=True), "full")


def fill_reference(xyz: torch.Tensor, idx: list) -> list:
    """_fill_repeats restated in float64 one row at a time: each repeat (a point an earlier row holds), rows in
    order, takes the free point nearest its pick (ties to the lower index); it stays when none is free."""
    xyz = xyz.double()
    taken, out, seen = set(idx), list(idx), set()
    for r, i in enumerate(idx):
        if i not in seen:
            seen.add(i)
            continue
        d2 = ((xyz - xyz[i]) ** 2).sum(1).tolist()
        free = [j for j in range(len(d2)) if j not in taken]
        if free:
            out[r] = min(free, key=lambda j: (d2[j], j))
            taken.add(out[r])
    return out


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=requires_cuda)])
def test_whole_cloud_picks_stay_distinct_when_candidates_run_out(device):
    from lidarops.models.casnet import _fill_repeats

    xyz = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [10, 0, 0]], device=device)
    # rows 2 and 3 repeat point 1: the free points nearest to it are 0 and 2 (a tie: row 2 takes the lower)
    assert _fill_repeats(xyz, torch.tensor([1, 4, 1, 1], device=device)).tolist() == [1, 4, 0, 2]
    # rows 2 and 3 repeat point 3: its nearest free points are 2 then 1
    assert _fill_repeats(xyz, torch.tensor([3, 4, 3, 3], device=device)).tolist() == [3, 4, 2, 1]
    # more rows than points: the rows past the free points keep their repeat
    assert _fill_repeats(xyz[:3], torch.tensor([1, 1, 1, 0], device=device)).tolist() == [1, 2, 1, 0]
    g = torch.Generator().manual_seed(0)
    for n, m in ((30, 30), (200, 60), (200, 199), (50, 40), (3000, 2500), (2100, 2100)):
        pts = torch.randint(0, 6, (n, 3), generator=g).double() * 0.5  # lattice points: many equal distances
        raw = torch.randint(0, n, (m,), generator=g)
        for dtype in (torch.float64, torch.float32):
            got = _fill_repeats(pts.to(device, dtype), raw.to(device))
            assert got.tolist() == fill_reference(pts, raw.tolist()), (n, m, dtype)
            assert got.unique().numel() == m
    assert torch.equal(_fill_repeats(xyz, torch.tensor([0, 4, 2], device=device)), torch.tensor([0, 4, 2], device=device))
    assert _fill_repeats(xyz, torch.zeros(0, dtype=torch.int64, device=device)).numel() == 0
    net = anchored(seed=6, candidates=4, device=device)
    pts = cloud(2, 30, seed=15, device=device)
    idx = CASNetSampler(net, whole=True)(pts, 30)
    assert all(idx[b].unique().numel() == 30 for b in range(2))
