"""Drop-in face of ``pytorch3d.ops``: ``sample_farthest_points``, ``knn_points``, ``knn_gather``,
``ball_query``.

Reproduces PyTorch3D's conventions (read from facebookresearch/pytorch3d ``pytorch3d/ops/knn.py``,
``ball_query.py``, ``sample_farthest_points.py`` and the kernels under ``pytorch3d/csrc/knn``,
``csrc/ball_query``, ``csrc/sample_farthest_points``):

* padded batches ``(N, P, D)`` with ``lengths (N,)``;
* ``knn_points``: squared Euclidean distances (``norm=2``) or L1 distances (``norm=1``), sorted
  ascending; missing neighbours (``k >= lengths2[n]``) and padded query rows have ``idx 0`` and
  ``dists 0``;
* ``ball_query``: the first ``K`` points in index order with ``dist2 < radius2``, ``radius2`` the
  float32 square of the float32 radius; padding ``idx -1``, ``dists 0``, ``knn 0.0``;
* ``sample_farthest_points``: starts at index 0 (or a random start drawn with
  ``torch.randint(high=lengths[n])``), ties to the lowest index, ``-1``/``0.0`` padding beyond
  ``min(K[n], lengths[n])``, and index 0 repeated once every distinct location has been taken.

Computation runs on the lidarops core ops (exact, grid-accelerated, CPU and CUDA) when ``D <= 3`` and
the metric is Euclidean (``D < 3`` gets zero columns: the squared distances are bit-identical); other
dimensions and ``norm=1`` run a chunked dense PyTorch path with the same conventions. Known
deviations are listed in ``docs/compat.md``.

The private helpers at the end (``_dense_*``, ``_repeat_first_after_exhaustion``,
``_ball_query_filtered``) are shared with the mmcv and torch_cluster faces.
"""
from __future__ import annotations

import math
import numbers
from collections import namedtuple
from typing import List, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor

from lidarops import extension
from lidarops.ops.neighbors import ball_query as _core_ball_query
from lidarops.ops.neighbors import fps as _core_fps
from lidarops.ops.neighbors import gather as _core_gather
from lidarops.ops.neighbors import knn as _core_knn
from lidarops.ops.validation import (
    check_positive_int,
    check_same_device,
    coordinate_checks,
    check_tensor,
    describe,
    lengths_or_full,
    run_value_checks,
    validation,
    value_checks_enabled,
)

__all__ = ["sample_farthest_points", "knn_points", "knn_gather", "ball_query", "_KNN"]

# Same name and fields as pytorch3d.ops.knn._KNN, so code that unpacks or reads .dists/.idx/.knn works.
_KNN = namedtuple("KNN", "dists idx knn")

# Elements of the (B, chunk, P2, D) difference tensor the dense path materialises at once.
_DENSE_CHUNK_ELEMENTS = 1 << 24


# ---------------------------------------------------------------------------------------------
# argument checks
# ---------------------------------------------------------------------------------------------

def _check_points(t, name: str, batch: Optional[int] = None, dim: Optional[int] = None) -> None:
    """A (N, P, D) floating tensor on a supported device."""
    check_tensor(t, name)
    if t.dim() != 3:
        raise ValueError(f"{name} must be (N, P, D), got {describe(t)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point, got {describe(t)}")
    if batch is not None and t.shape[0] != batch:
        raise ValueError(f"{name} must have batch size {batch} (pts1 and pts2 must have the same batch "
                         f"dimension), got {describe(t)}")
    if dim is not None and t.shape[2] != dim:
        raise ValueError(f"{name} must have point dimension {dim} (pts1 and pts2 must have the same point "
                         f"dimension), got {describe(t)}")
    if t.shape[2] < 1:
        raise ValueError(f"{name} must have a point dimension D >= 1, got {describe(t)}")
    extension.check_device(t, name)


def _check_radius(radius, name: str = "radius") -> float:
    if isinstance(radius, Tensor) and radius.numel() == 1:
        radius = float(radius)
    if isinstance(radius, bool) or not isinstance(radius, numbers.Real) or not math.isfinite(radius) or radius < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {radius!r}")
    return float(radius)


def _nan_and_lengths_checks(items: Sequence[Tuple[str, Tensor, str, Tensor]]) -> None:
    """One host sync for: finite coordinates within the core ops' bound (squared distances cannot
    overflow; :func:`lidarops.ops.validation.coordinate_bound`), every length in [0, P].
    ``items`` holds (points name, points, lengths name, lengths)."""
    if not value_checks_enabled():
        return
    checks = []
    for name, pts, lname, lengths in items:
        checks.extend(coordinate_checks([(name, pts)]))
        n = pts.shape[1]
        checks.append((((lengths < 0) | (lengths > n)).any(),
                       (lambda lengths=lengths, n=n, lname=lname:
                        f"{lname} must lie in [0, {n}], got {lengths.tolist()}")))
    run_value_checks(checks)


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


def _pad_dim_to_3(t: Tensor) -> Tensor:
    """(N, P, D<=3) -> (N, P, 3) with zero columns; squared distances are bit-identical."""
    if t.shape[-1] == 3:
        return t
    return torch.cat([t, t.new_zeros(*t.shape[:-1], 3 - t.shape[-1])], dim=-1)


# ---------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------

def sample_farthest_points(
    points: Tensor,
    lengths: Optional[Tensor] = None,
    K: Union[int, List[int], Tensor] = 50,
    random_start_point: bool = False,
) -> Tuple[Tensor, Tensor]:
    """Iterative farthest point sampling with PyTorch3D's conventions.

    Args:
        points (Tensor[N, P, D]): batch of point clouds, any floating dtype (computed in float64 for
            float64 input, else float32).
        lengths (Tensor[N], optional): valid points per cloud; default P.
        K (int | list[int] | Tensor[N]): samples per cloud; an int applies to every cloud.
        random_start_point (bool): start at a random point instead of index 0. The start of cloud n is
            ``torch.randint(high=lengths[n], size=(1,))`` drawn on the default CPU generator, cloud by
            cloud, exactly as PyTorch3D does, so ``torch.manual_seed`` reproduces its starts.

    Returns:
        selected_points (Tensor[N, max(K), D]): ``points[n, selected_indices[n]]``, 0.0 where the index
            is -1; differentiable with respect to ``points``; same dtype as ``points``.
        selected_indices (Tensor[N, max(K)] int64): selection order; -1 beyond ``min(K[n], lengths[n])``.

    Convention: the first index is the start point; each step takes the point with the largest
    squared distance to the selected set, ties to the lowest index. Once every distinct location of a
    cloud has been taken (duplicate points), PyTorch3D's kernels keep returning index 0 (its distance
    is 0, and the arg-max of an all-zero array is its first element); this face does the same.
    For ``D == 3`` the lidarops FPS kernel does the work; other ``D`` use a PyTorch loop over K.
    """
    _check_points(points, "points")
    B, P, D = points.shape
    device = points.device
    lengths = lengths_or_full(lengths, points, "lengths")
    if isinstance(K, bool):
        raise ValueError(f"K must be an int, a list of ints or an integer (N,) tensor, got {K!r}")
    if isinstance(K, numbers.Integral):
        K = int(K)
        if K < 0:
            raise ValueError(f"K must be >= 0, got {K}")
        k_per = torch.full((B,), K, dtype=torch.int64, device=device)
    elif isinstance(K, (list, tuple)):
        if not all(isinstance(k, numbers.Integral) and not isinstance(k, bool) for k in K):
            raise ValueError(f"K must be a list of ints, got {K!r}")
        k_per = torch.tensor([int(k) for k in K], dtype=torch.int64, device=device)
    elif isinstance(K, Tensor):
        if K.is_floating_point() or K.is_complex() or K.dtype == torch.bool:
            raise ValueError(f"K must be an integer tensor, got {describe(K)}")
        k_per = K.to(device=device, dtype=torch.int64)
    else:
        raise ValueError(f"K must be an int, a list of ints or an integer (N,) tensor, got {type(K).__name__}")
    if k_per.shape != (B,):
        raise ValueError(f"K and points must have the same batch dimension: K must be (N,) with N = {B}, "
                         f"got shape {tuple(k_per.shape)}")
    _nan_and_lengths_checks([("points", points, "lengths", lengths)])
    if value_checks_enabled() and B:
        run_value_checks([((k_per < 0).any(), lambda: f"K must be >= 0, got {k_per.tolist()}")])
    k_max = int(k_per.max()) if B else 0
    if k_max == 0 or B == 0:
        return points.new_zeros(B, k_max, D), torch.full((B, k_max), -1, dtype=torch.int64, device=device)

    if random_start_point not in (True, False):  # "no" or None would pass as truthy or falsy
        raise ValueError(f"random_start_point must be True or False, got {random_start_point!r}")
    if random_start_point:
        # PyTorch3D draws one torch.randint per cloud on the default generator; do the same so a seed
        # gives the same starts. (An empty cloud, where PyTorch3D raises, starts at 0 without a draw.)
        starts = [int(torch.randint(high=int(n), size=(1,)).item()) if int(n) > 0 else 0
                  for n in lengths.cpu().tolist()]
        start = torch.tensor(starts, dtype=torch.int64, device=device)
    else:
        start = torch.zeros(B, dtype=torch.int64, device=device)

    with validation(False):  # checked above, in this face's argument names
        if D <= 3:
            idx = _core_fps(_pad_dim_to_3(points), k_max, lengths, start)
        else:
            idx = _dense_fps(points, lengths, k_max, start)
        idx = _repeat_first_after_exhaustion(points, idx, fill=0)
        idx = torch.where(torch.arange(k_max, device=device) < k_per[:, None], idx, torch.full_like(idx, -1))
        return _core_gather(points, idx), idx


def knn_points(
    p1: Tensor,
    p2: Tensor,
    lengths1: Optional[Tensor] = None,
    lengths2: Optional[Tensor] = None,
    norm: int = 2,
    K: int = 1,
    version: int = -1,
    return_nn: bool = False,
    return_sorted: bool = True,
) -> _KNN:
    """K nearest neighbours with PyTorch3D's conventions.

    Args:
        p1 (Tensor[N, P1, D]): query clouds.
        p2 (Tensor[N, P2, D]): searched clouds, same dtype and device.
        lengths1, lengths2 (Tensor[N], optional): valid points per cloud; default P1 and P2.
        norm (int): 2 for squared Euclidean distances, 1 for L1 distances (sum of absolute
            differences). Anything else raises ``ValueError("Support for 1 or 2 norm.")``.
        K (int): neighbours per query.
        version (int): PyTorch3D's CUDA kernel selector; accepted and ignored.
        return_nn (bool): also return the neighbour coordinates ``knn_gather(p2, idx, lengths2)``.
        return_sorted (bool): accepted; results are always sorted ascending (a valid answer for
            ``return_sorted=False``, where PyTorch3D leaves the order unspecified).

    Returns:
        _KNN(dists, idx, knn):
            dists (Tensor[N, P1, K]): squared distances (norm=2) or L1 distances (norm=1), ascending;
                0 where ``k >= lengths2[n]`` and on padded query rows. Differentiable with respect to
                ``p1`` and ``p2``. float64 for float64 input, else float32.
            idx (Tensor[N, P1, K] int64): neighbour indices, ties to the lower index; 0 where missing.
            knn (Tensor[N, P1, K, D] | None): neighbour coordinates when ``return_nn``.

    ``D == 3`` with ``norm=2`` runs the lidarops kNN kernel; other cases a chunked dense PyTorch path.
    """
    _check_points(p1, "p1")
    _check_points(p2, "p2", batch=p1.shape[0], dim=p1.shape[2])
    check_same_device([("p1", p1), ("p2", p2)])
    if p1.dtype != p2.dtype:
        raise ValueError(f"p1 and p2 must have the same dtype, got {p1.dtype} and {p2.dtype}")
    if isinstance(norm, bool) or norm not in (1, 2):
        raise ValueError(f"Support for 1 or 2 norm. (got norm={norm!r})")
    K = check_positive_int(K, "K")
    if isinstance(version, bool) or not isinstance(version, numbers.Integral):
        raise ValueError(f"version must be an int, got {version!r}")
    lengths1 = lengths_or_full(lengths1, p1, "lengths1")
    lengths2 = lengths_or_full(lengths2, p2, "lengths2")
    _nan_and_lengths_checks([("p1", p1, "lengths1", lengths1), ("p2", p2, "lengths2", lengths2)])
    with validation(False):
        if norm == 2 and p1.shape[2] <= 3:
            dist, idx = _core_knn(_pad_dim_to_3(p1), _pad_dim_to_3(p2), K, lengths1, lengths2)
        else:
            dist, idx = _dense_knn(p1, p2, lengths1, lengths2, K, norm)
        found = idx >= 0
        dists = torch.where(found, dist, torch.zeros((), dtype=dist.dtype, device=dist.device))
        idx = torch.where(found, idx, torch.zeros_like(idx))
        nn = knn_gather(p2, idx, lengths2) if return_nn else None
    return _KNN(dists=dists, idx=idx, knn=nn)


def knn_gather(x: Tensor, idx: Tensor, lengths: Optional[Tensor] = None) -> Tensor:
    """Gather ``x`` by the indices of ``knn_points`` (PyTorch3D's ``knn_gather``).

    Args:
        x (Tensor[N, M, U]): features (any dtype).
        idx (Tensor[N, L, K] integer): indices in [0, M) (-1 is also accepted and gives zeros).
        lengths (Tensor[N], optional): valid rows of ``x``; default M.

    Returns:
        Tensor[N, L, K, U]: ``out[n, l, k] = x[n, idx[n, l, k]]``, set to 0.0 for every ``k >=
        lengths[n]`` (PyTorch3D masks by slot, not by index: padded query rows, whose indices are 0,
        gather ``x[n, 0]`` in the slots below ``lengths[n]``). Differentiable with respect to ``x``
        (backward is the registered scatter-add ``lidarops::gather_backward``).
    """
    check_tensor(x, "x")
    check_tensor(idx, "idx")
    if x.dim() != 3:
        raise ValueError(f"x must be (N, M, U), got {describe(x)}")
    if idx.dim() != 3:
        raise ValueError(f"idx must be (N, L, K), got {describe(idx)}")
    if idx.shape[0] != x.shape[0]:
        raise ValueError(f"x and idx must have same batch dimension, got {describe(x)} and {describe(idx)}")
    lengths = lengths_or_full(lengths, x, "lengths")
    out = _core_gather(x, idx)
    K = idx.shape[2]
    missing = torch.arange(K, device=x.device)[None, :] >= lengths[:, None]  # (N, K)
    return out.masked_fill(missing[:, None, :, None], 0)


def ball_query(
    p1: Tensor,
    p2: Tensor,
    lengths1: Optional[Tensor] = None,
    lengths2: Optional[Tensor] = None,
    K: int = 500,
    radius: float = 0.2,
    return_nn: bool = True,
) -> _KNN:
    """Ball query with PyTorch3D's conventions.

    Args:
        p1 (Tensor[N, P1, D]): ball centres.
        p2 (Tensor[N, P2, D]): searched clouds, same dtype and device.
        lengths1, lengths2 (Tensor[N], optional): valid points per cloud.
        K (int): at most K neighbours per centre.
        radius (float): >= 0. A point is inside when ``dist2 < radius2`` (strict) with
            ``radius2 = float32(radius) * float32(radius)``: PyTorch3D's kernels take ``radius`` as a
            C++ float and square it in float, whatever the point dtype.
        return_nn (bool): also return the neighbour coordinates.

    Returns:
        _KNN(dists, idx, knn):
            dists (Tensor[N, P1, K]): squared distances of the hits; 0 padding; differentiable.
            idx (Tensor[N, P1, K] int64): the first K hits in increasing index order (not the nearest);
                -1 padding (also on padded centre rows).
            knn (Tensor[N, P1, K, D] | None): hit coordinates, 0.0 where ``idx == -1``.

    ``D <= 3`` runs the lidarops ball-query kernel (for float64 points a slightly larger query filtered
    with the float32 ``radius2``); other ``D`` a chunked dense PyTorch path.
    """
    _check_points(p1, "p1")
    _check_points(p2, "p2", batch=p1.shape[0], dim=p1.shape[2])
    check_same_device([("p1", p1), ("p2", p2)])
    if p1.dtype != p2.dtype:
        raise ValueError(f"p1 and p2 must have the same dtype, got {p1.dtype} and {p2.dtype}")
    K = check_positive_int(K, "K")
    radius = _check_radius(radius)
    lengths1 = lengths_or_full(lengths1, p1, "lengths1")
    lengths2 = lengths_or_full(lengths2, p2, "lengths2")
    _nan_and_lengths_checks([("p1", p1, "lengths1", lengths1), ("p2", p2, "lengths2", lengths2)])
    r2 = _f32_square(radius)
    with validation(False):
        if p1.shape[2] > 3:
            dist, idx = _dense_ball(p1, p2, lengths1, lengths2, K, r2)
        elif _compute_dtype(p1.dtype) == torch.float32:
            # the core's rule, dist2 < float32(radius) * float32(radius), is PyTorch3D's here
            dist, idx = _core_ball_query(_pad_dim_to_3(p1), _pad_dim_to_3(p2), radius, K, lengths1, lengths2)
        else:
            _, idx = _ball_query_filtered(_pad_dim_to_3(p1), _pad_dim_to_3(p2), radius * (1 + 1e-6), K,
                                          lambda d2: d2 < r2, lengths1, lengths2)
            dist = _gathered_distances(p1, p2, idx, 2)
        dists = torch.where(idx >= 0, dist, torch.zeros((), dtype=dist.dtype, device=dist.device))
        nn = _core_gather(p2, idx) if return_nn else None
    return _KNN(dists=dists, idx=idx, knn=nn)


# ---------------------------------------------------------------------------------------------
# shared helpers (also used by lidarops.compat.mmcv and lidarops.compat.torch_cluster)
# ---------------------------------------------------------------------------------------------

def _valid_mask(lengths: Tensor, n: int) -> Tensor:
    return torch.arange(n, device=lengths.device)[None, :] < lengths[:, None]


def _f32_square(r: float) -> float:
    """``r * r`` as the imitated kernels compute it: a float32 radius squared in float32."""
    t = torch.tensor(r, dtype=torch.float32)
    return (t * t).item()


def _distances(diff: Tensor, norm: int) -> Tensor:
    """Sum over the last dim of ``|d|`` (norm 1) or ``d * d`` (norm 2). For D <= 4 the terms are added
    left to right, ``((t0 + t1) + t2) + ...``, the rounding of the lidarops kernels and of the imitated
    libraries' loops; larger D (feature spaces) use ``sum``."""
    terms = diff.abs() if norm == 1 else diff * diff
    if terms.shape[-1] > 4:
        return terms.sum(-1)
    out = terms[..., 0]
    for j in range(1, terms.shape[-1]):
        out = out + terms[..., j]
    return out


def _gathered_distances(p1: Tensor, p2: Tensor, idx: Tensor, norm: int) -> Tensor:
    """Differentiable distances from ``p1[b, i]`` to ``p2[b, idx[b, i, k]]``; +inf where idx is -1."""
    ct = _compute_dtype(p1.dtype)
    nn = _core_gather(p2.to(ct), idx)  # (B, P1, K, D); zeros for -1
    dist = _distances(p1.to(ct)[:, :, None, :] - nn, norm)
    return torch.where(idx >= 0, dist, torch.full((), math.inf, dtype=ct, device=p1.device))


def _dense_knn(p1: Tensor, p2: Tensor, lengths1: Tensor, lengths2: Tensor, K: int,
               norm: int = 2) -> Tuple[Tensor, Tensor]:
    """Brute-force kNN for any D and norm 1/2, chunked over queries.

    Returns (dist (Tensor[N, P1, K]), idx (Tensor[N, P1, K] int64)) with lidarops' padding (+inf, -1);
    ascending, ties to the lower index; ``dist`` differentiable with respect to p1 and p2.
    """
    B, P1, D = p1.shape
    P2 = p2.shape[1]
    ct = _compute_dtype(p1.dtype)
    idx = torch.full((B, P1, K), -1, dtype=torch.int64, device=p1.device)
    kk = min(K, P2)
    if B and P1 and kk:
        with torch.no_grad():
            a, b = p1.detach().to(ct), p2.detach().to(ct)
            point_ok = _valid_mask(lengths2, P2)  # (B, P2)
            slot_ok = torch.arange(kk, device=p1.device)[None, :] < lengths2[:, None]  # (B, kk)
            step = max(1, _DENSE_CHUNK_ELEMENTS // max(1, B * P2 * D))
            for s in range(0, P1, step):
                e = min(P1, s + step)
                d = _distances(a[:, s:e, None, :] - b[:, None, :, :], norm)
                d = d.masked_fill(~point_ok[:, None, :], math.inf)
                # stable: among equal distances the lower index comes first; padded points (+inf,
                # higher indices) sort after every real one.
                order = torch.sort(d, dim=-1, stable=True).indices[..., :kk]
                query_ok = (torch.arange(s, e, device=p1.device)[None, :] < lengths1[:, None])  # (B, c)
                ok = query_ok[:, :, None] & slot_ok[:, None, :]
                idx[:, s:e, :kk] = torch.where(ok, order, torch.full_like(order, -1))
    return _gathered_distances(p1, p2, idx, norm), idx


def _dense_ball(p1: Tensor, p2: Tensor, lengths1: Tensor, lengths2: Tensor, K: int,
                r2: float) -> Tuple[Tensor, Tensor]:
    """Brute-force ball query for any D: the first K points in index order with dist2 < r2.

    ``r2`` is compared in the computation dtype. Returns (dist2, idx) with (+inf, -1) padding;
    ``dist2`` differentiable.
    """
    B, P1, D = p1.shape
    P2 = p2.shape[1]
    ct = _compute_dtype(p1.dtype)
    idx = torch.full((B, P1, K), -1, dtype=torch.int64, device=p1.device)
    if B and P1 and P2:
        with torch.no_grad():
            a, b = p1.detach().to(ct), p2.detach().to(ct)
            point_ok = _valid_mask(lengths2, P2)
            thr = torch.tensor(r2, dtype=ct, device=p1.device)
            step = max(1, _DENSE_CHUNK_ELEMENTS // max(1, B * P2 * D))
            for s in range(0, P1, step):
                e = min(P1, s + step)
                d = _distances(a[:, s:e, None, :] - b[:, None, :, :], 2)
                query_ok = (torch.arange(s, e, device=p1.device)[None, :] < lengths1[:, None])
                hit = (d < thr) & point_ok[:, None, :] & query_ok[:, :, None]
                idx[:, s:e] = _first_k_hits(hit, torch.arange(P2, device=p1.device).expand_as(hit), K)
    return _gathered_distances(p1, p2, idx, 2), idx


def _first_k_hits(hit: Tensor, values: Tensor, K: int) -> Tensor:
    """Compact along the last dim: the first K ``values`` where ``hit``, in order; -1 padding."""
    rank = hit.to(torch.int64).cumsum(-1) - 1
    keep = hit & (rank < K)
    pos = torch.where(keep, rank, torch.full_like(rank, K))  # unkept entries go to a spare column
    out = torch.full((*hit.shape[:-1], K + 1), -1, dtype=torch.int64, device=hit.device)
    out.scatter_(-1, pos, torch.where(keep, values.to(torch.int64), torch.full_like(rank, -1)))
    return out[..., :K]


def _dense_fps(points: Tensor, lengths: Tensor, K: int, start: Tensor) -> Tensor:
    """FPS for any D (PyTorch loop over K): the lidarops convention (ties to the lowest index, never
    re-selecting, -1 beyond lengths)."""
    B, P, D = points.shape
    out = torch.full((B, K), -1, dtype=torch.int64, device=points.device)
    if B == 0 or P == 0:
        return out
    ct = _compute_dtype(points.dtype)
    with torch.no_grad():
        p = points.detach().to(ct)
        ok = _valid_mask(lengths, P)
        rows = torch.arange(B, device=points.device)
        dist = torch.full((B, P), math.inf, dtype=ct, device=points.device)
        taken = ~ok
        cur = start.clamp(0, P - 1)
        for i in range(K):
            active = lengths > i
            out[:, i] = torch.where(active, cur, torch.full_like(cur, -1))
            taken[rows, cur] = taken[rows, cur] | active
            dist = torch.minimum(dist, _distances(p - p[rows, cur][:, None, :], 2))
            cur = dist.masked_fill(taken, -1.0).argmax(1)  # first maximum = lowest index
    return out


def _repeat_first_after_exhaustion(points: Tensor, idx: Tensor, fill: int = 0) -> Tensor:
    """Reproduce what PyTorch3D, mmcv and torch_cluster FPS kernels do once a cloud has no distinct
    location left: the farthest remaining point is at distance 0 and their arg-max returns the cloud's
    first point, again and again.

    ``idx`` comes from the lidarops convention (distinct indices, -1 padding). Its first u picks are the
    u distinct locations, then duplicates; the libraries agree on the first u and return ``fill`` (the
    cloud's local index 0) afterwards. Cheap test first: a cloud ran out iff its last pick coincides
    with an earlier one (FPS distances never increase). Only then are distinct locations counted.
    """
    B, K = idx.shape
    if B == 0 or K < 2:
        return idx
    n_sel = (idx >= 0).sum(1)
    sel = _core_gather(points.detach(), idx)  # (B, K, D); zeros for -1
    sel = sel.to(_compute_dtype(points.dtype)) + 0.0  # -0.0 -> 0.0 (equal locations)
    rows = torch.arange(B, device=idx.device)
    last_pos = (n_sel - 1).clamp_min(0)
    last = sel[rows, last_pos]
    same = (sel == last[:, None, :]).all(-1)
    before = torch.arange(K, device=idx.device)[None, :] < last_pos[:, None]
    ran_out = (same & before).any(1)
    if not bool(ran_out.any()):
        return idx
    # distinct locations among the picks of each cloud
    valid = idx >= 0
    bcol = rows[:, None].expand(B, K).to(torch.float64)[valid][:, None]
    keyed = torch.cat([bcol, sel.to(torch.float64)[valid]], dim=1)
    uniq = torch.unique(keyed, dim=0)
    distinct = torch.bincount(uniq[:, 0].to(torch.int64), minlength=B)
    cut = torch.where(ran_out, distinct, torch.full_like(distinct, K))
    repeat = (torch.arange(K, device=idx.device)[None, :] >= cut[:, None]) & valid
    return torch.where(repeat, torch.full_like(idx, fill), idx)


def _ball_query_filtered(query: Tensor, points: Tensor, radius: float, k: int, keep,
                         query_lengths: Optional[Tensor] = None,
                         point_lengths: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """The first k points in index order among the core ball query's hits (``dist2 < radius**2``) for
    which ``keep(dist2)`` holds. Exact: when a query's hits were cut at k' and filtering left fewer than
    k, the query is repeated with a larger k' (up to N). Returns (dist2, idx) with (+inf, -1) padding
    (``dist2`` not differentiable)."""
    N = points.shape[1]
    kk = k
    while True:
        with torch.no_grad():
            d2, idx = _core_ball_query(query, points, radius, kk, query_lengths, point_lengths)
        ok = (idx >= 0) & keep(d2)
        if kk >= N:
            break
        cut = (ok.sum(-1) < k) & (idx[..., -1] >= 0)
        if not bool(cut.any()):
            break
        kk = min(N, kk * 4)
    out_idx = _first_k_hits(ok, idx, k)
    pos = torch.where(ok, ok.to(torch.int64).cumsum(-1) - 1, torch.full_like(idx, k))
    pos = pos.clamp_max(k)
    out_d2 = torch.full((*idx.shape[:-1], k + 1), math.inf, dtype=d2.dtype, device=d2.device)
    out_d2.scatter_(-1, pos, torch.where(ok & (pos < k), d2, torch.full_like(d2, math.inf)))
    return out_d2[..., :k], out_idx
