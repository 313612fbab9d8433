"""Drop-in face of ``torch_cluster``: ``fps``, ``knn``, ``radius`` in the flat layout.

torch_cluster stores a batch of clouds flat: ``src (Tensor[N, F])`` with a sorted batch vector
``batch (Tensor[N])`` that assigns each row to an example, and returns flat indices (``fps``) or an
edge index ``(2, E)`` whose first row indexes ``y`` (the queries) and second row ``x``. Conventions
were read from rusty1s/pytorch_cluster ``torch_cluster/{fps,knn,radius}.py`` and the kernels
``csrc/cpu/{fps,knn,radius}_cpu.cpp`` and ``csrc/cuda/{fps,knn,radius}_cuda.cu``.

The flat layout is converted to padded ``(B, N_max, F)`` + lengths with vectorised index arithmetic
(one ``bincount``, one scatter, no loop over examples), the lidarops core ops do the search, and the
results are flattened back. ``F <= 3`` runs the core kernels (zero columns added for ``F < 3``: the
squared distances are bit-identical); larger ``F`` runs a chunked dense PyTorch path with the same
conventions. Known deviations are listed in ``docs/compat.md``.
"""
from __future__ import annotations

import math
import numbers
from typing import List, Optional, Tuple, Union

import torch
import torch.nn.functional as F_
from torch import Tensor

from lidarops import extension
from lidarops.compat.pytorch3d import (
    _ball_query_filtered,
    _check_positive_int,
    _compute_dtype,
    _dense_ball,
    _dense_fps,
    _dense_knn,
    _pad_dim_to_3,
    _repeat_first_after_exhaustion,
)
from lidarops.ops.neighbors import fps as _core_fps
from lidarops.ops.neighbors import knn as _core_knn
from lidarops.ops.validation import check_output_size, check_same_device, check_tensor, coordinate_checks, describe, \
    run_value_checks, validation, value_checks_enabled

__all__ = ["fps", "knn", "radius"]


# ---------------------------------------------------------------------------------------------
# flat + batch vector  <->  padded + lengths
# ---------------------------------------------------------------------------------------------

def _as_matrix(t, name: str) -> Tensor:
    check_tensor(t, name)
    if t.dim() == 1:
        t = t.view(-1, 1)  # torch_cluster treats a vector as N points of one feature
    if t.dim() != 2:
        raise ValueError(f"{name} must be (N, F) (or (N,)), got {describe(t)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {describe(t)}")
    extension.check_device(t, name)
    return t


def _check_batch_vector(batch, n: int, name: str, like: Tensor) -> Optional[Tensor]:
    if batch is None:
        return None
    check_tensor(batch, name)
    if batch.dim() != 1 or batch.shape[0] != n:
        raise ValueError(f"{name} must be (N,) with N = {n}, got {describe(batch)}")
    if batch.is_floating_point() or batch.is_complex() or batch.dtype == torch.bool:
        raise ValueError(f"{name} must be an integer tensor, got {describe(batch)}")
    if batch.device != like.device:
        raise ValueError(f"{name} is on {batch.device} but the points are on {like.device}")
    batch = batch.to(torch.int64)
    if value_checks_enabled() and n:
        run_value_checks([
            ((batch < 0).any(), f"{name} must be >= 0 ({describe(batch)})"),
            ((batch[1:] < batch[:-1]).any(),
             f"{name} must be sorted (torch_cluster assigns each example a contiguous range of rows); "
             f"sort the points by example first, e.g. with torch.sort(batch, stable=True)"),
        ])
    return batch


def _batch_size(batches, batch_size: Optional[int]) -> int:
    if batch_size is not None:
        size = _check_positive_int(batch_size, "batch_size")
        asked = f"batch_size={size}"
    else:
        size = 1
        for b in batches:
            if b is not None and b.numel():
                size = max(size, int(b.max()) + 1)
        asked = f"batch values up to {size - 1}"
    check_output_size((size,), asked, "the per-example counts", "one example per batch value: renumber the examples")
    return size


def _to_padded(src: Tensor, batch: Optional[Tensor], B: int) -> Tuple[Tensor, Tensor, Tensor]:
    """Flat ``src (N, F)`` + sorted ``batch`` -> (padded (B, N_max, F), counts (B,), ptr (B + 1,))."""
    n = src.shape[0]
    device = src.device
    if batch is None:
        counts = torch.zeros(B, dtype=torch.int64, device=device)
        counts[0] = n
        batch = torch.zeros(n, dtype=torch.int64, device=device)
    else:
        if value_checks_enabled() and n:
            run_value_checks([((batch >= B).any(), f"batch values must be < batch_size = {B}")])
        counts = torch.bincount(batch, minlength=B)[:B]
    ptr = torch.zeros(B + 1, dtype=torch.int64, device=device)
    torch.cumsum(counts, 0, out=ptr[1:])
    n_max = int(counts.max()) if B else 0
    check_output_size((B, n_max, src.shape[1]), f"{B} examples of up to {n_max} rows", "the padded batch")
    padded = src.new_zeros(B, n_max, src.shape[1])
    if n:
        pos = torch.arange(n, device=device) - ptr[batch]
        padded[batch, pos] = src
    return padded, counts, ptr


def _edges(idx: Tensor, ptr_x: Tensor, ptr_y: Tensor) -> Tensor:
    """Local (B, M_max, k) neighbour indices (-1 padding) -> edge index (2, E) [row = y, col = x],
    ordered by y, then by slot."""
    B, M = idx.shape[:2]
    found = idx >= 0
    rows = (ptr_y[:-1, None] + torch.arange(M, device=idx.device)[None, :])[:, :, None].expand_as(idx)
    cols = idx + ptr_x[:-1, None, None]
    return torch.stack([rows[found], cols[found]], dim=0)


def _check_finite(*named) -> None:
    """One host sync: finite coordinates within the core ops' bound (squared distances cannot overflow)."""
    if value_checks_enabled():
        run_value_checks(coordinate_checks(named))


def _empty_edges(device) -> Tensor:
    return torch.empty(2, 0, dtype=torch.int64, device=device)


def _pair(x, y, batch_x, batch_y, batch_size):
    x = _as_matrix(x, "x")
    y = _as_matrix(y, "y")
    check_same_device([("x", x), ("y", y)])
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"x and y must have the same number of features, got {describe(x)} and {describe(y)}")
    if x.dtype != y.dtype:
        raise ValueError(f"x and y must have the same dtype, got {x.dtype} and {y.dtype}")
    batch_x = _check_batch_vector(batch_x, x.shape[0], "batch_x", x)
    batch_y = _check_batch_vector(batch_y, y.shape[0], "batch_y", y)
    B = _batch_size([batch_x, batch_y], batch_size)
    if B > 1 and (batch_x is None or batch_y is None):
        raise ValueError("batch_x and batch_y must both be given when the batch has more than one example "
                         f"(batch size {B})")
    return x, y, batch_x, batch_y, B


# ---------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------

def fps(src: Tensor, batch: Optional[Tensor] = None, ratio: Union[float, Tensor] = 0.5,
        random_start: bool = True, batch_size: Optional[int] = None,
        ptr: Optional[Union[Tensor, List[int]]] = None) -> Tensor:
    """Farthest point sampling as ``torch_cluster.fps``.

    Args:
        src (Tensor[N, F]): points of all examples, rows of each example contiguous.
        batch (Tensor[N] integer, optional): sorted example of each row; default one example.
        ratio (float | Tensor[] | Tensor[B]): fraction of each example to sample, in (0, 1].
        random_start (bool): start each example at a random point, ``floor(rand * n_b)`` with
            ``rand = torch.rand(B, dtype=src.dtype, device=src.device)`` (torch_cluster's CUDA rule;
            its CPU kernel uses C ``rand()``); otherwise at the example's first row.
        batch_size (int, optional): number of examples B; default ``batch.max() + 1``.
        ptr (Tensor[B + 1] | list[int], optional): example boundaries instead of ``batch``.

    Returns:
        Tensor[S] int64: indices into ``src``, example by example, each in selection order. Example b
        gets ``ceil(float32(n_b) * ratio)`` samples, ``ratio`` taken in ``src.dtype`` (torch_cluster's
        arithmetic, reproduced with the same torch ops). Ties go to the lowest index; once every
        distinct location of an example is taken, the example's first row repeats (torch_cluster's
        arg-max of an all-zero distance array).
    """
    src = _as_matrix(src, "src")
    device = src.device
    n = src.shape[0]
    if batch is not None and ptr is not None:
        raise ValueError("give batch or ptr, not both")
    if ptr is not None:
        ptr_t = ptr if isinstance(ptr, Tensor) else torch.tensor(list(ptr), dtype=torch.int64, device=device)
        if ptr_t.dim() != 1 or ptr_t.shape[0] < 2 or ptr_t.is_floating_point():
            raise ValueError(f"ptr must be an integer (B + 1,) tensor or list, got {describe(ptr_t)}")
        ptr_t = ptr_t.to(device=device, dtype=torch.int64)
        counts = ptr_t[1:] - ptr_t[:-1]
        if value_checks_enabled():
            run_value_checks([((ptr_t[0] != 0) | (ptr_t[-1] != n) | (counts < 0).any(),
                               lambda: f"ptr must rise from 0 to N = {n}, got {ptr_t.tolist()}")])
        B = counts.shape[0]
        batch = torch.repeat_interleave(torch.arange(B, device=device), counts, output_size=n)
    else:
        batch = _check_batch_vector(batch, n, "batch", src)
        B = _batch_size([batch], batch_size)
    if isinstance(ratio, Tensor):
        if not ratio.is_floating_point() or ratio.dim() > 1 or (ratio.dim() == 1 and ratio.shape[0] not in (1, B)):
            raise ValueError(f"ratio must be a float or a floating () or (B,) tensor with B = {B}, "
                             f"got {describe(ratio)}")
        r = ratio.to(device)
        bad = ~((r > 0) & (r <= 1)).all()  # NaN fails both comparisons: refused here, not as "k" later
        if bool(bad):
            raise ValueError(f"ratio must lie in (0, 1], got {r.tolist()}")
    else:
        if isinstance(ratio, bool) or not isinstance(ratio, numbers.Real) or not 0 < ratio <= 1:
            raise ValueError(f"ratio must lie in (0, 1], got {ratio!r}")
        r = torch.tensor(float(ratio), dtype=src.dtype, device=device)
    padded, counts, ptr_x = _to_padded(src, batch, B)
    _check_finite(("src", src))
    # torch_cluster: out_ptr = ceil(deg.float() * ratio).long()
    n_samples = torch.ceil(counts.to(torch.float32) * r).to(torch.int64)
    n_samples = torch.minimum(n_samples, counts)
    k = int(n_samples.max()) if B else 0
    if k == 0:
        return torch.empty(0, dtype=torch.int64, device=device)
    if random_start:
        start = (torch.rand(B, dtype=src.dtype, device=device) * counts.to(torch.float32)).to(torch.int64)
        start = torch.minimum(start, (counts - 1).clamp_min(0))
    else:
        start = torch.zeros(B, dtype=torch.int64, device=device)
    with validation(False):
        if src.shape[1] <= 3:
            idx = _core_fps(_pad_dim_to_3(padded), k, counts, start)
        else:
            idx = _dense_fps(padded, counts, k, start)
        idx = _repeat_first_after_exhaustion(padded, idx, fill=0)
    take = torch.arange(k, device=device)[None, :] < n_samples[:, None]
    return (idx + ptr_x[:-1, None])[take]


def knn(x: Tensor, y: Tensor, k: int, batch_x: Optional[Tensor] = None, batch_y: Optional[Tensor] = None,
        cosine: bool = False, num_workers: int = 1, batch_size: Optional[int] = None) -> Tensor:
    """k nearest neighbours as ``torch_cluster.knn``: for each row of ``y`` the k nearest rows of ``x``
    in the same example.

    Args:
        x (Tensor[N, F]): points searched.
        y (Tensor[M, F]): queries, same dtype and device.
        k (int): neighbours per query (torch_cluster's CUDA kernel caps k at 100; no cap here).
        batch_x, batch_y (Tensor integer, optional): sorted batch vectors; both needed when B > 1.
        cosine (bool): rank by cosine distance ``1 - <a, b> / (|a| |b|)`` instead of squared Euclidean
            distance, computed as the Euclidean ranking of the unit vectors (the same order, since
            ``|a/|a| - b/|b||^2 = 2 (1 - cos)``).
        num_workers (int): accepted and ignored (the core ops choose their own parallelism).
        batch_size (int, optional): number of examples; default from the batch vectors.

    Returns:
        Tensor[2, E] int64: ``[row, col]`` with ``row`` indexing ``y`` and ``col`` indexing ``x``;
        grouped by ``y`` in order, each query's neighbours by ascending distance (ties to the lower
        index, as torch_cluster's CUDA kernel), ``min(k, n_b)`` of them.
    """
    x, y, batch_x, batch_y, B = _pair(x, y, batch_x, batch_y, batch_size)
    k = _check_positive_int(k, "k")
    if x.numel() == 0 or y.numel() == 0:
        return _empty_edges(x.device)
    px, cx, ptr_x = _to_padded(x, batch_x, B)
    py, cy, ptr_y = _to_padded(y, batch_y, B)
    if cosine:
        px, py = F_.normalize(px, dim=-1), F_.normalize(py, dim=-1)
    _check_finite(("x", x), ("y", y))
    with validation(False), torch.no_grad():
        if x.shape[1] <= 3:
            _, idx = _core_knn(_pad_dim_to_3(py), _pad_dim_to_3(px), k, cy, cx)
        else:
            _, idx = _dense_knn(py, px, cy, cx, k, 2)
    return _edges(idx, ptr_x, ptr_y)


def radius(x: Tensor, y: Tensor, r: float, batch_x: Optional[Tensor] = None, batch_y: Optional[Tensor] = None,
           max_num_neighbors: int = 32, num_workers: int = 1, batch_size: Optional[int] = None) -> Tensor:
    """Radius search as ``torch_cluster.radius``: for each row of ``y`` the rows of ``x`` of the same
    example within distance ``r``.

    Args:
        x (Tensor[N, F]): points searched.
        y (Tensor[M, F]): queries, same dtype and device.
        r (float): radius >= 0. A point is inside when ``dist2 < r * r`` (strict), with ``r * r``
            computed in double and rounded to the computation dtype, as torch_cluster's kernels do.
        batch_x, batch_y (Tensor integer, optional): sorted batch vectors; both needed when B > 1.
        max_num_neighbors (int): at most this many neighbours per query: the first ones in index
            order (torch_cluster's CUDA kernel; its CPU kd-tree keeps an unspecified subset).
        num_workers (int): accepted and ignored.
        batch_size (int, optional): number of examples; default from the batch vectors.

    Returns:
        Tensor[2, E] int64: ``[row, col]`` with ``row`` indexing ``y`` and ``col`` indexing ``x``, grouped
        by ``y`` in order and, within a query, by increasing ``x`` index.
    """
    x, y, batch_x, batch_y, B = _pair(x, y, batch_x, batch_y, batch_size)
    if isinstance(r, Tensor) and r.numel() == 1:
        r = float(r)
    if isinstance(r, bool) or not isinstance(r, numbers.Real) or not math.isfinite(r) or r < 0:
        raise ValueError(f"r must be a finite number >= 0, got {r!r}")
    max_num_neighbors = _check_positive_int(max_num_neighbors, "max_num_neighbors")
    if x.numel() == 0 or y.numel() == 0:
        return _empty_edges(x.device)
    px, cx, ptr_x = _to_padded(x, batch_x, B)
    py, cy, ptr_y = _to_padded(y, batch_y, B)
    check_output_size((B, py.shape[1], max_num_neighbors), f"max_num_neighbors={max_num_neighbors}",
                      "the padded neighbour lists", "split the queries into chunks")
    ct = _compute_dtype(x.dtype)
    r2 = torch.tensor(float(r) * float(r), dtype=ct).item()  # double r*r rounded to the compute dtype
    _check_finite(("x", x), ("y", y))
    with validation(False), torch.no_grad():
        if x.shape[1] <= 3:
            # the core compares with T(r) * T(r); query a slightly larger ball and keep dist2 < r2 exactly
            _, idx = _ball_query_filtered(_pad_dim_to_3(py), _pad_dim_to_3(px), float(r) * (1 + 1e-6),
                                          max_num_neighbors, lambda d2: d2 < r2, cy, cx)
        else:
            _, idx = _dense_ball(py, px, cy, cx, max_num_neighbors, r2)
    return _edges(idx, ptr_x, ptr_y)
