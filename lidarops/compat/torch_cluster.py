"""Drop-in face of ``torch_cluster``: ``fps``, ``knn``, ``knn_graph``, ``radius``, ``radius_graph`` in
the flat layout, TorchScript-compatible.

torch_cluster stores a batch of clouds flat: ``src (Tensor[N, F])`` with a sorted batch vector
``batch (Tensor[N])`` that assigns each row to an example, and returns flat indices (``fps``) or an
edge index ``(2, E)`` whose first row indexes ``y`` (the queries) and second row ``x``. Conventions
were read from rusty1s/pytorch_cluster ``torch_cluster/{fps,knn,radius}.py`` and the kernels
``csrc/cpu/{fps,knn,radius}_cpu.cpp`` and ``csrc/cuda/{fps,knn,radius}_cuda.cu``.

PyG models are deployed with ``torch.jit.script``, so every public function here scripts:
``torch.jit.script(fps)`` compiles and returns what the eager call returns. The bodies are written
in the TorchScript subset (annotated signatures, no lambdas, f-strings or comprehensions; messages
built with ``+`` and ``str``) and call the registered ``torch.ops.lidarops`` ops directly. Eager-only
conveniences (accepting numpy integers, 0-d tensors for ``k``; the not-a-tensor check; the
``lidarops.validation(False)`` switch) sit in ``if not torch.jit.is_scripting():`` blocks, which the
TorchScript compiler skips; a scripted function always runs the value checks.

The flat layout is converted to padded ``(B, N_max, F)`` + lengths with vectorised index arithmetic
(one ``bincount``, one scatter, no loop over examples), the lidarops core ops do the search, and the
results are flattened back. ``F <= 3`` runs the core kernels (zero columns added for ``F < 3``: the
squared distances are bit-identical); larger ``F`` runs a chunked dense PyTorch path with the same
conventions. Known deviations are listed in ``docs/compat.md``.
"""
import math
import numbers
from typing import List, Optional, Tuple, Union

import torch
import torch.nn.functional as F_
from torch import Tensor

from lidarops import extension
from lidarops.ops.validation import check_tensor, value_checks_enabled

__all__ = ["fps", "knn", "knn_graph", "radius", "radius_graph"]

# Constants are written inline (TorchScript cannot read module-level ints): the output limit is
# lidarops.ops.validation.MAX_OUTPUT_ENTRIES = 2^31 - 1; the dense path materialises at most 2^24
# elements of its (B, chunk, P2, F) difference tensor at once.


# ---------------------------------------------------------------------------------------------
# scriptable helpers: messages, checks
# ---------------------------------------------------------------------------------------------

def _checks_on() -> bool:
    """Value checks (NaN, sortedness, ranges: host syncs) run unless eager code turned them off."""
    if torch.jit.is_scripting():
        return True
    else:
        return value_checks_enabled()


def _dtype_name(dtype: torch.dtype) -> str:
    # str(dtype) is an integer code under TorchScript
    if dtype == torch.float32:
        return "torch.float32"
    if dtype == torch.float64:
        return "torch.float64"
    if dtype == torch.float16:
        return "torch.float16"
    if dtype == torch.bfloat16:
        return "torch.bfloat16"
    if dtype == torch.int64:
        return "torch.int64"
    if dtype == torch.int32:
        return "torch.int32"
    if dtype == torch.int16:
        return "torch.int16"
    if dtype == torch.int8:
        return "torch.int8"
    if dtype == torch.uint8:
        return "torch.uint8"
    if dtype == torch.bool:
        return "torch.bool"
    return "a non-float dtype"


def _describe(t: Tensor) -> str:
    """``shape (2, 3), dtype torch.float32, device cpu``, the same text eager and scripted."""
    sizes = t.shape
    s = "("
    for i in range(len(sizes)):
        if i > 0:
            s += ", "
        s += str(sizes[i])
    if len(sizes) == 1:
        s += ","
    return "shape " + s + "), dtype " + _dtype_name(t.dtype) + ", device " + str(t.device)


def _check_size(entries: int, asked_by: str, what: str, hint: str) -> None:
    if entries > 2147483647:
        raise ValueError(asked_by + ": " + what + " would hold " + str(entries) + " entries, more than the "
                         "2^31 - 1 a lidarops output may hold; " + hint)


def _coordinate_bound(dtype: torch.dtype) -> float:
    """As :func:`lidarops.ops.validation.coordinate_bound`: squared distances cannot overflow."""
    if dtype == torch.float64:
        return 2.0 ** 510
    if dtype == torch.float16:
        return 65504.0
    return 2.0 ** 62


def _check_coordinates(t: Tensor, name: str) -> None:
    if t.numel() == 0:
        return
    largest = t.abs().amax()
    if not bool(largest.le(_coordinate_bound(t.dtype))):
        if not bool(torch.isfinite(t).all()):
            raise ValueError(name + " contains NaN or infinite coordinates (" + _describe(t) + ")")
        bound = "2^62 (about 4.6e18)"
        if t.dtype == torch.float64:
            bound = "2^510 (about 3.4e153)"
        elif t.dtype == torch.float16:
            bound = "65504"
        raise ValueError(name + " has a coordinate of magnitude " + str(float(largest)) + "; coordinates must "
                         "lie within +-" + bound + " for " + _dtype_name(t.dtype) + ", so that squared "
                         "distances cannot overflow (" + _describe(t) + ")")


def _as_matrix(t: Tensor, name: str) -> Tensor:
    if t.dim() == 1:
        t = t.view(-1, 1)  # torch_cluster treats a vector as N points of one feature
    if t.dim() != 2:
        raise ValueError(name + " must be (N, F) (or (N,)), got " + _describe(t))
    if not t.is_floating_point():
        raise ValueError(name + " must be floating point, got " + _describe(t))
    return t.detach()  # indices only: nothing to differentiate


def _batch_vector(batch: Optional[Tensor], n: int, name: str, like: Tensor) -> Optional[Tensor]:
    if batch is None:
        return None
    if batch.dim() != 1 or batch.shape[0] != n:
        raise ValueError(name + " must be (N,) with N = " + str(n) + ", got " + _describe(batch))
    if batch.is_floating_point() or batch.is_complex() or batch.dtype == torch.bool:
        raise ValueError(name + " must be an integer tensor, got " + _describe(batch))
    if batch.device != like.device:
        raise ValueError(name + " is on " + str(batch.device) + " but the points are on " + str(like.device))
    b = batch.to(torch.int64)
    if _checks_on() and n > 0:
        flags = torch.stack([(b < 0).any(), (b[1:] < b[:-1]).any()]).cpu()  # one host sync
        if bool(flags[0]):
            raise ValueError(name + " must be >= 0 (" + _describe(batch) + ")")
        if bool(flags[1]):
            raise ValueError(name + " must be sorted (torch_cluster assigns each example a contiguous range of "
                             "rows); sort the points by example first, e.g. with torch.sort(batch, stable=True)")
    return b


def _num_examples(batch_x: Optional[Tensor], batch_y: Optional[Tensor], batch_size: Optional[int]) -> int:
    if batch_size is not None:
        if batch_size <= 0:
            raise ValueError("batch_size must be a positive int, got " + str(batch_size))
        size = batch_size
        asked = "batch_size=" + str(size)
    else:
        size = 1
        if batch_x is not None and batch_x.numel() > 0:
            size = max(size, int(batch_x.max()) + 1)
        if batch_y is not None and batch_y.numel() > 0:
            size = max(size, int(batch_y.max()) + 1)
        asked = "batch values up to " + str(size - 1)
    _check_size(size, asked, "the per-example counts", "one example per batch value: renumber the examples")
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
        if _checks_on() and n > 0:
            if bool((batch >= B).any()):
                raise ValueError("batch values must be < batch_size = " + str(B))
        counts = torch.bincount(batch, minlength=B)[:B]
    ptr = torch.cat([torch.zeros(1, dtype=torch.int64, device=device), torch.cumsum(counts, 0)])
    n_max = int(counts.max()) if B > 0 else 0
    _check_size(B * n_max * src.shape[1], str(B) + " examples of up to " + str(n_max) + " rows",
                "the padded batch", "split the batch")
    padded = src.new_zeros([B, n_max, src.shape[1]])
    if n > 0:
        pos = torch.arange(n, device=device) - ptr[batch]
        padded[batch, pos] = src
    return padded, counts, ptr


def _edges(idx: Tensor, ptr_x: Tensor, ptr_y: Tensor) -> Tensor:
    """Local (B, M_max, k) neighbour indices (-1 padding) -> edge index (2, E) [row = y, col = x],
    ordered by y, then by slot."""
    M = idx.shape[1]
    found = idx >= 0
    rows = (ptr_y[:-1].unsqueeze(1) + torch.arange(M, device=idx.device).unsqueeze(0)).unsqueeze(2).expand_as(idx)
    cols = idx + ptr_x[:-1].unsqueeze(1).unsqueeze(2)
    return torch.stack([rows[found], cols[found]], dim=0)


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    return torch.float64 if dtype == torch.float64 else torch.float32


def _pad_dim_to_3(t: Tensor) -> Tensor:
    """(B, P, F<=3) -> (B, P, 3) with zero columns; squared distances are bit-identical."""
    if t.shape[2] == 3:
        return t
    return torch.cat([t, t.new_zeros([t.shape[0], t.shape[1], 3 - t.shape[2]])], dim=2)


def _pair(x: Tensor, y: Tensor, batch_x: Optional[Tensor], batch_y: Optional[Tensor],
          batch_size: Optional[int]) -> Tuple[Tensor, Tensor, Optional[Tensor], Optional[Tensor], int]:
    x = _as_matrix(x, "x")
    y = _as_matrix(y, "y")
    if x.device != y.device:
        raise ValueError("x and y must be on the same device, got " + str(x.device) + " and " + str(y.device))
    if x.shape[1] != y.shape[1]:
        raise ValueError("x and y must have the same number of features, got " + _describe(x) + " and "
                         + _describe(y))
    if x.dtype != y.dtype:
        raise ValueError("x and y must have the same dtype, got " + _dtype_name(x.dtype) + " and "
                         + _dtype_name(y.dtype))
    bx = _batch_vector(batch_x, x.shape[0], "batch_x", x)
    by = _batch_vector(batch_y, y.shape[0], "batch_y", y)
    B = _num_examples(bx, by, batch_size)
    if B > 1 and (bx is None or by is None):
        raise ValueError("batch_x and batch_y must both be given when the batch has more than one example "
                         "(batch size " + str(B) + ")")
    return x, y, bx, by, B


def _eager_prechecks(tensors: List[Tuple[str, object]]) -> None:
    """Eager only: arguments that are not tensors, devices the extension was not built for."""
    for name, t in tensors:
        if t is not None:
            check_tensor(t, name)
            extension.check_device(t, name)


def _eager_int(v, name: str) -> int:
    """Eager only: a positive int (numpy integers and 0-d integer tensors accepted)."""
    if isinstance(v, Tensor) and v.numel() == 1 and not v.is_floating_point() and not v.is_complex() \
            and v.dtype != torch.bool:
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v <= 0:
        raise ValueError(name + " must be a positive int, got " + repr(v))
    return int(v)


def _eager_bool(v, name: str) -> bool:
    if not isinstance(v, (bool, int)) and not (isinstance(v, Tensor) and v.numel() == 1):
        raise ValueError(name + " must be a bool, got " + repr(v))
    return bool(v)


# ---------------------------------------------------------------------------------------------
# scriptable helpers: search
# ---------------------------------------------------------------------------------------------

def _sqdist(diff: Tensor) -> Tensor:
    """Sum of squares over the last dim, left to right for F <= 4 (the kernels' rounding)."""
    terms = diff * diff
    F = terms.shape[-1]
    if F > 4:
        return terms.sum(-1)
    out = terms.select(-1, 0)
    for j in range(1, F):
        out = out + terms.select(-1, j)
    return out


def _first_k_hits(hit: Tensor, values: Tensor, K: int) -> Tensor:
    """(B, M, P) -> (B, M, K): the first K ``values`` where ``hit``, in order; -1 padding."""
    rank = hit.to(torch.int64).cumsum(-1) - 1
    keep = hit & (rank < K)
    pos = torch.where(keep, rank, torch.full_like(rank, K))  # unkept entries go to a spare column
    out = torch.full([hit.shape[0], hit.shape[1], K + 1], -1, dtype=torch.int64, device=hit.device)
    out.scatter_(2, pos, torch.where(keep, values.to(torch.int64), torch.full_like(rank, -1)))
    return out[:, :, :K]


def _valid(lengths: Tensor, n: int) -> Tensor:
    return torch.arange(n, device=lengths.device).unsqueeze(0) < lengths.unsqueeze(1)


def _dense_fps(points: Tensor, lengths: Tensor, K: int, start: Tensor) -> Tensor:
    """FPS for any F (loop over K): lidarops' convention (ties to the lowest index, never re-selecting,
    -1 beyond lengths)."""
    B, P = points.shape[0], points.shape[1]
    out = torch.full([B, K], -1, dtype=torch.int64, device=points.device)
    if B == 0 or P == 0:
        return out
    p = points.to(_compute_dtype(points.dtype))
    rows = torch.arange(B, device=points.device)
    dist = torch.full([B, P], math.inf, dtype=p.dtype, device=points.device)
    taken = ~_valid(lengths, P)
    cur = start.clamp(0, P - 1)
    for i in range(K):
        active = lengths > i
        out[:, i] = torch.where(active, cur, torch.full_like(cur, -1))
        taken[rows, cur] = taken[rows, cur] | active
        dist = torch.minimum(dist, _sqdist(p - p[rows, cur].unsqueeze(1)))
        cur = dist.masked_fill(taken, -1.0).argmax(1)  # first maximum = lowest index
    return out


def _dense_knn(q: Tensor, p: Tensor, lq: Tensor, lp: Tensor, K: int) -> Tensor:
    """Brute-force kNN indices for any F, chunked over queries: ascending, ties to the lower index."""
    B, P1, D = q.shape[0], q.shape[1], q.shape[2]
    P2 = p.shape[1]
    idx = torch.full([B, P1, K], -1, dtype=torch.int64, device=q.device)
    kk = min(K, P2)
    if B == 0 or P1 == 0 or kk == 0:
        return idx
    ct = _compute_dtype(q.dtype)
    a, b = q.to(ct), p.to(ct)
    point_ok = _valid(lp, P2)
    slot_ok = torch.arange(kk, device=q.device).unsqueeze(0) < lp.unsqueeze(1)
    step = max(1, 16777216 // max(1, B * P2 * D))
    for s in range(0, P1, step):
        e = min(P1, s + step)
        d = _sqdist(a[:, s:e].unsqueeze(2) - b.unsqueeze(1))
        d = d.masked_fill(~point_ok.unsqueeze(1), math.inf)
        order = torch.sort(d, dim=-1, stable=True).indices[:, :, :kk]  # stable: ties to the lower index
        query_ok = torch.arange(s, e, device=q.device).unsqueeze(0) < lq.unsqueeze(1)
        ok = query_ok.unsqueeze(2) & slot_ok.unsqueeze(1)
        idx[:, s:e, :kk] = torch.where(ok, order, torch.full_like(order, -1))
    return idx


def _dense_ball(q: Tensor, p: Tensor, lq: Tensor, lp: Tensor, K: int, r2: float, exclude: Optional[Tensor]) -> Tensor:
    """Brute-force ball query indices for any F: the first K points in index order with dist2 < r2
    (compared in the computation dtype), skipping ``exclude[b, i]`` (a local point index, or None)."""
    B, P1, D = q.shape[0], q.shape[1], q.shape[2]
    P2 = p.shape[1]
    idx = torch.full([B, P1, K], -1, dtype=torch.int64, device=q.device)
    if B == 0 or P1 == 0 or P2 == 0:
        return idx
    ct = _compute_dtype(q.dtype)
    a, b = q.to(ct), p.to(ct)
    point_ok = _valid(lp, P2)
    thr = torch.tensor(r2, dtype=ct, device=q.device)
    cols = torch.arange(P2, device=q.device)
    step = max(1, 16777216 // max(1, B * P2 * D))
    for s in range(0, P1, step):
        e = min(P1, s + step)
        d = _sqdist(a[:, s:e].unsqueeze(2) - b.unsqueeze(1))
        query_ok = torch.arange(s, e, device=q.device).unsqueeze(0) < lq.unsqueeze(1)
        hit = (d < thr) & point_ok.unsqueeze(1) & query_ok.unsqueeze(2)
        if exclude is not None:
            hit = hit & (cols.view(1, 1, -1) != exclude[:, s:e].unsqueeze(2))
        idx[:, s:e] = _first_k_hits(hit, cols.view(1, 1, -1).expand_as(hit), K)
    return idx


def _ball_filtered(q: Tensor, p: Tensor, lq: Tensor, lp: Tensor, radius: float, k: int, r2: float,
                   exclude: Optional[Tensor]) -> Tensor:
    """The first k points in index order among the core ball query's hits with ``dist2 < r2`` and not
    ``exclude[b, i]``. Exact: a query whose hits were cut and filtered below k is repeated with more
    candidates (up to N)."""
    N = p.shape[1]
    kk = k
    done = False
    idx = torch.empty(0, dtype=torch.int64)  # TorchScript wants the loop's results defined before it
    ok = torch.empty(0, dtype=torch.bool)
    while not done:
        d2, idx = torch.ops.lidarops.ball_query(q, p, lq, lp, kk, radius, 0)
        ok = (idx >= 0) & (d2 < r2)
        if exclude is not None:
            ok = ok & (idx != exclude.unsqueeze(2))
        if kk >= N:
            done = True
        elif not bool(((ok.sum(-1) < k) & (idx.select(-1, kk - 1) >= 0)).any()):
            done = True  # no query was cut short and then filtered below k
        else:
            kk = min(N, kk * 4)
    return _first_k_hits(ok, idx, k)


def _repeat_first_after_exhaustion(points: Tensor, idx: Tensor) -> Tensor:
    """torch_cluster's FPS once an example has no distinct location left: the farthest remaining point
    is at distance 0 and its arg-max returns the example's first row, again and again.

    ``idx`` follows lidarops' convention (distinct indices, -1 padding): its first u picks are the u
    distinct locations, then duplicates, which become local index 0. Cheap test first: an example ran
    out iff its last pick coincides with an earlier one (FPS distances never increase)."""
    B, K = idx.shape[0], idx.shape[1]
    if B == 0 or K < 2:
        return idx
    n_sel = (idx >= 0).sum(1)
    sel = torch.ops.lidarops.gather(points, idx)  # (B, K, F); zeros for -1
    sel = sel.to(_compute_dtype(points.dtype)) + 0.0  # -0.0 -> 0.0 (equal locations)
    rows = torch.arange(B, device=idx.device)
    last_pos = (n_sel - 1).clamp_min(0)
    last = sel[rows, last_pos]
    same = (sel == last.unsqueeze(1)).all(-1)
    before = torch.arange(K, device=idx.device).unsqueeze(0) < last_pos.unsqueeze(1)
    ran_out = (same & before).any(1)
    if not bool(ran_out.any()):
        return idx
    valid = idx >= 0
    bcol = rows.unsqueeze(1).expand(B, K).to(torch.float64)[valid].unsqueeze(1)
    keyed = torch.cat([bcol, sel.to(torch.float64)[valid]], dim=1)
    uniq = torch.unique(keyed, dim=0)
    distinct = torch.bincount(uniq[:, 0].to(torch.int64), minlength=B)
    cut = torch.where(ran_out, distinct, torch.full_like(distinct, K))
    repeat = (torch.arange(K, device=idx.device).unsqueeze(0) >= cut.unsqueeze(1)) & valid
    return torch.where(repeat, torch.zeros_like(idx), idx)


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
        ratio (float | Tensor[] | Tensor[1] | Tensor[B]): fraction of each example to sample, in (0, 1].
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

    Scripts with ``torch.jit.script``.
    """
    if not torch.jit.is_scripting():
        _eager_prechecks([("src", src), ("batch", batch)])
        if not isinstance(ratio, Tensor):
            if isinstance(ratio, bool) or not isinstance(ratio, numbers.Real):
                raise ValueError("ratio must lie in (0, 1], got " + repr(ratio))
            ratio = float(ratio)
        if ptr is not None and not isinstance(ptr, Tensor):
            ptr = [int(v) for v in ptr]
        if batch_size is not None:
            batch_size = _eager_int(batch_size, "batch_size")
        random_start = _eager_bool(random_start, "random_start")
    src = _as_matrix(src, "src")
    device = src.device
    n = src.shape[0]
    if batch is not None and ptr is not None:
        raise ValueError("give batch or ptr, not both")
    if ptr is not None:
        if isinstance(ptr, Tensor):
            ptr_t = ptr
        else:
            ptr_t = torch.tensor(ptr, dtype=torch.int64, device=device)
        if ptr_t.dim() != 1 or ptr_t.shape[0] < 2 or ptr_t.is_floating_point() or ptr_t.dtype == torch.bool:
            raise ValueError("ptr must be an integer (B + 1,) tensor or list, got " + _describe(ptr_t))
        ptr_t = ptr_t.to(device=device, dtype=torch.int64)
        counts = ptr_t[1:] - ptr_t[:-1]
        if _checks_on():
            if bool((ptr_t[0] != 0) | (ptr_t[-1] != n) | (counts < 0).any()):
                got: List[int] = ptr_t.tolist()
                raise ValueError("ptr must rise from 0 to N = " + str(n) + ", got " + str(got))
        B = counts.shape[0]
        bvec: Optional[Tensor] = torch.repeat_interleave(torch.arange(B, device=device), counts, output_size=n)
    else:
        bvec = _batch_vector(batch, n, "batch", src)
        B = _num_examples(bvec, None, batch_size)
    if isinstance(ratio, Tensor):
        if not ratio.is_floating_point() or ratio.dim() > 1 or \
                (ratio.dim() == 1 and ratio.shape[0] != 1 and ratio.shape[0] != B):
            raise ValueError("ratio must be a float or a floating () or (B,) tensor with B = " + str(B)
                             + ", got " + _describe(ratio))
        r = ratio.to(device)
        if not bool(((r > 0) & (r <= 1)).all()):  # NaN fails both comparisons
            got_r: List[float] = r.flatten().to(torch.float64).tolist()
            raise ValueError("ratio must lie in (0, 1], got " + str(got_r))
    else:
        if not (ratio > 0.0 and ratio <= 1.0):
            raise ValueError("ratio must lie in (0, 1], got " + str(ratio))
        r = torch.tensor(ratio, dtype=src.dtype, device=device)
    padded, counts, ptr_x = _to_padded(src, bvec, B)
    if _checks_on():
        _check_coordinates(src, "src")
    # torch_cluster: out_ptr = ceil(deg.float() * ratio).long()
    n_samples = torch.ceil(counts.to(torch.float32) * r).to(torch.int64)
    n_samples = torch.minimum(n_samples, counts)
    k = int(n_samples.max()) if B > 0 else 0
    if k == 0:
        return torch.empty(0, dtype=torch.int64, device=device)
    _check_size(B * k, "ratio", "the padded samples", "sample fewer points")
    if random_start:
        start = (torch.rand([B], dtype=src.dtype, device=device) * counts.to(torch.float32)).to(torch.int64)
        start = torch.minimum(start, (counts - 1).clamp_min(0))
    else:
        start = torch.zeros(B, dtype=torch.int64, device=device)
    if src.shape[1] <= 3:
        idx = torch.ops.lidarops.fps(_pad_dim_to_3(padded), counts, start, k, 0)
    else:
        idx = _dense_fps(padded, counts, k, start)
    idx = _repeat_first_after_exhaustion(padded, idx)
    take = torch.arange(k, device=device).unsqueeze(0) < n_samples.unsqueeze(1)
    return (idx + ptr_x[:-1].unsqueeze(1))[take]


def knn(x: Tensor, y: Tensor, k: int, batch_x: Optional[Tensor] = None, batch_y: Optional[Tensor] = None,
        cosine: bool = False, num_workers: int = 1, batch_size: Optional[int] = None,
        use_triton: bool = False) -> Tensor:
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
        use_triton (bool): accepted and ignored (torch_cluster master's Triton switch).

    Returns:
        Tensor[2, E] int64: ``[row, col]`` with ``row`` indexing ``y`` and ``col`` indexing ``x``;
        grouped by ``y`` in order, each query's neighbours by ascending distance (ties to the lower
        index, as torch_cluster's CUDA kernel), ``min(k, n_b)`` of them.

    Scripts with ``torch.jit.script``.
    """
    if not torch.jit.is_scripting():
        _eager_prechecks([("x", x), ("y", y), ("batch_x", batch_x), ("batch_y", batch_y)])
        k = _eager_int(k, "k")
        if batch_size is not None:
            batch_size = _eager_int(batch_size, "batch_size")
        cosine = _eager_bool(cosine, "cosine")
    x, y, bx, by, B = _pair(x, y, batch_x, batch_y, batch_size)
    if k <= 0:
        raise ValueError("k must be a positive int, got " + str(k))
    if x.numel() == 0 or y.numel() == 0:
        return torch.empty(2, 0, dtype=torch.int64, device=x.device)
    px, cx, ptr_x = _to_padded(x, bx, B)
    py, cy, ptr_y = _to_padded(y, by, B)
    _check_size(B * py.shape[1] * k, "k=" + str(k), "the padded neighbour lists", "split the queries into chunks")
    if cosine:
        px, py = F_.normalize(px, dim=-1), F_.normalize(py, dim=-1)
    if _checks_on():
        _check_coordinates(x, "x")
        _check_coordinates(y, "y")
    if x.shape[1] <= 3:
        idx = torch.ops.lidarops.knn(_pad_dim_to_3(py), _pad_dim_to_3(px), cy, cx, k, 0)[1]
    else:
        idx = _dense_knn(py, px, cy, cx, k)
    return _edges(idx, ptr_x, ptr_y)


def radius(x: Tensor, y: Tensor, r: float, batch_x: Optional[Tensor] = None, batch_y: Optional[Tensor] = None,
           max_num_neighbors: int = 32, num_workers: int = 1, batch_size: Optional[int] = None,
           ignore_same_index: bool = False, use_triton: bool = False) -> Tensor:
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
        ignore_same_index (bool): query ``y[i]`` skips ``x[i]`` (the same flat row index, whatever the
            coordinates), and the skipped row takes none of the ``max_num_neighbors`` slots
            (torch_cluster master; ``radius_graph`` passes ``not loop``).
        use_triton (bool): accepted and ignored.

    Returns:
        Tensor[2, E] int64: ``[row, col]`` with ``row`` indexing ``y`` and ``col`` indexing ``x``, grouped
        by ``y`` in order and, within a query, by increasing ``x`` index.

    Scripts with ``torch.jit.script``.
    """
    if not torch.jit.is_scripting():
        _eager_prechecks([("x", x), ("y", y), ("batch_x", batch_x), ("batch_y", batch_y)])
        if isinstance(r, Tensor) and r.numel() == 1:
            r = float(r)
        if isinstance(r, bool) or not isinstance(r, numbers.Real):
            raise ValueError("r must be a finite number >= 0, got " + repr(r))
        r = float(r)
        max_num_neighbors = _eager_int(max_num_neighbors, "max_num_neighbors")
        if batch_size is not None:
            batch_size = _eager_int(batch_size, "batch_size")
        ignore_same_index = _eager_bool(ignore_same_index, "ignore_same_index")
    x, y, bx, by, B = _pair(x, y, batch_x, batch_y, batch_size)
    if not math.isfinite(r) or r < 0.0:
        raise ValueError("r must be a finite number >= 0, got " + str(r))
    if max_num_neighbors <= 0:
        raise ValueError("max_num_neighbors must be a positive int, got " + str(max_num_neighbors))
    if x.numel() == 0 or y.numel() == 0:
        return torch.empty(2, 0, dtype=torch.int64, device=x.device)
    px, cx, ptr_x = _to_padded(x, bx, B)
    py, cy, ptr_y = _to_padded(y, by, B)
    _check_size(B * py.shape[1] * max_num_neighbors, "max_num_neighbors=" + str(max_num_neighbors),
                "the padded neighbour lists", "split the queries into chunks")
    ct = _compute_dtype(x.dtype)
    r2 = float(torch.tensor(r * r, dtype=torch.float64).to(ct))  # double r*r rounded to the compute dtype
    if _checks_on():
        _check_coordinates(x, "x")
        _check_coordinates(y, "y")
    exclude: Optional[Tensor] = None
    if ignore_same_index:
        # local x index with the query's flat row index: ptr_y[b] + i - ptr_x[b]
        exclude = ptr_y[:-1].unsqueeze(1) + torch.arange(py.shape[1], device=x.device).unsqueeze(0) \
            - ptr_x[:-1].unsqueeze(1)
    if x.shape[1] <= 3:
        # the core compares with T(r) * T(r); query a slightly larger ball and keep dist2 < r2 exactly
        idx = _ball_filtered(_pad_dim_to_3(py), _pad_dim_to_3(px), cy, cx, r * (1 + 1e-6), max_num_neighbors,
                             r2, exclude)
    else:
        idx = _dense_ball(py, px, cy, cx, max_num_neighbors, r2, exclude)
    return _edges(idx, ptr_x, ptr_y)


def _check_flow(flow: str) -> None:
    if flow != "source_to_target" and flow != "target_to_source":
        raise ValueError("flow must be 'source_to_target' or 'target_to_source', got '" + flow + "'")


def knn_graph(x: Tensor, k: int, batch: Optional[Tensor] = None, loop: bool = False,
              flow: str = "source_to_target", cosine: bool = False, num_workers: int = 1,
              batch_size: Optional[int] = None, use_triton: bool = False) -> Tensor:
    """The k-nearest-neighbour graph of ``x`` as ``torch_cluster.knn_graph``.

    Args:
        x (Tensor[N, F]), batch (Tensor[N] integer, optional): points and their sorted batch vector.
        k (int): neighbours per point.
        loop (bool): keep self-loops. Without, ``knn`` is asked for ``k + 1`` neighbours and the
            self-edges are dropped (torch_cluster's rule: a point with more than ``k`` exact duplicates
            of lower index keeps ``k + 1`` edges).
        flow (str): ``"source_to_target"`` (edges ``[neighbour, point]``) or ``"target_to_source"``
            (``[point, neighbour]``).
        cosine, num_workers, batch_size, use_triton: as :func:`knn`.

    Returns:
        Tensor[2, E] int64. Scripts with ``torch.jit.script``.
    """
    if not torch.jit.is_scripting():
        k = _eager_int(k, "k")
        loop = _eager_bool(loop, "loop")
        if not isinstance(flow, str):
            raise ValueError("flow must be 'source_to_target' or 'target_to_source', got " + repr(flow))
    _check_flow(flow)
    if k <= 0:
        raise ValueError("k must be a positive int, got " + str(k))
    edge_index = knn(x, x, k if loop else k + 1, batch, batch, cosine, num_workers, batch_size)
    if flow == "source_to_target":
        edge_index = edge_index.flip(0)
    if not loop:
        edge_index = edge_index[:, edge_index[0] != edge_index[1]]
    return edge_index.contiguous()


def radius_graph(x: Tensor, r: float, batch: Optional[Tensor] = None, loop: bool = False,
                 max_num_neighbors: int = 32, flow: str = "source_to_target", num_workers: int = 1,
                 batch_size: Optional[int] = None, use_triton: bool = False) -> Tensor:
    """The radius graph of ``x`` as ``torch_cluster.radius_graph`` (master): ``radius(x, x, ...,
    ignore_same_index=not loop)``, so without loops every point keeps up to ``max_num_neighbors``
    other points.

    Args:
        x (Tensor[N, F]), batch (Tensor[N] integer, optional): points and their sorted batch vector.
        r, max_num_neighbors, num_workers, batch_size, use_triton: as :func:`radius`.
        loop (bool): keep self-loops.
        flow (str): ``"source_to_target"`` (edges ``[neighbour, point]``) or ``"target_to_source"``.

    Returns:
        Tensor[2, E] int64. Scripts with ``torch.jit.script``.
    """
    if not torch.jit.is_scripting():
        loop = _eager_bool(loop, "loop")
        if not isinstance(flow, str):
            raise ValueError("flow must be 'source_to_target' or 'target_to_source', got " + repr(flow))
    _check_flow(flow)
    edge_index = radius(x, x, r, batch, batch, max_num_neighbors, num_workers, batch_size, not loop)
    if flow == "source_to_target":
        return edge_index.flip(0).contiguous()
    return edge_index
