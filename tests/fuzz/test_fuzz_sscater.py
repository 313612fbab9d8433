"""Fuzz: lidarops.sscater.ops.dense_finalize_ (a layer's state from a dense convolution's output) against its
float64 reference.

Documented: acc = active ? y : 0 and out (and out_nchw) = active ? max(y * scale + shift, 0) : 0 with a NaN
giving 0, for y in NCHW, channels-last or any strides and out any strides; a bad shape, dtype or layout raises
ValueError naming the argument; empty maps are no-ops.
"""
from __future__ import annotations

import math

import torch
from hypothesis import given
from hypothesis import strategies as st

from lidarops.sscater import ops as sops
from .fuzzing import assert_clear_error, assert_no_error, assert_same, fuzz, outcome

_EPS = {torch.float32: 2.0 ** -23, torch.float64: 2.0 ** -52}


def _values(draw, shape, dtype):
    """Random values of a drawn magnitude, with a drawn handful of zeros, NaN, infinities and subnormals."""
    g = torch.Generator().manual_seed(draw(st.integers(0, 2**31 - 1)))
    v = torch.randn(shape, generator=g, dtype=torch.float64) * draw(st.sampled_from([1e-3, 1.0, 1e3]))
    flat = v.view(-1)
    for _ in range(draw(st.integers(0, min(6, flat.numel())))):
        flat[draw(st.integers(0, flat.numel() - 1))] = draw(st.sampled_from(
            [0.0, -0.0, math.nan, math.inf, -math.inf, 1e-42, -1e-42, 1e-30]))
    return v.to(dtype)


def _check_out(got, acc_ref, scale, shift, ref, dtype, what):
    """``got`` within the dtype's rounding of y * scale + shift (one multiply and one add), specials exact."""
    got = got.detach().cpu().double()
    tiny = torch.finfo(dtype).smallest_normal * _EPS[dtype]  # the spacing of subnormals
    bound = 4 * _EPS[dtype] * (acc_ref.abs() * scale.double().abs() + shift.double().abs()) + 2 * tiny
    finite = torch.isfinite(ref) & torch.isfinite(bound)
    close = (got - ref).abs() <= bound
    same = (got == ref) | (torch.isnan(got) & torch.isnan(ref))
    bad = ~torch.where(finite, close | same, same)
    assert not bool(bad.any()), f"{what}: {int(bad.sum())} entries off; first at " \
                                f"{tuple(torch.nonzero(bad)[0].tolist())}"


@fuzz
@given(data=st.data())
def test_dense_finalize(device, data):
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    C, Ho, Wo = (data.draw(st.integers(0, 40), n) for n in ("C", "Ho", "Wo"))
    y = _values(data.draw, (C, Ho, Wo), dtype)
    scale = _values(data.draw, (C,), dtype).nan_to_num(0.0, 1.0, -1.0)  # folded BatchNorm: finite
    shift = _values(data.draw, (C,), dtype).nan_to_num(0.0, 1.0, -1.0)
    share = data.draw(st.sampled_from([None, 0.0, 0.5, 1.0]), "active share")  # None: no mask
    active = None if share is None else \
        torch.rand(Ho, Wo, generator=torch.Generator().manual_seed(C + Ho + Wo)) < share
    layout = data.draw(st.sampled_from(["nchw", "channels_last", "strided"]), "layout")
    if layout == "nchw":
        y_dev = y.to(device)
    elif layout == "channels_last":
        y_dev = y.permute(1, 2, 0).contiguous().to(device).permute(2, 0, 1)
    else:
        y_dev = torch.zeros(C, Ho, 2 * Wo, dtype=dtype, device=device)[:, :, 1::2]
        y_dev.copy_(y)
    acc = torch.full((Ho, Wo, C), 7.0, dtype=dtype, device=device)
    out = torch.full((Ho, Wo, C), 7.0, dtype=dtype, device=device) if data.draw(st.booleans(), "own out") else \
        torch.full((C, Ho, Wo), 7.0, dtype=dtype, device=device).permute(1, 2, 0)
    out_nchw = torch.full((C, Ho, Wo), 7.0, dtype=dtype, device=device) if data.draw(st.booleans(), "nchw") else None
    what = f"dense_finalize_({dtype}, (C, Ho, Wo) = {(C, Ho, Wo)}, {layout}, masked {active is not None})"
    _, err = outcome(sops.dense_finalize_, y_dev, acc, out, scale.to(device), shift.to(device),
                     None if active is None else active.to(device), out_nchw)
    assert_no_error(err, what)
    acc_ref, out_ref = sops._dense_finalize_reference(y, scale, shift, active)
    assert_same(acc, acc_ref, what + ": acc")
    _check_out(out, acc_ref, scale, shift, out_ref, dtype, what + ": out")
    if out_nchw is not None:
        _check_out(out_nchw.permute(1, 2, 0), acc_ref, scale, shift, out_ref, dtype, what + ": out_nchw")


@fuzz
@given(data=st.data())
def test_dense_finalize_bad_arguments(device, data):
    C, Ho, Wo = 3, 4, 5
    args = dict(y=torch.zeros(C, Ho, Wo), acc=torch.zeros(Ho, Wo, C), out=torch.zeros(Ho, Wo, C), scale=torch.ones(C),
                shift=torch.zeros(C), active=torch.ones(Ho, Wo, dtype=torch.bool), out_nchw=torch.zeros(C, Ho, Wo))
    name = data.draw(st.sampled_from(sorted(args)), "argument")
    bad = data.draw(st.sampled_from(["shape", "dtype", "layout"]), "how")
    t = args[name]
    if bad == "shape":
        t = torch.zeros(*[s + 1 for s in t.shape], dtype=t.dtype)
    elif bad == "dtype":
        t = t.to(torch.float16 if t.dtype != torch.bool else torch.float32)
    else:
        if name not in ("acc", "out_nchw", "active"):  # any strides are allowed there
            return
        t = t.transpose(0, 1).contiguous().transpose(0, 1) if t.dim() >= 2 and t.shape[0] != t.shape[1] else t
        if t.is_contiguous():
            return
    args[name] = t
    moved = {k: v.to(device) for k, v in args.items()}
    _, err = outcome(sops.dense_finalize_, **moved)
    names = [name] + (["acc"] if name in ("scale", "shift") else []) + (["y", "out", "scale"] if name == "acc" else [])
    assert_clear_error(err, ValueError, names, f"dense_finalize_ with a bad {bad} of {name}")


@fuzz
@given(data=st.data())
def test_finalize_compact_matches_its_reference(device, data):
    """finalize_compact_ over up to tens of thousands of candidates (the CPU op compacts them chunk by chunk): out,
    the changed sites in the candidates' order (any order on CUDA), their deltas and the counts as the float64
    reference, with NaN, infinities, exact zeros and rows already up to date among them."""
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    C = data.draw(st.integers(1, 5), "C")
    H, W = data.draw(st.integers(1, 140), "H"), data.draw(st.integers(1, 150), "W")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**31 - 1), "seed"))
    keys = torch.randperm(H * W, generator=g)[:data.draw(st.integers(0, H * W), "candidates")]
    cand = torch.stack([keys // W, keys % W], 1).to(torch.int32)
    count = torch.tensor([data.draw(st.integers(-2, len(keys) + 2), "count")])
    acc = _values(data.draw, (H, W, C), dtype)
    scale, shift = _values(data.draw, (C,), dtype), _values(data.draw, (C,), dtype)
    active = torch.rand(H, W, generator=g) < data.draw(st.sampled_from([0.0, 0.5, 1.0]), "active share")
    # rows already up to date: their new value is 0 whatever the rounding (inactive, or BatchNorm's output clearly
    # negative) and out holds 0 there; the other rows hold other values, so they change
    pre = acc.double() * scale.double() + shift.double()
    zero = ~active[..., None] | (pre < 0) & (pre.abs() > 1e-6 * ((acc.double() * scale.double()).abs() + shift.double().abs()))
    same = zero.all(-1) & (torch.rand(H, W, generator=g) < data.draw(st.sampled_from([0.0, 0.5, 0.95]), "share unchanged"))
    out = torch.where(same[..., None], 0.0, _values(data.draw, (H, W, C), torch.float64).abs() + 0.5).to(dtype)
    stamp = torch.randint(0, 3, (H, W), generator=g, dtype=torch.int32)
    ref_out, ref_sites, ref_delta, ref_counts = sops._finalize_compact_reference(
        acc.double(), out.double(), active, cand, count, stamp, 2, scale.double(), shift.double())
    old = out.double()  # the values the op replaces
    got = out.clone().to(device)
    res, err = outcome(sops.finalize_compact_, acc.to(device), got, active.to(device), cand.to(device),
                       count.to(device), stamp.to(device), 2, scale.to(device), shift.to(device))
    assert_no_error(err, "finalize_compact_ on valid input")
    sites, delta, counts = res
    # the op computes in dtype: compare where the float64 reference rounds to the same value, specials exactly
    assert counts.cpu().tolist() == ref_counts
    n = ref_counts[0]
    assert sites.shape == cand.shape and bool(sites.cpu()[n:].eq(-1).all())
    got_sites = [tuple(r) for r in sites.cpu()[:n].tolist()]
    if device == "cpu":
        assert got_sites == ref_sites
    else:
        assert sorted(got_sites) == sorted(ref_sites)
    _check_out(got, acc.double(), scale, shift, ref_out, dtype, "out")
    order = {site: i for i, site in enumerate(ref_sites)}
    rows = [order[site] for site in got_sites]
    ys, xs = [y for y, _ in got_sites], [x for _, x in got_sites]
    # delta = new - old: within the rounding of the new value and of the subtraction, specials exact
    ref, got_d = ref_delta[rows], delta.cpu()[:n].double()
    bound = 8 * _EPS[dtype] * (ref_out[ys, xs].abs() + old[ys, xs].abs()) + 1e-300
    finite = torch.isfinite(ref) & torch.isfinite(bound)
    ok = torch.where(finite, (got_d - ref).abs() <= bound, (got_d == ref) | (torch.isnan(got_d) & torch.isnan(ref)))
    assert bool(ok.all()), f"delta: {int((~ok).sum())} entries off"


@fuzz
@given(pillars=st.one_of(st.integers(-5, 0), st.floats(allow_nan=True), st.booleans(), st.text(max_size=3),
                         st.none(), st.integers(1, 3000)),
       points=st.one_of(st.just(16384), st.integers(-3, 5000), st.floats(allow_nan=True), st.booleans(), st.none()))
def test_warm_up_takes_a_count_of_pillars(pillars, points):
    """SSCATeRPointPillars.warm_up(pillars, points): pillars an int >= 1 (or None, the stream's max_pillars) and
    points an int >= 0 record the graphs (none on the CPU); anything else raises ValueError naming the argument;
    after the first step it raises."""
    from lidarops.models.sscater_pointpillars import PillarFeatureNet, SSCATeRPointPillars
    from lidarops.models import BaseBEVBackbone
    from lidarops.stream import PillarGrid
    model = SSCATeRPointPillars(PillarFeatureNet(9, 64).eval(), BaseBEVBackbone().eval(),
                                PillarGrid((0.0, -8.0, -3.0, 16.0, 8.0, 1.0), (0.5, 0.5, 4.0)), device="cpu")
    res, err = outcome(model.warm_up, pillars, points)
    what = f"warm_up({pillars!r}, points={points!r})"
    good_points = isinstance(points, int) and not isinstance(points, bool) and points >= 0
    if pillars is None or (isinstance(pillars, int) and not isinstance(pillars, bool) and pillars >= 1):
        if good_points:
            assert_no_error(err, what)
            assert res == 0
        else:
            assert_clear_error(err, ValueError, ["points"], what)
    else:
        assert_clear_error(err, ValueError, ["pillars"], what)
