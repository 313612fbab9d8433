"""Comparisons that say where tensors differ."""
from __future__ import annotations

import torch


def assert_equal_report(actual: torch.Tensor, expected: torch.Tensor, what: str) -> None:
    """Exact equality (NaN never expected; +inf == +inf), with the first mismatches in the message."""
    actual, expected = actual.detach().cpu(), expected.detach().cpu()
    assert actual.shape == expected.shape, f"{what}: shape {tuple(actual.shape)} != {tuple(expected.shape)}"
    assert actual.dtype == expected.dtype, f"{what}: dtype {actual.dtype} != {expected.dtype}"
    bad = actual != expected
    if bad.any():
        where = bad.nonzero()[:5].tolist()
        detail = "; ".join(f"at {tuple(w)}: got {actual[tuple(w)].item()} expected {expected[tuple(w)].item()}"
                           for w in where)
        raise AssertionError(f"{what}: {int(bad.sum())} of {bad.numel()} entries differ; {detail}")


def assert_close_report(actual: torch.Tensor, expected: torch.Tensor, rtol: float, atol: float, what: str) -> None:
    """|actual - expected| <= atol + rtol |expected| in float64, infinities equal; reports the max difference."""
    a, e = actual.detach().cpu().double(), expected.detach().cpu().double()
    assert a.shape == e.shape, f"{what}: shape {tuple(a.shape)} != {tuple(e.shape)}"
    inf_a, inf_e = torch.isinf(a), torch.isinf(e)
    assert torch.equal(inf_a, inf_e) and torch.equal(a[inf_a], e[inf_e]), f"{what}: infinities differ"
    fin = ~inf_e
    if not fin.any():
        return
    diff = torch.where(fin, (a - e).abs(), torch.zeros_like(a))
    excess = diff - (atol + rtol * torch.where(fin, e.abs(), torch.zeros_like(e)))
    if (excess > 0).any() or torch.isnan(a).any():
        w = tuple(torch.nonzero(excess == excess.max())[0].tolist())
        raise AssertionError(f"{what}: max difference {diff.max().item():.3e} (rtol {rtol:.1e}, atol {atol:.1e}); "
                             f"worst at {w}: got {a[w].item()!r} expected {e[w].item()!r}")
