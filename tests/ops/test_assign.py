"""lidarops.greedy_assign (lidarops/ops/assign.py, csrc/cpu/assign_kernel.cpp): the C++ scan against a plain
Python re-statement on random lists with repeats and ties, empty inputs, the limit, and clear errors."""
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


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_fuzz_against_the_reference(data):
    num_rows = data.draw(st.integers(0, 12), "num_rows")
    num_cols = data.draw(st.integers(1, 12), "num_cols")
    L = data.draw(st.integers(0, 40), "L") if num_rows else 0
    rows = data.draw(st.lists(st.integers(0, max(num_rows - 1, 0)), min_size=L, max_size=L), "rows")
    cols = data.draw(st.lists(st.integers(0, num_cols - 1), min_size=L, max_size=L), "cols")
    limit = data.draw(st.integers(0, num_rows), "limit")
    got = greedy_assign(torch.tensor(rows, dtype=torch.int64), torch.tensor(cols, dtype=torch.int64), num_rows,
                        num_cols, limit)
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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_cuda_pairs_come_back_on_cuda():
    rows = torch.tensor([0, 1, 1, 2, 2, 0], device="cuda")
    cols = torch.tensor([4, 4, 2, 2, 3, 1], device="cuda")
    got = greedy_assign(rows, cols, 3, 5)
    assert got.device.type == "cuda" and got.tolist() == [4, 2, 3]
