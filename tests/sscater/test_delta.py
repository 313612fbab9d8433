"""lidarops.sscater: the delta-convolution ops against dense references, and the recycling backbone
against a full recomputation (``BaseBEVBackbone(mode="sparse")``) at every step of random
streams of pillar maps: pillars appear, vanish, change, and some steps change nothing (the streaming
PointPillars front built on them: tests/models/test_sscater_pointpillars.py)."""
from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from helpers.devices import DEVICES
from helpers.models import small_backbone
from lidarops import extension
from lidarops.sparse import SparseConvTensor
from lidarops.sscater import delta as delta_module
from lidarops.sscater.delta import DeltaBackbone

extension.load()
_ops = torch.ops.lidarops


def _dense_delta(H, W, sites, delta):
    img = delta.new_zeros(1, delta.shape[1], H, W)
    img[0, :, sites[:, 0].long(), sites[:, 1].long()] = delta.t()
    return img


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kind,k,s,p", [("conv", 3, 1, 1), ("conv", 3, 2, 1), ("transposed", 2, 2, 0),
                                        ("transposed", 4, 4, 0), ("transposed", 1, 1, 0), ("conv", 3, 2, 0)])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_scatter_equals_dense_convolution_of_the_delta(device, kind, k, s, p, dtype):
    g = torch.Generator().manual_seed(k * 10 + s)
    H, W, cin, cout = 13, 11, 5, 7
    keys = torch.randperm(H * W, generator=g)[:40]
    sites = torch.stack([keys // W, keys % W], 1).int()
    delta = torch.randn(40, cin, generator=g, dtype=torch.float64)
    weight = torch.randn(cout, k, k, cin, generator=g, dtype=torch.float64)
    img = _dense_delta(H, W, sites, delta)
    if kind == "conv":
        ref = F.conv2d(img, weight.permute(0, 3, 1, 2), None, s, p)[0].permute(1, 2, 0)
    else:
        ref = F.conv_transpose2d(img, weight.permute(3, 0, 1, 2), None, s, p)[0].permute(1, 2, 0)
    start = torch.randn(*ref.shape, generator=g, dtype=torch.float64)
    acc = start.to(device, dtype).clone()
    reached = _ops.sscater_scatter_(acc, sites.to(device), delta.to(device, dtype), weight.to(device, dtype), s, p,
                                    kind == "transposed")
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    assert (acc.double().cpu() - (start + ref)).abs().max() <= tol * (start + ref).abs().max()
    # the reached sites are exactly those where a one-hot delta at each site lands
    hit = (F.conv2d if kind == "conv" else lambda a, w, b, s_, p_: F.conv_transpose2d(a, w, b, s_, p_))(
        _dense_delta(H, W, sites, torch.ones(40, 1, dtype=torch.float64)), torch.ones(1, 1, k, k, dtype=torch.float64),
        None, s, p)[0, 0]
    got = reached.cpu()
    assert reached.shape == (40 * k * k,) and sorted(set(got[got >= 0].tolist())) == torch.nonzero(
        hit.flatten() > 0).flatten().tolist()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kind,k,s,p", [("conv", 3, 1, 1), ("conv", 3, 2, 1), ("transposed", 2, 2, 0)])
@pytest.mark.parametrize("cin,cout", [(5, 7), (33, 40), (64, 130), (300, 20)])  # 300: more channels than a block's threads
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_channel_sparse_scatter_equals_the_dense_convolution(device, kind, k, s, p, cin, cout, dtype):
    """The channel-sparse kernel (channel_sparse=0: always; > 1: never, the per-tap GEMM; 0.5: chosen from the
    zeros, on CUDA on the device) on deltas whose channels are mostly exactly 0, with whole-zero rows, padding
    rows, inactive outputs and a count: each equals the float64 dense convolution of the delta. On the CPU the
    sparse one gives the same bits whatever the thread count (its threads split the output channels)."""
    g = torch.Generator().manual_seed(cin * 100 + k * 10 + s)
    H, W, n = 14, 12, 50
    keys = torch.randperm(H * W, generator=g)[:n]
    sites = torch.stack([keys // W, keys % W], 1).int()
    sites[7] = -1  # a padding row
    delta = torch.randn(n, cin, generator=g, dtype=torch.float64)
    delta[torch.rand(n, cin, generator=g) < 0.65] = 0.0  # zero before and after ReLU
    delta[3] = 0.0
    weight = torch.randn(cout, k, k, cin, generator=g, dtype=torch.float64)
    real = sites[:, 0] >= 0
    counted = torch.arange(n) < 40  # count: the first 40 rows
    use = real & counted
    img = _dense_delta(H, W, sites[use], delta[use])
    if kind == "conv":
        ref = F.conv2d(img, weight.permute(0, 3, 1, 2), None, s, p)[0].permute(1, 2, 0)
    else:
        ref = F.conv_transpose2d(img, weight.permute(3, 0, 1, 2), None, s, p)[0].permute(1, 2, 0)
    active = torch.rand(ref.shape[:2], generator=g) > 0.3
    start = torch.randn(*ref.shape, generator=g, dtype=torch.float64)
    want = torch.where(active[..., None], start + ref, start)  # inactive outputs are left as they were
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    results = {}
    runs = (("sparse", 2), ("sparse", 1), ("gemm", 2)) if device == "cpu" else (("sparse", 0), ("gemm", 0),
                                                                                ("chosen", 0))
    for mode, threads in runs:
        acc = start.to(device=device, dtype=dtype, copy=True)
        saved = torch.get_num_threads()
        torch.set_num_threads(threads or saved)
        try:
            reached = _ops.sscater_scatter_(acc, sites.to(device), delta.to(device, dtype), weight.to(device, dtype), s,
                                            p, kind == "transposed", active.to(device), torch.tensor([40], device=device),
                                            {"sparse": 0.0, "gemm": 2.0, "chosen": 0.5}[mode])
        finally:
            torch.set_num_threads(saved)
        assert (acc.cpu().double() - want).abs().max() <= tol * want.abs().max(), (mode, threads)
        results[mode, threads] = (acc.cpu(), reached.cpu())
    if device == "cpu":
        assert torch.equal(results["sparse", 1][0], results["sparse", 2][0])
    first = next(iter(results.values()))[1]
    assert all(torch.equal(r[1], first) for r in results.values())  # the same reached sites


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("reach", ["every tap", "few taps"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_scatter_of_rows_that_reach_every_tap_or_few(device, reach, dtype):
    """The CPU's GEMM paths: rows whose taps almost all reach an active site take one GEMM by every tap's weights
    (in chunks of rows: 600 output channels x 9 taps make chunks of 776 rows, so two here), rows that reach few (most outputs inactive) one GEMM per
    tap over the rows that reach it. Both equal the float64 dense convolution of the delta at the active outputs."""
    g = torch.Generator().manual_seed(11)
    H, W, cin, cout = 48, 40, 24, 600
    inner = torch.stack(torch.meshgrid(torch.arange(1, H - 1), torch.arange(1, W - 1), indexing="ij"), -1).view(-1, 2)
    sites = inner[torch.randperm(inner.shape[0], generator=g)[:1500]].int()  # interior: all 9 taps inside the grid
    delta = torch.randn(sites.shape[0], cin, generator=g, dtype=torch.float64)
    delta[torch.rand(delta.shape, generator=g) < 0.5] = 0.0
    weight = torch.randn(cout, 3, 3, cin, generator=g, dtype=torch.float64)
    active = torch.ones(H, W, dtype=torch.bool) if reach == "every tap" else torch.rand(H, W, generator=g) < 0.2
    start = torch.randn(H, W, cout, generator=g, dtype=torch.float64)
    ref = F.conv2d(_dense_delta(H, W, sites, delta), weight.permute(0, 3, 1, 2), None, 1, 1)[0].permute(1, 2, 0)
    want = torch.where(active[..., None], start + ref, start)
    acc = start.to(device=device, dtype=dtype, copy=True)
    # tap-major memory, as DeltaBackbone holds the weight (the all-taps GEMM reads it without a copy)
    w = weight.permute(1, 2, 0, 3).contiguous().permute(2, 0, 1, 3).to(device, dtype)
    reached = _ops.sscater_scatter_(acc, sites.to(device), delta.to(device, dtype), w, 1, 1, False, active.to(device),
                                    None, 2.0)
    share = float((reached >= 0).double().mean())
    assert share > 0.9 if reach == "every tap" else share < 0.3, share
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    assert (acc.cpu().double() - want).abs().max() <= tol * want.abs().max()


@pytest.mark.parametrize("device", DEVICES)
def test_channel_sparse_scatter_is_chosen_by_the_share_of_zeros(device):
    """The default (0.85): deltas with at least 85 % exact zeros take the channel-sparse kernel, denser ones the
    GEMM (on CUDA the choice is made on the device). Told apart by an infinite weight on a channel whose delta is
    zero at every row: the GEMM multiplies it (0 x inf = NaN in the sums), the sparse kernel skips it."""
    g = torch.Generator().manual_seed(5)
    H, W, n, cin, cout = 20, 20, 120, 64, 64
    keys = torch.randperm(H * W, generator=g)[:n]
    sites = torch.stack([keys // W, keys % W], 1).int().to(device)
    weight = torch.randn(cout, 3, 3, cin, generator=g)
    weight[:, 1, 1, 9] = float("inf")
    weight = weight.to(device)
    for zeros, sparse in ((0.95, True), (0.6, False), (0.85, True), (0.8, False)):
        delta = torch.randn(n, cin, generator=g)
        flat = delta.view(-1)
        flat[torch.randperm(n * cin, generator=g)[:round(zeros * n * cin)]] = 0.0  # exactly this share
        delta[:, 9] = 0.0
        delta[0, 8] = 1.0 if delta[0, 8] == 0 and zeros < 0.85 else delta[0, 8]  # keep the share below the default
        share = float((delta == 0).double().mean())
        assert (share >= 0.85) == sparse, share
        delta = delta.to(device)
        for arg, forced in ((None, sparse), (0.0, True), (2.0, False)):
            acc = torch.zeros(H, W, cout, device=device)
            extra = () if arg is None else (None, None, arg)
            _ops.sscater_scatter_(acc, sites, delta, weight, 1, 1, False, *extra)
            assert bool(acc.isnan().any()) != forced, (zeros, arg)
    with pytest.raises(ValueError, match="channel_sparse"):
        _ops.sscater_scatter_(acc, sites, delta, weight, 1, 1, False, None, None, float("nan"))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("channels_first", [False, True])
def test_finalize_applies_folded_bn_relu_on_active_sites(device, channels_first):
    g = torch.Generator().manual_seed(3)
    H, W, C = 6, 7, 5
    acc = torch.randn(H, W, C, generator=g, dtype=torch.float64)
    active = torch.rand(H, W, generator=g) > 0.4
    scale, shift = torch.rand(C, generator=g, dtype=torch.float64) + 0.5, torch.randn(C, generator=g, dtype=torch.float64)
    old = torch.relu(torch.randn(H, W, C, generator=g, dtype=torch.float64))
    old[0, 0] = torch.relu(acc[0, 0] * scale + shift) if active[0, 0] else 0.0  # an unchanged site
    sites = torch.tensor([[0, 0], [1, 2], [5, 6], [3, 3], [2, 0]], dtype=torch.int32)
    if channels_first:
        store = old.permute(2, 0, 1).contiguous().to(device)
        out = store.permute(1, 2, 0)
    else:
        out = old.clone().to(device)
    changed, delta = _ops.sscater_finalize_(acc.to(device), out, active.to(device), sites.to(device),
                                            scale.to(device), shift.to(device))
    ys, xs = sites[:, 0].long(), sites[:, 1].long()
    new = torch.where(active[ys, xs][:, None], torch.relu(acc[ys, xs] * scale + shift), torch.zeros(1, dtype=acc.dtype))
    assert torch.allclose(out.cpu()[ys, xs], new, rtol=0, atol=1e-14)
    assert torch.allclose(delta.cpu(), new - old[ys, xs], rtol=0, atol=1e-14)
    assert changed.cpu().tolist() == (new != old[ys, xs]).any(1).tolist()
    assert not changed[0]
    untouched = torch.ones(H, W, dtype=torch.bool)
    untouched[ys, xs] = False
    assert torch.equal(out.cpu()[untouched], old[untouched])


# ---- the fused layer-step ops, against Python references ---------------------------------------

def _rows(t):
    """The valid (y, x) rows of a padded site list, as a sorted list of tuples."""
    t = t.cpu()
    return sorted(map(tuple, t[t[:, 0] >= 0].tolist()))


def _random_sites(g, H, W, n):
    keys = torch.randperm(H * W, generator=g)[:n]
    return torch.stack([keys // W, keys % W], 1).int()


@pytest.mark.parametrize("device", DEVICES)
def test_cover_update_flips_the_outputs_whose_cover_crosses_zero(device):
    g = torch.Generator().manual_seed(21)
    Hi, Wi, k, s, p = 12, 10, 3, 2, 1
    Ho, Wo = (Hi + 2 * p - k) // s + 1, (Wi + 2 * p - k) // s + 1
    ones = torch.ones(1, 1, k, k, dtype=torch.float64)

    def cover_of(act_in):
        return F.conv2d(act_in[None, None].double(), ones, None, s, p)[0, 0].round().int()

    act_in = torch.rand(Hi, Wi, generator=g) > 0.6
    cover = cover_of(act_in)
    active = cover > 0
    sites_on = torch.nonzero(act_in).int()
    sites_off = torch.nonzero(~act_in).int()
    removed = sites_on[torch.randperm(sites_on.shape[0], generator=g)[:7]]
    added = sites_off[torch.randperm(sites_off.shape[0], generator=g)[:9]]
    padded_added = torch.cat([added, torch.full((3, 2), -1, dtype=torch.int32)])  # padding rows are skipped
    new_in = act_in.clone()
    new_in[added[:, 0].long(), added[:, 1].long()] = True
    new_in[removed[:, 0].long(), removed[:, 1].long()] = False
    new_cover = cover_of(new_in)
    stamp = torch.zeros(Ho, Wo, dtype=torch.int32, device=device)
    cv, act = cover.to(device), active.to(device)
    a_out, r_out, counts = _ops.sscater_cover_update_(cv, act, stamp, 4, padded_added.to(device), removed.to(device),
                                                      k, k, s, p)
    assert torch.equal(cv.cpu(), new_cover) and torch.equal(act.cpu(), new_cover > 0)
    assert _rows(a_out) == sorted(map(tuple, torch.nonzero((new_cover > 0) & ~active).tolist()))
    assert _rows(r_out) == sorted(map(tuple, torch.nonzero(~(new_cover > 0) & active).tolist()))
    assert counts.tolist() == [len(_rows(a_out)), len(_rows(r_out))]
    assert (a_out.cpu()[: counts[0]] >= 0).all() and (r_out.cpu()[: counts[1]] >= 0).all()  # filled from the top


@pytest.mark.parametrize("device", DEVICES)
def test_children_mark_every_upsampled_child(device):
    g = torch.Generator().manual_seed(22)
    Hi, Wi, k = 5, 6, 2
    active = torch.zeros(Hi * k, Wi * k, dtype=torch.bool)
    active[::3] = True
    added, removed = _random_sites(g, Hi, Wi, 6)[:4], _random_sites(g, Hi, Wi, 6)[:3]
    ref = active.clone()
    for sites, on in ((added, True), (removed, False)):
        for y, x in sites.tolist():
            ref[y * k:(y + 1) * k, x * k:(x + 1) * k] = on
    act = active.to(device)
    ca, cr = _ops.sscater_children_(act, added.to(device), removed.to(device), k, k, k, 0)
    assert torch.equal(act.cpu(), ref)
    assert _rows(ca) == sorted((y * k + i, x * k + j) for y, x in added.tolist() for i in range(k) for j in range(k))
    assert _rows(cr) == sorted((y * k + i, x * k + j) for y, x in removed.tolist() for i in range(k) for j in range(k))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("s", [1, 2])
def test_gather_sets_the_full_convolution_at_the_sites(device, s):
    g = torch.Generator().manual_seed(23 + s)
    Hi, Wi, cin, cout = 9, 8, 5, 6
    inp = torch.randn(Hi, Wi, cin, generator=g, dtype=torch.float64)
    w = torch.randn(cout, 3, 3, cin, generator=g, dtype=torch.float64)
    ref = F.conv2d(inp.permute(2, 0, 1)[None], w.permute(0, 3, 1, 2), None, s, 1)[0].permute(1, 2, 0)
    start = torch.randn(*ref.shape, generator=g, dtype=torch.float64)
    sites = _random_sites(g, ref.shape[0], ref.shape[1], 7)
    padded = torch.cat([sites[:3], torch.full((2, 2), -1, dtype=torch.int32), sites[3:]])
    acc = start.clone().to(device)
    _ops.sscater_gather_(acc, inp.to(device), w.to(device), padded.to(device), s, 1)
    exp = start.clone()
    exp[sites[:, 0].long(), sites[:, 1].long()] = ref[sites[:, 0].long(), sites[:, 1].long()]
    assert (acc.cpu() - exp).abs().max() <= 1e-12 * exp.abs().max()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_scatter_and_gather_read_only_the_counted_rows(device, dtype):
    """A padded list whose length is on the device: (-1, -1) rows and rows past ``count`` are ignored
    (they hold real sites and deltas here, which would land if read). Channel counts that are not
    multiples of the CUDA tile (64), and more rows than one tile."""
    g = torch.Generator().manual_seed(31)
    H, W, cin, cout, n = 20, 18, 70, 67, 150
    keys = torch.randperm(H * W, generator=g)[:n + 40]
    sites = torch.stack([keys // W, keys % W], 1).int()
    sites[5] = sites[77] = -1  # padding inside the counted rows
    delta = torch.randn(n + 40, cin, generator=g, dtype=torch.float64)
    weight = torch.randn(cout, 3, 3, cin, generator=g, dtype=torch.float64)
    used = torch.ones(n, dtype=torch.bool)
    used[5] = used[77] = False
    ref = F.conv2d(_dense_delta(H, W, sites[:n][used], delta[:n][used]), weight.permute(0, 3, 1, 2), None, 1, 1)
    ref = ref[0].permute(1, 2, 0)
    start = torch.randn(H, W, cout, generator=g, dtype=torch.float64)
    acc = start.to(device, dtype).clone()
    count = torch.tensor([n], device=device)
    reached = _ops.sscater_scatter_(acc, sites.to(device), delta.to(device, dtype), weight.to(device, dtype), 1, 1,
                                    False, None, count)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    assert (acc.double().cpu() - (start + ref)).abs().max() <= tol * (start + ref).abs().max()
    r = reached.cpu().view(n + 40, 9)
    assert (r[n:] == -1).all() and (r[5] == -1).all() and (r[77] == -1).all() and (r[:5] >= -1).all()
    # the gather: the first 100 of 150 listed sites, in float64 against conv2d of a random input
    inp = torch.randn(H, W, cin, generator=g, dtype=torch.float64)
    full = F.conv2d(inp.permute(2, 0, 1)[None], weight.permute(0, 3, 1, 2), None, 1, 1)[0].permute(1, 2, 0)
    acc = start.to(device, dtype).clone()
    _ops.sscater_gather_(acc, inp.to(device, dtype), weight.to(device, dtype), sites.to(device), 1, 1,
                         torch.tensor([100], device=device))
    exp = start.clone()
    s_ = sites[:100][used[:100]].long()
    exp[s_[:, 0], s_[:, 1]] = full[s_[:, 0], s_[:, 1]]
    assert (acc.double().cpu() - exp).abs().max() <= tol * exp.abs().max()
    with pytest.raises(ValueError, match="count must be an int64"):
        _ops.sscater_gather_(acc, inp.to(device, dtype), weight.to(device, dtype), sites.to(device), 1, 1,
                             torch.tensor([1], dtype=torch.int32, device=device))


@pytest.mark.parametrize("device", DEVICES)
def test_touch_then_finalize_compact(device):
    g = torch.Generator().manual_seed(24)
    H, W, C = 7, 9, 5
    acc = torch.randn(H, W, C, generator=g, dtype=torch.float64)
    active = torch.rand(H, W, generator=g) > 0.3
    active[1, 1] = active[6, 8] = True
    scale, shift = torch.rand(C, generator=g, dtype=torch.float64) + 0.5, torch.randn(C, generator=g, dtype=torch.float64)
    acc[6, 8] = (1.0 - shift) / scale  # a positive value at (6, 8) before it is removed
    acc_d, active_d = acc.clone().to(device), active.clone().to(device)
    sc, sh = scale.to(device), shift.to(device)
    stamp_d = torch.zeros(H, W, dtype=torch.int32, device=device)
    feats_d = torch.zeros(H, W, C, dtype=torch.float64, device=device)
    # settle every site with the device's own arithmetic (stamp values 2 and 3), then perturb two
    everything = torch.arange(H * W, device=device)
    none = torch.zeros(0, 2, dtype=torch.int32, device=device)
    cand, count = _ops.sscater_touch_(stamp_d, acc_d, 2, torch.cat([everything, everything.flip(0)]), none, none)
    assert cand.shape == (H * W, 2) and count.item() == H * W  # each site once: the list is capped at the grid
    _ops.sscater_finalize_compact_(acc_d, feats_d, active_d, cand, count, stamp_d, 3, sc, sh)
    ref = torch.where(active[..., None], torch.relu(acc * scale + shift), torch.zeros(1, dtype=acc.dtype))
    assert (feats_d.cpu() - ref).abs().max() <= 1e-12 * ref.abs().max()
    settled = feats_d.cpu().clone()
    feats_d[2, 4] += 1.0  # key 22: reached below, so evaluated again: changes back
    feats_d[3, 0] += 1.0  # key 27: not reached: stays stale
    # this step: reached keys with duplicates and a -1, one added site (also reached), two removed
    targets = torch.tensor([5, -1, 22, 5, 40, 22, 62], dtype=torch.int64)
    added = torch.tensor([[0, 5], [-1, -1]], dtype=torch.int32)  # (0, 5) = key 5
    removed = torch.tensor([[1, 1], [6, 8]], dtype=torch.int32)
    active_d[1, 1] = active_d[6, 8] = False
    stamp_d[2, 3] = 8  # touched in an earlier step: not listed now
    old = feats_d.cpu().clone()  # (on CPU, .cpu() is the same tensor)
    cand, count = _ops.sscater_touch_(stamp_d, acc_d, 10, targets.to(device), added.to(device), removed.to(device))
    keys = {5, 22, 40, 62, 1 * W + 1, 6 * W + 8}
    assert count.item() == len(keys) and cand.shape == (targets.shape[0] + 4, 2)
    assert _rows(cand) == sorted((k_ // W, k_ % W) for k_ in keys) and (cand.cpu()[: len(keys)] >= 0).all()
    st = stamp_d.cpu().flatten()
    assert st[5] == 11 and st[22] == 10 and st[40] == 10 and st[W + 1] == 11 and st[6 * W + 8] == 11
    assert st[2 * W + 3] == 8 and (acc_d.cpu()[1, 1] == 0).all() and (acc_d.cpu()[6, 8] == 0).all()
    sites, delta, counts = _ops.sscater_finalize_compact_(acc_d, feats_d, active_d, cand, count, stamp_d, 11, sc, sh)
    new = feats_d.cpu()
    # changed: the perturbed site that was evaluated, and the two removed sites (both were > 0)
    changed = [(1, 1), (2, 4), (6, 8)]
    n = counts[0].item()
    assert sorted(map(tuple, sites.cpu()[:n].tolist())) == changed
    for (y, x), d in zip(sites.cpu()[:n].tolist(), delta.cpu()[:n]):
        assert torch.equal(d, new[y, x] - old[y, x])
    assert (sites.cpu()[n:] == -1).all()  # (the padding rows' delta is unspecified)
    assert counts.tolist() == [3, 4, len(keys)]  # changed or status: the three, and (0, 5)
    assert torch.equal(new[2, 4], settled[2, 4]) and torch.equal(new[3, 0], old[3, 0])
    assert (new[1, 1] == 0).all() and (new[6, 8] == 0).all()


def test_fused_ops_opcheck():
    g = torch.Generator().manual_seed(1)
    d = torch.float64
    sites = torch.tensor([[0, 1], [4, 5], [-1, -1]], dtype=torch.int32)
    torch.library.opcheck(_ops.sscater_cover_update_, (torch.ones(3, 3, dtype=torch.int32),
                                                       torch.ones(3, 3, dtype=torch.bool),
                                                       torch.zeros(3, 3, dtype=torch.int32), 4, sites[:1], sites[1:2],
                                                       3, 3, 2, 1))
    torch.library.opcheck(_ops.sscater_children_, (torch.zeros(12, 12, dtype=torch.bool), sites, sites[:1], 2, 2, 2, 0))
    torch.library.opcheck(_ops.sscater_gather_, (torch.zeros(5, 6, 3, dtype=d), torch.randn(5, 6, 2, generator=g, dtype=d),
                                                 torch.randn(3, 3, 3, 2, generator=g, dtype=d), sites, 1, 1))
    acc = torch.randn(5, 6, 3, generator=g, dtype=d)
    stamp = torch.zeros(5, 6, dtype=torch.int32)
    args = (stamp, acc, 4, torch.tensor([0, 7, -1]), sites[:1], sites[1:])
    torch.library.opcheck(_ops.sscater_touch_, args)
    cand, count = _ops.sscater_touch_(stamp.clone(), acc.clone(), 8, torch.tensor([0, 7, -1]), sites[:1], sites[1:])
    torch.library.opcheck(_ops.sscater_finalize_compact_, (acc, torch.zeros_like(acc), torch.ones(5, 6, dtype=torch.bool),
                                                           cand, count, stamp, 9, torch.ones(3, dtype=d),
                                                           torch.zeros(3, dtype=d)))


def test_ops_reject_bad_arguments():
    acc = torch.zeros(4, 4, 3)
    sites = torch.zeros(2, 2, dtype=torch.int32)
    with pytest.raises(ValueError, match="sites must be int32"):
        _ops.sscater_scatter_(acc, sites.long(), torch.zeros(2, 2), torch.zeros(3, 3, 3, 2), 1, 1, False)
    with pytest.raises(ValueError, match="weight must be"):
        _ops.sscater_scatter_(acc, sites, torch.zeros(2, 2), torch.zeros(3, 3, 3, 5), 1, 1, False)
    with pytest.raises(ValueError, match="acc must be float32 or float64"):
        _ops.sscater_scatter_(acc.half(), sites, torch.zeros(2, 2).half(), torch.zeros(3, 3, 3, 2).half(), 1, 1, False)
    with pytest.raises(ValueError, match="lies outside"):
        _ops.sscater_finalize_(acc, acc.clone(), torch.ones(4, 4, dtype=torch.bool),
                               torch.tensor([[4, 0]], dtype=torch.int32), torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="active must be a contiguous bool"):
        _ops.sscater_finalize_(acc, acc.clone(), torch.ones(4, 4), sites, torch.ones(3), torch.zeros(3))
    stamp = torch.zeros(4, 4, dtype=torch.int32)
    with pytest.raises(ValueError, match="cover must be a contiguous Int"):
        _ops.sscater_cover_update_(torch.zeros(4, 4), torch.ones(4, 4, dtype=torch.bool), stamp, 4, sites, sites, 3, 3, 2, 1)
    with pytest.raises(ValueError, match="stride 0"):
        _ops.sscater_children_(torch.ones(4, 4, dtype=torch.bool), sites, sites, 2, 2, 0, 0)
    with pytest.raises(ValueError, match="weight must be"):
        _ops.sscater_gather_(acc, torch.zeros(4, 4, 2), torch.zeros(3, 3, 3, 5), sites, 1, 1)
    with pytest.raises(ValueError, match="targets must be int64"):
        _ops.sscater_touch_(stamp, acc, 4, torch.zeros(3, dtype=torch.int32), sites, sites)
    with pytest.raises(ValueError, match="stamp and acc must cover the same"):
        _ops.sscater_touch_(torch.zeros(5, 4, dtype=torch.int32), acc, 4, torch.zeros(3, dtype=torch.int64), sites, sites)


def test_ops_opcheck():
    g = torch.Generator().manual_seed(0)
    acc = torch.randn(5, 6, 4, generator=g, dtype=torch.float64)
    sites = torch.tensor([[0, 1], [4, 5], [2, 2]], dtype=torch.int32)
    torch.library.opcheck(_ops.sscater_scatter_, (acc, sites, torch.randn(3, 2, dtype=torch.float64),
                                                  torch.randn(4, 3, 3, 2, dtype=torch.float64), 1, 1, False))
    torch.library.opcheck(_ops.sscater_finalize_, (acc, torch.zeros_like(acc), torch.ones(5, 6, dtype=torch.bool),
                                                   sites, torch.ones(4, dtype=torch.float64),
                                                   torch.zeros(4, dtype=torch.float64)))


class PillarMapStream:
    """A random stream of pillar maps: each step some pillars appear, vanish or change features."""

    def __init__(self, H, W, C, seed, start=150, dtype=torch.float64):
        self.H, self.W, self.C, self.dtype = H, W, C, dtype
        self.g = torch.Generator().manual_seed(seed)
        self.state: dict[int, torch.Tensor] = {}
        for k in torch.randperm(H * W, generator=self.g)[:start].tolist():
            self.state[k] = self._feat()

    def _feat(self):
        return torch.rand(self.C, generator=self.g, dtype=torch.float64).to(self.dtype)

    def current(self):
        ks = torch.tensor(sorted(self.state), dtype=torch.long)
        feats = torch.stack([self.state[k] for k in ks.tolist()]) if len(ks) else torch.zeros(0, self.C, dtype=self.dtype)
        return torch.stack([ks // self.W, ks % self.W], 1).int(), feats

    def step(self, n_changes, p_remove=0.4, only_remove=False):
        sites, feats, removed = [], [], []
        for k in torch.randperm(self.H * self.W, generator=self.g)[:n_changes].tolist():
            if k in self.state and (only_remove or torch.rand(1, generator=self.g).item() < p_remove):
                del self.state[k]
                removed.append(True)
                feats.append(torch.zeros(self.C, dtype=self.dtype))
            elif only_remove:
                continue
            else:
                self.state[k] = self._feat()
                removed.append(False)
                feats.append(self.state[k])
            sites.append([k // self.W, k % self.W])
        if not sites:
            return torch.zeros(0, 2, dtype=torch.int32), torch.zeros(0, self.C, dtype=self.dtype), torch.zeros(0, dtype=torch.bool)
        return torch.tensor(sites, dtype=torch.int32), torch.stack(feats), torch.tensor(removed)


def _full(bb, sites, feats, H, W, device):
    c = torch.cat([torch.zeros(sites.shape[0], 1, dtype=torch.int32), sites], 1)
    with torch.no_grad():
        return bb(SparseConvTensor(feats.to(device), c.to(device), [H, W], 1), mode="sparse")


STEP_MODES = ["trimmed", "sync_free", "cuda_graph"]


def _delta_backbone(bb, shape, dtype, device, mode, **kwargs):
    """trimmed: lists trimmed on the host each layer (the CPU default); sync_free: padded lists and
    row counts on the device; cuda_graph: the sync-free step captured in CUDA graphs (the CUDA default)."""
    if mode == "cuda_graph" and torch.device(device).type != "cuda":
        pytest.skip("CUDA graphs need a GPU")
    return DeltaBackbone(bb, shape, dtype, device, sync_free=mode != "trimmed", cuda_graph=mode == "cuda_graph",
                         **kwargs)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("negative_bias", [0.0, 0.8])
@pytest.mark.parametrize("mode", STEP_MODES)
@pytest.mark.parametrize("channel_sparse", [None, 0.0])  # the device's default; every scatter channel-sparse
def test_recycling_backbone_equals_full_recomputation_float64(device, negative_bias, mode, channel_sparse):
    H, W = 40, 48
    bb = small_backbone(seed=7, negative_bias=negative_bias).to(device)
    stream = PillarMapStream(H, W, 8, seed=11)
    db = _delta_backbone(bb, (H, W), torch.float64, device, mode, channel_sparse=channel_sparse)
    sites, feats = stream.current()
    out = db.refresh(sites, feats)
    ref = _full(bb, sites, feats, H, W, device)
    assert (out - ref).abs().max() <= 1e-12 * ref.abs().max()
    plan = [25] * 10 + [0, 0] + [3] * 5 + [200] + [25] * 10  # quiet steps, tiny steps, a burst
    zeros_seen = 0
    for i, n in enumerate(plan):
        s, f, r = stream.step(n)
        out = db.update(s, f, r)
        sites, feats = stream.current()
        ref = _full(bb, sites, feats, H, W, device)
        diff = (out - ref).abs().max().item()
        assert diff <= 1e-12 * ref.abs().max().item(), f"step {i}: max |diff| {diff:.3e}"
        zeros_seen += int((ref == 0).sum())
        if n == 0:
            assert all(st.changed == 0 for st in db.stats), "a step with no input change must change nothing"
    if negative_bias:
        assert zeros_seen > 0.5 * ref.numel() * len(plan), "the negative bias should zero most outputs"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", STEP_MODES)
def test_recycling_backbone_float32_and_emptying_the_grid(device, mode):
    H, W = 32, 40
    bb = small_backbone(seed=2, dtype=torch.float32).to(device)
    stream = PillarMapStream(H, W, 8, seed=5, start=60, dtype=torch.float32)
    db = _delta_backbone(bb, (H, W), torch.float32, device, mode)
    db.refresh(*stream.current())
    emptied = False
    for i in range(50):
        if i < 30:
            s, f, r = stream.step(30)
        elif i < 38:  # only removals, 30 random sites a step
            s, f, r = stream.step(30, only_remove=True)
        elif i == 38:  # every site of the grid listed: whatever is left is removed, the grid empties
            s, f, r = stream.step(H * W, only_remove=True)
        else:  # a quiet step on the empty grid, then refilling
            s, f, r = stream.step(0 if i == 39 else 30, p_remove=0.0)
        out = db.update(s, f, r)
        ref = _full(bb, *stream.current(), H, W, device)
        assert (out - ref).abs().max() <= 1e-5 * max(ref.abs().max().item(), 1e-6), f"step {i}"
        if i in (38, 39):
            # no pillar: no active site in any layer, and an all-zero map (inactive sites are zero,
            # not bias), exactly, as the recomputation of an empty grid
            assert not stream.state and bool(r.all())  # whatever was listed was removed
            assert all(st.active == 0 for st in db.stats), [st.active for st in db.stats]
            assert not out.any() and not ref.any(), f"step {i}"
            emptied = True
    assert emptied and len(stream.state) > 100 and db.stats[0].active > 0  # refilled


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", STEP_MODES)
@pytest.mark.parametrize("negative_bias", [0.0, 0.8])
@pytest.mark.parametrize("given", [0.7, 1.0])  # 1.0: every site, so every layer's every site is active (no masks)
@pytest.mark.parametrize("channels_last", [False, True])  # NCHW: each layer passes an NCHW copy to the next
def test_dense_refresh_equals_the_sparse_recomputation(device, mode, negative_bias, given, channels_last,
                                                       monkeypatch):
    """A refresh given most of the grid's sites runs dense convolutions: its output equals the sparse backbone's,
    and the recycled steps after it stay equal (its active maps, covers and accumulators are the sparse refresh's)."""
    monkeypatch.setitem(delta_module.DENSE_REFRESH, torch.device(device).type, 0.5)  # whatever the default
    monkeypatch.setitem(delta_module.DENSE_CHANNELS_LAST, torch.device(device).type, channels_last)
    H, W = 24, 32
    bb = small_backbone(seed=6, negative_bias=negative_bias).to(device)
    stream = PillarMapStream(H, W, 8, seed=4, start=int(given * H * W))
    db = _delta_backbone(bb, (H, W), torch.float64, device, mode)
    db._refresh_sparse = None  # not called: the refresh must take the dense path
    sites, feats = stream.current()
    out = db.refresh(sites, feats)
    ref = _full(bb, sites, feats, H, W, device)
    assert (out - ref).abs().max() <= 1e-12 * ref.abs().max()
    sparse = _delta_backbone(bb, (H, W), torch.float64, device, mode)
    sparse._refresh_sparse(*sparse._check_input(sites, feats))  # the same state by the sparse ops
    for a, b in zip(db.layers + db.up_layers, sparse.layers + sparse.up_layers):
        assert torch.equal(a.active, b.active), a.name
        assert (a.acc - b.acc).abs().max() <= 1e-12 * max(b.acc.abs().max().item(), 1.0), a.name
    assert all(torch.equal(db.block_cover[k], sparse.block_cover[k]) for k in db.block_cover)
    for i in range(8):
        out = db.update(*stream.step(30))
        ref = _full(bb, *stream.current(), H, W, device)
        assert (out - ref).abs().max() <= 1e-12 * ref.abs().max(), f"step {i}"


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", STEP_MODES)
@pytest.mark.parametrize("as_function", [False, True])
def test_refreshes_of_every_site_again_and_again(device, mode, as_function):
    """A stream that lists every site (SSCATeRPointPillars.from_detector's): each refresh (with cuda_graph the
    first records a CUDA graph, the later ones replay it) equals the full recomputation of its own input, given
    as a tensor or as a function of the sites (recorded in the graph), the recycled steps between refreshes stay
    equal, and the figures are the refresh's own."""
    H, W = 24, 32
    bb = small_backbone(seed=9, negative_bias=0.8).to(device)
    stream = PillarMapStream(H, W, 8, seed=5, start=int(0.8 * H * W))
    db = _delta_backbone(bb, (H, W), torch.float64, device, mode)
    every = torch.stack(torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij"), -1).view(-1, 2).int()
    held = torch.zeros(H * W, 8, dtype=torch.float64, device=device)  # what the function reads

    def features(sites):
        assert sites.shape == (H * W, 2)
        return held * 1.0  # computed from the held input (inside a graph: at each replay)

    for r in range(3):
        sites, feats = stream.current()
        dense = torch.zeros(H * W, feats.shape[1], dtype=feats.dtype)
        dense[sites[:, 0].long() * W + sites[:, 1].long()] = feats  # every site listed: the empty ones with 0
        held.copy_(dense)
        out = db.refresh(every.to(device), features if as_function else dense.to(device), check=not as_function)
        ref = _full(bb, every, dense, H, W, device)
        assert (out - ref).abs().max() <= 1e-12 * ref.abs().max(), f"refresh {r}"
        assert [st.active for st in db.stats] == [int(lay.active.sum()) for lay in db.layers + db.up_layers]
        assert db.state_max == max(float(lay.acc.abs().max()) for lay in db.layers + db.up_layers)
        for i in range(3):  # every site stays listed: an emptied one is a site whose input went back to 0
            sites, feats, removed = stream.step(40)
            feats = torch.where(removed[:, None], torch.zeros_like(feats), feats)
            out = db.update(sites.to(device), feats.to(device), torch.zeros_like(removed).to(device))
            dense = torch.zeros(H * W, feats.shape[1], dtype=feats.dtype)
            cur_sites, cur_feats = stream.current()
            dense[cur_sites[:, 0].long() * W + cur_sites[:, 1].long()] = cur_feats
            ref = _full(bb, every, dense, H, W, device)
            assert (out - ref).abs().max() <= 1e-12 * ref.abs().max(), f"refresh {r}, step {i}"
    if mode == "cuda_graph":
        assert list(db._refresh_graphs) == [features if as_function else None]  # the later ones replayed it


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", STEP_MODES)
def test_features_given_as_a_function_of_the_sites(device, mode):
    """update(sites, fn, removed, check=False): the features computed from the sites by ``fn`` (in a CUDA graph
    step, inside the graph, on sites padded with (-1, -1) rows) give what the same features given as a tensor
    give, step by step (to float64 rounding)."""
    H, W, C = 24, 32, 8
    bb = small_backbone(seed=3).to(device)
    stream = PillarMapStream(H, W, C, seed=9)
    given, computed = (_delta_backbone(bb, (H, W), torch.float64, device, mode) for _ in range(2))
    table = torch.zeros(H * W + 1, C, dtype=torch.float64, device=device)  # the last row for padding sites
    seen = []

    def features(sites):  # a pure function of the sites and the table's current contents
        seen.append(sites.shape[0])
        keys = torch.where(sites[:, 0] >= 0, sites[:, 0].long() * W + sites[:, 1].long(), H * W)
        return table[keys] * 2.0

    sites, feats = stream.current()
    given.refresh(sites, feats * 2.0)
    computed.refresh(sites, feats * 2.0)
    for i, n in enumerate([20, 0, 5, 120, 20]):
        s, f, r = stream.step(n)
        keys = s[:, 0].long() * W + s[:, 1].long()
        table[keys.to(device)] = f.to(device)
        want = given.update(s, f * 2.0, r).clone()
        got = computed.update(s.to(device), features, r.to(device), check=False)
        # CUDA's scatter adds with atomics: two runs of one input may round differently in the last bits
        assert (got - want).abs().max() <= 1e-12 * max(want.abs().max().item(), 1.0), f"step {i}"
    assert seen and (mode != "cuda_graph" or min(seen) >= 256)  # a graph step sees its padded capacity
    with pytest.raises(ValueError, match="only with check=False"):
        computed.update(s.to(device), features, r.to(device))


def _two_backbones(device, given, monkeypatch, backbone_seed, stream_seed, dtype):
    """A 24 x 32 stream holding ``given`` of the grid's sites and two recycling backbones of one network, with
    the dense refresh taken from half the grid on (``given`` 0.3: the sparse refresh, 1.0: the dense one)."""
    monkeypatch.setitem(delta_module.DENSE_REFRESH, torch.device(device).type, 0.5)
    H, W = 24, 32
    bb = small_backbone(seed=backbone_seed).to(device)
    stream = PillarMapStream(H, W, 8, seed=stream_seed, start=int(given * H * W))
    return stream, *(DeltaBackbone(bb, (H, W), dtype, device) for _ in range(2))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("given", [0.3, 1.0])  # the sparse and the dense refresh
def test_refresh_without_the_input_check_and_its_figures(device, given, monkeypatch):
    """refresh(..., check=False) on input that is already right gives what the checked call gives, and the
    figures read in one go (active sites per layer, state_max) are the layers' own."""
    stream, a, b = _two_backbones(device, given, monkeypatch, 8, 2, torch.float64)
    sites, feats = stream.current()
    want = a.refresh(sites, feats).clone()
    got = b.refresh(sites.to(device), feats.to(device), check=False)
    assert (got - want).abs().max() <= 1e-12 * want.abs().max()  # CUDA's sums may add in another order
    for st, layer in zip(b.stats, b.layers + b.up_layers):
        assert st.active == st.changed == st.touched == int(layer.active.sum()), st.name
    assert b.state_max == max(float(layer.acc.abs().max()) for layer in b.layers + b.up_layers)
    assert abs(b.state_max - a.state_max) <= 1e-12 * a.state_max


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("given", [0.3, 1.0])  # the sparse and the dense refresh
def test_refresh_under_a_callers_autocast_keeps_the_state_dtype(device, given, monkeypatch):
    """A refresh inside the caller's torch.autocast computes in the state's dtype (float32 here), as the steps
    do: the same outputs and accumulators as outside it, and the recycled steps after it still match."""
    stream, a, b = _two_backbones(device, given, monkeypatch, 5, 3, torch.float32)
    sites, feats = stream.current()
    want = a.refresh(sites, feats.float()).clone()
    with torch.autocast(torch.device(device).type, dtype=torch.bfloat16):
        got = b.refresh(sites, feats.float())
    assert got.dtype == torch.float32
    assert (got - want).abs().max() <= 1e-6 * want.abs().max()  # CUDA's sums may add in another order
    for la, lb in zip(a.layers + a.up_layers, b.layers + b.up_layers):
        assert (la.acc - lb.acc).abs().max() <= 1e-6 * max(la.acc.abs().max().item(), 1.0), la.name
    s, f, r = stream.step(20)
    want = a.update(s, f.float(), r)
    got = b.update(s, f.float(), r)
    assert (got - want).abs().max() <= 1e-6 * want.abs().max()


def test_recycling_backbone_bad_input():
    bb = small_backbone()
    db = DeltaBackbone(bb, (16, 16), torch.float64)
    with pytest.raises(ValueError, match="sites lie outside the"):
        db.update(torch.tensor([[16, 0]]), torch.zeros(1, 8, dtype=torch.float64), torch.tensor([False]))
    with pytest.raises(ValueError, match=r"features must be \(1, 8\)"):
        db.update(torch.tensor([[1, 0]]), torch.zeros(1, 4), torch.tensor([False]))
    with pytest.raises(ValueError, match="removed must be bool"):
        db.update(torch.tensor([[1, 0]]), torch.zeros(1, 8), torch.tensor([0]))
    with pytest.raises(ValueError, match="a function of the sites only with check=False"):
        db.refresh(torch.tensor([[1, 0]]), lambda sites: torch.zeros(1, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="eval mode"):
        DeltaBackbone(small_backbone().train(), (16, 16))
    with pytest.raises(ValueError, match="dtype must be"):
        DeltaBackbone(bb, (16, 16), torch.float16)
    with pytest.raises(ValueError, match="cuda_graph needs a CUDA device and sync_free=True"):
        DeltaBackbone(bb, (16, 16), torch.float64, "cpu", sync_free=True, cuda_graph=True)
    for bad in ("0.5", float("nan"), True):
        with pytest.raises(ValueError, match="channel_sparse must be a number"):
            DeltaBackbone(bb, (16, 16), torch.float64, channel_sparse=bad)
