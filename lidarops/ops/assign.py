"""``greedy_assign``: the greedy one-to-one assignment over a ranked list of (row, col) pairs, scanned in C++
(``lidarops::greedy_assign``, CPU). CAS-Net's distinct picks (:func:`lidarops.models.casnet.greedy_distinct_rows`)
rank their pairs on the device and scan them here: the scan is sequential by nature, and in Python it cost
seconds for a segment of 8,192 points."""
from __future__ import annotations

import torch
from torch import Tensor

from lidarops.ops.validation import check_tensor, describe

__all__ = ["greedy_assign"]


def greedy_assign(rows: Tensor, cols: Tensor, num_rows: int, num_cols: int, limit: int | None = None) -> Tensor:
    """Take the pairs ``(rows[i], cols[i])`` in order, each unless its row already holds a col or its col is
    already taken, until ``limit`` rows hold one.

    Args:
        rows, cols (Tensor[L] int64): the pairs, in the order they are offered (e.g. by decreasing score);
            any device (they are scanned on the CPU).
        num_rows, num_cols (int): ``rows`` lie in ``[0, num_rows)``, ``cols`` in ``[0, num_cols)``.
        limit (int, optional): stop once this many rows are served (default ``num_rows``).

    Returns:
        Tensor[num_rows] int64 on ``rows``' device: each row's col, ``-1`` where the list served none.

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
    out = torch.ops.lidarops.greedy_assign(rows.cpu(), cols.cpu(), num_rows, num_cols, limit)
    return out.to(rows.device)
