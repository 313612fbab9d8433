"""Fuzz: CAS-Net's parts: the offset-attention layer (both paths, padding masks, BatchNorm modes), the Chamfer distance
and the selection cosine loss, against their float64 references (lidarops.models.offset_attention,
lidarops.models.casnet_losses).

The rule of this folder: bad shapes, dtypes, devices or values raise a ``ValueError`` naming the argument; anything
else returns a finite result equal (within the dtype's rounding) to the reference computed on the same numbers.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from hypothesis import assume, given
from hypothesis import strategies as st

from lidarops.models.casnet_losses import _selection_cosine_reference, chamfer_distance, selection_cosine_loss
from lidarops.models.offset_attention import OffsetAttention, _offset_attention_reference
from lidarops.ops.validation import coordinate_bound

from .fuzzing import Cloud, assert_clear_error, assert_close, assert_no_error, clouds, fuzz, outcome

_CHUNKS = st.none() | st.just("auto") | st.just("fused") | st.integers(1, 14)


# ---------------------------------------------------------------------------------------------- offset attention
def _layer(C: int, d: int, seed: int, training: bool, device) -> OffsetAttention:
    torch.manual_seed(seed)
    layer = OffsetAttention(C, d, chunk=None).double()
    g = torch.Generator().manual_seed(seed)
    bn = layer.after_norm
    bn.running_mean.copy_(torch.rand(C, generator=g, dtype=torch.float64) - 0.5)
    bn.running_var.copy_(torch.rand(C, generator=g, dtype=torch.float64) + 0.5)
    bn.weight.data.copy_(torch.rand(C, generator=g, dtype=torch.float64) + 0.5)
    return layer.to(device).train(training)


@fuzz
@given(data=st.data())
def test_offset_attention_matches_the_pct_reference(device, data):
    B, N = data.draw(st.integers(1, 3), "B"), data.draw(st.integers(0, 12), "N")
    C, d = data.draw(st.integers(1, 4), "C"), data.draw(st.integers(1, 3), "d")
    chunk, training = data.draw(_CHUNKS, "chunk"), data.draw(st.booleans(), "training")
    scale = data.draw(st.sampled_from([1e-3, 1.0, 10.0]), "scale")
    seed = data.draw(st.integers(0, 2**16), "seed")
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(B, C, N, generator=g, dtype=torch.float64) * scale
    mask = None
    if data.draw(st.booleans(), "masked"):
        mask = torch.tensor(data.draw(st.lists(st.booleans(), min_size=B * N, max_size=B * N)),
                            dtype=torch.bool).reshape(B, N)
    real = B * N if mask is None else int(mask.sum())
    assume(not training or real != 1)  # BatchNorm cannot normalise one value in training (torch's rule)
    layer = _layer(C, d, seed, training, device)
    bn = layer.after_norm
    mean, var = bn.running_mean.clone(), bn.running_var.clone()
    what = f"OffsetAttention(B={B}, N={N}, C={C}, d={d}, chunk={chunk!r}, training={training}, masked={mask is not None})"
    got, err = outcome(layer, x.to(device), None if mask is None else mask.to(device), chunk)
    assert_no_error(err, what)
    want = x.clone() if real == 0 else _offset_attention_reference(
        x.to(device), layer.q_conv.weight, layer.v_conv.weight, layer.v_conv.bias, layer.trans_conv.weight,
        layer.trans_conv.bias, bn.weight, bn.bias, mean, var, training, bn.momentum, bn.eps,
        mask=None if mask is None else mask.to(device))
    assert torch.isfinite(got).all(), what
    assert_close(got, want, 1e-9, 1e-9, what)
    if real:
        assert_close(bn.running_mean, mean, 1e-12, 1e-12, what + " running_mean")


_BAD_OA = ["x_dim", "x_channels", "x_int", "x_list", "mask_dtype", "mask_shape", "mask_device", "chunk"]


@fuzz
@given(data=st.data())
def test_offset_attention_refuses_bad_arguments(device, data):
    kind = data.draw(st.sampled_from(_BAD_OA), "kind")
    B, C, N = data.draw(st.integers(1, 2), "B"), data.draw(st.integers(1, 3), "C"), data.draw(st.integers(1, 6), "N")
    layer = _layer(C, 1, 0, False, device)
    x = torch.randn(B, C, N, dtype=torch.float64, device=device)
    mask, chunk = None, None
    if kind == "x_dim":
        x = x.reshape(data.draw(st.sampled_from([(B * C * N,), (B, C, N, 1), (1, B, C, N)])))
    elif kind == "x_channels":
        x = torch.randn(B, C + data.draw(st.integers(1, 3)), N, dtype=torch.float64, device=device)
    elif kind == "x_int":
        x = x.to(data.draw(st.sampled_from([torch.int64, torch.int32, torch.bool, torch.uint8])))
    elif kind == "x_list":
        x = x.tolist()
    elif kind == "mask_dtype":
        mask = torch.ones(B, N, device=device, dtype=data.draw(st.sampled_from([torch.int64, torch.float32])))
    elif kind == "mask_shape":
        mask = torch.ones(*data.draw(st.sampled_from([(B, N + 1), (B + 1, N), (B * N,), (B, N, 1)])), dtype=torch.bool,
                          device=device)
    elif kind == "mask_device":
        mask = torch.ones(B, N, dtype=torch.bool, device="meta")
    else:
        chunk = data.draw(st.sampled_from([0, -1, -64, True, False, 2.0, math.nan, "8", "Auto", [4]]))
    name = kind.split("_")[0]
    _, err = outcome(layer, x, mask, chunk)
    assert_clear_error(err, ValueError, [name], f"OffsetAttention with bad {kind}")


# ---------------------------------------------------------------------------------------------- Chamfer
def _numpy_chamfer(a: np.ndarray, b: np.ndarray, la, lb) -> tuple[float, float]:
    """The loss in float64 and the largest sum it adds up (to tell when float32 must overflow)."""
    total, largest = 0.0, 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        for c in range(a.shape[0]):
            d = ((a[c, :la[c], None, :] - b[c, None, :lb[c], :]) ** 2).sum(-1)
            sums = (d.min(axis=1).sum(), d.min(axis=0).sum())
            largest = max(largest, *sums)
            total += sums[0] / la[c] + sums[1] / lb[c]
    return total / a.shape[0], largest


def _chamfer_errors(a: Cloud, b: Cloud) -> tuple[list, list]:
    """(names one of which the ValueError must name, names it may name instead of returning a result)."""
    B, N, M = a.points.shape[0], a.points.shape[1], b.points.shape[1]
    must = []
    if B == 0 or N == 0:
        must.append("a")
    if M == 0:
        must.append("b")
    for name, c, n in (("a_lengths", a, N), ("b_lengths", b, M)):
        if c.lengths is not None and not bool(((c.lengths >= 1) & (c.lengths <= n)).all()):
            must.append(name)
    for name, c in (("a", a), ("b", b)):
        if not c.finite():
            must.append(name)
    may = []
    for name, c in (("a", a), ("b", b)):  # coordinates beyond the bound knn accepts
        if c.finite() and c.points.numel() and float(c.points.abs().max()) > coordinate_bound(c.points.dtype):
            may.append(name)
    return must, may


@fuzz
@given(data=st.data())
def test_chamfer_distance(device, data):
    a = data.draw(clouds(max_n=9), "a")
    b = data.draw(clouds(batch=a.points.shape[0], dtype=a.points.dtype, max_n=9), "b")
    what = f"chamfer_distance({a.regime}/{b.regime}, {a.points.dtype}, B={a.points.shape[0]})"
    on = (lambda t: None if t is None else t.to(device))
    got, err = outcome(chamfer_distance, a.points.to(device), b.points.to(device), on(a.lengths), on(b.lengths))
    must, may = _chamfer_errors(a, b)
    if must:
        return assert_clear_error(err, ValueError, must + may, what)
    if err is not None and may:
        return assert_clear_error(err, ValueError, may, what)
    assert_no_error(err, what)
    want, largest = _numpy_chamfer(a.points.double().numpy(), b.points.double().numpy(), a.rows(), b.rows())
    ct = torch.float64 if a.points.dtype == torch.float64 else torch.float32
    assert got.dtype == ct and got.shape == (), what
    if not largest < torch.finfo(ct).max / 2:  # a sum beyond the computation dtype: inf, as documented for knn
        return
    assert math.isfinite(got.item()), what
    rtol, atol = (1e-12, 1e-300) if ct == torch.float64 else (1e-5, 1e-36)
    assert abs(got.item() - want) <= atol + rtol * abs(want), f"{what}: got {got.item()!r}, reference {want!r}"


@fuzz
@given(data=st.data())
def test_chamfer_distance_refuses_mismatched_arguments(device, data):
    kind = data.draw(st.sampled_from(["dtype", "batch", "shape", "int", "device", "lengths_float"]), "kind")
    a = torch.rand(2, 4, 3, dtype=torch.float64, device=device)
    b = torch.rand(2, 5, 3, dtype=torch.float64, device=device)
    la = None
    names = {"dtype": ["dtype"], "batch": ["b"], "shape": ["a"], "int": ["a"], "device": ["b"],
             "lengths_float": ["a_lengths"]}[kind]
    if kind == "dtype":
        b = b.float()
    elif kind == "batch":
        b = b[:1]
    elif kind == "shape":
        a = a[..., :data.draw(st.integers(1, 2))]
    elif kind == "int":
        a, b = a.long(), b.long()
    elif kind == "device":
        b = b.to("meta")
    else:
        la = torch.tensor([1.0, 2.0], device=device)
    _, err = outcome(chamfer_distance, a, b, la)
    assert_clear_error(err, ValueError, names, f"chamfer_distance with bad {kind}")


# ---------------------------------------------------------------------------------------------- cosine loss
@fuzz
@given(data=st.data())
def test_selection_cosine_loss(device, data):
    B, m, N = (data.draw(st.integers(0, 3), n) for n in ("B", "m", "N"))
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    form = data.draw(st.sampled_from(["paper", "frobenius"]) | st.sampled_from(["Paper", "fro", "", None, 1]), "form")
    kind = data.draw(st.sampled_from(["softmax", "any", "sparse"]), "values")
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**16), "seed"))
    raw = torch.randn(B, m, N, generator=g, dtype=torch.float64) * 4
    w = {"softmax": lambda: torch.softmax(raw, -1) if N else raw, "any": lambda: raw,
         "sparse": lambda: (raw > 1).double()}[kind]().to(dtype)
    what = f"selection_cosine_loss({tuple(w.shape)}, {dtype}, form={form!r}, {kind})"
    got, err = outcome(selection_cosine_loss, w.to(device), form)
    if 0 in (B, m, N):
        return assert_clear_error(err, ValueError, ["weights"], what)
    if form not in ("paper", "frobenius"):
        return assert_clear_error(err, ValueError, ["form"], what)
    assert_no_error(err, what)
    want = _selection_cosine_reference(w.double(), form)
    assert got.dtype == dtype and torch.isfinite(got), what
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert_close(got.reshape(1), want.reshape(1), tol, tol, what)
    if form == "paper":
        assert 0 <= got.item() <= 1 + tol, what


@fuzz
@given(data=st.data())
def test_selection_cosine_loss_refuses_bad_weights(data):
    w = data.draw(st.sampled_from([torch.rand(3), torch.rand(2, 3), torch.rand(1, 2, 3, 1), torch.ones(1, 2, 3).long(),
                                   torch.ones(1, 2, 3, dtype=torch.bool), [[[0.5]]], None]), "weights")
    _, err = outcome(selection_cosine_loss, w)
    assert_clear_error(err, ValueError, ["weights"], f"selection_cosine_loss({w!r})")
