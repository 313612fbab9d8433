"""lidarops.models.offset_attention: PCT's offset-attention layer against a literal re-statement of the PCT formula
(cloud by cloud on the real points), the chunked path against the plain one (forward and every gradient), gradcheck,
padding that neither attends nor is attended, BatchNorm in both modes, and the chunked path's promise: no tensor of
N x N entries, forward or backward."""
from __future__ import annotations

import math

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from helpers.compare import assert_close_report
from helpers.devices import requires_cuda
from helpers.models import randomize_bn
from lidarops.models import offset_attention as oa
from lidarops.models.offset_attention import (OffsetAttention, _offset_attention_reference,
                                              column_normalized_attention)


def make_layer(C=6, d=3, seed=0, dtype=torch.float64, device="cpu", training=True) -> OffsetAttention:
    torch.manual_seed(seed)
    layer = OffsetAttention(C, d, chunk=None)
    randomize_bn(layer, seed)
    return layer.to(dtype=dtype, device=device).train(training)


def random_input(B, C, N, seed, dtype=torch.float64, device="cpu", scale=1.0):
    g = torch.Generator().manual_seed(seed)
    return (torch.randn(B, C, N, generator=g, dtype=torch.float64) * scale).to(dtype=dtype, device=device)


def random_mask(B, N, seed, keep=0.6, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(B, N, generator=g) < keep
    mask[:, 0] = True  # every cloud has a real point (and 2 in the batch, for BatchNorm in training)
    mask[0, -1] = True
    return mask.to(device)


def reference(layer: OffsetAttention, x, mask=None):
    """The literal reference with the layer's weights; its own copies of the running statistics (returned too)."""
    bn = layer.after_norm
    mean, var = bn.running_mean.clone(), bn.running_var.clone()
    out = _offset_attention_reference(x, layer.q_conv.weight, layer.v_conv.weight, layer.v_conv.bias,
                                      layer.trans_conv.weight, layer.trans_conv.bias, bn.weight, bn.bias, mean, var,
                                      layer.training, bn.momentum, bn.eps, mask=mask)
    return out, mean, var


def grads(layer: OffsetAttention, x, mask=None, chunk=None, seed=9):
    """The output and the gradients of a fixed random projection of it w.r.t. x and every parameter."""
    x = x.detach().clone().requires_grad_(True)
    out = layer(x, mask, chunk=chunk)
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    params = [p for p in layer.parameters()]
    gs = torch.autograd.grad((out * w.to(out)).sum(), [x] + params)
    return out.detach(), gs


# ------------------------------------------------------------------------------------------ against PCT's formula
@pytest.mark.parametrize("training", [True, False], ids=["train", "eval"])
@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
@pytest.mark.parametrize("chunk", [None, 4, "fused"], ids=["plain", "chunk4", "fused"])
def test_layer_matches_literal_pct_reference(training, masked, chunk):
    layer = make_layer(training=training, seed=1)
    x = random_input(3, 6, 19, seed=2)
    mask = random_mask(3, 19, seed=3) if masked else None
    want, want_mean, want_var = reference(layer, x, mask)
    got = layer(x, mask, chunk=chunk)
    assert_close_report(got, want, 1e-12, 1e-12, f"OA(training={training}, masked={masked}, chunk={chunk})")
    # the running statistics move as BatchNorm over the real points moves them (and not at all in eval)
    assert_close_report(layer.after_norm.running_mean, want_mean, 1e-12, 1e-14, "running_mean")
    assert_close_report(layer.after_norm.running_var, want_var, 1e-12, 1e-14, "running_var")


def test_zero_projection_gives_the_column_mean_by_hand():
    """Q = K = 0: every energy is 0, each row of P is uniform 1/N, each column sums to 1, so
    A = (1/N) / (1e-9 + 1) and x_r[:, j] = mean_i V[:, i] / (1 + 1e-9), the same for every j."""
    N = 5
    v = torch.tensor([[[1.0, 2.0, 3.0, 4.0, 10.0]]], dtype=torch.float64)  # (1, 1, 5), mean 4
    q = torch.zeros(1, 2, N, dtype=torch.float64)
    want = torch.full((1, 1, N), 4.0 / (1 + 1e-9), dtype=torch.float64)
    for chunk in (None, 2):
        assert_close_report(column_normalized_attention(q, q, v, chunk=chunk), want, 1e-15, 0, f"chunk={chunk}")


def test_two_point_case_by_hand():
    """N = 2, d = 1, q = (1, 0): energies [[1, 0], [0, 0]]; rows softmax to [e/(e+1), 1/(e+1)] and [1/2, 1/2];
    column sums c0 = e/(e+1) + 1/2, c1 = 1/(e+1) + 1/2; x_r[:, j] = sum_i v_i P[i, j] / (1e-9 + c_j)."""
    e = math.e
    p = [[e / (e + 1), 1 / (e + 1)], [0.5, 0.5]]
    c = [p[0][0] + p[1][0], p[0][1] + p[1][1]]
    v = [3.0, -1.0]
    want = torch.tensor([[[(v[0] * p[0][j] + v[1] * p[1][j]) / (1e-9 + c[j]) for j in range(2)]]], dtype=torch.float64)
    q = torch.tensor([[[1.0, 0.0]]], dtype=torch.float64)
    vt = torch.tensor([[v]], dtype=torch.float64)
    for chunk in (None, 1, 2):
        assert_close_report(column_normalized_attention(q, q, vt, chunk=chunk), want, 1e-14, 0, f"chunk={chunk}")


# ------------------------------------------------------------------------------------------ chunked against plain
@pytest.mark.parametrize("N,chunk", [(1, 1), (7, 3), (20, 6), (20, 64), (33, 1)])
@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_chunked_matches_plain_forward_and_gradients(N, chunk, masked):
    layer = make_layer(seed=N)
    x = random_input(2, 6, N, seed=N + 1, scale=2.0)
    mask = random_mask(2, N, seed=N + 2) if masked else None
    plain, g_plain = grads(layer, x, mask, chunk=None)
    chunked, g_chunk = grads(layer, x, mask, chunk=chunk)
    assert_close_report(chunked, plain, 1e-11, 1e-12, f"forward N={N} chunk={chunk}")
    names = ["x"] + [n for n, _ in layer.named_parameters()]
    for name, a, b in zip(names, g_chunk, g_plain):
        assert_close_report(a, b, 1e-9, 1e-11, f"d/d{name} N={N} chunk={chunk}")


def test_chunked_gradients_match_plain_on_a_larger_cloud():
    layer = make_layer(C=8, d=4, seed=5)
    x = random_input(2, 8, 200, seed=6)
    mask = random_mask(2, 200, seed=7, keep=0.8)
    plain, g_plain = grads(layer, x, mask, chunk=None)
    chunked, g_chunk = grads(layer, x, mask, chunk=37)
    assert_close_report(chunked, plain, 1e-10, 1e-12, "forward N=200")
    for a, b in zip(g_chunk, g_plain):
        assert_close_report(a, b, 1e-8, 1e-10, "gradients N=200")


def test_attention_with_distinct_q_and_k_chunked_matches_plain():
    g = torch.Generator().manual_seed(11)
    q, k = (torch.randn(2, 3, 23, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(2))
    v = torch.randn(2, 5, 23, generator=g, dtype=torch.float64, requires_grad=True)
    mask = random_mask(2, 23, seed=12)
    w = torch.randn(2, 5, 23, generator=g, dtype=torch.float64)
    for m in (None, mask):
        ref = torch.autograd.grad((column_normalized_attention(q, k, v, m) * w).sum(), (q, k, v))
        got = torch.autograd.grad((column_normalized_attention(q, k, v, m, chunk=4) * w).sum(), (q, k, v))
        for name, a, b in zip("qkv", got, ref):
            assert_close_report(a, b, 1e-10, 1e-12, f"d/d{name} mask={m is not None}")


@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_gradcheck_chunked_attention(masked):
    g = torch.Generator().manual_seed(int(masked))
    q = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    k = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    v = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    mask = random_mask(2, 5, seed=5) if masked else None
    assert torch.autograd.gradcheck(lambda q, k, v: column_normalized_attention(q, k, v, mask, chunk=2), (q, k, v))
    # Q and K as one tensor, the way the layer calls it
    assert torch.autograd.gradcheck(lambda q, v: column_normalized_attention(q, q, v, mask, chunk=3), (q, v))


@pytest.mark.parametrize("N", [1, 7, 33])
@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_fused_matches_plain_forward_and_gradients(N, masked):
    """torch's fused attention with the row log-sum-exps as a key coordinate and a sink key for PCT's 1e-9: the
    plain path's x_r and every gradient."""
    layer = make_layer(seed=12)
    x = random_input(2, 6, N, seed=13)
    mask = random_mask(2, N, seed=14) if masked else None
    plain, g_plain = grads(layer, x, mask, chunk=None)
    fused, g_fused = grads(layer, x, mask, chunk="fused")
    assert_close_report(fused, plain, 1e-11, 1e-12, f"forward N={N}")
    for a, b in zip(g_fused, g_plain):
        assert_close_report(a, b, 1e-9, 1e-11, f"gradients N={N}")


@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_gradcheck_fused_attention(masked):
    g = torch.Generator().manual_seed(7 + int(masked))
    q = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    k = torch.randn(2, 2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    v = torch.randn(2, 3, 5, generator=g, dtype=torch.float64, requires_grad=True)
    mask = random_mask(2, 5, seed=5) if masked else None
    assert torch.autograd.gradcheck(lambda q, k, v: column_normalized_attention(q, k, v, mask, chunk="fused"),
                                    (q, k, v))
    assert torch.autograd.gradcheck(lambda q, v: column_normalized_attention(q, q, v, mask, chunk="fused"), (q, v))


def test_fused_column_eps_is_pcts():
    """A column that no query attends to (its sum of P far below 1e-9) comes out near 0, as PCT's 1e-9 makes it,
    not as the mean of the values a plain normalisation would give."""
    q = torch.zeros(1, 1, 3, dtype=torch.float64)
    q[0, 0] = torch.tensor([6.0, 6.0, -6.0])  # e = q_i q_j: column 2 gets exp(-36 - lse) from rows 0 and 1
    v = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
    want = column_normalized_attention(q, q, v, chunk=None)
    got = column_normalized_attention(q, q, v, chunk="fused")
    assert_close_report(got, want, 1e-12, 1e-12, "tiny column")


@pytest.mark.parametrize("training", [True, False], ids=["train", "eval"])
def test_gradcheck_layer_chunked(training):
    layer = make_layer(C=2, d=1, seed=4, training=training)
    x = random_input(2, 2, 5, seed=5).requires_grad_(True)
    mask = random_mask(2, 5, seed=6)
    assert torch.autograd.gradcheck(lambda x: layer(x, mask, chunk=2), (x,), fast_mode=True)


# ------------------------------------------------------------------------------------------ padding
@pytest.mark.parametrize("chunk", [None, 3, "fused"], ids=["plain", "chunk3", "fused"])
@pytest.mark.parametrize("training", [True, False], ids=["train", "eval"])
def test_padding_neither_attends_nor_is_attended(chunk, training):
    layer = make_layer(seed=8, training=training)
    x = random_input(2, 6, 15, seed=9)
    mask = random_mask(2, 15, seed=10)
    garbage = torch.where(mask[:, None, :], x, random_input(2, 6, 15, seed=11, scale=1e3))
    out = layer(x, mask, chunk=chunk)
    out_garbage = layer(garbage, mask, chunk=chunk)
    m = mask[:, None, :].expand_as(x)
    assert torch.equal(out_garbage[~m], garbage[~m]), "padded points must come out unchanged"
    assert_close_report(out_garbage[m], out[m], 1e-12, 1e-12, "real points with other padding")
    # the gradient of a padded input is the identity's, and no real output depends on it
    xg = garbage.clone().requires_grad_(True)
    w = random_input(2, 6, 15, seed=12)
    (gx,) = torch.autograd.grad((layer(xg, mask, chunk=chunk) * w).sum(), (xg,))
    assert torch.equal(gx[~m], w[~m])


def test_masked_cloud_equals_the_real_points_alone_in_eval():
    layer = make_layer(seed=13, training=False)
    x = random_input(2, 6, 12, seed=14)
    mask = random_mask(2, 12, seed=15)
    out = layer(x, mask, chunk=5)
    for b in range(2):
        alone = layer(x[b:b + 1, :, mask[b]], chunk=None)
        assert_close_report(out[b:b + 1, :, mask[b]], alone, 1e-12, 1e-12, f"cloud {b} alone")


def test_all_padding_and_empty_inputs_pass_through():
    layer = make_layer(seed=16)
    x = random_input(2, 6, 5, seed=17)
    assert torch.equal(layer(x, torch.zeros(2, 5, dtype=torch.bool)), x)
    for shape in [(0, 6, 5), (2, 6, 0)]:
        e = torch.zeros(shape, dtype=torch.float64)
        assert layer(e).shape == shape
        assert column_normalized_attention(e[:, :3], e[:, :3], e, chunk=2).shape == shape


def test_full_mask_equals_no_mask():
    layer = make_layer(seed=18)
    x = random_input(2, 6, 9, seed=19)
    full = torch.ones(2, 9, dtype=torch.bool)
    assert_close_report(layer(x, full, chunk=4), make_layer(seed=18)(x, None, chunk=None), 1e-12, 1e-12, "full mask")


# ------------------------------------------------------------------------------------------ memory
class _LargestTensor(TorchDispatchMode):
    """The most entries of any tensor an op returns while active (forward and backward)."""

    def __init__(self):
        super().__init__()
        self.largest = 0

    @classmethod
    def _should_skip_dynamo(cls) -> bool:  # never compiled: spare the seconds of importing torch._dynamo
        return False

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in (out if isinstance(out, (tuple, list)) else (out,)):
            if isinstance(t, torch.Tensor):
                self.largest = max(self.largest, t.numel())
        return out


@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_chunked_path_never_holds_n_by_n(masked):
    B, C, N, rows = 2, 4, 48, 4
    layer = make_layer(C=C, d=2, seed=20)
    x = random_input(B, C, N, seed=21).requires_grad_(True)
    mask = random_mask(B, N, seed=22) if masked else None
    sizes = {}
    for chunk in (None, rows):
        with _LargestTensor() as probe:
            layer(x, mask, chunk=chunk).square().sum().backward()
        sizes[chunk] = probe.largest
    assert sizes[None] >= B * N * N, "the probe must see the plain path's N x N energies"
    # the chunked path's largest tensors: a block (B, rows, N) and (B, C + 1, N)
    assert sizes[rows] <= max(B * rows * N, B * (C + 1) * N), sizes


@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_fused_path_never_holds_n_by_n(masked, monkeypatch):
    """float32 on the CPU (torch's blocked flash kernel), the row log-sum-exps in blocks of 4 rows."""
    B, C, N = 2, 4, 48
    monkeypatch.setattr(oa, "AUTO_ENTRIES", B * 4 * N)
    layer = make_layer(C=C, d=2, seed=20, dtype=torch.float32)
    x = random_input(B, C, N, seed=21, dtype=torch.float32).requires_grad_(True)
    mask = random_mask(B, N, seed=22) if masked else None
    with _LargestTensor() as probe:
        layer(x, mask, chunk="fused").square().sum().backward()
    assert probe.largest < B * N * N, probe.largest


def test_auto_chunks_large_inputs(monkeypatch):
    assert oa._rows_per_chunk("auto", 1, 4096) is None  # 2^24 entries: plain
    rows = oa._rows_per_chunk("auto", 2, 20000)
    assert rows % 64 == 0 and 2 * rows * 20000 <= oa.AUTO_ENTRIES
    assert oa._rows_per_chunk("auto", 1, 2**25) == 1
    # through the layer, with a budget small enough to chunk a small cloud
    monkeypatch.setattr(oa, "AUTO_ENTRIES", 2 * 6 * 10)
    layer = make_layer(seed=23)
    x = random_input(2, 6, 10, seed=24)
    with _LargestTensor() as probe:
        got = layer(x, chunk="auto")
    assert probe.largest < 2 * 10 * 10
    assert_close_report(got, reference(make_layer(seed=23), x)[0], 1e-12, 1e-12, "auto")


# ------------------------------------------------------------------------------------------ dtypes, modules
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 1e-5), (torch.bfloat16, 3e-2)], ids=["f32", "bf16"])
def test_low_precision_chunked_against_float64(dtype, tol):
    g = torch.Generator().manual_seed(25)
    q = torch.randn(2, 4, 40, generator=g, dtype=torch.float64)
    v = torch.randn(2, 8, 40, generator=g, dtype=torch.float64)
    want = column_normalized_attention(q, q, v)
    got = column_normalized_attention(q.to(dtype), q.to(dtype), v.to(dtype), chunk=7)
    assert got.dtype == dtype
    assert_close_report(got.float(), want, tol, tol, f"{dtype}")


def test_state_dict_has_pct_names_and_shares_q_and_k():
    layer = OffsetAttention(8, 2)
    keys = set(layer.state_dict())
    assert {"q_conv.weight", "k_conv.weight", "v_conv.weight", "v_conv.bias", "trans_conv.weight",
            "trans_conv.bias", "after_norm.running_mean"} <= keys
    assert "q_conv.bias" not in keys and "k_conv.bias" not in keys
    assert layer.k_conv.weight is layer.q_conv.weight
    assert sum(p.numel() for p in layer.parameters()) == 8 * 2 + (8 * 8 + 8) * 2 + 8 * 2


@pytest.mark.parametrize("chunk", [None, 5, "fused"], ids=["plain", "chunk5", "fused"])
def test_device_matches_cpu(device, chunk):
    layer = make_layer(seed=26, training=True)
    x = random_input(2, 6, 17, seed=27)
    mask = random_mask(2, 17, seed=28)
    want, g_want = grads(layer, x, mask, chunk=None)
    other = make_layer(seed=26, device=device)
    got, g_got = grads(other, x.to(device), mask.to(device), chunk=chunk)
    assert_close_report(got, want, 1e-10, 1e-12, f"{device} forward")
    for a, b in zip(g_got, g_want):
        assert_close_report(a, b, 1e-8, 1e-10, f"{device} gradients")


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=requires_cuda)])
@pytest.mark.parametrize("chunk", [None, 8, "fused"], ids=["plain", "chunk8", "fused"])
def test_rows_equal_forward_in_eval_and_follow_weight_changes(device, chunk):
    """The row layout with BatchNorm folded (CAS-Net's inference path) against the literal PCT reference; the
    folded weights are rebuilt after an in-place change and a move."""
    layer = make_layer(C=8, d=8, seed=41, training=False)
    layer.chunk = chunk
    x = random_input(2, 8, 40, seed=42)
    got = layer.to(device).rows(x.transpose(1, 2).to(device)).transpose(1, 2).cpu()
    assert_close_report(got, reference(layer.cpu(), x)[0], 1e-10, 1e-12, "rows vs PCT")
    with torch.no_grad():
        layer.after_norm.running_var.mul_(3.0)
        layer.trans_conv.weight.add_(0.1)
    got = layer.to(device).rows(x.transpose(1, 2).to(device)).transpose(1, 2).cpu()
    assert_close_report(got, reference(layer.cpu(), x)[0], 1e-10, 1e-12, "rows after the weights changed")
    layer.train()  # training: forward itself (BatchNorm's batch statistics)
    assert_close_report(layer.rows(x.transpose(1, 2)).transpose(1, 2), layer(x), 1e-12, 1e-12, "rows in training")


@requires_cuda
def test_cuda_autocast_chunked_is_close_to_float32():
    layer = make_layer(C=16, d=4, seed=29, dtype=torch.float32, device="cuda")
    x = random_input(2, 16, 500, seed=30, dtype=torch.float32, device="cuda")
    want = layer(x, chunk=None)
    with torch.autocast("cuda", dtype=torch.float16):
        got = layer(x, chunk=64)
    assert torch.isfinite(got).all()
    assert_close_report(got.float(), want, 5e-2, 5e-2, "autocast f16 (q, v rounded to half before the attention)")


@requires_cuda
def test_cuda_autocast_fused_is_close_to_float32():
    """float16 autocast on CUDA runs the flash kernel; the row log-sum-exps stay float32 (split across two
    half-precision coordinates)."""
    layer = make_layer(C=16, d=4, seed=29, dtype=torch.float32, device="cuda")
    x = random_input(2, 16, 500, seed=30, dtype=torch.float32, device="cuda")
    want = layer(x, chunk=None)
    with torch.autocast("cuda", dtype=torch.float16):
        got = layer(x, chunk="fused")
    assert torch.isfinite(got).all()
    assert_close_report(got.float(), want, 5e-2, 5e-2, "autocast f16 fused")


@requires_cuda
@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-5), (torch.float16, 2e-3)], ids=["f32", "f16"])
@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
@pytest.mark.parametrize("d", [8, 16])
def test_cuda_row_logsumexp_from_the_fused_kernel_matches_the_blocks(dtype, tol, masked, d):
    """Without a gradient the fused path takes the row log-sum-exps from torch's memory-efficient kernel: they
    must be the natural-log sums over the real keys that the blocks compute (in float32 from the same inputs)."""
    g = torch.Generator().manual_seed(41)
    q = (torch.randn(2, d, 700, generator=g) * 2).to(device="cuda", dtype=dtype)
    k = (torch.randn(2, d, 700, generator=g) * 2).to(device="cuda", dtype=dtype)
    mask = random_mask(2, 700, seed=42, device="cuda") if masked else None
    got = oa._row_logsumexp_fused(q, k, mask, dtype)
    assert got is not None, "the memory-efficient kernel refused float inputs"
    want = oa._RowLogSumExp.apply(q, k, mask, 64)
    e = torch.einsum("bdi,bdj->bij", q.double(), k.double())  # float64 literal, as a third opinion
    if mask is not None:
        e = e.masked_fill(~mask[:, None, :], -math.inf)
    lit = torch.logsumexp(e, dim=-1)
    if mask is not None:
        lit = lit.masked_fill(~mask, 0.0)
    assert_close_report(want.double(), lit, 1e-5, 1e-5, "blocks vs float64")
    assert_close_report(got.double(), lit, tol, tol, f"fused kernel's log-sum-exps ({dtype}) vs float64")


@requires_cuda
@pytest.mark.parametrize("masked", [False, True], ids=["full", "masked"])
def test_cuda_fused_without_gradient_matches_plain(masked):
    layer = make_layer(C=16, d=8, seed=43, dtype=torch.float32, device="cuda", training=False)
    x = random_input(2, 16, 600, seed=44, dtype=torch.float32, device="cuda")
    mask = random_mask(2, 600, seed=45, device="cuda") if masked else None
    with torch.no_grad():
        want = layer(x, mask, chunk=None)
        got = layer(x, mask, chunk="fused")
    assert_close_report(got, want, 1e-3, 1e-3, "fused, no gradient (kernel log-sum-exps), float32")


@requires_cuda
def test_cuda_auto_takes_the_fused_kernels_for_inference_only(monkeypatch):
    calls = []
    real = oa._attention_fused
    monkeypatch.setattr(oa, "_attention_fused", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(oa, "AUTO_ENTRIES", 2**12)  # 2 x 600^2 entries: large
    layer = make_layer(C=16, d=8, seed=46, dtype=torch.float32, device="cuda", training=False)
    x = random_input(2, 16, 600, seed=47, dtype=torch.float32, device="cuda")
    with torch.no_grad():
        plain = layer(x, chunk=None)
        got = layer(x, chunk="auto")
    assert len(calls) == 1
    assert_close_report(got, plain, 1e-3, 1e-3, "auto without a gradient on CUDA")
    out = layer(x.requires_grad_(True), chunk="auto")  # a gradient: the blocks, exact backward
    assert len(calls) == 1
    assert_close_report(out.detach(), plain, 1e-4, 1e-4, "auto with a gradient")


# ------------------------------------------------------------------------------------------ errors
@pytest.mark.parametrize("call,name", [
    (lambda l, x: l(x[:, :5]), "x"),
    (lambda l, x: l(x[0]), "x"),
    (lambda l, x: l(x.long()), "x"),
    (lambda l, x: l("x"), "x"),
    (lambda l, x: l(x, torch.ones(2, 7, dtype=torch.int64)), "mask"),
    (lambda l, x: l(x, torch.ones(2, 6, dtype=torch.bool)), "mask"),
    (lambda l, x: l(x, torch.ones(2, 7, dtype=torch.bool, device="meta")), "mask"),
    (lambda l, x: l(x.float()), "x"),
    (lambda l, x: l(x.to("meta")), "x"),
    (lambda l, x: l(x, chunk=0), "chunk"),
    (lambda l, x: l(x, chunk=True), "chunk"),
    (lambda l, x: l(x, chunk=2.0), "chunk"),
    (lambda l, x: l(x, chunk="rows"), "chunk"),
    (lambda l, x: OffsetAttention(6, 0), "qk_channels"),
    (lambda l, x: OffsetAttention(6, 3, chunk=-1), "chunk"),
    (lambda l, x: column_normalized_attention(x[:, :3], x[:, :2], x), "k"),
    (lambda l, x: column_normalized_attention(x[:, :3], x[:, :3], x[:, :, :4]), "v"),
    (lambda l, x: column_normalized_attention(x[:, :3], x[:, :3].float(), x), "k"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_bad_arguments_raise_value_error_naming_them(call, name):
    layer = make_layer()
    x = random_input(2, 6, 7, seed=31)
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call(layer, x)
