"""Every registered op called directly (``torch.ops.lidarops.<op>``) with values and shapes its Python
wrapper would never pass: out-of-range indices, counts, offsets and slots, and inconsistent shapes.

Each case expects either a ValueError naming the argument, or the result the op documents for such
entries (skipped, clamped), computed by hand here. The bug class is a segfault, so the cases run in a
subprocess (this file run as a script): a crash fails the test, naming the case, instead of killing
pytest. Ops that check values at entry on the CPU skip bad entries on CUDA instead (no host sync);
both behaviours are the documented ones (docs/ops.md, "Calling the registered ops directly").
``pillar_stream_push`` / ``pillar_stream_gather`` have their own tests (tests/stream/).
"""
from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import traceback

import torch

F64 = torch.float64
I32 = torch.int32
I64 = torch.int64
INT32_MAX = 2**31 - 1


# ---------------------------------------------------------------------------------------------------
# helpers used inside the subprocess

def _ops():
    return torch.ops.lidarops


def raises(call, pattern: str, exc=ValueError) -> None:
    try:
        call()
    except exc as e:  # noqa: PERF203
        assert re.search(pattern, str(e)), f"{type(e).__name__} message {str(e)!r} does not match {pattern!r}"
        return
    except Exception as e:  # a different type is a failure of this case
        raise AssertionError(f"expected {exc.__name__} matching {pattern!r}, got {type(e).__name__}: {e}") from None
    raise AssertionError(f"expected {exc.__name__} matching {pattern!r}, nothing was raised")


def on_cpu_raises_else(dev: str, call, pattern: str, check) -> None:
    """CPU kernels check values at entry (ValueError); CUDA kernels skip the bad entries: check(result)."""
    if dev == "cpu":
        raises(call, pattern)
    else:
        check(call())


def close(a, b, tol=1e-9) -> None:
    # Python lists become float64 directly (through float32 they would carry its rounding, ~1e-9 here)
    a = (a if isinstance(a, torch.Tensor) else torch.as_tensor(a, dtype=F64)).detach().to("cpu", F64)
    b = (b if isinstance(b, torch.Tensor) else torch.as_tensor(b, dtype=F64)).detach().to("cpu", F64)
    assert a.shape == b.shape, f"shape {tuple(a.shape)} != {tuple(b.shape)}"
    both_inf = torch.isinf(a) & torch.isinf(b) & (torch.sign(a) == torch.sign(b))
    diff = torch.where(both_inf, torch.zeros_like(a), (a - b).abs())
    assert diff.numel() == 0 or diff.max().item() <= tol, f"max difference {diff.max().item()}: {a} vs {b}"


def equal(a, b) -> None:
    a = torch.as_tensor(a).detach().cpu()
    b = torch.as_tensor(b).detach().cpu()
    assert a.shape == b.shape and bool((a == b).all()), f"{a.tolist()} != {b.tolist()}"


# ---------------------------------------------------------------------------------------------------
# neighbours

def case_gather_index_out_of_range(dev):
    x = torch.arange(6, dtype=F64, device=dev).view(1, 3, 2)
    idx = torch.tensor([[0, 5, -1, -2]], device=dev)
    on_cpu_raises_else(dev, lambda: _ops().gather(x, idx), r"idx must lie in \[-1, 3\)",
                       lambda out: equal(out, [[[0.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]]))


def case_gather_shapes(dev):
    x = torch.zeros(1, 3, 2, device=dev)
    raises(lambda: _ops().gather(x, torch.zeros(2, 4, dtype=I64, device=dev)), r"idx must be \(B, L\) with B = 1")
    raises(lambda: _ops().gather(x, torch.zeros(1, 4, dtype=I32, device=dev)), r"idx must be int64")
    raises(lambda: _ops().gather(x[0], torch.zeros(1, 4, dtype=I64, device=dev)), r"x must be \(B, N, C\)")


def case_gather_backward_index_out_of_range(dev):
    grad = torch.ones(1, 3, 2, dtype=F64, device=dev)
    idx = torch.tensor([[0, 7, 0]], device=dev)
    on_cpu_raises_else(dev, lambda: _ops().gather_backward(grad, idx, 2), r"idx must lie in \[-1, 2\)",
                       lambda out: equal(out, [[[2.0, 2.0], [0.0, 0.0]]]))
    raises(lambda: _ops().gather_backward(grad, idx[:, :2], 2), r"grad must be \(B, L, C\) with L = 2")
    raises(lambda: _ops().gather_backward(grad, idx, -1), r"n must be >= 0")


def _cloud(dev, n=4):
    return torch.tensor([[[0.0, 0, 0], [1, 0, 0], [3, 0, 0], [7, 0, 0]][:n]], dtype=F64, device=dev)


def case_fps_lengths_and_start_out_of_range(dev):
    p = _cloud(dev)
    start = torch.tensor([0], device=dev)
    # lengths 9 > N = 4: CUDA clamps to 4; from point 0 the farthest are 7, then 3, then 1
    on_cpu_raises_else(dev, lambda: _ops().fps(p, torch.tensor([9], device=dev), start, 4, 0),
                       r"lengths\[0\] = 9 is outside \[0, 4\]", lambda out: equal(out, [[0, 3, 2, 1]]))
    # start 7 >= lengths 4: CUDA clamps it to the last point (x = 7); then x = 0, then x = 3 (3 > 1)
    on_cpu_raises_else(dev, lambda: _ops().fps(p, torch.tensor([4], device=dev), torch.tensor([7], device=dev), 3, 0),
                       r"start_idx\[0\] = 7 is outside", lambda out: equal(out, [[3, 0, 2]]))
    raises(lambda: _ops().fps(p, torch.tensor([4, 4], device=dev), start, 2, 0), r"lengths must be \(B,\) with B = 1")
    raises(lambda: _ops().fps(p, torch.tensor([4], dtype=I32, device=dev), start, 2, 0), r"lengths must be int64")
    raises(lambda: _ops().fps(p, torch.tensor([4], device=dev), start, 0, 0), r"k must be positive")


def case_knn_lengths_out_of_range(dev):
    q = torch.tensor([[[0.9, 0, 0], [6.0, 0, 0]]], dtype=F64, device=dev)
    p = _cloud(dev)
    ql, pl = torch.tensor([2], device=dev), torch.tensor([4], device=dev)

    def unclamped(res):  # point_lengths 5 clamped to 4: nearest two of each query
        dist, idx = res
        equal(idx, [[[1, 0], [3, 2]]])
        close(dist, [[[0.01, 0.81], [1.0, 9.0]]], 1e-15)
    on_cpu_raises_else(dev, lambda: _ops().knn(q, p, ql, torch.tensor([5], device=dev), 2, 0),
                       r"point_lengths\[0\] = 5 is outside \[0, 4\]", unclamped)

    def no_queries(res):  # query_lengths -1 clamped to 0: every row is padding
        dist, idx = res
        equal(idx, torch.full((1, 2, 2), -1))
        assert bool(torch.isinf(dist).all())
    on_cpu_raises_else(dev, lambda: _ops().knn(q, p, torch.tensor([-1], device=dev), pl, 2, 0),
                       r"query_lengths\[0\] = -1 is outside", no_queries)
    raises(lambda: _ops().knn(q, torch.cat([p, p]), ql, torch.tensor([4, 4], device=dev), 2, 0),
           r"query and points must have the same batch size")
    raises(lambda: _ops().knn(q.float(), p, ql, pl, 2, 0), r"query and points must have the same dtype")


def case_ball_query_lengths_out_of_range(dev):
    q = torch.tensor([[[0.9, 0, 0]]], dtype=F64, device=dev)
    p = _cloud(dev)

    def empty(res):  # point_lengths -3 clamped to 0: no neighbour
        dist, idx = res
        equal(idx, torch.full((1, 1, 2), -1))
        assert bool(torch.isinf(dist).all())
    on_cpu_raises_else(dev, lambda: _ops().ball_query(q, p, torch.tensor([1], device=dev),
                                                      torch.tensor([-3], device=dev), 2, 1.0, 0),
                       r"point_lengths\[0\] = -3 is outside", empty)
    raises(lambda: _ops().ball_query(q, p, torch.tensor([1], device=dev), torch.tensor([4], device=dev), 2,
                                     float("nan"), 0), r"radius must be finite")
    raises(lambda: _ops().ball_query(q, p[..., :2], torch.tensor([1], device=dev), torch.tensor([4], device=dev), 2,
                                     1.0, 0), r"points must be \(B, N, 3\)")


# ---------------------------------------------------------------------------------------------------
# sparse convolution

# 1D grid of 3 sites, kernel 3, stride 1, padding 1: input p feeds output q through offset t when
# p = q - 1 + t. Inputs at 0 and 2: the map of outputs 0, 1, 2 is [[-1, 0, -1], [0, -1, 1], [-1, 1, -1]].
_MAP_1D = [[-1, 0, -1], [0, -1, 1], [-1, 1, -1]]


def _conv_reference(x, w, nbr):
    """out[o] = sum_k w[:, k, :] @ x[nbr[o, k]] over entries in [0, N_in), in float64."""
    x, w, nbr = x.cpu().to(F64), w.cpu().to(F64), nbr.cpu()
    out = torch.zeros(nbr.shape[0], w.shape[0], dtype=F64)
    for o in range(nbr.shape[0]):
        for k in range(nbr.shape[1]):
            i = int(nbr[o, k])
            if 0 <= i < x.shape[0]:
                out[o] += w[:, k, :] @ x[i]
    return out


def case_sparse_kernel_map_rows_outside_grid(dev):
    ops = _ops()
    idx = torch.tensor([[0, 0], [0, 2], [0, 7], [0, 2]], dtype=I32, device=dev)  # row 2 outside, row 3 a duplicate
    out_idx = torch.tensor([[0, 0], [0, 1], [0, 2], [0, 9], [5, 1], [-1, 0]], dtype=I32, device=dev)
    args = (1, [3], [3], [1], [1], [1], False)
    raises(lambda: ops.sparse_kernel_map(idx, out_idx, *args, True, 0), r"indices row 2 = \(0, 7\).*lies outside")
    nbr = ops.sparse_kernel_map(idx, out_idx, *args, False, 0).cpu()
    # rows outside the grid are ignored; the duplicate (row 3) loses to row 1 on CPU ("first wins"),
    # either may win on CUDA; out_indices rows outside the batch or grid have no neighbours
    if dev != "cpu":
        nbr = torch.where(nbr == 3, torch.ones_like(nbr), nbr)
    equal(nbr, _MAP_1D + [[-1, -1, -1]] * 3)
    raises(lambda: ops.sparse_kernel_map(idx[:, :1], out_idx, *args, False, 0), r"indices must be \(N, 2\) for D = 1")
    raises(lambda: ops.sparse_kernel_map(idx, out_idx.long(), *args, False, 0), r"out_indices must be int32")
    raises(lambda: ops.sparse_conv_out_indices(idx, 1, [3], [3], [3], [1], [1], [1], False, 0),
           r"indices row 2 = \(0, 7\).*lies outside")


def case_sparse_conv_out_indices_checked_with_bad_rows(dev):
    """``checked=True`` is the caller's word that the rows are valid; rows that break it (outside the grid,
    repeated) are never read out of bounds: an upsampling map whose kernel is its stride gives the valid rows'
    outputs, sorted, and on CUDA rows of -1 for the N K outputs it had counted on; with ``validate`` the bad row
    still raises."""
    ops = _ops()
    idx = torch.tensor([[0, 0], [0, 2], [0, 7], [0, 2]], dtype=I32, device=dev)  # row 2 outside, row 3 a duplicate
    args = (1, [3], [6], [2], [2], [0], [1], True, 0)  # transposed, kernel 2 = stride 2: blocks {0, 1} and {4, 5}
    out = ops.sparse_conv_out_indices(idx, *args, False, True).cpu()
    equal(out[:4], [[0, 0], [0, 1], [0, 4], [0, 5]])
    assert bool((out[4:] == -1).all()), out.tolist()
    assert out.shape[0] == (4 if dev == "cpu" else 8), out.shape  # the CPU counts; CUDA takes N K = 8 rows
    raises(lambda: ops.sparse_conv_out_indices(idx, *args, True, True), r"indices row 2 = \(0, 7\).*lies outside")


def case_sparse_kernel_map_deferred_rows_outside_grid(dev):
    """The deferred check raises what the map's own check raises, when its ticket is redeemed (CUDA) or at once
    (CPU, ticket -1); a passed check's slot holds ticket << 2 (CUDA; the CPU has no slots); an unknown ticket is
    refused; bad shapes are refused before any work."""
    ops = _ops()
    idx = torch.tensor([[0, 0], [0, 2], [0, 7], [0, 2]], dtype=I32, device=dev)  # row 2 outside, row 3 a duplicate
    out_idx = torch.tensor([[0, 0], [0, 1], [0, 2]], dtype=I32, device=dev)
    args = (1, [3], [3], [1], [1], [1], False, 0)

    def deferred(i):
        nbr, ticket = ops.sparse_kernel_map_deferred(i, out_idx, *args)
        ops.sparse_site_check(i, ticket, 1, [3])
        return nbr

    raises(lambda: deferred(idx), r"indices row 2 = \(0, 7\).*lies outside")
    raises(lambda: deferred(idx[[0, 1, 3]]), r"indices rows 1 and 2 both hold")
    equal(deferred(idx[:2]), _MAP_1D)
    nbr, ticket = ops.sparse_kernel_map_deferred(idx[:2], out_idx, *args)
    assert (ticket == -1) == (dev == "cpu"), ticket
    ops.sparse_site_check(idx[:2], ticket, 1, [3])
    slots = ops.sparse_site_check_slots(idx)
    assert slots.device.type == "cpu" and slots.dtype == torch.int64
    if dev != "cpu":
        ops.sparse_site_check(idx[:2], ticket, 1, [3])  # read again: still passes
        assert int(slots[ticket % len(slots)]) == ticket << 2
        _, bad = ops.sparse_kernel_map_deferred(idx[[0, 1, 3]], out_idx, *args)
        torch.cuda.synchronize()
        assert int(slots[bad % len(slots)]) == (bad << 2) | 2  # bit 2: a repeated site
        raises(lambda: ops.sparse_site_check(idx[:2], ticket + 10**6, 1, [3]), r"ticket \d+ is unknown")
        raises(lambda: ops.sparse_site_check(idx[[0, 1, 3]], bad, 1, [3]), r"indices rows 1 and 2 both hold")
        # the word's verdict stands when the indices passed with the ticket are not the map's: a general message
        raises(lambda: ops.sparse_site_check(idx[:2], bad, 1, [3]), r"indices hold duplicate coordinates")
    else:
        assert slots.numel() == 0
        raises(lambda: ops.sparse_site_check(idx[:2], 3, 1, [3]), r"ticket 3 was not issued for CPU indices")
    equal(ops.sparse_kernel_map_deferred(idx[:0], out_idx, *args)[0], [[-1, -1, -1]] * 3)
    raises(lambda: ops.sparse_kernel_map_deferred(idx[:, :1], out_idx, *args), r"indices must be \(N, 2\) for D = 1")
    raises(lambda: ops.sparse_kernel_map_deferred(idx, out_idx.long(), *args), r"out_indices must be int32")


def case_sparse_kernel_map_transpose_out_of_range(dev):
    nbr = torch.tensor([[0, 5], [-7, 1]], dtype=I32, device=dev)
    on_cpu_raises_else(dev, lambda: _ops().sparse_kernel_map_transpose(nbr, 2),
                       r"kernel_map entries must lie in \[-1, n_in = 2\), got 5",
                       lambda out: equal(out, [[0, -1], [-1, 1]]))
    raises(lambda: _ops().sparse_kernel_map_transpose(nbr, -1), r"n_in must lie in")
    raises(lambda: _ops().sparse_kernel_map_transpose(nbr.long(), 2), r"kernel_map must be \(N_out, K\) int32")


def case_sparse_kernel_map_order_any_values(dev):
    nbr = torch.tensor([[99, -7, 3], [-1, -1, -1], [INT32_MAX, 0, -1]], dtype=I32, device=dev)
    order = _ops().sparse_kernel_map_order(nbr).cpu()
    equal(order.sort().values, [0, 1, 2])  # a permutation whatever the entries
    equal(order, [1, 2, 0])  # row masks 0b101, 0, 0b011 (bit k: entry k >= 0), sorted stably
    raises(lambda: _ops().sparse_kernel_map_order(nbr.long()), r"kernel_map must be \(N_out, K\) int32")


def case_sparse_conv_map_out_of_range(dev):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, generator=g, dtype=F64)
    w = torch.randn(4, 3, 3, generator=g, dtype=F64)
    bad = torch.tensor([[-1, 0, 2], [0, -5, 1], [-1, 1, INT32_MAX]], dtype=I32)  # 2, -5, 2^31-1 are bad
    expect = _conv_reference(x, w, bad)  # bad entries are no input
    xd, wd, nd = x.to(dev), w.to(dev), bad.to(dev)
    pattern = r"kernel_map entries must lie in \[-1, N_in = 2\)"
    on_cpu_raises_else(dev, lambda: _ops().sparse_conv(xd, wd, nd, None), pattern, lambda out: close(out, expect))
    on_cpu_raises_else(dev, lambda: _ops().sparse_conv_affine(xd, wd, nd, None, None, None, False), pattern,
                       lambda out: close(out, expect))
    # weight gradient: dW[:, k, :] = sum_o g[o] (x) x[nbr[o, k]] over the good entries
    go = torch.randn(3, 4, generator=g, dtype=F64)
    expect_dw = torch.zeros(4, 3, 3, dtype=F64)
    for o in range(3):
        for k in range(3):
            i = int(bad[o, k])
            if 0 <= i < 2:
                expect_dw[:, k, :] += torch.outer(go[o], x[i])
    on_cpu_raises_else(dev, lambda: _ops().sparse_conv_weight_grad(xd, go.to(dev), nd), pattern,
                       lambda out: close(out, expect_dw))
    # hot-path entry checks stay O(1): shapes, dtypes, devices
    good = torch.tensor(_MAP_1D, dtype=I32, device=dev)
    raises(lambda: _ops().sparse_conv(xd, wd[:, :2], good, None), r"weight has K = 2 kernel offsets but kernel_map has 3")
    raises(lambda: _ops().sparse_conv(xd, wd[..., :2], good, None), r"weight expects Cin = 2 input channels")
    raises(lambda: _ops().sparse_conv(xd, wd, good, torch.zeros(2, dtype=I32, device=dev)),
           r"order must be an \(N_out,\) = \(3,\) int32 permutation")
    raises(lambda: _ops().sparse_conv_affine(xd, wd, good, None, torch.ones(3, device=dev), None, False),
           r"scale must be a float32 \(Cout,\) = \(4,\)")
    raises(lambda: _ops().sparse_conv_weight_grad(xd, go[:2].to(dev), good), r"grad_out has 2 rows but kernel_map has 3")


def case_sparse_conv_affine_chain_map_out_of_range(dev):
    """The chain's layers are sparse_conv_affine calls: a bad map entry raises on the CPU and is no input on CUDA,
    in every layer; a map whose rows are not the features' is refused before any layer runs."""
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 3, generator=g, dtype=F64)
    w1, w2 = torch.randn(4, 3, 3, generator=g, dtype=F64), torch.randn(2, 3, 4, generator=g, dtype=F64)
    bad = torch.tensor([[-1, 0, 2], [0, -5, 1], [-1, 1, INT32_MAX]], dtype=I32)  # -5, 2^31-1 are bad
    expect = _conv_reference(_conv_reference(x, w1, bad), w2, bad)
    ones = [torch.ones(c, device=dev) for c in (4, 2)]
    zeros = [torch.zeros(c, device=dev) for c in (4, 2)]
    call = lambda m: _ops().sparse_conv_affine_chain(x.to(dev), [w1.to(dev), w2.to(dev)], m, None, ones, zeros,  # noqa: E731
                                                     [False, False])
    on_cpu_raises_else(dev, lambda: call(bad.to(dev)), r"kernel_map entries must lie in \[-1, N_in = 3\)",
                       lambda out: close(out, expect))
    raises(lambda: call(bad[:2].to(dev)), r"kernel_map must be a submanifold map, \(N, K\) with N = 3")


def case_sparse_max_pool_out_of_range(dev):
    x = torch.tensor([[1.0, -2.0], [3.0, -4.0]], dtype=F64, device=dev)
    nbr = torch.tensor([[0, 7], [-1, 1], [9, -3]], dtype=I32, device=dev)

    def skipped(res):
        out, arg = res
        equal(out, [[1.0, -2.0], [3.0, -4.0], [0.0, 0.0]])
        equal(arg, [[0, 0], [1, 1], [-1, -1]])
    on_cpu_raises_else(dev, lambda: _ops().sparse_max_pool(x, nbr), r"kernel_map entries must lie in \[-1, N_in = 2\)",
                       skipped)
    # backward: kernel_map_t (N_in, K) entries index grad rows; argmax values are only compared
    grad = torch.tensor([[10.0, 20.0], [30.0, 40.0]], dtype=F64, device=dev)
    arg = torch.tensor([[0, 1000], [1, -9]], device=dev)
    nbr_t = torch.tensor([[0, 8], [1, -1]], dtype=I32, device=dev)
    on_cpu_raises_else(dev, lambda: _ops().sparse_max_pool_backward(grad, arg, nbr_t),
                       r"kernel_map_t entries must lie in \[-1, N_out = 2\)",
                       lambda out: equal(out, [[10.0, 0.0], [30.0, 0.0]]))
    good_t = torch.tensor([[0, -1], [1, -1]], dtype=I32, device=dev)
    equal(_ops().sparse_max_pool_backward(grad, arg, good_t), [[10.0, 0.0], [30.0, 0.0]])
    raises(lambda: _ops().sparse_max_pool_backward(grad, arg[:1], good_t), r"argmax must be int64 with the shape of grad")


def case_sparse_dense_rows_outside_grid(dev):
    f = torch.tensor([[1.0], [2.0], [3.0], [4.0]], dtype=F64, device=dev)
    idx = torch.tensor([[0, 1], [1, 0], [0, 5], [-1, 0]], dtype=I32, device=dev)  # rows 2 and 3 outside
    dense = _ops().sparse_to_dense(f, idx, 2, [2])
    equal(dense, [[[0.0, 1.0]], [[2.0, 0.0]]])  # (B, C, S); outside rows skipped
    back = _ops().sparse_from_dense(dense, idx)
    equal(back, [[1.0], [2.0], [0.0], [0.0]])  # outside rows read as zero
    raises(lambda: _ops().sparse_to_dense(f[:3], idx, 2, [2]), r"indices has 4 rows but features has 3")
    raises(lambda: _ops().sparse_to_dense(f, idx, 2, [2, 2]), r"indices must be \(N, 3\) for D = 2")
    raises(lambda: _ops().sparse_from_dense(dense, idx.long()), r"indices must be int32")


# ---------------------------------------------------------------------------------------------------
# voxelization

def case_voxelize_scatter_bad_slots(dev):
    f = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]], dtype=F64, device=dev)
    pv = torch.tensor([0, 5, -3, 1], device=dev)  # voxel 5 >= num_voxels, -3: not stored
    ps = torch.tensor([1, 0, 0, 9], device=dev)  # slot 9 >= max_points_per_voxel
    out = _ops().voxelize_scatter(f, pv, ps, 2, 2)
    expect = torch.zeros(2, 2, 2, dtype=F64)
    expect[0, 1] = torch.tensor([1.0, 2.0])
    equal(out, expect)
    raises(lambda: _ops().voxelize_scatter(f, pv[:3], ps, 2, 2), r"point_voxel must be int64 \(N,\) with N = 4")
    raises(lambda: _ops().voxelize_scatter(f, pv, ps.int(), 2, 2), r"point_slot must be int64")
    raises(lambda: _ops().voxelize_scatter(f, pv, ps, -1, 2), r"num_voxels must be >= 0")
    rng = [0.0, 0.0, 0.0, 1.0, 1.0, 1.0]
    raises(lambda: _ops().voxelize_assign(f, [1.0, 1.0, 1.0], rng, [1, 1, 1], 1, 1, 0), r"points must be \(N, C\) with C >= 3")
    raises(lambda: _ops().voxelize_assign(f.new_zeros(2, 3), [1.0, 1.0, 1.0], rng, [1, 1, 1], 0, 1, 0),
           r"max_points_per_voxel")


# ---------------------------------------------------------------------------------------------------
# SSCATeR delta convolution

def _sites(rows, dev):
    return torch.tensor(rows, dtype=I32, device=dev).view(-1, 2)


def case_sscater_scatter_sites_and_count(dev):
    acc = torch.zeros(3, 3, 1, dtype=F64, device=dev)
    sites = _sites([[100, 100], [-1, 5], [1, 1]], dev)  # far outside, padding, inside
    delta = torch.ones(3, 1, dtype=F64, device=dev)
    w = torch.ones(1, 3, 3, 1, dtype=F64, device=dev)
    # count 99 > rows: clamped to 3. Site (1, 1) reaches every output of the 3 x 3 grid (o = i + 1 - k).
    t = _ops().sscater_scatter_(acc, sites, delta, w, 1, 1, False, None, torch.tensor([99], device=dev))
    equal(acc, torch.ones(3, 3, 1))
    equal(t[:18], torch.full((18,), -1))
    equal(t[18:].sort().values, torch.arange(9))
    # a negative count reads no row
    acc2 = torch.zeros_like(acc)
    t2 = _ops().sscater_scatter_(acc2, sites, delta, w, 1, 1, False, None, torch.tensor([-4], device=dev))
    equal(acc2, torch.zeros(3, 3, 1))
    equal(t2, torch.full((27,), -1))
    raises(lambda: _ops().sscater_scatter_(acc, sites, delta[:2], w, 1, 1, False), r"delta must be \(n = 3, Cin\)")
    raises(lambda: _ops().sscater_scatter_(acc, sites, delta, w, 1, 1, False, None,
                                           torch.tensor([1], dtype=I32, device=dev)), r"count must be an int64 \(1,\)")
    raises(lambda: _ops().sscater_scatter_(acc, sites, delta, w, 1, 1, False,
                                           torch.ones(2, 3, dtype=torch.bool, device=dev)),
           r"out_active must be a contiguous bool \(Ho, Wo\) map")


def case_sscater_finalize_sites_outside(dev):
    acc = torch.ones(3, 3, 1, dtype=F64, device=dev)
    out = torch.zeros_like(acc)
    active = torch.ones(3, 3, dtype=torch.bool, device=dev)
    one, zero = torch.ones(1, dtype=F64, device=dev), torch.zeros(1, dtype=F64, device=dev)
    sites = _sites([[3, 0], [0, -1]], dev)

    def skipped(res):
        changed, _ = res
        equal(changed, [False, False])
        equal(out, torch.zeros(3, 3, 1))
    on_cpu_raises_else(dev, lambda: _ops().sscater_finalize_(acc, out, active, sites, one, zero),
                       r"sites\[0\] = \(3, 0\) lies outside the \(3, 3\) grid", skipped)
    raises(lambda: _ops().sscater_finalize_(acc.half(), out.half(), active, sites, one.half(), zero.half()),
           r"acc must be a contiguous float32/float64")


def case_sscater_dense_finalize_shapes(dev):
    # no site lists: the kernel's only bounds are the shapes, which it checks before indexing with them
    y = torch.randn(2, 3, 3, dtype=F64, device=dev)
    acc, out = torch.zeros(3, 3, 2, dtype=F64, device=dev), torch.zeros(3, 3, 2, dtype=F64, device=dev)
    one, zero = torch.ones(2, dtype=F64, device=dev), torch.zeros(2, dtype=F64, device=dev)
    _ops().sscater_dense_finalize_(y, acc, out, one, zero)
    equal(acc, y.permute(1, 2, 0))
    raises(lambda: _ops().sscater_dense_finalize_(y[:, :2], acc, out, one, zero), r"y must be Double \(C, Ho, Wo\)")
    raises(lambda: _ops().sscater_dense_finalize_(y, acc, out, one, zero, None, torch.zeros(2, 3, 2, dtype=F64,
                                                                                              device=dev)),
           r"out_nchw must be a contiguous")
    raises(lambda: _ops().sscater_dense_finalize_(y, acc, out, one, zero, torch.ones(9, dtype=torch.bool, device=dev)),
           r"active must be a contiguous bool \(Ho, Wo\) map")
    raises(lambda: _ops().sscater_dense_finalize_(y.float(), acc.float(), out.float(), one, zero),
           r"scale and shift must be \(C = 2,\) of acc's dtype")


def case_sscater_cover_and_children_sites_outside(dev):
    cover = torch.zeros(3, 3, dtype=I32, device=dev)
    active = torch.zeros(3, 3, dtype=torch.bool, device=dev)
    stamp = torch.zeros(3, 3, dtype=I32, device=dev)
    far = _sites([[50, 50], [2**30, 0]], dev)
    none = _sites([], dev)
    added, removed, counts = _ops().sscater_cover_update_(cover, active, stamp, 4, far, none, 3, 3, 1, 1)
    equal(counts, [0, 0])
    equal(cover, torch.zeros(3, 3, dtype=I32))
    assert not bool(active.any())
    raises(lambda: _ops().sscater_cover_update_(cover, active, stamp, INT32_MAX, far, none, 3, 3, 1, 1),
           r"value must lie in \[-2\^31, 2\^31 - 1\)")
    # sizes that cannot be meant: the tap lists would overflow int64 (or loop for ages)
    raises(lambda: _ops().sscater_cover_update_(cover, active, stamp, 4, far, none, 2**40, 2**40, 1, 1),
           r"kernel 1099511627776x1099511627776, stride 1 and padding 1: need")
    raises(lambda: _ops().sscater_children_(active, far, none, 3, 3, 2**40, 1), r"stride, padding <= 2\^24")
    a, r = _ops().sscater_children_(active, far, none, 3, 3, 2, 1)
    equal(a, torch.full((18, 2), -1))
    assert not bool(active.any()) and r.shape == (0, 2)


def case_sscater_gather_sites_outside(dev):
    acc = torch.full((3, 3, 1), 7.0, dtype=F64, device=dev)
    inp = torch.ones(3, 3, 1, dtype=F64, device=dev)
    w = torch.ones(1, 3, 3, 1, dtype=F64, device=dev)
    sites = _sites([[9, 9], [-1, -1], [0, 0]], dev)
    _ops().sscater_gather_(acc, inp, w, sites, 1, 1, torch.tensor([99], device=dev))  # count clamped to 3
    expect = torch.full((3, 3, 1), 7.0, dtype=F64)
    expect[0, 0, 0] = 4.0  # the corner's 2 x 2 window of ones
    equal(acc, expect)
    raises(lambda: _ops().sscater_gather_(acc, inp, w, sites.long(), 1, 1), r"sites must be int32 \(n, 2\)")


def case_sscater_touch_value_and_targets(dev):
    acc = torch.ones(2, 2, 1, dtype=F64, device=dev)
    stamp = torch.zeros(2, 2, dtype=I32, device=dev)
    targets = torch.tensor([-5, 100, 3], device=dev)  # only key 3 is a site
    added = _sites([[0, 0]] * 10, dev)  # one site, ten times: listed once
    removed = _sites([[7, 7]], dev)
    # value + 1 = 2^31 - 1 still fits: the largest value accepted
    cand, count = _ops().sscater_touch_(stamp, acc, INT32_MAX - 1, targets, added, removed)
    equal(count, [2])
    assert cand.shape == (4, 2)
    equal(sorted(cand[:2].cpu().tolist()), [[0, 0], [1, 1]])  # key 3 = (1, 1) and (0, 0), once each
    equal(cand[2:], torch.full((2, 2), -1))
    # value + 1 would wrap around int32: before the entry check, the repeated site was listed again at
    # every row and the candidate list (min(R + a + r, Ho * Wo) rows) was written past its end
    stamp.zero_()
    raises(lambda: _ops().sscater_touch_(stamp, acc, INT32_MAX, targets, added, removed),
           r"value must lie in \[-2\^31, 2\^31 - 1\)")
    raises(lambda: _ops().sscater_touch_(stamp, acc, 2**40, targets, added, removed), r"value must lie in")
    raises(lambda: _ops().sscater_touch_(stamp, acc, 4, targets.int(), added, removed), r"targets must be int64")


def case_sscater_finalize_compact_count(dev):
    acc = torch.ones(2, 2, 1, dtype=F64, device=dev)
    active = torch.ones(2, 2, dtype=torch.bool, device=dev)
    stamp = torch.zeros(2, 2, dtype=I32, device=dev)
    one, zero = torch.ones(1, dtype=F64, device=dev), torch.zeros(1, dtype=F64, device=dev)
    cand = _sites([[0, 1], [1, 0]], dev)
    ops = _ops()
    out = torch.zeros_like(acc)
    # count 99 > rows: clamped to 2; both sites change 0 -> 1
    sites, delta, counts = ops.sscater_finalize_compact_(acc, out, active, cand, torch.tensor([99], device=dev),
                                                         stamp, 9, one, zero)
    equal(counts, [2, 2, 2])
    equal(sites.cpu().sort(dim=0).values, [[0, 0], [1, 1]])
    out2 = torch.zeros_like(acc)
    _, _, counts2 = ops.sscater_finalize_compact_(acc, out2, active, cand, torch.tensor([-4], device=dev), stamp, 9,
                                                  one, zero)
    equal(counts2, [0, 0, 0])
    equal(out2, torch.zeros(2, 2, 1))
    bad = _sites([[5, 5], [1, 0]], dev)

    def skipped(res):
        _, _, c = res
        equal(c, [1, 1, 2])  # the row outside is evaluated (counted) but skipped
    on_cpu_raises_else(dev, lambda: ops.sscater_finalize_compact_(acc, torch.zeros_like(acc), active, bad,
                                                                  torch.tensor([2], device=dev), stamp, 9, one, zero),
                       r"lies outside the \(2, 2\) grid", skipped)
    raises(lambda: ops.sscater_finalize_compact_(acc, out, active, cand, torch.tensor([1], dtype=I32, device=dev),
                                                 stamp, 9, one, zero), r"count must be an int64 \(1,\)")
    raises(lambda: ops.sscater_finalize_compact_(acc, out, active, cand, torch.tensor([1], device=dev), stamp, 2**40,
                                                 one, zero), r"status_value must lie in")
    raises(lambda: ops.sscater_finalize_compact_(acc, out, active, cand.long(), torch.tensor([1], device=dev), stamp,
                                                 9, one, zero), r"cand must be int32")


# ---------------------------------------------------------------------------------------------------
# boxes, value flags

def case_boxes_shapes_and_groups(dev):
    box = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]], dtype=F64, device=dev)
    boxes = torch.cat([box, box])
    scores = torch.tensor([0.9, 0.8], dtype=F64, device=dev)
    ops = _ops()
    # groups are only compared: any int64 values
    equal(ops.nms_bev(boxes, scores, torch.tensor([2**62, -7], device=dev), 0.5, -1, -1), [0, 1])
    equal(ops.nms_bev(boxes, scores, torch.tensor([-7, -7], device=dev), 0.5, -1, -1), [0])
    raises(lambda: ops.nms_bev(boxes, scores[:1], None, 0.5, -1, -1), r"scores must be \(N,\) with N = 2")
    raises(lambda: ops.nms_bev(boxes, scores, torch.tensor([0, 0], dtype=I32, device=dev), 0.5, -1, -1),
           r"idxs must be int64")
    raises(lambda: ops.nms_bev(boxes, scores, torch.tensor([0], device=dev), 0.5, -1, -1), r"idxs must be \(N,\)")
    raises(lambda: ops.box_iou_bev(boxes[:, :6], boxes), r"must be \(N, 7\) boxes")
    raises(lambda: ops.box_iou_3d(boxes, boxes.float()), r"a and b must have the same dtype")
    raises(lambda: ops.points_in_boxes(torch.zeros(3, 2, dtype=F64, device=dev), boxes), r"points must be \(P, C >= 3\)")


def case_nms_frames_shapes_and_values(dev):
    ops = _ops()
    box = torch.tensor([[0.0, 0, 0, 2, 2, 2, 0]], dtype=F64, device=dev)
    far = torch.tensor([[50.0, 0, 0, 2, 2, 2, 0]], dtype=F64, device=dev)
    boxes = torch.stack([torch.cat([box, box, far]), torch.cat([far, box, box])])  # (2, 3, 7)
    scores = torch.tensor([[0.9, 0.8, 0.1], [0.2, 0.3, 0.3]], dtype=F64, device=dev)
    keep, count = ops.nms_bev_padded_batched(boxes, scores, 0.5, None, -1, -1)
    equal(keep, [[0, 2, -1], [1, 0, -1]])  # frame 1: a tie (0.3) visits the lower index first
    equal(count, [2, 2])
    keep, count = ops.nms_bev_padded_batched(boxes, scores, 0.5, 0.25, 2, 1)  # threshold, then the caps
    equal(keep, [[0], [1]])
    equal(count, [1, 1])
    keep, count = ops.nms_bev_padded_batched(boxes, scores, 0.5, 0.95, -1, -1)  # no candidate
    equal(count, [0, 0])
    equal(keep, [[-1, -1, -1]] * 2)
    raises(lambda: ops.nms_bev_padded_batched(boxes[0], scores, 0.5, None, -1, -1), r"boxes must be \(B, N, 7\)")
    raises(lambda: ops.nms_bev_padded_batched(boxes, scores[:, :2], 0.5, None, -1, -1),
           r"scores must be \(B, N\) with \(B, N\) = \(2, 3\)")
    raises(lambda: ops.nms_bev_padded_batched(boxes, scores, -1.0, None, -1, -1), r"iou_threshold must be")
    raises(lambda: ops.nms_bev_padded_batched(boxes, scores, 0.5, math.nan, -1, -1), r"score_threshold must be")
    raises(lambda: ops.nms_bev_padded_batched(boxes.long(), scores, 0.5, None, -1, -1), r"boxes must be floating")


def case_value_flags_shapes(dev):
    ops = _ops()
    raises(lambda: ops.value_flags([], [torch.arange(3, device=dev)], [0, 1], [2]), r"lo and hi must have 1 entries")
    raises(lambda: ops.value_flags([torch.arange(3, device=dev)], [], [], []), r"finite\[0\] must be floating")


# ---------------------------------------------------------------------------------------------------
# CPU-only ops: the KITTI matching step, the ray caster

def _kitti_args(**over):
    a = dict(overlaps=torch.tensor([0.9], dtype=F64), overlap_offsets=torch.tensor([0, 1]),
             gt_offsets=torch.tensor([0, 1]), dt_offsets=torch.tensor([0, 1]), ignored_gt=torch.tensor([0]),
             ignored_dt=torch.tensor([0]), dt_scores=torch.tensor([0.5], dtype=F64),
             dt_dontcare=torch.tensor([0.0], dtype=F64), gt_alpha=torch.tensor([0.0], dtype=F64),
             dt_alpha=torch.tensor([0.0], dtype=F64), thresholds=torch.tensor([0.0], dtype=F64), min_overlap=0.7,
             compute_fp=True, compute_aos=False)
    a.update(over)
    return a


def case_kitti_match_tables(dev):
    if dev != "cpu":
        return  # a CPU-only op
    k = _ops().kitti_match
    _, counts = k(**_kitti_args())
    equal(counts, [[1.0, 0.0, 0.0, 0.0]])  # one detection over one gt at 0.9 > 0.7: a true positive
    raises(lambda: k(**_kitti_args(gt_offsets=torch.tensor([0, 2]))), r"gt_offsets must start at 0 and end at 1")
    raises(lambda: k(**_kitti_args(gt_offsets=torch.tensor([0, 1, 1]), dt_offsets=torch.tensor([0, 2, 1]),
                                   overlap_offsets=torch.tensor([0, 1, 1]))), r"dt_offsets must be non-decreasing")
    raises(lambda: k(**_kitti_args(overlaps=torch.tensor([0.9, 0.1], dtype=F64),
                                   overlap_offsets=torch.tensor([0, 2]))), r"frame 0 has 1 detections and 1 gts but 2")
    raises(lambda: k(**_kitti_args(ignored_dt=torch.tensor([3]))), r"ignored_dt values must be -1, 0 or 1, got 3")
    raises(lambda: k(**_kitti_args(dt_offsets=torch.tensor([0.0, 1.0]))), r"dt_offsets must be an integer tensor")
    raises(lambda: k(**_kitti_args(gt_alpha=torch.zeros(2, dtype=F64))), r"gt_alpha must have 1 entries")


def _raycast_args(**over):
    z = lambda *s: torch.zeros(*s, dtype=F64)  # noqa: E731
    a = dict(origins=z(2, 3), dirs=torch.tensor([[1.0, 0, 0], [0, 1.0, 0]], dtype=F64), times=z(2),
             origin_samples=z(1, 3), ground_plane=torch.tensor([-1.7, 0.0, 0.0], dtype=F64), wave_amp=z(0),
             wave_k=z(0, 2), wave_phase=z(0), box_center=torch.tensor([[5.0, 0, 0]], dtype=F64),
             box_half=torch.ones(1, 3, dtype=F64), box_yaw=z(1), box_velocity=z(1, 3), box_yaw_rate=z(1),
             box_reflectivity=torch.full((1,), 0.5, dtype=F64), box_kind=torch.tensor([2], dtype=torch.uint8),
             box_object=torch.tensor([0], dtype=I32), cyl_center_xy=z(0, 2), cyl_z_min=z(0), cyl_z_max=z(0),
             cyl_radius=z(0), cyl_reflectivity=z(0), cyl_kind=torch.zeros(0, dtype=torch.uint8), ell_center=z(0, 3),
             ell_radii=z(0, 3), ell_mean_free_path=z(0), ell_reflectivity=z(0), max_distance=50.0, foliage_key=1,
             num_objects=1, ground_iterations=3, ground_tolerance=1e-4)
    a.update(over)
    return a


def case_raycast_object_table(dev):
    if dev != "cpu":
        return  # a CPU-only op
    rc = _ops().raycast_scene
    distance, _, obj, _, _, rays, visible = rc(**_raycast_args())
    close(distance, [4.0, math.inf], 1e-9)  # the box's face at x = 4; the other ray misses everything
    equal(obj, [0, -1])
    equal(visible, [1])
    raises(lambda: rc(**_raycast_args(num_objects=0)), r"box_object\[0\] = 0 but num_objects = 0")
    raises(lambda: rc(**_raycast_args(num_objects=-1)), r"num_objects must be >= 0")
    raises(lambda: rc(**_raycast_args(box_object=torch.tensor([0, 0], dtype=I32))),
           r"box_object must have size 1 in dimension 0")
    raises(lambda: rc(**_raycast_args(dirs=torch.zeros(3, 3, dtype=F64))), r"dirs must have size 2 in dimension 0")


# ---------------------------------------------------------------------------------------------------
# pillar_decorate (csrc/cpu/pillar_stream_kernel.cpp): counts are clamped to [0, N]

def case_pillar_decorate_counts(dev):
    raw = torch.tensor([[[1.0, 2, 3, 4], [3, 4, 5, 6]]], dtype=F64, device=dev)
    coords = torch.zeros(1, 3, dtype=I32, device=dev)
    out = _ops().pillar_decorate(raw, torch.tensor([7], dtype=I32, device=dev), coords, [1.0, 1.0], [0.0, 0.0])
    # 7 > N = 2: both points, mean (2, 3, 4), centre (0.5, 0.5)
    equal(out, [[[1.0, 2, 3, 4, -1, -1, -1, 0.5, 1.5], [3, 4, 5, 6, 1, 1, 1, 2.5, 3.5]]])
    out = _ops().pillar_decorate(raw, torch.tensor([-3], dtype=I32, device=dev), coords, [1.0, 1.0], [0.0, 0.0])
    equal(out, torch.zeros(1, 2, 9))


CASES = {name[len("case_"):]: fn for name, fn in sorted(globals().items()) if name.startswith("case_")}


def _run(dev: str) -> None:
    from lidarops import extension

    extension.load()
    for name, fn in CASES.items():
        print(f"RUN {name}", flush=True)
        try:
            fn(dev)
            print(f"PASS {name}", flush=True)
        except Exception:  # report and go on: one line per case
            msg = traceback.format_exc().strip().splitlines()
            print(f"FAIL {name}: {' | '.join(msg[-3:])}", flush=True)
    print("DONE", flush=True)


# ---------------------------------------------------------------------------------------------------
# the test: every case, in one subprocess per device

def test_registered_ops_reject_or_skip_bad_values(device):
    env = dict(os.environ, OMP_NUM_THREADS="2")
    proc = subprocess.run([sys.executable, __file__, device], capture_output=True, text=True, timeout=300, env=env)
    lines = proc.stdout.splitlines()
    ran = [ln[4:] for ln in lines if ln.startswith("RUN ")]
    if proc.returncode != 0 or "DONE" not in lines:
        last = ran[-1] if ran else "(before the first case)"
        raise AssertionError(f"the case subprocess died (exit code {proc.returncode}) during case {last!r}\n"
                             f"stderr tail:\n{proc.stderr[-3000:]}")
    failures = [ln for ln in lines if ln.startswith("FAIL ")]
    assert not failures, "\n".join(failures)
    assert len([ln for ln in lines if ln.startswith("PASS ")]) == len(CASES)


if __name__ == "__main__":
    _run(sys.argv[1] if len(sys.argv) > 1 else "cpu")
