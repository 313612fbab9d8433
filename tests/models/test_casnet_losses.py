"""lidarops.models.casnet_losses: the Chamfer distance against a brute-force float64 NumPy reference (random, ragged,
duplicate points, single points) and its gradients against autograd through a brute-force torch version; the
selection cosine loss against cases worked out by hand."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import lidarops
from helpers.compare import assert_close_report
from lidarops.models.casnet_losses import (_chamfer_reference, _selection_cosine_reference, chamfer_distance,
                                           selection_cosine_loss)


def numpy_chamfer(a: np.ndarray, b: np.ndarray, la=None, lb=None) -> float:
    """Every pair, float64, loops over the clouds: mean_i min_j |a_i - b_j|^2 + mean_j min_i |b_j - a_i|^2, then the
    mean over the batch."""
    total = 0.0
    for c in range(a.shape[0]):
        ac = a[c, :(a.shape[1] if la is None else la[c])].astype(np.float64)
        bc = b[c, :(b.shape[1] if lb is None else lb[c])].astype(np.float64)
        d = ((ac[:, None, :] - bc[None, :, :]) ** 2).sum(-1)
        total += d.min(axis=1).mean() + d.min(axis=0).mean()
    return total / a.shape[0]


def clouds(B, N, M, seed, dtype=torch.float64, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    a = (torch.rand(B, N, 3, generator=g, dtype=torch.float64) * 10 - 5).to(dtype=dtype, device=device)
    b = (torch.rand(B, M, 3, generator=g, dtype=torch.float64) * 10 - 5).to(dtype=dtype, device=device)
    return a, b


# ------------------------------------------------------------------------------------------ Chamfer
@pytest.mark.parametrize("B,N,M", [(1, 1, 1), (1, 1, 17), (2, 30, 12), (3, 64, 64)])
def test_chamfer_matches_numpy_brute_force(device, B, N, M):
    a, b = clouds(B, N, M, seed=N + M, device=device)
    got = chamfer_distance(a, b)
    want = numpy_chamfer(a.cpu().numpy(), b.cpu().numpy())
    assert got.dtype == torch.float64 and got.shape == ()
    assert math.isclose(got.item(), want, rel_tol=1e-12, abs_tol=1e-14), (got.item(), want)


def test_chamfer_ragged_batches_ignore_padding(device):
    a, b = clouds(3, 20, 15, seed=1, device=device)
    la, lb = [20, 4, 1], [1, 15, 9]
    got = chamfer_distance(a, b, torch.tensor(la, device=device), torch.tensor(lb, device=device))
    want = numpy_chamfer(a.cpu().numpy(), b.cpu().numpy(), la, lb)
    assert math.isclose(got.item(), want, rel_tol=1e-12), (got.item(), want)
    # padding holds anything: far away or NaN-free garbage changes nothing
    a2, b2 = a.clone(), b.clone()
    a2[1, 4:] = 1e6
    b2[0, 1:] = -1e6
    got2 = chamfer_distance(a2, b2, torch.tensor(la, device=device), torch.tensor(lb, device=device))
    assert got2.item() == got.item()


def test_chamfer_duplicates_and_identical_clouds():
    a, _ = clouds(2, 12, 1, seed=2)
    assert chamfer_distance(a, a).item() == 0.0
    dup = torch.cat([a, a[:, :5]], 1)  # repeated points: still a distance of 0 both ways
    assert chamfer_distance(dup, a).item() == 0.0
    # by hand: a = {(0,0,0), (0,0,0), (2,0,0)}, b = {(1,0,0)}: a -> b: (1 + 1 + 1) / 3; b -> a: 1
    a = torch.tensor([[[0.0, 0, 0], [0, 0, 0], [2, 0, 0]]], dtype=torch.float64)
    b = torch.tensor([[[1.0, 0, 0]]], dtype=torch.float64)
    assert chamfer_distance(a, b).item() == 2.0
    # a single point each: |a - b|^2 twice
    a = torch.tensor([[[1.0, 2.0, 3.0]]], dtype=torch.float64)
    b = torch.tensor([[[0.0, 4.0, 3.5]]], dtype=torch.float64)
    assert chamfer_distance(a, b).item() == 2 * (1 + 4 + 0.25)


def test_chamfer_gradient_matches_autograd_of_brute_force(device):
    a, b = clouds(2, 25, 10, seed=3, device=device)
    la, lb = torch.tensor([25, 7], device=device), torch.tensor([10, 3], device=device)
    for lengths in [(None, None), (la, lb)]:
        a1, b1 = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
        a2, b2 = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
        got = torch.autograd.grad(chamfer_distance(a1, b1, *lengths), (a1, b1))
        want = torch.autograd.grad(_chamfer_reference(a2, b2, *lengths), (a2, b2))
        for name, g, w in zip("ab", got, want):
            assert_close_report(g, w, 1e-12, 1e-14, f"d/d{name} lengths={lengths[0] is not None}")
        if lengths[0] is not None:  # padding gets no gradient
            assert (got[0][1, 7:] == 0).all() and (got[1][1, 3:] == 0).all()


def test_chamfer_gradcheck():
    a, b = clouds(2, 4, 3, seed=4)
    a.requires_grad_(True)
    b.requires_grad_(True)
    la, lb = torch.tensor([4, 2]), torch.tensor([1, 3])
    with lidarops.validation(False):  # checked once is enough; gradcheck calls it ~100 times
        assert torch.autograd.gradcheck(lambda a, b: chamfer_distance(a, b, la, lb), (a, b))


@pytest.mark.parametrize("dtype,rtol", [(torch.float32, 1e-5), (torch.float16, 1e-5), (torch.bfloat16, 1e-5)],
                         ids=["f32", "f16", "bf16"])
def test_chamfer_low_precision_inputs_in_float32(dtype, rtol):
    a, b = clouds(2, 40, 30, seed=5, dtype=dtype)
    got = chamfer_distance(a, b)
    assert got.dtype == torch.float32
    # the reference on the same (rounded) coordinates, in float64
    want = numpy_chamfer(a.double().numpy(), b.double().numpy())
    assert math.isclose(got.item(), want, rel_tol=rtol), (got.item(), want)


@pytest.mark.parametrize("call,name", [
    (lambda a, b: chamfer_distance(a[..., :2], b), "a"),
    (lambda a, b: chamfer_distance(a, b[:1]), "b"),
    (lambda a, b: chamfer_distance(a, b.float()), "dtype"),
    (lambda a, b: chamfer_distance(a.long(), b.long()), "a"),
    (lambda a, b: chamfer_distance(a, b.to("meta")), "b"),
    (lambda a, b: chamfer_distance(a[:, :0], b), "a"),
    (lambda a, b: chamfer_distance(a, b[:, :0]), "b"),
    (lambda a, b: chamfer_distance(a[:0], b[:0]), "a"),
    (lambda a, b: chamfer_distance(a, b, torch.tensor([3, 0])), "a_lengths"),
    (lambda a, b: chamfer_distance(a, b, torch.tensor([3, 9])), "a_lengths"),
    (lambda a, b: chamfer_distance(a, b, None, torch.tensor([1.0, 2.0])), "b_lengths"),
    (lambda a, b: chamfer_distance(a, b, None, torch.tensor([1, 2, 3])), "b_lengths"),
    (lambda a, b: chamfer_distance(a, b, None, torch.tensor([5, 6])), "b_lengths"),
    (lambda a, b: chamfer_distance(a.index_fill(1, torch.tensor([1]), math.nan), b), "a"),
    (lambda a, b: chamfer_distance(a, b.index_fill(1, torch.tensor([0]), math.inf)), "b"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_chamfer_bad_arguments_raise_value_error_naming_them(call, name):
    a, b = clouds(2, 4, 5, seed=6)
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call(a, b)


# ------------------------------------------------------------------------------------------ cosine loss
def test_cosine_loss_hand_computed_two_by_three():
    """S = [[1, 0, 1], [0, 1, 1]] (unnormalised rows are fine: only their directions count):
    <S_0, S_1> = 1, |S_0| = |S_1| = sqrt(2), so cos_01 = cos_10 = 1 / 2 (+ the 1e-10 in the denominator).
    paper: (|1/2| + |1/2|) / (2 * 1) = 1/2;  frobenius: sqrt((1/2)^2 + (1/2)^2) = sqrt(2) / 2."""
    s = torch.tensor([[[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]]], dtype=torch.float64)
    cos = 1.0 / (2.0 + 1e-10)
    assert math.isclose(selection_cosine_loss(s, "paper").item(), cos, rel_tol=1e-15)
    assert math.isclose(selection_cosine_loss(s, "frobenius").item(), math.sqrt(2) * cos, rel_tol=1e-15)
    assert selection_cosine_loss(s).item() == selection_cosine_loss(s, "paper").item()  # the paper's is the default


def test_cosine_loss_hand_computed_three_by_four_and_batch_mean():
    """Rows a = [1, 1, 0, 0], b = [1, 0, 0, 0], c = [0, 0, 3, 4]: cos(a, b) = 1 / sqrt(2), cos(a, c) = cos(b, c) = 0.
    paper: 2 / sqrt(2) / (3 * 2) = sqrt(2) / 6; frobenius: sqrt(2 * 1/2) = 1. A second cloud of orthogonal rows
    gives 0 and halves the batch means."""
    one = torch.tensor([[1.0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 3, 4]], dtype=torch.float64)
    orth = torch.tensor([[0.0, 0, 0, 2], [0, 5, 0, 0], [1, 0, 0, 0]], dtype=torch.float64)
    s = torch.stack([one, orth])
    assert math.isclose(selection_cosine_loss(s[:1], "paper").item(), math.sqrt(2) / 6, rel_tol=1e-9)
    assert math.isclose(selection_cosine_loss(s[:1], "frobenius").item(), 1.0, rel_tol=1e-9)
    assert math.isclose(selection_cosine_loss(s, "paper").item(), math.sqrt(2) / 12, rel_tol=1e-9)
    assert math.isclose(selection_cosine_loss(s, "frobenius").item(), 0.5, rel_tol=1e-9)


def test_cosine_loss_takes_absolute_cosines():
    """Rows [1, 0] and [-1, 1] (not a softmax, but the loss is defined for any rows): cos = -1 / sqrt(2);
    paper: 2 |cos| / 2 = 1 / sqrt(2), not -1 / sqrt(2); frobenius: sqrt(2 cos^2) = 1."""
    s = torch.tensor([[[1.0, 0.0], [-1.0, 1.0]]], dtype=torch.float64)
    assert math.isclose(selection_cosine_loss(s, "paper").item(), 1 / math.sqrt(2), rel_tol=1e-9)
    assert math.isclose(selection_cosine_loss(s, "frobenius").item(), 1.0, rel_tol=1e-9)


@pytest.mark.parametrize("form", ["paper", "frobenius"])
def test_cosine_loss_of_orthogonal_rows_is_zero_with_finite_gradient(form):
    s = torch.eye(4, 7, dtype=torch.float64)[None].repeat(2, 1, 1).requires_grad_(True)
    loss = selection_cosine_loss(s, form)
    assert loss.item() == 0.0
    (g,) = torch.autograd.grad(loss, s)
    assert torch.isfinite(g).all()


@pytest.mark.parametrize("form", ["paper", "frobenius"])
def test_cosine_loss_of_identical_rows(form):
    """m identical rows: every cosine is 1 (up to the 1e-10), paper -> 1, frobenius -> sqrt(m (m - 1))."""
    s = torch.softmax(torch.randn(1, 1, 9, dtype=torch.float64), -1).repeat(2, 5, 1)
    want = 1.0 if form == "paper" else math.sqrt(20)
    assert math.isclose(selection_cosine_loss(s, form).item(), want, rel_tol=1e-8)


@pytest.mark.parametrize("form", ["paper", "frobenius"])
def test_cosine_loss_matches_pairwise_loops_and_autograd(device, form):
    g = torch.Generator().manual_seed(7)
    s = torch.softmax(torch.randn(3, 6, 20, generator=g, dtype=torch.float64) * 3, -1).to(device)
    s1, s2 = s.clone().requires_grad_(True), s.clone().requires_grad_(True)
    got, want = selection_cosine_loss(s1, form), _selection_cosine_reference(s2, form)
    assert math.isclose(got.item(), want.item(), rel_tol=1e-12)
    assert_close_report(torch.autograd.grad(got, s1)[0], torch.autograd.grad(want, s2)[0], 1e-10, 1e-13, form)


def test_cosine_loss_single_row_is_zero():
    s = torch.softmax(torch.randn(2, 1, 5), -1).requires_grad_(True)
    loss = selection_cosine_loss(s, "frobenius")
    assert loss.item() == 0.0
    loss.backward()


@pytest.mark.parametrize("call,name", [
    (lambda: selection_cosine_loss(torch.rand(3, 4)), "weights"),
    (lambda: selection_cosine_loss(torch.ones(1, 2, 3, dtype=torch.int64)), "weights"),
    (lambda: selection_cosine_loss(torch.rand(0, 2, 3)), "weights"),
    (lambda: selection_cosine_loss(torch.rand(1, 0, 3)), "weights"),
    (lambda: selection_cosine_loss(torch.rand(1, 2, 0)), "weights"),
    (lambda: selection_cosine_loss([[1.0]]), "weights"),
    (lambda: selection_cosine_loss(torch.rand(1, 2, 3), "l2"), "form"),
    (lambda: selection_cosine_loss(torch.rand(1, 2, 3), None), "form"),
], ids=lambda v: v if isinstance(v, str) else "")
def test_cosine_loss_bad_arguments_raise_value_error_naming_them(call, name):
    with pytest.raises(ValueError, match=rf"\b{name}\b"):
        call()
