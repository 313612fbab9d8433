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
