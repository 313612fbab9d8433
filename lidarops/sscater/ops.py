"""Validated wrappers of the SSCATeR delta-convolution ops (``torch.ops.lidarops.sscater_*``, schemas and
semantics in csrc/ops/sscater.cpp) and their pure-PyTorch references (``_<op>_reference``, used by the
tests).

The ops update their state arguments in place (the trailing ``_``): ``acc (Tensor[Ho, Wo, Cout])`` holds
a layer's pre-activation sums, ``out (Tensor[Ho, Wo, C])`` its outputs, ``active (Tensor[Ho, Wo] bool)``
its active sites, ``stamp (Tensor[Ho, Wo] int32)`` the step that last touched each site. Site lists are
int32 ``(n, 2)`` of ``(y, x)``; a row with a negative coordinate is padding. Weights are
``(Cout, kh, kw, Cin)``. Regular convolutions reach output ``o`` from input ``i`` through tap ``k`` where
``o * stride - padding + k = i``; transposed ones where ``o = i * stride - padding + k``. float32 and
float64. Not differentiable (SSCATeR is an inference-time method). The wrappers check types, shapes,
dtypes and devices (``ValueError`` naming the argument); the kernels check the values they index with.
:class:`lidarops.sscater.delta.DeltaBackbone` calls the registered ops directly (its inputs are built
right, and each layer step must not synchronise with the host).
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from lidarops import extension
from lidarops.ops.validation import check_same_device, check_tensor, describe

extension.load()

__all__ = ["scatter_", "finalize_", "cover_update_", "children_", "gather_", "touch_", "finalize_compact_",
           "dense_finalize_"]

_FLOATS = (torch.float32, torch.float64)


def _check_grid(t, name: str, dims: int, dtype=None) -> None:
    check_tensor(t, name)
    if t.dim() != dims:
        raise ValueError(f"{name} must have {dims} dimensions, got {describe(t)}")
    if dtype is None and t.dtype not in _FLOATS:
        raise ValueError(f"{name} must be float32 or float64, got {describe(t)}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name} must be {dtype}, got {describe(t)}")
    extension.check_device(t, name)


def _check_sites(t, name: str) -> None:
    check_tensor(t, name)
    if t.dim() != 2 or t.shape[1] != 2 or t.dtype != torch.int32:
        raise ValueError(f"{name} must be an int32 (n, 2) list of (y, x) sites, got {describe(t)}")


def _check_count(count, rows_of: str) -> None:
    if count is not None:
        check_tensor(count, "count")
        if count.numel() != 1 or count.dtype != torch.int64:
            raise ValueError(f"count must be an int64 (1,) tensor (rows of {rows_of} to use), got {describe(count)}")


def _check_geometry(kh, kw, stride, padding) -> None:
    for name, v, lo in (("kh", kh, 1), ("kw", kw, 1), ("stride", stride, 1), ("padding", padding, 0)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")


def _check_weight(weight, acc, cin: int, what: str) -> None:
    _check_grid(weight, "weight", 4)
    if weight.dtype != acc.dtype or weight.shape[0] != acc.shape[2] or weight.shape[3] != cin:
        raise ValueError(f"weight must be {acc.dtype} (Cout = {acc.shape[2]}, kh, kw, Cin = {cin}) for acc "
                         f"{describe(acc)} and {what}, got {describe(weight)}")


def _check_channels(scale, shift, acc) -> None:
    for name, t in (("scale", scale), ("shift", shift)):
        check_tensor(t, name)
        if t.shape != (acc.shape[2],) or t.dtype != acc.dtype:
            raise ValueError(f"{name} must be {acc.dtype} ({acc.shape[2]},), got {describe(t)}")


# ---- wrappers -------------------------------------------------------------------------------------

def scatter_(acc: Tensor, sites: Tensor, delta: Tensor, weight: Tensor, stride: int = 1, padding: int = 0,
             transposed: bool = False, out_active: Optional[Tensor] = None, count: Optional[Tensor] = None,
             channel_sparse: float = 0.85) -> Tensor:
    """Add to ``acc`` the convolution of a zero image holding ``delta`` at ``sites``.

    Args:
        acc (Tensor[Ho, Wo, Cout] float): updated in place.
        sites (Tensor[n, 2] int32): input sites (padding rows: a negative coordinate).
        delta (Tensor[n, Cin]): the change of the input at each site, acc's dtype.
        weight (Tensor[Cout, kh, kw, Cin]): acc's dtype.
        out_active (Tensor[Ho, Wo] bool, optional): update only the active outputs.
        count (Tensor[1] int64, optional): use only the first count[0] rows of ``sites``.
        channel_sparse (float): the share of exactly-zero delta values from which each row's nonzero channels
            are multiplied alone instead of the whole delta in one GEMM per tap (0: always, above 1: never); the
            results differ only in the order of the float sums. CUDA decides on the device (no host wait).

    Returns:
        Tensor[n * kh * kw] int64: the output key ``oy * Wo + ox`` reached by row i through tap (ky, kx)
        at entry ``i * kh * kw + ky * kw + kx``, -1 where none (outside the grid, inactive, padding).
    """
    _check_grid(acc, "acc", 3)
    _check_sites(sites, "sites")
    _check_grid(delta, "delta", 2)
    if delta.shape[0] != sites.shape[0] or delta.dtype != acc.dtype:
        raise ValueError(f"delta must be {acc.dtype} ({sites.shape[0]}, Cin), one row per site, got {describe(delta)}")
    _check_weight(weight, acc, delta.shape[1], "delta")
    _check_geometry(weight.shape[1], weight.shape[2], stride, padding)
    if out_active is not None:
        _check_grid(out_active, "out_active", 2, torch.bool)
        if out_active.shape != acc.shape[:2]:
            raise ValueError(f"out_active must be ({acc.shape[0]}, {acc.shape[1]}), got {describe(out_active)}")
    _check_count(count, "sites")
    named = [("acc", acc), ("sites", sites), ("delta", delta), ("weight", weight)]
    check_same_device(named + [(n, t) for n, t in (("out_active", out_active), ("count", count)) if t is not None])
    if isinstance(channel_sparse, bool) or not isinstance(channel_sparse, (int, float)) or \
            channel_sparse != channel_sparse:
        raise ValueError(f"channel_sparse must be a number (a share of zero delta values), got {channel_sparse!r}")
    return torch.ops.lidarops.sscater_scatter_(acc, sites, delta, weight, stride, padding, bool(transposed),
                                               out_active, count, float(channel_sparse))


def finalize_(acc: Tensor, out: Tensor, active: Tensor, sites: Tensor, scale: Tensor,
              shift: Tensor) -> tuple[Tensor, Tensor]:
    """Set ``out`` at ``sites`` (unique, inside the grid) to ``active ? relu(acc * scale + shift) : 0``.

    Returns:
        (changed (Tensor[m] bool), delta (Tensor[m, C])): whether a site's value changed in some channel,
        and the new value minus the previous one.
    """
    _check_grid(acc, "acc", 3)
    _check_grid(out, "out", 3)
    if out.shape != acc.shape or out.dtype != acc.dtype:
        raise ValueError(f"out must be {acc.dtype} {tuple(acc.shape)} like acc, got {describe(out)}")
    _check_grid(active, "active", 2, torch.bool)
    if active.shape != acc.shape[:2]:
        raise ValueError(f"active must be ({acc.shape[0]}, {acc.shape[1]}), got {describe(active)}")
    _check_sites(sites, "sites")
    _check_channels(scale, shift, acc)
    check_same_device([("acc", acc), ("out", out), ("active", active), ("sites", sites), ("scale", scale),
                       ("shift", shift)])
    return torch.ops.lidarops.sscater_finalize_(acc, out, active, sites, scale, shift)


def cover_update_(cover: Tensor, active: Tensor, stamp: Tensor, value: int, added: Tensor, removed: Tensor,
                  kh: int, kw: int, stride: int, padding: int) -> tuple[Tensor, Tensor, Tensor]:
    """A strided layer's active outputs after input sites were ``added`` / ``removed``.

    ``cover (Tensor[Ho, Wo] int32)`` counts the active inputs under each output's kernel; every tap of an
    added (removed) input adds (removes) one. ``active (Tensor[Ho, Wo] bool)`` flips where the cover
    crosses zero; ``stamp (Tensor[Ho, Wo] int32)`` is raised to ``value`` at the touched outputs.

    Returns:
        (added, removed, counts): the outputs that became active / inactive, each
        ``((a + r) * kh * kw, 2)`` int32 filled from the first row (then ``(-1, -1)``), and
        ``counts (Tensor[2] int64)`` of their used rows.
    """
    _check_grid(cover, "cover", 2, torch.int32)
    _check_grid(active, "active", 2, torch.bool)
    _check_grid(stamp, "stamp", 2, torch.int32)
    for name, t in (("active", active), ("stamp", stamp)):
        if t.shape != cover.shape:
            raise ValueError(f"{name} must be {tuple(cover.shape)} like cover, got {describe(t)}")
    _check_sites(added, "added")
    _check_sites(removed, "removed")
    _check_geometry(kh, kw, stride, padding)
    check_same_device([("cover", cover), ("active", active), ("stamp", stamp), ("added", added),
                       ("removed", removed)])
    return torch.ops.lidarops.sscater_cover_update_(cover, active, stamp, value, added, removed, kh, kw, stride,
                                                    padding)


def children_(active: Tensor, added: Tensor, removed: Tensor, kh: int, kw: int, stride: int,
              padding: int) -> tuple[Tensor, Tensor]:
    """A transposed layer's active outputs: the children (every tap's output) of the ``added`` input
    sites become active, then those of the ``removed`` ones inactive.

    Returns:
        (added, removed): the children, ``(a * kh * kw, 2)`` and ``(r * kh * kw, 2)`` int32, row
        ``i * kh * kw + k`` for tap k of input row i, ``(-1, -1)`` where outside the grid or padding.
    """
    _check_grid(active, "active", 2, torch.bool)
    _check_sites(added, "added")
    _check_sites(removed, "removed")
    _check_geometry(kh, kw, stride, padding)
    check_same_device([("active", active), ("added", added), ("removed", removed)])
    return torch.ops.lidarops.sscater_children_(active, added, removed, kh, kw, stride, padding)


def gather_(acc: Tensor, input: Tensor, weight: Tensor, sites: Tensor, stride: int = 1, padding: int = 0,
            count: Optional[Tensor] = None) -> None:
    """Set ``acc`` at ``sites`` of the output grid to the full convolution (no bias) of ``input
    (Tensor[Hi, Wi, Cin])`` there (zero outside the input grid); with ``count``, only the first count[0]
    rows of ``sites`` are used."""
    _check_grid(acc, "acc", 3)
    _check_grid(input, "input", 3)
    if input.dtype != acc.dtype:
        raise ValueError(f"input must be {acc.dtype} like acc, got {describe(input)}")
    _check_weight(weight, acc, input.shape[2], "input")
    _check_sites(sites, "sites")
    _check_geometry(weight.shape[1], weight.shape[2], stride, padding)
    _check_count(count, "sites")
    check_same_device([("acc", acc), ("input", input), ("weight", weight), ("sites", sites)]
                      + ([("count", count)] if count is not None else []))
    torch.ops.lidarops.sscater_gather_(acc, input, weight, sites, stride, padding, count)


def touch_(stamp: Tensor, acc: Tensor, value: int, targets: Tensor, added: Tensor,
           removed: Tensor) -> tuple[Tensor, Tensor]:
    """The sites to re-evaluate, each once: the reached keys ``targets (Tensor[R] int64)`` (-1: none;
    stamp raised to ``value``) and the status changes ``added`` / ``removed`` (stamp raised to
    ``value + 1``); ``acc`` is zeroed at the removed sites. A site is listed when its stamp was below
    ``value``.

    Returns:
        (cand (Tensor[min(R + a + r, Ho * Wo), 2] int32), count (Tensor[1] int64)): the sites in the
        order met (targets, added, removed), then ``(-1, -1)`` rows; count of the used rows.
    """
    _check_grid(stamp, "stamp", 2, torch.int32)
    _check_grid(acc, "acc", 3)
    if acc.shape[:2] != stamp.shape:
        raise ValueError(f"acc must be ({stamp.shape[0]}, {stamp.shape[1]}, C) like stamp, got {describe(acc)}")
    check_tensor(targets, "targets")
    if targets.dim() != 1 or targets.dtype != torch.int64:
        raise ValueError(f"targets must be an int64 (R,) tensor of output keys, got {describe(targets)}")
    _check_sites(added, "added")
    _check_sites(removed, "removed")
    check_same_device([("stamp", stamp), ("acc", acc), ("targets", targets), ("added", added), ("removed", removed)])
    return torch.ops.lidarops.sscater_touch_(stamp, acc, value, targets, added, removed)


def finalize_compact_(acc: Tensor, out: Tensor, active: Tensor, cand: Tensor, count: Tensor, stamp: Tensor,
                      status_value: int, scale: Tensor, shift: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`finalize_` over the first ``count[0]`` rows of ``cand``, compacted.

    Returns:
        (sites, delta, counts): the sites whose value changed ``(rows of cand, 2)`` int32 in their first
        rows (then ``(-1, -1)``), their deltas ``(rows of cand, C)`` (padding rows unspecified), and
        ``counts (Tensor[3] int64)``: changed sites, sites changed or with a status change
        (``stamp == status_value``), sites evaluated.
    """
    _check_grid(acc, "acc", 3)
    _check_grid(out, "out", 3)
    if out.shape != acc.shape or out.dtype != acc.dtype:
        raise ValueError(f"out must be {acc.dtype} {tuple(acc.shape)} like acc, got {describe(out)}")
    _check_grid(active, "active", 2, torch.bool)
    _check_grid(stamp, "stamp", 2, torch.int32)
    for name, t in (("active", active), ("stamp", stamp)):
        if t.shape != acc.shape[:2]:
            raise ValueError(f"{name} must be ({acc.shape[0]}, {acc.shape[1]}), got {describe(t)}")
    _check_sites(cand, "cand")
    _check_count(count, "cand")
    _check_channels(scale, shift, acc)
    check_same_device([("acc", acc), ("out", out), ("active", active), ("cand", cand), ("count", count),
                       ("stamp", stamp), ("scale", scale), ("shift", shift)])
    return torch.ops.lidarops.sscater_finalize_compact_(acc, out, active, cand, count, stamp, status_value, scale,
                                                        shift)


def dense_finalize_(y: Tensor, acc: Tensor, out: Tensor, scale: Tensor, shift: Tensor,
                    active: Optional[Tensor] = None, out_nchw: Optional[Tensor] = None) -> None:
    """A layer's state from a dense convolution of its whole input (a full recomputation): ``acc`` (contiguous)
    = ``active ? y : 0`` and ``out`` (any strides) = ``active ? relu(y * scale + shift) : 0`` at every site,
    in one pass over ``y (Tensor[C, Ho, Wo])`` (any strides: the convolution's NCHW or channels-last output).
    ``active`` None: every site. ``out_nchw (Tensor[C, Ho, Wo])`` (contiguous), when given, gets ``out``'s
    values too: the next layer's input for a convolution in NCHW. The ReLU is ``v > 0 ? v : 0``, as in
    :func:`finalize_`: a NaN gives 0 in ``out`` and stays in ``acc``, where the state check looks."""
    _check_grid(acc, "acc", 3)
    if not acc.is_contiguous():
        raise ValueError(f"acc must be contiguous, got {describe(acc)}")
    Ho, Wo, C = acc.shape
    _check_grid(y, "y", 3)
    if tuple(y.shape) != (C, Ho, Wo) or y.dtype != acc.dtype:
        raise ValueError(f"y must be {acc.dtype} (C, Ho, Wo) = {(C, Ho, Wo)}, got {describe(y)}")
    _check_grid(out, "out", 3)
    if out.shape != acc.shape or out.dtype != acc.dtype:
        raise ValueError(f"out must be {acc.dtype} {tuple(acc.shape)} like acc, got {describe(out)}")
    _check_channels(scale, shift, acc)
    named = [("y", y), ("acc", acc), ("out", out), ("scale", scale), ("shift", shift)]
    if active is not None:
        _check_grid(active, "active", 2, torch.bool)
        if active.shape != acc.shape[:2]:
            raise ValueError(f"active must be ({Ho}, {Wo}), got {describe(active)}")
        named.append(("active", active))
    if out_nchw is not None:
        _check_grid(out_nchw, "out_nchw", 3)
        if tuple(out_nchw.shape) != (C, Ho, Wo) or out_nchw.dtype != acc.dtype or not out_nchw.is_contiguous():
            raise ValueError(f"out_nchw must be a contiguous {acc.dtype} (C, Ho, Wo) = {(C, Ho, Wo)} tensor, "
                             f"got {describe(out_nchw)}")
        named.append(("out_nchw", out_nchw))
    check_same_device(named)
    torch.ops.lidarops.sscater_dense_finalize_(y, acc, out, scale, shift, active, out_nchw)


# ---- pure-PyTorch references (float64 arithmetic; they return new tensors, inputs are not changed) -----

def _reach_reference(i: int, k: int, stride: int, padding: int, n_out: int, transposed: bool) -> int:
    if transposed:
        o = i * stride - padding + k
    else:
        t = i + padding - k
        if t < 0 or t % stride:
            return -1
        o = t // stride
    return o if 0 <= o < n_out else -1


def _used_rows(rows: int, count: Optional[Tensor]) -> int:
    return rows if count is None else min(max(int(count.reshape(-1)[0]), 0), rows)


def _site(sites: Tensor, i: int) -> tuple[int, int]:
    y, x = sites[i].tolist()
    return int(y), int(x)


def _taps_reference(sites: Tensor, rows: int, kh: int, kw: int, stride: int, padding: int, Ho: int, Wo: int,
                    transposed: bool):
    """(row i, tap k = ky * kw + kx, oy, ox) of every output inside the grid that the first ``rows``
    rows of ``sites`` reach (padding rows skipped)."""
    for i in range(rows):
        y, x = _site(sites, i)
        if y < 0 or x < 0:
            continue
        for k in range(kh * kw):
            oy = _reach_reference(y, k // kw, stride, padding, Ho, transposed)
            ox = _reach_reference(x, k % kw, stride, padding, Wo, transposed)
            if oy >= 0 and ox >= 0:
                yield i, k, oy, ox


def _scatter_reference(acc, sites, delta, weight, stride=1, padding=0, transposed=False, out_active=None,
                       count=None) -> tuple[Tensor, Tensor]:
    """(acc after :func:`scatter_` in float64, reached keys)."""
    acc = acc.detach().cpu().double().clone()
    sites, delta, weight = sites.cpu(), delta.cpu().double(), weight.cpu().double()
    Ho, Wo = acc.shape[:2]
    _, kh, kw, _ = weight.shape
    reached = torch.full((sites.shape[0] * kh * kw,), -1, dtype=torch.int64)
    for i, k, oy, ox in _taps_reference(sites, _used_rows(sites.shape[0], count), kh, kw, stride, padding, Ho, Wo,
                                        transposed):
        if out_active is None or bool(out_active[oy, ox]):
            acc[oy, ox] += weight[:, k // kw, k % kw, :] @ delta[i]
            reached[i * kh * kw + k] = oy * Wo + ox
    return acc, reached


def _finalize_values(acc, active, scale, shift, ys, xs) -> Tensor:
    acc, scale, shift = acc.cpu().double(), scale.cpu().double(), shift.cpu().double()
    v = acc[ys, xs] * scale + shift
    zero = torch.zeros((), dtype=torch.float64)
    return torch.where(active.cpu()[ys, xs][:, None] & (v > 0), v, zero)  # as the kernels: NaN gives 0


def _finalize_reference(acc, out, active, sites, scale, shift) -> tuple[Tensor, Tensor, Tensor]:
    """(out after :func:`finalize_` in float64, changed, delta)."""
    sites = sites.cpu().long()
    ys, xs = sites[:, 0], sites[:, 1]
    new_out = out.detach().cpu().double().clone()
    new = _finalize_values(acc, active, scale, shift, ys, xs)
    old = new_out[ys, xs]
    new_out[ys, xs] = new
    return new_out, (new != old).any(1), new - old


def _dense_finalize_reference(y, scale, shift, active=None) -> tuple[Tensor, Tensor]:
    """(acc, out) after :func:`dense_finalize_`, (Ho, Wo, C) float64."""
    zero = torch.zeros((), dtype=torch.float64)
    acc = y.detach().cpu().double().permute(1, 2, 0)
    on = torch.ones(acc.shape[:2], dtype=torch.bool) if active is None else active.cpu()
    acc = torch.where(on[..., None], acc, zero)  # an inactive site's y is not read (a NaN there stays out)
    v = acc * scale.cpu().double() + shift.cpu().double()
    out = torch.where(on[..., None] & (v > 0), v, zero)  # max(v, 0) as the kernels take it: NaN gives 0
    return acc.contiguous(), out.contiguous()


def _cover_update_reference(cover, active, stamp, value, added, removed, kh, kw, stride, padding):
    """(cover, active, stamp after :func:`cover_update_`, set of added sites, set of removed sites)."""
    cover, active, stamp = cover.cpu().clone(), active.cpu().clone(), stamp.cpu().clone()
    Ho, Wo = cover.shape
    touched = []
    for sites, step in ((added.cpu(), 1), (removed.cpu(), -1)):
        for _, _, oy, ox in _taps_reference(sites, sites.shape[0], kh, kw, stride, padding, Ho, Wo, False):
            cover[oy, ox] += step
            if int(stamp[oy, ox]) < value:
                stamp[oy, ox] = value
                touched.append((oy, ox))
    on, off = set(), set()
    for o in touched:
        after = bool(cover[o] > 0)
        if after != bool(active[o]):
            active[o] = after
            (on if after else off).add(o)
    return cover, active, stamp, on, off


def _children_reference(active, added, removed, kh, kw, stride, padding) -> tuple[Tensor, Tensor, Tensor]:
    """(active after :func:`children_`, added children, removed children)."""
    active = active.cpu().clone()
    Ho, Wo = active.shape
    lists = []
    for sites, on in ((added.cpu(), True), (removed.cpu(), False)):
        kids = torch.full((sites.shape[0] * kh * kw, 2), -1, dtype=torch.int32)
        for i, k, oy, ox in _taps_reference(sites, sites.shape[0], kh, kw, stride, padding, Ho, Wo, True):
            active[oy, ox] = on
            kids[i * kh * kw + k] = torch.tensor([oy, ox], dtype=torch.int32)
        lists.append(kids)
    return active, lists[0], lists[1]


def _gather_reference(acc, input, weight, sites, stride=1, padding=0, count=None) -> Tensor:
    """acc after :func:`gather_`, in float64."""
    acc = acc.detach().cpu().double().clone()
    input, weight, sites = input.cpu().double(), weight.cpu().double(), sites.cpu()
    Ho, Wo = acc.shape[:2]
    Hi, Wi = input.shape[:2]
    _, kh, kw, _ = weight.shape
    for i in range(_used_rows(sites.shape[0], count)):
        y, x = _site(sites, i)
        if not (0 <= y < Ho and 0 <= x < Wo):
            continue
        s = torch.zeros(acc.shape[2], dtype=torch.float64)
        for ky in range(kh):
            for kx in range(kw):
                iy, ix = y * stride - padding + ky, x * stride - padding + kx
                if 0 <= iy < Hi and 0 <= ix < Wi:
                    s += weight[:, ky, kx, :] @ input[iy, ix]
        acc[y, x] = s
    return acc


def _touch_reference(stamp, acc, value, targets, added, removed):
    """(stamp, acc after :func:`touch_` (float64), candidate sites in order as a list of (y, x))."""
    stamp, acc = stamp.cpu().clone(), acc.detach().cpu().double().clone()
    Ho, Wo = stamp.shape
    cand = []

    def mark(y, x, v):
        old = int(stamp[y, x])
        if old < v:
            stamp[y, x] = v
        if old < value:
            cand.append((y, x))

    for key in targets.cpu().tolist():
        if 0 <= key < Ho * Wo:
            mark(key // Wo, key % Wo, value)
    for sites, zero in ((added.cpu(), False), (removed.cpu(), True)):
        for i in range(sites.shape[0]):
            y, x = _site(sites, i)
            if 0 <= y < Ho and 0 <= x < Wo:
                mark(y, x, value + 1)
                if zero:
                    acc[y, x] = 0
    return stamp, acc, cand


def _finalize_compact_reference(acc, out, active, cand, count, stamp, status_value, scale, shift):
    """(out after :func:`finalize_compact_` (float64), changed sites in order as a list of (y, x), their
    deltas (Tensor[n, C] float64), counts [changed, changed or status change, evaluated])."""
    m = _used_rows(cand.shape[0], count)
    used = cand.cpu()[:m]
    new_out, changed, delta = _finalize_reference(acc, out, active, used, scale, shift)
    status = stamp.cpu()[used[:, 0].long(), used[:, 1].long()] == status_value
    sites = [tuple(s) for s in used[changed].tolist()]
    return new_out, sites, delta[changed], [len(sites), int((changed | status).sum()), m]
