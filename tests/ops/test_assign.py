"""lidarops.greedy_assign (lidarops/ops/assign.py, csrc/cpu/assign_kernel.cpp, csrc/cuda/assign_kernel.cu): the C++
scan against a plain Python re-statement on random lists with repeats and ties, empty inputs, the limit, and clear
errors; the CUDA rounds against the scan on random, CAS-Net-like and worst-case (alike rows) lists."""
from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings, strategies as st

from lidarops.ops import greedy_assign


def _reference(rows, cols, num_rows, limit):
    out = [-1] * num_rows
    taken = set()
    served = 0
    for r, c in zip(rows, cols):
        if served == limit:
            break
        if out[r] >= 0 or c in taken:
            continue
        out[r] = c
        taken.add(c)
        served += 1
    return out


@pytest.mark.parametrize("seed", range(6))
def test_equals_the_python_scan(seed):
    g = torch.Generator().manual_seed(seed)
    num_rows, num_cols = [(5, 3), (8, 40), (64, 64), (1, 1), (30, 7), (200, 1000)][seed]
    L = int(torch.randint(0, 3 * num_rows * 4 + 1, (1,), generator=g))
    rows = torch.randint(0, num_rows, (L,), generator=g)
    cols = torch.randint(0, min(num_cols, 6) if seed % 2 else num_cols, (L,), generator=g)  # many repeats
    for limit in (num_rows, num_rows // 2, 0):
        got = greedy_assign(rows, cols, num_rows, num_cols, limit)
        assert got.tolist() == _reference(rows.tolist(), cols.tolist(), num_rows, limit)


def test_by_hand_and_empty():
    rows = torch.tensor([0, 1, 1, 2, 2, 0])
    cols = torch.tensor([4, 4, 2, 2, 3, 1])
    assert greedy_assign(rows, cols, 3, 5).tolist() == [4, 2, 3]
    assert greedy_assign(rows, cols, 4, 5).tolist() == [4, 2, 3, -1]   # a row no pair names stays -1
    assert greedy_assign(rows, cols, 3, 5, limit=2).tolist() == [4, 2, -1]
    empty = torch.empty(0, dtype=torch.int64)
    assert greedy_assign(empty, empty, 3, 0).tolist() == [-1, -1, -1]
    assert greedy_assign(empty, empty, 0, 0).tolist() == []


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="needs a GPU"))])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_fuzz_against_the_reference(device, data):
    num_rows = data.draw(st.integers(0, 12), "num_rows")
    num_cols = data.draw(st.integers(1, 12), "num_cols")
    L = data.draw(st.integers(0, 40), "L") if num_rows else 0
    rows = data.draw(st.lists(st.integers(0, max(num_rows - 1, 0)), min_size=L, max_size=L), "rows")
    cols = data.draw(st.lists(st.integers(0, num_cols - 1), min_size=L, max_size=L), "cols")
    limit = data.draw(st.integers(0, num_rows), "limit")
    got = greedy_assign(torch.tensor(rows, dtype=torch.int64, device=device),
                        torch.tensor(cols, dtype=torch.int64, device=device), num_rows, num_cols, limit)
    assert got.tolist() == _reference(rows, cols, num_rows, limit)


@pytest.mark.parametrize("call, match", [
    (lambda r, c: greedy_assign(r.float(), c, 3, 5), "int64"),
    (lambda r, c: greedy_assign(r, c[:-1], 3, 5), "one length"),
    (lambda r, c: greedy_assign(r.view(2, 3), c.view(2, 3), 3, 5), "one length"),
    (lambda r, c: greedy_assign(r, c, 2, 5), r"rows\[\d\] = 2 is outside \[0, num_rows=2\)"),
    (lambda r, c: greedy_assign(r, c, 3, 4), r"cols\[\d\] = 4 is outside \[0, num_cols=4\)"),
    (lambda r, c: greedy_assign(r, -c, 3, 5), "cols"),
    (lambda r, c: greedy_assign(r, c, -1, 5), "num_rows"),
    (lambda r, c: greedy_assign(r, c, 3, 5, limit=-1), "limit"),
    (lambda r, c: greedy_assign(r, c, 3, 5.0), "num_cols"),
    (lambda r, c: greedy_assign([0, 1], c, 3, 5), "rows"),
])
def test_bad_arguments_are_named(call, match):
    rows = torch.tensor([0, 1, 1, 2, 2, 0])
    cols = torch.tensor([4, 4, 2, 2, 3, 1])
    with pytest.raises(ValueError, match=match):
        call(rows, cols)


def test_the_registered_op_checks_its_values():
    from lidarops import extension

    extension.load()
    with pytest.raises(ValueError, match="rows"):
        torch.ops.lidarops.greedy_assign(torch.tensor([5]), torch.tensor([0]), 3, 5, 3)
    with pytest.raises(ValueError, match="int64"):
        torch.ops.lidarops.greedy_assign(torch.tensor([0.0]), torch.tensor([0]), 3, 5, 3)
    fake = torch.ops.lidarops.greedy_assign(torch.tensor([0], device="meta"), torch.tensor([0], device="meta"), 3, 5, 3)
    assert fake.shape == (3,) and fake.dtype == torch.int64  # the fake kernel: shapes for torch.compile


requires_gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")


@requires_gpu
def test_cuda_pairs_come_back_on_cuda():
    rows = torch.tensor([0, 1, 1, 2, 2, 0], device="cuda")
    cols = torch.tensor([4, 4, 2, 2, 3, 1], device="cuda")
    got = greedy_assign(rows, cols, 3, 5)
    assert got.device.type == "cuda" and got.tolist() == [4, 2, 3]
    assert greedy_assign(rows, cols, 3, 5, limit=2).tolist() == [4, 2, -1]


def _knn_like(num_rows, num_cols, k, seed):
    """Pairs as CAS-Net's picks make them: each row's k candidates around its own col, ranked by a random score
    over all pairs (the list's order); plus every row ranking the same cols alike (one take per round)."""
    g = torch.Generator().manual_seed(seed)
    centre = torch.randint(0, num_cols, (num_rows, 1), generator=g)
    cand = (centre + torch.randint(-3 * k, 3 * k + 1, (num_rows, k), generator=g)).clamp(0, num_cols - 1)
    order = torch.randperm(num_rows * k, generator=g)
    return torch.arange(num_rows).repeat_interleave(k)[order], cand.reshape(-1)[order]


@requires_gpu
@pytest.mark.parametrize("case", ["random", "repeats", "knn", "alike", "big"])
def test_cuda_rounds_equal_the_cpu_scan(case):
    g = torch.Generator().manual_seed(7)
    if case == "random":
        num_rows, num_cols = 200, 1000
        rows, cols = torch.randint(0, num_rows, (3000,), generator=g), torch.randint(0, num_cols, (3000,), generator=g)
    elif case == "repeats":  # few cols, many rows: most rows go unserved
        num_rows, num_cols = 300, 6
        rows, cols = torch.randint(0, num_rows, (2000,), generator=g), torch.randint(0, num_cols, (2000,), generator=g)
    elif case == "knn":
        num_rows, num_cols = 2500, 20000
        rows, cols = _knn_like(num_rows, num_cols, 16, seed=8)
    elif case == "alike":  # every row ranks cols 0..39 alike: the longest chain, one take per round
        num_rows, num_cols = 40, 60
        rows = torch.arange(num_rows).repeat_interleave(num_cols)
        cols = torch.arange(num_cols).repeat(num_rows)
    else:  # more pairs than threads many times over, cols beyond a 32-bit block of them
        num_rows, num_cols = 30000, 200000
        rows, cols = _knn_like(num_rows, num_cols, 16, seed=9)
    for limit in (num_rows, num_rows // 3, 1, 0):
        want = greedy_assign(rows, cols, num_rows, num_cols, limit)
        got = greedy_assign(rows.cuda(), cols.cuda(), num_rows, num_cols, limit)
        assert got.device.type == "cuda" and torch.equal(got.cpu(), want), (case, limit)
        if case == "alike":  # row r takes col r, and the limit keeps the first rows
            assert want.tolist() == [r if r < limit else -1 for r in range(num_rows)]


@requires_gpu
def test_cuda_names_bad_pairs_and_skips_them_unchecked():
    from lidarops.ops.validation import validation

    rows = torch.tensor([0, 1, 5, 2, 2, 0], device="cuda")
    cols = torch.tensor([4, 4, 2, 2, 3, 1], device="cuda")
    with pytest.raises(ValueError, match=r"rows\[2\] = 5 is outside \[0, num_rows=3\)"):
        greedy_assign(rows, cols, 3, 5)
    with pytest.raises(ValueError, match=r"cols\[0\] = 4 is outside \[0, num_cols=4\)"):
        greedy_assign(rows.clamp(max=2), cols, 3, 4)
    with pytest.raises(ValueError, match="move them to one device"):
        greedy_assign(rows, cols.cpu(), 3, 5)
    with validation(False):  # the raw kernel skips the pair (row 5) instead of reading a flag back
        got = greedy_assign(rows, cols, 3, 5)
    keep = torch.tensor([True, True, False, True, True, True])
    assert got.tolist() == _reference(rows.cpu()[keep].tolist(), cols.cpu()[keep].tolist(), 3, 3)


# ------------------------------------------------------------------------------------ fill_repeats (CAS-Net's sampler)
def _fill_reference(points, idx):
    """Each repeat (a point an earlier row holds), rows in order, takes the free point nearest its pick (float64,
    ties to the lower index); it stays when no point is free."""
    taken, out, seen = set(idx), list(idx), set()
    for r, i in enumerate(idx):
        if i in seen:
            d2 = [sum((a - b) ** 2 for a, b in zip(p, points[i])) for p in points]
            free = [j for j in range(len(points)) if j not in taken]
            if free:
                out[r] = min(free, key=lambda j: (d2[j], j))
                taken.add(out[r])
        seen.add(i)
    return out


def _fill(points, idx):
    from lidarops import extension

    extension.load()
    return torch.ops.lidarops.fill_repeats(points, idx)


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=requires_gpu)])
@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_fill_repeats_fuzz_against_the_reference(device, data):
    n = data.draw(st.integers(1, 20), "n")
    m = data.draw(st.integers(0, 25), "m")
    coords = data.draw(st.lists(st.integers(-3, 3), min_size=3 * n, max_size=3 * n), "coords")  # ties everywhere
    idx = data.draw(st.lists(st.integers(0, n - 1), min_size=m, max_size=m), "idx")
    dtype = data.draw(st.sampled_from([torch.float32, torch.float64]), "dtype")
    points = torch.tensor(coords, dtype=dtype).view(n, 3) * 0.25
    got = _fill(points.to(device), torch.tensor(idx, dtype=torch.int64, device=device))
    assert got.device.type == device
    assert got.tolist() == _fill_reference(points.double().tolist(), idx)


@pytest.mark.parametrize("call, match", [
    (lambda p, i: _fill(p[:, :2].contiguous(), i), r"points must be a contiguous \(n, 3\)"),
    (lambda p, i: _fill(p.t().contiguous().t(), i), "contiguous"),
    (lambda p, i: _fill(p.half(), i), "float32 or float64"),
    (lambda p, i: _fill(p, i.int()), "idx must be 1-D int64"),
    (lambda p, i: _fill(p, i.view(1, -1)), "idx must be 1-D int64"),
    (lambda p, i: _fill(p, i + 2), r"idx\[2\] = 4 is outside \[0, n=4\)"),
    (lambda p, i: _fill(p, -i), r"idx\[1\] = -1 is outside"),
])
def test_fill_repeats_bad_arguments_are_named(call, match):
    points = torch.rand(4, 3)
    idx = torch.tensor([0, 1, 2, 1])
    with pytest.raises(ValueError, match=match):
        call(points, idx)
    fake = torch.ops.lidarops.fill_repeats(points.to("meta"), idx.to("meta"))
    assert fake.shape == (4,) and fake.dtype == torch.int64


@requires_gpu
def test_cuda_fill_repeats_equals_the_cpu_on_large_clouds_and_leaves_bad_rows():
    g = torch.Generator().manual_seed(3)
    for n, m in ((20000, 2500), (5000, 5000), (3000, 40)):
        points = torch.rand(n, 3, generator=g) * 50
        idx = torch.randint(0, n, (m,), generator=g)
        assert torch.equal(_fill(points.cuda(), idx.cuda()).cpu(), _fill(points, idx)), (n, m)
    with pytest.raises(ValueError, match="points is on"):
        _fill(points.cuda(), idx)
    # on CUDA a row outside [0, n) is left as it is and holds nothing (the CPU raises: checking needs a host read)
    got = _fill(torch.rand(4, 3).cuda(), torch.tensor([7, 1, 1, -2], device="cuda"))
    assert got[[0, 1, 3]].tolist() == [7, 1, -2] and got[2].item() in (0, 2, 3)
