"""``greedy_assign``: the greedy one-to-one assignment over a ranked list of (row, col) pairs
(``lidarops::greedy_assign``): a sequential scan in C++ on the CPU, and on CUDA the same answer in parallel rounds
(``csrc/cuda/assign_kernel.cu`` says why they agree), so CAS-Net's distinct picks
(:func:`lidarops.models.casnet.greedy_distinct_rows`) stay on the device."""
from __future__ import annotations

import torch
from torch import Tensor

from lidarops.ops.validation import check_tensor, check_values, describe, value_checks_enabled

__all__ = ["greedy_assign"]


def greedy_assign(rows: Tensor, cols: Tensor, num_rows: int, num_cols: int, limit: int | None = None) -> Tensor:
    """Take the pairs ``(rows[i], cols[i])`` in order, each unless its row already holds a col or its col is
    already taken, until ``limit`` rows hold one.

    Args:
        rows, cols (Tensor[L] int64): the pairs, in the order they are offered (e.g. by decreasing score),
            on one device: the CPU scans them in order; CUDA finds the same assignment in rounds, each taking
            every pair that comes first among the open pairs of its row and of its col (a handful of rounds
            when rows rank different cols; as many as rows when all rank the same cols alike).
        num_rows, num_cols (int): ``rows`` lie in ``[0, num_rows)``, ``cols`` in ``[0, num_cols)``.
        limit (int, optional): stop once this many rows are served (default ``num_rows``).

    Returns:
        Tensor[num_rows] int64 on ``rows``' device: each row's col, ``-1`` where the list served none.
        On CUDA the range check of ``rows`` and ``cols`` reads one flag back to the host (skipped under
        ``lidarops.validation(False)``, where pairs out of range are ignored).

    Raises:
        ValueError: naming ``rows``, ``cols``, ``num_rows``, ``num_cols`` or ``limit``.
    """
    from lidarops import extension

    extension.load()
    check_tensor(rows, "rows")
    check_tensor(cols, "cols")
    if rows.dim() != 1 or cols.shape != rows.shape or rows.dtype != torch.int64 or cols.dtype != torch.int64:
        raise ValueError(f"rows and cols must be int64 tensors of one length (L,), got rows {describe(rows)}, "
                         f"cols {describe(cols)}")
    for name, v in (("num_rows", num_rows), ("num_cols", num_cols), ("limit", limit)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise ValueError(f"{name} must be an int >= 0, got {v!r}")
    limit = num_rows if limit is None else limit
    if rows.device != cols.device:
        raise ValueError(f"rows is on {rows.device} but cols is on {cols.device}; move them to one device")
    if rows.device.type == "cuda":
        if value_checks_enabled() and rows.numel():
            check_values(ranged=[(rows, 0, num_rows - 1, lambda: _outside("rows", rows, num_rows)),
                                 (cols, 0, num_cols - 1, lambda: _outside("cols", cols, num_cols))])
        return torch.ops.lidarops.greedy_assign(rows, cols, num_rows, num_cols, limit)
    out = torch.ops.lidarops.greedy_assign(rows.cpu(), cols.cpu(), num_rows, num_cols, limit)
    return out.to(rows.device)


def _outside(name: str, values: Tensor, bound: int) -> str:
    """The CPU kernel's message for the first value of ``values`` outside ``[0, bound)``."""
    i = int(((values < 0) | (values >= bound)).nonzero()[0, 0])
    return f"greedy_assign: {name}[{i}] = {int(values[i])} is outside [0, num_{name}={bound})"
