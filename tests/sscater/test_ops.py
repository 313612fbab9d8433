"""lidarops.sscater.ops: each SSCATeR op (through its wrapper) against its float64 pure-PyTorch reference
on random inputs, and the wrappers' errors on bad input."""
from __future__ import annotations

import pytest
import torch

from lidarops.sscater import ops as sops
from helpers.devices import DEVICES

_TOL = {torch.float64: 1e-12, torch.float32: 2e-5}


def _sites(g, H, W, n, pad=0):
    keys = torch.randperm(H * W, generator=g)[:n]
    s = torch.stack([keys // W, keys % W], 1).int()
    return torch.cat([s, torch.full((pad, 2), -1, dtype=torch.int32)])


def _close(got, ref, dtype, what):
    diff = (got.double().cpu() - ref).abs()
    scale = max(float(ref.abs().max()) if ref.numel() else 0.0, 1.0)
    where = tuple(int(i) for i in torch.nonzero(diff == diff.max())[0]) if diff.numel() else ()
    assert float(diff.max() if diff.numel() else 0.0) <= _TOL[dtype] * scale, \
        f"{what}: max diff {float(diff.max()):.3g} at {where}"


def _valid(t):
    t = t.cpu()
    return {tuple(r) for r in t[t[:, 0] >= 0].tolist()}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("k,s,p,transposed", [(3, 1, 1, False), (3, 2, 1, False), (2, 2, 0, True), (3, 2, 1, True)])
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("channel_sparse", [0.85, 0.0])  # the default; on the CPU, the channel-sparse kernel forced
def test_scatter_matches_reference(device, dtype, k, s, p, transposed, seed, channel_sparse):
    g = torch.Generator().manual_seed(seed * 100 + k * 10 + s)
    H, W, cin, cout, n = 9, 8, 4, 5, 20
    sites = _sites(g, H, W, n, pad=3)
    delta = torch.randn(sites.shape[0], cin, generator=g, dtype=torch.float64)
    delta[torch.rand(delta.shape, generator=g) < 0.5] = 0.0  # zero before and after ReLU
    weight = torch.randn(cout, k, k, cin, generator=g, dtype=torch.float64)
    Ho, Wo = (H * s, W * s) if transposed else ((H + 2 * p - k) // s + 1, (W + 2 * p - k) // s + 1)
    acc = torch.randn(Ho, Wo, cout, generator=g, dtype=torch.float64)
    out_active = torch.rand(Ho, Wo, generator=g) > 0.3 if seed else None
    count = torch.tensor([n - 2]) if seed else None
    ref_acc, ref_reached = sops._scatter_reference(acc, sites, delta, weight, s, p, transposed, out_active, count)
    got = acc.to(device, dtype)
    reached = sops.scatter_(got, sites.to(device), delta.to(device, dtype), weight.to(device, dtype), s, p, transposed,
                            None if out_active is None else out_active.to(device),
                            None if count is None else count.to(device), channel_sparse)
    _close(got, ref_acc, dtype, "acc")
    assert torch.equal(reached.cpu(), ref_reached)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_finalize_matches_reference(device, dtype, seed):
    g = torch.Generator().manual_seed(seed)
    H, W, C = 7, 6, 5
    acc = torch.randn(H, W, C, generator=g, dtype=torch.float64).to(dtype).double()
    active = torch.rand(H, W, generator=g) > 0.4
    scale = (torch.rand(C, generator=g, dtype=torch.float64) + 0.5).to(dtype).double()
    shift = torch.randn(C, generator=g, dtype=torch.float64).to(dtype).double()
    out = torch.relu(torch.randn(H, W, C, generator=g, dtype=torch.float64)).to(dtype).double()
    sites = _sites(g, H, W, 15)
    ref_out, ref_changed, ref_delta = sops._finalize_reference(acc, out, active, sites, scale, shift)
    got = out.to(device, dtype)
    changed, delta = sops.finalize_(acc.to(device, dtype), got, active.to(device), sites.to(device),
                                    scale.to(device, dtype), shift.to(device, dtype))
    _close(got, ref_out, dtype, "out")
    _close(delta, ref_delta, dtype, "delta")
    if dtype == torch.float64:
        assert torch.equal(changed.cpu(), ref_changed)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("layout", ["nchw", "channels_last", "strided"])
def test_dense_finalize_matches_reference(device, dtype, masked, layout):
    g = torch.Generator().manual_seed(7 + masked)
    C, H, W = 37, 9, 35  # more than one 32-wide tile of channels and of sites, partial tiles at both ends
    y = torch.randn(C, H, W, generator=g, dtype=torch.float64)
    y[:, 2, 3] = 0.0  # zeros and ties at the ReLU's edge
    scale = (torch.rand(C, generator=g, dtype=torch.float64) + 0.5)
    shift = torch.randn(C, generator=g, dtype=torch.float64)
    shift[:4] = 0.0
    active = torch.rand(H, W, generator=g) > 0.4 if masked else None
    ref_acc, ref_out = sops._dense_finalize_reference(y.to(dtype), scale.to(dtype), shift.to(dtype), active)
    if layout == "nchw":
        y_dev = y.to(device, dtype)
    elif layout == "channels_last":  # the CPU refresh's convolution output: (C, H, W) view of (H, W, C) memory
        y_dev = y.permute(1, 2, 0).contiguous().to(device, dtype).permute(2, 0, 1)
    else:
        y_dev = torch.randn(C, H, 2 * W, dtype=torch.float64).to(device, dtype)[:, :, ::2]
        y_dev.copy_(y)
    acc = torch.full((H, W, C), float("nan"), dtype=dtype, device=device)
    # out as the output map's view (channels-last memory, more channels than this layer's) or its own buffer
    big = torch.full((H, W, C + 5), float("nan"), dtype=dtype, device=device)
    out = big[:, :, 2:2 + C] if layout != "nchw" else torch.full((C, H, W), float("nan"), dtype=dtype,
                                                                   device=device).permute(1, 2, 0)
    out_nchw = torch.full((C, H, W), float("nan"), dtype=dtype, device=device)
    sops.dense_finalize_(y_dev, acc, out, scale.to(device, dtype), shift.to(device, dtype),
                         None if active is None else active.to(device), out_nchw)
    _close(acc, ref_acc, dtype, "acc")
    _close(out, ref_out, dtype, "out")
    _close(out_nchw.permute(1, 2, 0), ref_out, dtype, "out_nchw")
    if layout != "nchw":  # the map's other channels are not touched
        assert torch.isnan(big[:, :, :2]).all() and torch.isnan(big[:, :, 2 + C:]).all()
    if dtype == torch.float64:  # zeros exactly where the reference has them (masked sites, ReLU)
        assert torch.equal(out.cpu() == 0, ref_out == 0)
    acc2 = torch.zeros_like(acc)
    sops.dense_finalize_(y_dev, acc2, torch.zeros_like(acc), scale.to(device, dtype), shift.to(device, dtype))
    _close(acc2, y.to(dtype).double().permute(1, 2, 0), dtype, "acc without a mask or out_nchw")


@pytest.mark.parametrize("device", DEVICES)
def test_dense_finalize_empty_and_opcheck(device):
    for H, W, C in ((0, 4, 3), (4, 0, 3), (4, 4, 0)):
        acc = torch.zeros(H, W, C, device=device)
        sops.dense_finalize_(torch.zeros(C, H, W, device=device), acc, torch.zeros(H, W, C, device=device),
                             torch.ones(C, device=device), torch.zeros(C, device=device))
    y = torch.randn(5, 3, 4, device=device)
    args = (y, torch.zeros(3, 4, 5, device=device), torch.zeros(3, 4, 5, device=device), torch.ones(5, device=device),
            torch.zeros(5, device=device), torch.rand(3, 4, device=device) > 0.5, torch.zeros(5, 3, 4, device=device))
    torch.library.opcheck(torch.ops.lidarops.sscater_dense_finalize_, args)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cover_update_matches_reference(device, seed):
    g = torch.Generator().manual_seed(seed)
    Hi, Wi, k, s, p = 11, 10, 3, 2, 1
    Ho, Wo = (Hi + 2 * p - k) // s + 1, (Wi + 2 * p - k) // s + 1
    act_in = torch.rand(Hi, Wi, generator=g) > 0.6
    on = torch.nonzero(act_in).int()
    off = torch.nonzero(~act_in).int()
    removed = on[torch.randperm(on.shape[0], generator=g)[:5]]
    added = off[torch.randperm(off.shape[0], generator=g)[:6]]
    # the cover of the current input, and a consistent active map
    cover = torch.zeros(Ho, Wo, dtype=torch.int32)
    cover, _, _, _, _ = sops._cover_update_reference(cover, torch.zeros(Ho, Wo, dtype=torch.bool),
                                                     torch.zeros(Ho, Wo, dtype=torch.int32), 1, on,
                                                     torch.zeros(0, 2, dtype=torch.int32), k, k, s, p)
    active = cover > 0
    stamp = torch.randint(0, 4, (Ho, Wo), generator=g, dtype=torch.int32)
    pad = torch.full((2, 2), -1, dtype=torch.int32)
    added, removed = torch.cat([added, pad]), torch.cat([removed, pad])
    ref = sops._cover_update_reference(cover, active, stamp, 5, added, removed, k, k, s, p)
    c, a, st = cover.to(device), active.to(device), stamp.to(device)
    got_on, got_off, counts = sops.cover_update_(c, a, st, 5, added.to(device), removed.to(device), k, k, s, p)
    assert torch.equal(c.cpu(), ref[0]) and torch.equal(a.cpu(), ref[1]) and torch.equal(st.cpu(), ref[2])
    assert _valid(got_on) == ref[3] and _valid(got_off) == ref[4]
    assert counts.cpu().tolist() == [len(ref[3]), len(ref[4])]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("k,s,p", [(2, 2, 0), (4, 4, 0), (3, 2, 1)])
def test_children_matches_reference(device, k, s, p):
    g = torch.Generator().manual_seed(k * 10 + s)
    Hi, Wi = 6, 5
    active = torch.rand(Hi * s, Wi * s, generator=g) > 0.5
    added, removed = _sites(g, Hi, Wi, 6, pad=1), _sites(g, Hi, Wi, 4, pad=1)
    ref_active, ref_a, ref_r = sops._children_reference(active, added, removed, k, k, s, p)
    got = active.to(device)
    a, r = sops.children_(got, added.to(device), removed.to(device), k, k, s, p)
    assert torch.equal(got.cpu(), ref_active) and torch.equal(a.cpu(), ref_a) and torch.equal(r.cpu(), ref_r)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("s,p,counted", [(1, 1, False), (2, 1, True), (2, 0, False)])
def test_gather_matches_reference(device, dtype, s, p, counted):
    g = torch.Generator().manual_seed(s * 10 + p)
    Hi, Wi, cin, cout, k = 10, 9, 4, 6, 3
    Ho, Wo = (Hi + 2 * p - k) // s + 1, (Wi + 2 * p - k) // s + 1
    inp = torch.randn(Hi, Wi, cin, generator=g, dtype=torch.float64)
    weight = torch.randn(cout, k, k, cin, generator=g, dtype=torch.float64)
    acc = torch.randn(Ho, Wo, cout, generator=g, dtype=torch.float64)
    sites = _sites(g, Ho, Wo, 12, pad=2)
    count = torch.tensor([9]) if counted else None
    ref = sops._gather_reference(acc, inp, weight, sites, s, p, count)
    got = acc.to(device, dtype)
    sops.gather_(got, inp.to(device, dtype), weight.to(device, dtype), sites.to(device), s, p,
                 None if count is None else count.to(device))
    _close(got, ref, dtype, "acc")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_touch_then_finalize_compact_match_references(device, seed):
    g = torch.Generator().manual_seed(seed)
    H, W, C, value = 8, 7, 4, 10
    stamp = torch.randint(0, value + 2, (H, W), generator=g, dtype=torch.int32)
    acc = torch.randn(H, W, C, generator=g, dtype=torch.float64)
    targets = torch.randint(-1, H * W, (25,), generator=g)
    added, removed = _sites(g, H, W, 5, pad=1), _sites(g, H, W, 3, pad=1)
    ref_stamp, ref_acc, ref_cand = sops._touch_reference(stamp, acc, value, targets, added, removed)
    st, ac = stamp.to(device), acc.to(device)
    cand, count = sops.touch_(st, ac, value, targets.to(device), added.to(device), removed.to(device))
    assert torch.equal(st.cpu(), ref_stamp)
    _close(ac, ref_acc, torch.float64, "acc")
    assert int(count) == len(ref_cand) and _valid(cand) == set(ref_cand)
    assert len(_valid(cand)) == len(ref_cand)  # each site once

    active = torch.rand(H, W, generator=g) > 0.3
    scale, shift = torch.rand(C, generator=g, dtype=torch.float64) + 0.5, torch.randn(C, generator=g, dtype=torch.float64)
    out = torch.relu(torch.randn(H, W, C, generator=g, dtype=torch.float64))
    cand_cpu = cand.cpu()
    out[cand_cpu[0, 0], cand_cpu[0, 1]] = 0.0
    ref_out, ref_sites, ref_delta, ref_counts = sops._finalize_compact_reference(
        ac.cpu(), out, active, cand_cpu, count.cpu(), st.cpu(), value + 1, scale, shift)
    got = out.to(device)
    sites, delta, counts = sops.finalize_compact_(ac, got, active.to(device), cand, count, st, value + 1,
                                                  scale.to(device), shift.to(device))
    _close(got, ref_out, torch.float64, "out")
    assert counts.cpu().tolist() == ref_counts
    n = ref_counts[0]
    got_sites = [tuple(r) for r in sites.cpu()[:n].tolist()]
    assert set(got_sites) == set(ref_sites) and sites.cpu()[n:].eq(-1).all()
    order = {site: i for i, site in enumerate(ref_sites)}
    _close(delta.cpu()[:n], ref_delta[[order[site] for site in got_sites]], torch.float64, "delta")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("C,unchanged", [(2, 0.5), (3, 0.97), (1, 0.0)])
def test_finalize_compact_over_many_rows_keeps_the_candidates_order(device, C, unchanged):
    # Tens of thousands of candidates, so that the CPU op splits them into chunks and moves the later
    # chunks' changed rows down (the first rows, a run of unchanged ones, or none); a tail of rows past count.
    g = torch.Generator().manual_seed(C)
    H, W = 170, 160
    keys = torch.randperm(H * W, generator=g)
    m = 24_000
    cand = torch.stack([keys // W, keys % W], 1).to(torch.int32)
    count = torch.tensor([m])
    acc = torch.randn(H, W, C, generator=g, dtype=torch.float64)
    scale, shift = torch.rand(C, generator=g, dtype=torch.float64) + 0.5, torch.randn(C, generator=g, dtype=torch.float64)
    out = torch.relu(torch.randn(H, W, C, generator=g, dtype=torch.float64)) + 0.5
    same = torch.rand(H, W, generator=g) < unchanged
    same[keys[:3000] // W, keys[:3000] % W] = unchanged > 0.9  # the first rows all unchanged, or none
    # an unchanged row: an inactive site that already holds 0 (exact on every device, whatever the rounding of
    # the BatchNorm, which CUDA fuses into one multiply-add)
    active = ~same & (torch.rand(H, W, generator=g) > 0.1)
    out = torch.where(same[..., None], 0.0, out)
    stamp = torch.randint(0, 3, (H, W), generator=g, dtype=torch.int32)
    ref_out, ref_sites, ref_delta, ref_counts = sops._finalize_compact_reference(
        acc, out, active, cand, count, stamp, 2, scale, shift)
    got = out.to(device)
    sites, delta, counts = sops.finalize_compact_(acc.to(device), got, active.to(device), cand.to(device),
                                                  count.to(device), stamp.to(device), 2, scale.to(device),
                                                  shift.to(device))
    assert counts.cpu().tolist() == ref_counts and 0 < ref_counts[0] <= m and (ref_counts[0] < m) == (unchanged > 0)
    _close(got, ref_out, torch.float64, "out")
    n = ref_counts[0]
    assert sites.shape == cand.shape and sites.cpu()[n:].eq(-1).all()
    if device == "cpu":  # in the candidates' order (CUDA compacts in any order)
        assert [tuple(r) for r in sites[:n].tolist()] == ref_sites
        _close(delta[:n], ref_delta, torch.float64, "delta")
    else:
        got_sites = [tuple(r) for r in sites.cpu()[:n].tolist()]
        order = {site: i for i, site in enumerate(ref_sites)}
        assert set(got_sites) == set(ref_sites)
        _close(delta.cpu()[:n], ref_delta[[order[site] for site in got_sites]], torch.float64, "delta")


def test_wrappers_name_the_bad_argument():
    acc = torch.zeros(4, 4, 3)
    sites = torch.zeros(2, 2, dtype=torch.int32)
    w = torch.zeros(3, 3, 3, 2)
    with pytest.raises(ValueError, match="sites must be an int32"):
        sops.scatter_(acc, sites.long(), torch.zeros(2, 2), w, 1, 1)
    with pytest.raises(ValueError, match="delta must be"):
        sops.scatter_(acc, sites, torch.zeros(3, 2), w, 1, 1)
    with pytest.raises(ValueError, match="weight must be"):
        sops.scatter_(acc, sites, torch.zeros(2, 2), w.double(), 1, 1)
    with pytest.raises(ValueError, match="stride must be an int >= 1"):
        sops.scatter_(acc, sites, torch.zeros(2, 2), w, 0, 1)
    for bad in (float("nan"), "0.5", True, None):
        with pytest.raises(ValueError, match="channel_sparse must be a number"):
            sops.scatter_(acc, sites, torch.zeros(2, 2), w, 1, 1, channel_sparse=bad)
    with pytest.raises(ValueError, match="acc must be float32 or float64"):
        sops.finalize_(acc.half(), acc.half(), torch.ones(4, 4, dtype=torch.bool), sites, torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="active must be"):
        sops.finalize_(acc, acc.clone(), torch.ones(4, 4), sites, torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="scale must be"):
        sops.finalize_(acc, acc.clone(), torch.ones(4, 4, dtype=torch.bool), sites, torch.ones(2), torch.zeros(3))
    y = torch.zeros(3, 4, 4)
    with pytest.raises(ValueError, match=r"y must be torch.float32 \(C, Ho, Wo\)"):
        sops.dense_finalize_(y.permute(1, 2, 0), acc, acc.clone(), torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="acc must be contiguous"):
        sops.dense_finalize_(y, acc.transpose(0, 1), acc.clone(), torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="out must be"):
        sops.dense_finalize_(y, acc, acc.double(), torch.ones(3), torch.zeros(3))
    with pytest.raises(ValueError, match="shift must be"):
        sops.dense_finalize_(y, acc, acc.clone(), torch.ones(3), torch.zeros(4))
    with pytest.raises(ValueError, match="active must be"):
        sops.dense_finalize_(y, acc, acc.clone(), torch.ones(3), torch.zeros(3), torch.ones(4, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="out_nchw must be a contiguous"):
        sops.dense_finalize_(y, acc, acc.clone(), torch.ones(3), torch.zeros(3), None, acc.clone())
    with pytest.raises(ValueError, match="stamp must be"):
        sops.touch_(torch.zeros(4, 4), acc, 1, torch.zeros(1, dtype=torch.int64), sites, sites)
    with pytest.raises(ValueError, match="targets must be"):
        sops.touch_(torch.zeros(4, 4, dtype=torch.int32), acc, 1, torch.zeros(1), sites, sites)
    with pytest.raises(ValueError, match="count must be"):
        sops.gather_(acc, torch.zeros(4, 4, 2), w, sites, 1, 1, torch.zeros(1))
    with pytest.raises(ValueError, match="cover must be"):
        sops.cover_update_(torch.zeros(4, 4), torch.zeros(4, 4, dtype=torch.bool), torch.zeros(4, 4, dtype=torch.int32),
                           1, sites, sites, 3, 3, 2, 1)
    with pytest.raises(ValueError, match="kh must be"):
        sops.children_(torch.zeros(4, 4, dtype=torch.bool), sites, sites, 0, 2, 2, 0)
