"""Neighborhood ops: farthest point sampling, k nearest neighbours, ball query, gather.

All indices are int64. Missing results are padded with index -1 and squared distance +inf (never a
value that could be a real distance). Distances are squared Euclidean distances evaluated as
``((dx*dx + dy*dy) + dz*dz)`` with every operation rounded (no fused multiply-add), identically on
CPU and CUDA, so the tie rules (lower index first) give the same answer on every device.

float16 and bfloat16 inputs are accepted and computed in float32; the distances they return are
float32 (a float16 squared distance overflows beyond 256 m). float64 stays float64.

Bad input (``ValueError`` naming the argument): wrong shapes, dtypes or devices; ``k`` that is not a
positive int or whose padded output would exceed 2^31 - 1 entries (refused before allocating);
and, with the value checks on (:func:`lidarops.validation`), NaN or infinite coordinates, and
coordinates beyond +-2^62 (float32, bfloat16) or +-2^510 (float64), where a squared distance could
overflow to infinity (see :func:`lidarops.ops.validation.coordinate_bound`); lengths, start indices
and gather indices out of range.
"""
from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

from lidarops import extension
from lidarops.ops.validation import (
    check_cloud,
    check_output_size,
    check_positive_int,
    check_same_device,
    check_tensor,
    check_values,
    describe,
    lengths_or_full,
    value_checks_enabled,
)

extension.load()

__all__ = ["fps", "knn", "ball_query", "gather"]

_METHODS = {"auto": 0, "brute": 1, "grid": 2}
_KNN_METHODS = {**_METHODS, "tree": 3}  # the k-d tree is CPU-only
_FPS_METHODS = {"auto": 0, "plain": 1, "leaves": 2}


def _method(method: str, table: dict, name: str = "method") -> int:
    if not isinstance(method, str) or method not in table:
        raise ValueError(f"{name} must be one of {sorted(table)}, got {method!r}")
    return table[method]


def _check_k(k, shape: tuple, n: int, what: str) -> int:
    """k as a positive int whose padded output ``(*shape, k)`` fits (refused before allocating)."""
    k = check_positive_int(k, "k")
    check_output_size((*shape, k), f"k={k}", what, (f"k beyond the {n} points per cloud only adds -1 padding" if k > n
                                                  else "split the queries into chunks"))
    return k


def _lengths_range(lengths: Tensor | None, full: Tensor, n: int, name: str) -> list:
    """The range check of user-given lengths (the default, all rows full, needs none)."""
    if lengths is None:
        return []
    return [(full, 0, n, lambda: f"{name} must lie in [0, {n}], got {full.tolist()}")]


def fps(points: Tensor, k: int, lengths: Tensor | None = None, start_idx: Tensor | int | None = None,
        method: str = "auto") -> Tensor:
    """Exact farthest point sampling.

    Starts at ``start_idx`` and at each step takes the point with the largest squared distance to
    the points selected so far; ties go to the lowest index, and a point is never selected twice:
    a cloud of n points yields n distinct indices (duplicates included), then -1.

    Args:
        points (Tensor[B, N, 3]): float32/float64 (float16/bfloat16 computed in float32).
        k (int): number of samples per cloud.
        lengths (Tensor[B], optional): valid points per cloud (ragged batch); default N.
        start_idx (Tensor[B] | int, optional): first sample of each cloud; default 0.
        method (str): ``"auto"``; ``"plain"`` (O(NK) loop) or ``"leaves"`` (CPU bounding-box pruning),
            for tests and benchmarks. Every method returns the same indices.

    Returns:
        Tensor[B, k] int64: sample indices in selection order; -1 where ``lengths[b] < k``.

    Raises:
        ValueError: bad shapes, dtypes or devices; ``k`` not a positive int or ``B * k`` above 2^31 - 1;
            with the value checks on, NaN, infinite or too large coordinates (beyond
            :func:`~lidarops.ops.validation.coordinate_bound`), lengths or ``start_idx`` out of range.

    Follows PyTorch3D's ``sample_farthest_points`` (with ``random_start_point=False``) and the
    PointNet++ FPS; the tie rule is stated here so results are reproducible across devices.
    """
    check_cloud(points, "points")
    extension.check_device(points, "points")
    B, N = points.shape[0], points.shape[1]
    k = _check_k(k, (B,), N, "the sample indices")
    given_lengths = lengths
    lengths = lengths_or_full(lengths, points, "lengths")
    start = _start_indices(start_idx, B, N, points.device)
    m = _method(method, _FPS_METHODS)
    if value_checks_enabled():
        extra = []
        if start_idx is not None:
            bad_start = (((start < 0) | (start >= lengths)) & (lengths > 0)).any()
            extra = [(bad_start, lambda: f"start_idx must lie in [0, lengths), got start_idx={start.tolist()}, "
                                         f"lengths={lengths.tolist()}")]
        check_values(coords=[(points, "points")], ranged=_lengths_range(given_lengths, lengths, N, "lengths"),
                     extra=extra)
    return torch.ops.lidarops.fps(points, lengths, start, k, m)


def _start_indices(start_idx, B: int, N: int, device) -> Tensor:
    """``start_idx`` of fps as an int64 (B,) tensor (its range is a value check)."""
    expected = f"start_idx must be an int in [0, {N}) or an integer (B,) tensor with B = {B}"
    if start_idx is None:
        return torch.zeros(B, dtype=torch.int64, device=device)
    if isinstance(start_idx, numbers.Integral) and not isinstance(start_idx, bool):
        if not -2**63 <= int(start_idx) < 2**63:  # the range itself is a value check, as for tensors
            raise ValueError(f"{expected}, got {int(start_idx)}")
        return torch.full((B,), int(start_idx), dtype=torch.int64, device=device)
    if not isinstance(start_idx, Tensor) or start_idx.shape != (B,) or start_idx.is_floating_point() \
            or start_idx.is_complex() or start_idx.dtype == torch.bool:
        raise ValueError(f"{expected}, got {describe(start_idx) if isinstance(start_idx, Tensor) else repr(start_idx)}")
    return start_idx.to(device=device, dtype=torch.int64)


def _pair_args(query, points, query_lengths, point_lengths, k):
    check_cloud(query, "query")
    check_cloud(points, "points", batch=query.shape[0])
    check_same_device([("query", query), ("points", points)])
    extension.check_device(query, "query")
    if query.dtype != points.dtype:
        raise ValueError(f"query and points must have the same dtype, got {query.dtype} and {points.dtype}")
    k = _check_k(k, tuple(query.shape[:2]), points.shape[1], "dist2 and idx")
    ql = lengths_or_full(query_lengths, query, "query_lengths")
    pl = lengths_or_full(point_lengths, points, "point_lengths")
    if value_checks_enabled():
        check_values(coords=[(query, "query"), (points, "points")],
                     ranged=_lengths_range(query_lengths, ql, query.shape[1], "query_lengths")
                     + _lengths_range(point_lengths, pl, points.shape[1], "point_lengths"))
    return ql, pl, k


def knn(query: Tensor, points: Tensor, k: int, query_lengths: Tensor | None = None,
        point_lengths: Tensor | None = None, method: str = "auto") -> tuple[Tensor, Tensor]:
    """Exact k nearest neighbours by squared Euclidean distance.

    Args:
        query (Tensor[B, M, 3]): query points.
        points (Tensor[B, N, 3]): points searched, same dtype and device as ``query``.
        k (int): neighbours per query.
        query_lengths, point_lengths (Tensor[B], optional): ragged batch lengths; default M and N.
        method (str): ``"auto"`` (brute force for small clouds; for large ones a k-d tree on CPU, the
            uniform grid on CUDA), ``"brute"``, ``"grid"``, ``"tree"`` (CPU only). Every method returns
            the same result.

    Returns:
        dist2 (Tensor[B, M, k]): squared distances, ascending; +inf where fewer than k points exist
            (and for padded queries). Differentiable with respect to ``query`` and ``points``.
        idx (Tensor[B, M, k] int64): neighbour indices, ties to the lower index; -1 padding.

    Raises:
        ValueError: bad shapes, dtypes or devices; ``k`` not a positive int or ``B * M * k`` above
            2^31 - 1; with the value checks on, NaN, infinite or too large coordinates (beyond
            :func:`~lidarops.ops.validation.coordinate_bound`: 2^62 for float32, 2^510 for float64,
            so that squared distances cannot overflow) and lengths out of range.

    Same convention as PyTorch3D's ``knn_points`` except the padding (-1/+inf here, 0/0 there; see
    ``lidarops.compat.pytorch3d``).
    """
    m = _method(method, _KNN_METHODS)
    check_tensor(query, "query")
    if method == "tree" and query.device.type != "cpu":
        raise ValueError(f"method='tree' is CPU-only, got query on {query.device}; use 'auto' or 'grid'")
    ql, pl, k = _pair_args(query, points, query_lengths, point_lengths, k)
    return torch.ops.lidarops.knn(query, points, ql, pl, k, m)


def ball_query(query: Tensor, points: Tensor, radius: float, k: int, query_lengths: Tensor | None = None,
               point_lengths: Tensor | None = None, method: str = "auto") -> tuple[Tensor, Tensor]:
    """The first ``k`` points, in index order, within ``radius`` of each query.

    A point is within the radius when its squared distance is strictly below ``radius**2``, both
    evaluated in the computation dtype (PyTorch3D's convention).

    Args:
        query (Tensor[B, M, 3]), points (Tensor[B, N, 3]): same dtype and device.
        radius (float): >= 0.
        k (int): maximum neighbours per query.
        query_lengths, point_lengths (Tensor[B], optional): ragged batch lengths.
        method (str): ``"auto"``, ``"brute"`` or ``"grid"`` (cells of edge ``radius``); same result.

    Returns:
        dist2 (Tensor[B, M, k]): squared distances of the hits, +inf padding; differentiable.
        idx (Tensor[B, M, k] int64): indices of the hits in increasing order, -1 padding.

    Raises:
        ValueError: as :func:`knn`, and ``radius`` that is not a finite real number >= 0 (a radius
            whose square overflows the computation dtype is fine: every point is then inside).
    """
    if isinstance(radius, bool) or not isinstance(radius, numbers.Real) or not math.isfinite(radius) or radius < 0:
        raise ValueError(f"radius must be a finite number >= 0, got {radius!r}")
    ql, pl, k = _pair_args(query, points, query_lengths, point_lengths, k)
    return torch.ops.lidarops.ball_query(query, points, ql, pl, k, float(radius), _method(method, _METHODS))


def gather(x: Tensor, idx: Tensor) -> Tensor:
    """Gather rows of ``x`` by index (the grouping operation of PointNet++ and CAS-Net).

    Args:
        x (Tensor[B, N, C]): features of any dtype.
        idx (Tensor[B, ...] integer): row indices in [-1, N); -1 gives a row of zeros.

    Returns:
        Tensor[B, *idx.shape[1:], C]: ``out[b, ..., :] = x[b, idx[b, ...], :]``. Differentiable with
        respect to ``x``; the backward is the registered scatter-add op ``gather_backward``.
    """
    check_tensor(x, "x")
    check_tensor(idx, "idx")
    if x.dim() != 3:
        raise ValueError(f"x must be (B, N, C), got {describe(x)}")
    if idx.dim() < 1 or idx.shape[0] != x.shape[0]:
        raise ValueError(f"idx must be (B, ...) with B = {x.shape[0]}, got {describe(idx)}")
    if idx.is_floating_point() or idx.is_complex() or idx.dtype == torch.bool:
        raise ValueError(f"idx must be an integer tensor, got {describe(idx)}")
    check_same_device([("x", x), ("idx", idx)])
    extension.check_device(x, "x")
    check_output_size((*idx.shape, x.shape[2]), f"idx of shape {tuple(idx.shape)}", "the gathered rows")
    flat = idx.reshape(idx.shape[0], math.prod(idx.shape[1:])).to(torch.int64)  # not -1: B may be 0
    if value_checks_enabled() and flat.numel():
        n = x.shape[1]
        check_values(ranged=[(flat, -1, n - 1, lambda: f"idx must lie in [-1, {n}), got values in "
                                                        f"[{int(flat.min())}, {int(flat.max())}]")])
    out = torch.ops.lidarops.gather(x, flat)
    return out.reshape(*idx.shape, x.shape[2])


# ---- pure-PyTorch references (float64 where it matters), used by the tests ----

def _sqdist_reference(a: Tensor, b: Tensor) -> Tensor:
    """Squared distances with the kernels' exact rounding: ((dx*dx + dy*dy) + dz*dz)."""
    d = a.unsqueeze(-2) - b.unsqueeze(-3)
    sq = d * d
    return (sq[..., 0] + sq[..., 1]) + sq[..., 2]


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


def _fps_reference(points: Tensor, k: int, lengths: Tensor | None = None, start_idx=None) -> Tensor:
    """The plain O(N K) loop with the documented tie rule, one cloud at a time."""
    B, N = points.shape[:2]
    p = points.to(_compute_dtype(points.dtype)).cpu()
    out = torch.full((B, k), -1, dtype=torch.int64)
    for b in range(B):
        n = N if lengths is None else int(lengths[b])
        s = 0 if start_idx is None else int(start_idx if isinstance(start_idx, int) else start_idx[b])
        if n == 0:
            continue
        dist = torch.full((n,), math.inf, dtype=p.dtype)
        selected = torch.zeros(n, dtype=torch.bool)
        for i in range(min(k, n)):
            out[b, i] = s
            selected[s] = True
            dist = torch.minimum(dist, _sqdist_reference(p[b, :n], p[b, s:s + 1]).squeeze(-1))
            cand = torch.where(selected, torch.tensor(-1.0, dtype=p.dtype), dist)
            s = int(torch.argmax(cand))  # torch.argmax returns the first maximal index
    return out


def _knn_reference(query: Tensor, points: Tensor, k: int, query_lengths=None, point_lengths=None):
    """Brute force with the tie rule: sort by (dist2, index)."""
    B, M = query.shape[:2]
    N = points.shape[1]
    ct = _compute_dtype(query.dtype)
    d = _sqdist_reference(query.to(ct).cpu(), points.to(ct).cpu())  # (B, M, N)
    dist = torch.full((B, M, k), math.inf, dtype=ct)
    idx = torch.full((B, M, k), -1, dtype=torch.int64)
    for b in range(B):
        m = M if query_lengths is None else int(query_lengths[b])
        n = N if point_lengths is None else int(point_lengths[b])
        if m == 0 or n == 0:
            continue
        db = d[b, :m, :n]
        # stable sort by distance keeps the lower index first among equal distances
        order = torch.sort(db, dim=1, stable=True).indices[:, :k]
        kk = order.shape[1]
        idx[b, :m, :kk] = order
        dist[b, :m, :kk] = torch.gather(db, 1, order)
    return dist, idx


def _ball_query_reference(query: Tensor, points: Tensor, radius: float, k: int, query_lengths=None,
                          point_lengths=None):
    B, M = query.shape[:2]
    N = points.shape[1]
    ct = _compute_dtype(query.dtype)
    d = _sqdist_reference(query.to(ct).cpu(), points.to(ct).cpu())
    r2 = torch.tensor(radius, dtype=ct) * torch.tensor(radius, dtype=ct)
    dist = torch.full((B, M, k), math.inf, dtype=ct)
    idx = torch.full((B, M, k), -1, dtype=torch.int64)
    for b in range(B):
        m = M if query_lengths is None else int(query_lengths[b])
        n = N if point_lengths is None else int(point_lengths[b])
        for i in range(m):
            hits = torch.nonzero(d[b, i, :n] < r2).flatten()[:k]
            idx[b, i, :len(hits)] = hits
            dist[b, i, :len(hits)] = d[b, i, hits]
    return dist, idx


def _gather_reference(x: Tensor, idx: Tensor) -> Tensor:
    B = x.shape[0]
    flat = idx.reshape(B, math.prod(idx.shape[1:]))
    if B == 0 or x.shape[1] == 0:  # nothing to read: every index is -1 (others are errors)
        return x.new_zeros(*idx.shape, x.shape[2])
    safe = flat.clamp_min(0)
    out = torch.stack([x[b, safe[b]] for b in range(B)])
    out = out * (flat >= 0).unsqueeze(-1).to(out.dtype)
    return out.reshape(*idx.shape, x.shape[2])
