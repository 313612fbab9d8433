"""Sparse convolution: kernel maps, gather-GEMM-scatter convolution and max pooling.

Semantics (checked by tests/test_sparse_*.py against dense PyTorch on ``x.dense()``):

- ``"conv"`` (regular): ``conv(x, w).dense() == F.convNd(x.dense(), w')`` read at the output sites,
  which are every site of the output grid whose receptive field holds an input site.
- ``"subm"`` (submanifold): the dense convolution with ``padding = dilation * (k // 2)`` and stride 1,
  read at the input sites; the output has exactly the input's sites.
- ``"transposed"``: ``F.conv_transposeNd(x.dense(), w'')`` read at every site some input reaches.
- ``"inverse"``: back to the input sites of the strided convolution registered under the same
  ``indice_key``: ``F.conv_transposeNd`` with that convolution's stride/padding/dilation, no kernel
  flip, and ``output_padding`` chosen to land exactly on its input grid.

with ``w' = w.permute(0, D + 1, 1, ..., D)`` (``[Cout, Cin, *k]``) and ``w'' = w.permute(D + 1, 0, 1,
..., D)`` (``[Cin, Cout, *k]``) for weights in spconv 2.x's layout ``w[Cout, *kernel, Cin]``.
"""
from __future__ import annotations

import contextlib
import math
import weakref
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from lidarops import extension
from lidarops.ops.validation import check_tensor, describe, run_value_checks, value_checks_enabled
from lidarops.sparse.tensor import KernelMap, SparseConvTensor, check_sites, mark_sites_checked, sites_checked

extension.load()
from lidarops.sparse import _registrations  # noqa: E402,F401  (fake kernels and autograd)

_compiling = torch.compiler.is_compiling

__all__ = [
    "conv_output_shape", "conv_transpose_output_shape", "conv_out_indices", "kernel_map", "build_kernel_map",
    "sparse_conv", "conv", "max_pool", "norm_affine", "CONV_ALGOS",
]

_METHODS = {"auto": 0, "dense": 1, "hash": 2}
#: The convolution's kernel choices (``algo=``), CUDA tuning that gives the same sums in the dtype's
#: precision: ``"auto"`` (the library's choice per layer), ``"mma_sync"`` (tensor-core layers on mma.sync,
#: never Hopper's wgmma), ``"wgmma_2blocks"`` / ``"wgmma_3blocks"`` (Hopper TF32 layers with Cout > 64:
#: two or three wgmma blocks per multiprocessor, whatever the layer's size) and ``"3xtf32"``
#: (experimental: float32 without TF32 on the tensor cores as three TF32 products, about 3.5x the error
#: of the FFMA tiles; an infinite input may give NaN). Where a choice does not apply (CPU, other GPUs,
#: other dtypes), it is ``"auto"``.
CONV_ALGOS = ("auto", "mma_sync", "wgmma_2blocks", "wgmma_3blocks", "3xtf32")
_KINDS = ("subm", "conv", "transposed", "inverse")


def _ntuple(v, ndim: int, name: str, minimum: int) -> tuple:
    if type(v) is tuple and len(v) == ndim:  # what the layers pass on every call (a loop: host time per layer)
        for e in v:
            if type(e) is not int or e < minimum:
                break
        else:
            return v
    if isinstance(v, bool):
        raise ValueError(f"{name} must be an int or a sequence of {ndim} ints, got {v!r}")
    if isinstance(v, int):
        t = (v,) * ndim
    else:
        try:
            t = tuple(int(e) for e in v)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be an int or a sequence of {ndim} ints, got {v!r}") from None
        if any(isinstance(e, bool) or (isinstance(e, float) and not float(e).is_integer()) for e in v):
            raise ValueError(f"{name} must hold ints, got {v!r}")
    if len(t) != ndim:
        raise ValueError(f"{name} must have {ndim} entries (one per spatial dimension), got {v!r}")
    if any(e < minimum for e in t):
        raise ValueError(f"{name} entries must be >= {minimum}, got {v!r}")
    return t


def _method(method: str) -> int:
    if method not in _METHODS:
        raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    return _METHODS[method]


def _conv_algo(algo: str) -> str:
    if not isinstance(algo, str) or algo not in CONV_ALGOS:
        raise ValueError(f"algo must be one of {CONV_ALGOS}, got {algo!r}")
    return algo


def conv_output_shape(spatial_shape: Sequence[int], kernel_size, stride=1, padding=0, dilation=1) -> tuple:
    """Output grid of a regular convolution (PyTorch's and spconv's formula)."""
    D = len(spatial_shape)
    k, s = _ntuple(kernel_size, D, "kernel_size", 1), _ntuple(stride, D, "stride", 1)
    p, d = _ntuple(padding, D, "padding", 0), _ntuple(dilation, D, "dilation", 1)
    out = tuple((n + 2 * p[i] - d[i] * (k[i] - 1) - 1) // s[i] + 1 for i, n in enumerate(spatial_shape))
    if any(o < 1 for o in out):
        raise ValueError(f"the convolution (kernel {k}, stride {s}, padding {p}, dilation {d}) leaves no output "
                         f"site on the grid {list(spatial_shape)}: output grid {list(out)}")
    return out


def conv_transpose_output_shape(spatial_shape: Sequence[int], kernel_size, stride=1, padding=0, dilation=1,
                                output_padding=0) -> tuple:
    """Output grid of a transposed convolution (PyTorch's formula, ``conv_transposeNd``)."""
    D = len(spatial_shape)
    k, s = _ntuple(kernel_size, D, "kernel_size", 1), _ntuple(stride, D, "stride", 1)
    p, d = _ntuple(padding, D, "padding", 0), _ntuple(dilation, D, "dilation", 1)
    op = _ntuple(output_padding, D, "output_padding", 0)
    if any(op[i] >= max(s[i], d[i]) for i in range(D)):
        raise ValueError(f"output_padding must be smaller than stride or dilation, got output_padding {op}, "
                         f"stride {s}, dilation {d}")
    out = tuple((n - 1) * s[i] - 2 * p[i] + d[i] * (k[i] - 1) + op[i] + 1 for i, n in enumerate(spatial_shape))
    if any(o < 1 for o in out):
        raise ValueError(f"the transposed convolution leaves an empty output grid {list(out)}")
    return out


def _check_indices(indices, name: str, ndim: Optional[int] = None) -> None:
    check_tensor(indices, name)
    if indices.dim() != 2 or indices.shape[1] < 2 or (ndim is not None and indices.shape[1] != ndim + 1):
        want = "(N, 1 + D)" if ndim is None else f"(N, {ndim + 1})"
        raise ValueError(f"{name} must be {want} int32 with the batch index in column 0, got {describe(indices)}")
    if indices.dtype != torch.int32:
        raise ValueError(f"{name} must be int32, got {describe(indices)}")
    extension.check_device(indices, name)


def conv_out_indices(indices: Tensor, batch_size: int, spatial_shape: Sequence[int], out_spatial_shape: Sequence[int],
                     kernel_size, stride=1, padding=0, dilation=1, transposed: bool = False,
                     method: str = "auto", validate: bool = True) -> Tensor:
    """Output sites of a regular or transposed sparse convolution.

    Args:
        indices (Tensor[N, 1 + D] int32): input sites (batch, coordinates), inside the grid.
        batch_size (int), spatial_shape (Sequence[int]): the input grid.
        out_spatial_shape (Sequence[int]): the output grid (see :func:`conv_output_shape`).
        kernel_size, stride, padding, dilation: ints or D-sequences.
        transposed (bool): transposed convolution (input p reaches q = p * stride - padding + t * dilation).
        method (str): ``"auto"``, ``"dense"`` (index grid) or ``"hash"``; same result.
        validate (bool): raise ValueError for input rows outside the batch or grid (one host sync on CUDA);
            when False such rows are skipped.

    Returns:
        Tensor[M, 1 + D] int32: every output site reached by some input site, sorted by linear index
        (batch, then row-major coordinates), so the order is the same on every device.
    """
    _check_indices(indices, "indices")
    D = indices.shape[1] - 1
    shape = _ntuple(spatial_shape, D, "spatial_shape", 1)
    out_shape = _ntuple(out_spatial_shape, D, "out_spatial_shape", 1)
    return torch.ops.lidarops.sparse_conv_out_indices(
        indices, int(batch_size), list(shape), list(out_shape), list(_ntuple(kernel_size, D, "kernel_size", 1)),
        list(_ntuple(stride, D, "stride", 1)), list(_ntuple(padding, D, "padding", 0)),
        list(_ntuple(dilation, D, "dilation", 1)), bool(transposed), _method(method), bool(validate))


def kernel_map(indices: Tensor, out_indices: Tensor, batch_size: int, spatial_shape: Sequence[int], kernel_size,
               stride=1, padding=0, dilation=1, transposed: bool = False, validate: bool = True,
               method: str = "auto") -> Tensor:
    """Kernel map (rulebook) between input and output sites.

    ``out_indices`` may be any set of output sites (e.g. only the sites that changed), so a map
    restricted to a subset costs only that subset.

    Args:
        indices (Tensor[N_in, 1 + D] int32): input sites, unique and inside ``spatial_shape``.
        out_indices (Tensor[N_out, 1 + D] int32): output sites.
        batch_size, spatial_shape: the input grid.
        kernel_size, stride, padding, dilation: geometry; for a submanifold convolution pass
            ``out_indices = indices``, stride 1 and ``padding = dilation * (kernel_size // 2)``.
        transposed (bool): pairing of a transposed convolution.
        validate (bool): raise ValueError for input sites outside the grid or duplicated (one host
            sync on CUDA); when False such rows are skipped.
        method (str): coordinate table, ``"auto"``, ``"dense"`` or ``"hash"``; same result.

    Returns:
        Tensor[N_out, K] int32: ``[o, k]`` = input row feeding output row o through kernel offset k
        (row-major over the kernel window), or -1.
    """
    _check_indices(indices, "indices")
    D = indices.shape[1] - 1
    _check_indices(out_indices, "out_indices", D)
    if out_indices.device != indices.device:
        raise ValueError(f"out_indices is on {out_indices.device} but indices is on {indices.device}")
    return torch.ops.lidarops.sparse_kernel_map(
        indices, out_indices, int(batch_size), list(_ntuple(spatial_shape, D, "spatial_shape", 1)),
        list(_ntuple(kernel_size, D, "kernel_size", 1)), list(_ntuple(stride, D, "stride", 1)),
        list(_ntuple(padding, D, "padding", 0)), list(_ntuple(dilation, D, "dilation", 1)), bool(transposed),
        bool(validate), _method(method))


def build_kernel_map(x: SparseConvTensor, kind: str, kernel_size, stride=1, padding=0, dilation=1,
                     output_padding=0, out_spatial_shape: Optional[Sequence[int]] = None,
                     method: str = "auto") -> KernelMap:
    """Build the kernel map of one layer on the sites of ``x``.

    Args:
        x (SparseConvTensor): input sites.
        kind (str): ``"subm"``, ``"conv"``, ``"pool"`` (as conv) or ``"transposed"``.
        kernel_size, stride, padding, dilation, output_padding: geometry (a submanifold map ignores
            stride and padding: stride 1, padding ``dilation * (k // 2)``).
        out_spatial_shape (Sequence[int], optional): override the output grid (spconv's transposed
            formula differs from PyTorch's when dilation > 1).
        method (str): coordinate table, ``"auto"``, ``"dense"`` or ``"hash"``.

    The input sites are checked (inside the grid, each once: ValueError; one host synchronisation on CUDA)
    unless they are known valid: checked before at their current version, or made by a layer (the output
    sites of a map built here are). Under ``lidarops.validation(False)`` bad rows are skipped instead.

    Returns:
        KernelMap.
    """
    if not isinstance(x, SparseConvTensor):
        raise ValueError(f"x must be a SparseConvTensor, got {type(x).__name__}")
    extension.check_device(x.indices, "indices")
    km, _ = _build_kernel_map(x, kind, kernel_size, stride, padding, dilation, output_padding, out_spatial_shape,
                              method, defer=False)
    return km


def _build_kernel_map(x: SparseConvTensor, kind: str, kernel_size, stride, padding, dilation, output_padding,
                      out_spatial_shape, method, defer: bool) -> tuple:
    """:func:`build_kernel_map` and the site check it leaves to the caller (None when none is left): with
    ``defer`` a new frame's check on CUDA is read later (:func:`_settle`, after the caller has queued the
    convolution on the map), not before the map's last kernel is launched. The caller has checked ``x`` and
    its device (its features' device is its indices')."""
    D = x.ndim
    k = _ntuple(kernel_size, D, "kernel_size", 1)
    d = _ntuple(dilation, D, "dilation", 1)
    shape = tuple(x.spatial_shape)
    m = _method(method)
    ops = torch.ops.lidarops
    validate = value_checks_enabled() and not sites_checked(x.indices, x.batch_size, shape)  # (the docstring's rule)
    if kind == "subm":
        s, p = (1,) * D, tuple([d[i] * (k[i] // 2) for i in range(D)])
        out_shape, out_indices, transposed = shape, x.indices, False
    elif kind in ("conv", "pool", "transposed"):
        s, p = _ntuple(stride, D, "stride", 1), _ntuple(padding, D, "padding", 0)
        transposed = kind == "transposed"
        if out_spatial_shape is not None:
            out_shape = _ntuple(out_spatial_shape, D, "out_spatial_shape", 1)
        elif transposed:
            out_shape = conv_transpose_output_shape(shape, k, s, p, d, output_padding)
        else:
            out_shape = conv_output_shape(shape, k, s, p, d)
        # bad input rows are skipped here and reported by the map's validation below (one sync, not two);
        # sites checked before or by that validation let a transposed map whose kernel is its stride know its
        # output count without reading it back
        checked = transposed and (validate or sites_checked(x.indices, x.batch_size, shape))
        out_indices = ops.sparse_conv_out_indices(x.indices, x.batch_size, list(shape), list(out_shape), list(k),
                                                  list(s), list(p), list(d), transposed, m, False, checked)
    else:
        raise ValueError(f"kind must be 'subm', 'conv', 'pool' or 'transposed', got {kind!r}")
    pending = None
    if validate and defer and x.indices.is_cuda and not torch.cuda.is_current_stream_capturing():
        neighbors, ticket = ops.sparse_kernel_map_deferred(x.indices, out_indices, x.batch_size, list(shape), list(k),
                                                           list(s), list(p), list(d), transposed, m)
        pending = (x.indices, ticket, x.batch_size, shape)
    else:
        neighbors = ops.sparse_kernel_map(x.indices, out_indices, x.batch_size, list(shape), list(k), list(s),
                                          list(p), list(d), transposed, validate, m)
        if validate:
            mark_sites_checked(x.indices, x.batch_size, shape)
    if out_indices is not x.indices:  # made here: inside the output grid, each site once
        mark_sites_checked(out_indices, x.batch_size, out_shape)
    km = KernelMap(kind=kind, indices=x.indices, out_indices=out_indices, spatial_shape=shape,
                   out_spatial_shape=tuple(out_shape), kernel_size=k, stride=s, padding=p, dilation=d,
                   neighbors=neighbors)
    return km, pending


_check_slots = None  # the deferred checks' words (numpy over pinned host memory), read in place


def _settle(pending) -> None:
    """Read a deferred site check (ValueError for sites outside the grid or repeated, as the map's own check)
    and remember the sites as checked."""
    global _check_slots
    indices, ticket, batch_size, shape = pending
    if _check_slots is None:
        _check_slots = torch.ops.lidarops.sparse_site_check_slots(indices).numpy()
    # a passed check's word is ticket << 2; otherwise (not written yet, or a flag) the op waits for it and raises
    if _check_slots[ticket % len(_check_slots)] != ticket << 2:
        torch.ops.lidarops.sparse_site_check(indices, ticket, batch_size, list(shape))
    mark_sites_checked(indices, batch_size, shape)


def sparse_conv(features: Tensor, weight: Tensor, neighbors: Tensor, order: Optional[Tensor] = None,
                algo: str = "auto", splits: int = 0) -> Tensor:
    """Gather-GEMM-scatter convolution over a kernel map.

    Args:
        features (Tensor[N_in, Cin]): float32/float64/float16/bfloat16.
        weight (Tensor[Cout, *kernel, Cin] or Tensor[Cout, K, Cin]): same dtype and device.
        neighbors (Tensor[N_out, K] int32): a kernel map (:func:`kernel_map`), entries in [-1, N_in).
        order (Tensor[N_out] int32, optional): processing order of the output rows for the CUDA kernel
            (``torch.ops.lidarops.sparse_kernel_map_order(neighbors)``, cached as ``KernelMap.order``);
            it changes only the speed.
        algo (str): the CUDA kernel choice, one of :data:`CONV_ALGOS` (default ``"auto"``).
        splits (int): offset splits of the CUDA pipelined kernels (split-K over the kernel offsets),
            forced, at most K; 0 (default): chosen per layer. For tests and tuning.

    Returns:
        Tensor[N_out, Cout]: ``out[o] = sum_k weight[:, k, :] @ features[neighbors[o, k]]``,
        accumulated in float32 (float64 for float64). Differentiable with respect to features and
        weight (gradcheck-clean, twice differentiable).
    """
    check_tensor(features, "features")
    check_tensor(weight, "weight")
    check_tensor(neighbors, "neighbors")
    _conv_algo(algo)
    if isinstance(splits, bool) or not isinstance(splits, int) or splits < 0:
        raise ValueError(f"splits must be an int >= 0 (0: chosen per layer), got {splits!r}")
    if features.dim() != 2 or not features.is_floating_point():
        raise ValueError(f"features must be a floating (N_in, Cin) tensor, got {describe(features)}")
    if weight.dim() < 3 or weight.dtype != features.dtype:
        raise ValueError(f"weight must be (Cout, *kernel, Cin) with the dtype of features ({features.dtype}), "
                         f"got {describe(weight)}")
    if neighbors.dim() != 2 or neighbors.dtype != torch.int32:
        raise ValueError(f"neighbors must be an (N_out, K) int32 kernel map, got {describe(neighbors)}")
    for name, t in (("weight", weight), ("neighbors", neighbors)):
        if t.device != features.device:
            raise ValueError(f"{name} is on {t.device} but features is on {features.device}")
    extension.check_device(features, "features")
    w = weight.reshape(weight.shape[0], -1, weight.shape[-1])
    if w.shape[1] != neighbors.shape[1] or w.shape[2] != features.shape[1]:
        raise ValueError(f"weight {tuple(weight.shape)} must be (Cout, K = {neighbors.shape[1]} offsets, "
                         f"Cin = {features.shape[1]})")
    if value_checks_enabled() and neighbors.numel():
        n = features.shape[0]
        run_value_checks([(((neighbors < -1) | (neighbors >= n)).any(),
                           lambda: f"neighbors must lie in [-1, {n}), got values in "
                                   f"[{int(neighbors.min())}, {int(neighbors.max())}]")])
    if order is not None and (order.dtype != torch.int32 or order.shape != (neighbors.shape[0],)
                              or order.device != neighbors.device):
        raise ValueError(f"order must be an ({neighbors.shape[0]},) int32 permutation on {neighbors.device}, "
                         f"got {describe(order)}")
    return torch.ops.lidarops.sparse_conv(features, w, neighbors, order, algo, splits)


# ---- layer-level functions on SparseConvTensor ----------------------------------------------------

def _kernel_map_for(x: SparseConvTensor, kind: str, ksize: tuple, stride, padding, dilation, output_padding,
                    indice_key, out_spatial_shape, method, defer: bool = False) -> tuple:
    """(kernel map, indice_dict of the output, the site check left to the caller or None) under spconv's reuse
    rules, with fit checks; ``defer``: :func:`_build_kernel_map`'s."""
    cache = x.indice_dict
    if kind == "inverse":
        if indice_key is None:
            raise ValueError("an inverse convolution needs the indice_key of the strided convolution it inverts")
        km = cache.get(indice_key)
        if km is None:
            raise ValueError(f"indice_key {indice_key!r} is not in this tensor's indice_dict (keys: {sorted(cache)}); "
                             "an inverse convolution must follow the convolution that registered it")
        if km.kind not in ("conv", "pool", "transposed"):
            raise ValueError(f"indice_key {indice_key!r} holds a {km.kind} kernel map; an inverse convolution "
                             "inverts a regular (strided) convolution, a transposed convolution or a max pool")
        if tuple(ksize) != km.kernel_size:
            raise ValueError(f"the inverse convolution has kernel {tuple(ksize)} but the convolution registered "
                             f"under {indice_key!r} has kernel {km.kernel_size}; they must be equal")
        if x.indices.shape[0] != km.out_indices.shape[0] or tuple(x.spatial_shape) != km.out_spatial_shape:
            raise ValueError(f"the inverse convolution's input ({x.indices.shape[0]} sites on grid {x.spatial_shape}) "
                             f"is not the output of the convolution registered under {indice_key!r} "
                             f"({km.out_indices.shape[0]} sites on grid {list(km.out_spatial_shape)})")
        _check_sites(km, "out", x.indices, indice_key)
        return km.inverse(), cache, None
    D = x.ndim
    if indice_key is not None and indice_key in cache:
        km = cache[indice_key]
        # the layers pass their own tuple, which needs no normalising when it is the map's
        d = km.dilation if type(dilation) is tuple and dilation == km.dilation else _ntuple(dilation, D, "dilation", 1)
        fits = (km.kind == kind and km.kernel_size == tuple(ksize) and km.dilation == d
                and km.indices.shape[0] == x.indices.shape[0] and km.spatial_shape == tuple(x.spatial_shape))
        if fits and kind != "subm":
            fits = (km.stride == _ntuple(stride, D, "stride", 1) and km.padding == _ntuple(padding, D, "padding", 0))
        if not fits:
            raise ValueError(
                f"indice_key {indice_key!r} holds the kernel map of a {km.kind} layer (kernel {km.kernel_size}, "
                f"stride {km.stride}, dilation {km.dilation}, {km.indices.shape[0]} input sites on grid "
                f"{list(km.spatial_shape)}) that does not fit this {kind} layer (kernel {tuple(ksize)}, "
                f"{x.indices.shape[0]} input sites on grid {x.spatial_shape}); give this layer its own indice_key")
        _check_sites(km, "in", x.indices, indice_key)
        return km, cache, None
    km, pending = _build_kernel_map(x, kind, ksize, stride, padding, dilation, output_padding, out_spatial_shape,
                                    method, defer)
    if indice_key is not None:
        km._sites = _MapSites(km)
        cache = dict(cache)
        cache[indice_key] = km
        for maps in _recorders:
            if maps.setdefault(indice_key, km) is not km:
                maps[CONFLICT] = indice_key
    elif kind != "subm":  # built again every call, with a host read (its output count)
        for maps in _recorders:
            maps.setdefault(UNKEYED, kind)
    return km, cache, pending


# The maps a forward registers, for GraphedSparseNet: one dict holding every layer's map, also where
# branches fork the indice_dict and the output carries only one branch's (or none: a dense output).
_recorders: list = []
CONFLICT = object()  # the key under which a recording notes an indice_key registered twice on other maps
UNKEYED = object()   # ... and a strided, transposed or pooling map built without an indice_key


@contextlib.contextmanager
def recording_maps(maps: dict):
    """Within the block, every kernel map a layer builds and registers under an ``indice_key`` is also put in
    ``maps`` (the first one per key; a second, different map under the same key sets ``maps[CONFLICT]``, a
    strided, transposed or pooling map without a key sets ``maps[UNKEYED]`` to its kind)."""
    _recorders.append(maps)
    try:
        yield maps
    finally:  # by identity: list.remove would drop the first equal dict
        del _recorders[next(i for i, m in enumerate(_recorders) if m is maps)]


# A kernel map cached under an indice_key belongs to the sites it was built on: the same number of
# sites elsewhere gives a map of the right size but the wrong pairs, so the fit check above cannot see
# it. A reuse is accepted, with host-side tests only (no synchronisation, so a forward whose maps are
# all cached stays CUDA-graph capturable), when the layer's indices tensor is the map's own, unchanged
# in place since the map was built (identity and version counter; every layer with a cached map
# returns the map's own output tensor, so a network's layers all pass this way), or a tensor already
# found equal to it at its current version. Any other tensor is compared once on the device (one host
# synchronisation), and remembered when equal.
class _Sites:
    """One side (input or output sites) of a cached map: the version of the map's own tensor when the
    map was built, and the last other tensor found equal to it (a weak reference) with its version."""

    __slots__ = ("version", "copy", "copy_version")

    def __init__(self, t: Tensor):
        self.version = _version(t)
        self.copy = None
        self.copy_version = None


class _MapSites:
    __slots__ = ("sides",)

    def __init__(self, km: KernelMap):
        sites = _Sites(km.indices)  # a submanifold map's two sides are one tensor: one state
        self.sides = {"in": sites, "out": sites if km.out_indices is km.indices else _Sites(km.out_indices)}


def _version(t: Tensor) -> Optional[int]:
    """The in-place version counter of ``t`` (None for an inference tensor, which keeps none)."""
    return None if t.is_inference() else t._version


def _check_sites(km: KernelMap, side: str, indices: Tensor, indice_key) -> None:
    """Raise ValueError unless ``indices`` are the sites of ``km``'s ``side`` (``"in"``: ``km.indices``,
    what a layer reusing the map reads; ``"out"``: ``km.out_indices``, what an inverse convolution reads)."""
    own = km.indices if side == "in" else km.out_indices
    if _compiling():  # dynamo guards the identity; version counters and weak references are not traceable
        if indices is not own:
            _compare_sites(indices, own, side, indice_key)  # a data-dependent branch: a graph break
        return
    state = km._sites
    if state is None:  # a map put into an indice_dict by hand: its sites are what its tensors hold now
        state = km._sites = _MapSites(km)
    sites = state.sides[side]
    if _version(own) != sites.version:
        raise ValueError(f"the sites of the kernel map under indice_key {indice_key!r} were changed in place after "
                         "the map was built, so its pairs are stale; build a new map (a fresh indice_dict or a new "
                         "indice_key) after changing indices")
    if indices is own:
        return
    copy = None if sites.copy is None else sites.copy()
    if copy is indices and sites.copy_version == _version(indices):
        return
    if indices.is_cuda and torch.cuda.is_current_stream_capturing():
        raise ValueError(f"indice_key {indice_key!r}: these indices are not the tensor its kernel map was built on, "
                         "and comparing them needs a host synchronisation, which a CUDA graph capture forbids; run "
                         "the forward once on this tensor before capturing (it is then checked once and remembered)")
    _compare_sites(indices, own, side, indice_key)
    sites.copy, sites.copy_version = weakref.ref(indices), _version(indices)


def _compare_sites(indices: Tensor, own: Tensor, side: str, indice_key) -> None:
    if indices.device != own.device:
        raise ValueError(f"indices are on {indices.device} but the kernel map under indice_key {indice_key!r} was "
                         f"built on {own.device}")
    if not torch.equal(indices, own):
        what = "output sites of the convolution it inverts" if side == "out" else "sites it was built on"
        raise ValueError(f"indice_key {indice_key!r} holds a kernel map of other sites: this layer's "
                         f"{indices.shape[0]} sites are not the {own.shape[0]} {what}, and reusing its pairs "
                         "would put the result on the wrong sites; give this layer its own indice_key or start "
                         "from a fresh indice_dict (a new SparseConvTensor without indice_dict)")


def cached_by_version(owner, attr: str, tensors: Sequence[Optional[Tensor]], compute, extra=()):
    """``compute()``, kept in ``owner.__dict__[attr]`` until one of ``tensors`` is replaced or changed in
    place (the key holds each one's data pointer, version counter and device, plus ``extra``).
    Inference tensors keep no version counter: then nothing is cached."""
    try:
        key = [None if t is None else (t.data_ptr(), t._version, t.device) for t in tensors]
    except RuntimeError:
        return compute()
    key.append(extra)
    cached = owner.__dict__.get(attr)
    if cached is not None and cached[0] == key:
        return cached[1]
    value = compute()
    owner.__dict__[attr] = (key, value)
    return value


def fusable_norm(x: SparseConvTensor, norm: torch.nn.Module, *params: Optional[Tensor]) -> bool:
    """Whether a convolution of ``x`` followed by ``norm`` can run as one fused inference convolution:
    ``norm`` is a BatchNorm in eval mode with running statistics, no gradient is needed (``x`` and the
    layers' ``params``), the features are not float64 (which keeps BatchNorm's own float64
    arithmetic), and the code is not being compiled."""
    if not isinstance(norm, torch.nn.modules.batchnorm._BatchNorm) or norm.training:
        return False
    buffers = norm._buffers  # not through nn.Module.__getattr__: host time per layer
    if (buffers.get("running_mean") is None or buffers.get("running_var") is None
            or x.features.dtype == torch.float64 or _compiling()):
        return False
    return not (torch.is_grad_enabled() and (x.features.requires_grad or any(
        p is not None and p.requires_grad for p in params + tuple(norm._parameters.values()))))


def norm_affine(norm: torch.nn.Module, bias: Optional[Tensor] = None) -> tuple:
    """``(scale, shift)``, float32 ``(C,)``, such that ``norm(y + bias) == y * scale + shift`` for a
    BatchNorm in eval mode (running statistics): what :func:`conv` fuses into its epilogue.

    Cached on the module until one of its parameters or buffers (or ``bias``) is replaced or changed
    in place (:func:`cached_by_version`).
    """
    params, buffers = norm._parameters, norm._buffers  # not through nn.Module.__getattr__: host time per layer
    if not isinstance(norm, torch.nn.modules.batchnorm._BatchNorm) or norm.training \
            or buffers.get("running_mean") is None:
        raise ValueError(f"norm_affine takes a BatchNorm in eval mode with running statistics, got {norm!r}")

    def compute():
        with torch.no_grad():
            scale = torch.rsqrt(norm.running_var.float() + norm.eps)
            if norm.weight is not None:
                scale = scale * norm.weight.float()
            shift = -norm.running_mean.float() * scale
            if norm.bias is not None:
                shift = shift + norm.bias.float()
            if bias is not None:
                shift = shift + bias.float() * scale
            return scale.contiguous(), shift.contiguous()

    return cached_by_version(norm, "_lidarops_affine",
                             (params.get("weight"), params.get("bias"), buffers["running_mean"],
                              buffers["running_var"], bias), compute, norm.eps)


def _affine_torch(out: Tensor, scale: Optional[Tensor], shift: Optional[Tensor], relu: bool) -> Tensor:
    """The fused epilogue in differentiable torch ops (the path with gradients)."""
    if scale is not None:
        out = out * scale.to(out.dtype)
    if shift is not None:
        out = out + shift.to(out.dtype)
    return torch.relu(out) if relu else out


def _autocast_on(f: Tensor) -> bool:
    """Whether ``torch.autocast`` is on for the device of ``f`` (where :func:`_autocast` casts)."""
    dev = f.device.type
    return dev in ("cuda", "cpu") and torch.is_autocast_enabled(dev)


def _subm_chain(x: SparseConvTensor, km: KernelMap, indice_dict: dict, weights: list, scales: list, shifts: list,
                relus: list, algo: str) -> SparseConvTensor:
    """Consecutive fused submanifold layers on ``km`` (the map of ``x``'s sites, built or checked by the caller) in
    one op call, without gradients: what ``SparseSequential`` runs; the output carries ``indice_dict``."""
    with torch._C._AutoDispatchBelowAutograd():
        out = torch.ops.lidarops.sparse_conv_affine_chain(x.features, weights, km.neighbors, km.layer_order(), scales,
                                                          shifts, relus, algo)
    return SparseConvTensor._derived(out, x.indices, x.spatial_shape, x.batch_size, indice_dict)


def _autocast(x: SparseConvTensor, weight: Tensor, bias: Optional[Tensor]) -> tuple:
    """Features, weight and bias in the autocast dtype of the features' device, where ``torch.autocast`` is on
    (:func:`_autocast_on`), as ``F.conv2d`` is cast (float64 and non-floating tensors are left alone, so their
    errors stay)."""
    dt = torch.get_autocast_dtype(x.features.device.type)

    def cast(t):
        return t.to(dt) if t is not None and t.is_floating_point() and t.dtype not in (dt, torch.float64) else t

    f = x.features
    return (x if cast(f) is f else x.replace_feature(cast(f))), cast(weight), cast(bias)


def conv(x: SparseConvTensor, weight: Tensor, bias: Optional[Tensor] = None, kind: str = "conv", stride=1,
         padding=0, dilation=1, output_padding=0, indice_key: Optional[str] = None,
         out_spatial_shape: Optional[Sequence[int]] = None, method: str = "auto", *,
         scale: Optional[Tensor] = None, shift: Optional[Tensor] = None, relu: bool = False,
         algo: str = "auto") -> SparseConvTensor:
    """Sparse convolution of one layer.

    Args:
        x (SparseConvTensor): input, features (N, Cin).
        weight (Tensor[Cout, *kernel, Cin]): spconv 2.x layout, dtype of ``x.features``.
        bias (Tensor[Cout], optional).
        kind (str): ``"subm"``, ``"conv"``, ``"transposed"`` or ``"inverse"`` (see the module docstring).
        stride, padding, dilation, output_padding: geometry (ignored by ``"inverse"``, which takes the
            registered convolution's; ``"subm"`` uses stride 1 and padding ``dilation * (k // 2)``).
        indice_key (str, optional): kernel-map cache key. A layer whose key is in ``x.indice_dict``
            reuses that map (it must fit: same kind, kernel, dilation, stride, padding and input
            sites, else ValueError); otherwise the new map is registered in the output's dict.
        out_spatial_shape (Sequence[int], optional): override the output grid of conv / transposed.
        method (str): coordinate table for a new map: ``"auto"``, ``"dense"`` or ``"hash"``.
        scale, shift (Tensor[Cout] float32, optional), relu (bool): an epilogue, ``out = relu?((conv +
            bias) * scale + shift)`` (a BatchNorm in eval mode and a ReLU: :func:`norm_affine`). Without
            gradients it runs inside the convolution kernel on its float accumulator
            (``torch.ops.lidarops.sparse_conv_affine``): no separate BatchNorm and ReLU kernels.
        algo (str): the CUDA kernel choice, one of :data:`CONV_ALGOS` (default ``"auto"``).

    Under ``torch.autocast`` (CUDA or CPU), features, weight and bias run in the autocast dtype, as
    ``F.conv2d`` does; the epilogue's ``scale`` and ``shift`` stay float32.

    Returns:
        SparseConvTensor with features (N_out, Cout): same sites as x for ``"subm"``, the registered
        convolution's input sites for ``"inverse"``, else the reached output sites in linear order.

    Raises:
        ValueError: naming the argument: bad shapes, dtypes or devices; sites outside the grid or
            duplicated (checked once per indices tensor, when a kernel map is first built on it or, for a
            1 x 1 ``"subm"`` convolution, which builds no map, before the product; sites made by a layer
            are not checked again); a reused ``indice_key`` whose map was built on other sites.
    """
    if not isinstance(x, SparseConvTensor):
        raise ValueError(f"x must be a SparseConvTensor, got {type(x).__name__}")
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    _conv_algo(algo)
    D = x.ndim
    check_tensor(weight, "weight")
    f = x.features  # read once (a property): host time per layer
    cin = f.shape[1]
    if weight.dim() != D + 2 or weight.shape[-1] != cin:
        raise ValueError(f"weight must be (Cout, *kernel ({D} dims), Cin = {cin}) for this {D}D input, "
                         f"got {describe(weight)}")
    if _autocast_on(f):
        x, weight, bias = _autocast(x, weight, bias)
        f = x.features
    if weight.dtype != f.dtype or weight.device != f.device:
        raise ValueError(f"weight ({weight.dtype}, {weight.device}) must match the features "
                         f"({f.dtype}, {f.device})")
    if not f.is_floating_point():
        raise ValueError(f"features must be floating point, got {describe(f)}")
    cout = weight.shape[0]
    if bias is not None and (bias.shape != (cout,) or bias.dtype != weight.dtype):
        raise ValueError(f"bias must be ({cout},) of dtype {weight.dtype}, got {describe(bias)}")
    epilogue = scale is not None or shift is not None
    if epilogue:
        for name, t in (("scale", scale), ("shift", shift)):
            if t is not None and (not isinstance(t, Tensor) or t.shape != (cout,) or t.dtype != torch.float32
                                  or t.device != weight.device):
                raise ValueError(f"{name} must be a float32 ({cout},) tensor on {weight.device}, got {describe(t)}")
    epilogue = epilogue or bool(relu)
    extension.check_device(f, "features")
    ksize = tuple(weight.shape[1:-1])
    K = math.prod(ksize)
    w = weight.reshape(cout, K, cin)
    if kind == "subm" and K == 1:
        # every site is its own only neighbour: a matrix product, no kernel map needed (and none checks the
        # sites, so they are checked here, once per indices tensor)
        check_sites(x)
        out = f.matmul(w[:, 0, :].t())
        out = out + bias if bias is not None else out
        return x.replace_feature(_affine_torch(out, scale, shift, relu) if epilogue else out)
    # a new frame's site check is read once the convolution is queued (the host need not wait for the map)
    km, cache, pending = _kernel_map_for(x, kind, ksize, stride, padding, dilation, output_padding, indice_key,
                                         out_spatial_shape, method, defer=True)
    grad = torch.is_grad_enabled() and (f.requires_grad or w.requires_grad
                                        or (bias is not None and bias.requires_grad))
    compiling = _compiling()
    order = km.order if compiling else km.layer_order()
    if grad or compiling or (epilogue and f.dtype == torch.float64):  # float64: the float32 epilogue would round
        out = torch.ops.lidarops.sparse_conv(f, w, km.neighbors, order, algo)
        if bias is not None:
            out = out + bias
        if epilogue:
            out = _affine_torch(out, scale, shift, relu)
    else:  # no autograd node to record: skip the Python autograd wrapper (host time of eager inference)
        with torch._C._AutoDispatchBelowAutograd():
            if epilogue:
                if bias is not None:  # (conv + bias) * scale + shift
                    b = bias.float() if scale is None else bias.float() * scale
                    shift = b if shift is None else shift + b
                out = torch.ops.lidarops.sparse_conv_affine(f, w, km.neighbors, order, scale, shift, bool(relu),
                                                            algo)
            else:
                out = torch.ops.lidarops.sparse_conv(f, w, km.neighbors, order, algo)
                if bias is not None:
                    out = out + bias
    if pending is not None:
        _settle(pending)
    return SparseConvTensor._derived(out, km.out_indices, km.out_spatial_shape, x.batch_size, cache)


def max_pool(x: SparseConvTensor, kernel_size, stride=None, padding=0, dilation=1, subm: bool = False,
             indice_key: Optional[str] = None, method: str = "auto") -> SparseConvTensor:
    """Sparse max pooling: the maximum over the active sites of each output's window.

    Output sites are those of a regular convolution with the same geometry (``subm=True``: the input
    sites, window centred). Inactive sites do not take part (a window of negative features gives a
    negative maximum, not zero). Ties go to the first kernel offset; NaN propagates.

    Args:
        x (SparseConvTensor): input.
        kernel_size, stride (default ``kernel_size``), padding, dilation: ints or D-sequences.
        subm (bool): submanifold pooling.
        indice_key (str, optional): kernel-map cache key (an inverse convolution can invert a pool).
        method (str): coordinate table for a new map.

    Returns:
        SparseConvTensor; features differentiable (the gradient goes to the selected input).
    """
    if not isinstance(x, SparseConvTensor):
        raise ValueError(f"x must be a SparseConvTensor, got {type(x).__name__}")
    D = x.ndim
    k = _ntuple(kernel_size, D, "kernel_size", 1)
    s = k if stride is None else _ntuple(stride, D, "stride", 1)
    if not x.features.is_floating_point():
        raise ValueError(f"features must be floating point, got {describe(x.features)}")
    extension.check_device(x.features, "features")
    km, cache, _ = _kernel_map_for(x, "subm" if subm else "pool", k, s, padding, dilation, 0, indice_key, None,
                                   method)
    out, _ = torch.ops.lidarops.sparse_max_pool(x.features, km.neighbors)
    return SparseConvTensor._derived(out, km.out_indices, km.out_spatial_shape, x.batch_size, cache)


# ---- dense references (used by the tests) -----------------------------------------------------------

def _dense_conv_fn(D: int, transposed: bool):
    table = {(1, False): F.conv1d, (2, False): F.conv2d, (3, False): F.conv3d,
             (1, True): F.conv_transpose1d, (2, True): F.conv_transpose2d, (3, True): F.conv_transpose3d}
    if (D, transposed) not in table:
        raise ValueError(f"the dense reference supports D = 1, 2, 3, got {D}")
    return table[(D, transposed)]


def _sites_of(mask: Tensor) -> Tensor:
    """(M, 1 + D) int64 sites where a (B, 1, *S) mask is > 0, in row-major order."""
    return torch.nonzero(mask[:, 0] > 0.5)


def _conv_reference(x: SparseConvTensor, weight: Tensor, bias: Optional[Tensor] = None, kind: str = "conv",
                    stride=1, padding=0, dilation=1, output_padding=0, inverse_of: Optional[KernelMap] = None):
    """Dense PyTorch reference of :func:`conv`.

    Returns:
        (indices Tensor[M, 1 + D] int64 in row-major order, features Tensor[M, Cout]).
    """
    D = x.ndim
    ksize = tuple(weight.shape[1:-1])
    dense = x.dense()
    mask = torch.zeros([x.batch_size, 1] + x.spatial_shape, dtype=dense.dtype, device=dense.device)
    if x.indices.shape[0]:
        mask[(x.indices[:, 0].long(), 0) + tuple(x.indices[:, 1:].long().unbind(1))] = 1.0
    ones = torch.ones((1, 1) + ksize, dtype=dense.dtype, device=dense.device)
    d = _ntuple(dilation, D, "dilation", 1)
    if kind == "subm":
        pad = tuple(d[i] * (ksize[i] // 2) for i in range(D))
        y = _dense_conv_fn(D, False)(dense, weight.permute(0, D + 1, *range(1, D + 1)), bias, 1, pad, d)
        sites = x.indices.long()
    elif kind == "conv":
        s, p = _ntuple(stride, D, "stride", 1), _ntuple(padding, D, "padding", 0)
        fn = _dense_conv_fn(D, False)
        y = fn(dense, weight.permute(0, D + 1, *range(1, D + 1)), bias, s, p, d)
        sites = _sites_of(fn(mask, ones, None, s, p, d))
    elif kind in ("transposed", "inverse"):
        fn = _dense_conv_fn(D, True)
        wt = weight.permute(D + 1, 0, *range(1, D + 1))
        if kind == "inverse":
            km = inverse_of
            s, p, d = km.stride, km.padding, km.dilation
            op = tuple(km.spatial_shape[i] - ((km.out_spatial_shape[i] - 1) * s[i] - 2 * p[i] + d[i] * (ksize[i] - 1) + 1)
                       for i in range(D))
            y = fn(dense, wt, bias, s, p, op, 1, d)
            sites = km.indices.long()
        else:
            s, p = _ntuple(stride, D, "stride", 1), _ntuple(padding, D, "padding", 0)
            op = _ntuple(output_padding, D, "output_padding", 0)
            y = fn(dense, wt, bias, s, p, op, 1, d)
            sites = _sites_of(fn(mask, ones, None, s, p, op, 1, d))
    else:
        raise ValueError(f"unknown kind {kind!r}")
    feats = y.movedim(1, -1)[tuple(sites.unbind(1))] if sites.shape[0] else y.new_zeros(0, weight.shape[0])
    return sites, feats


def _max_pool_reference(x: SparseConvTensor, kernel_size, stride=None, padding=0, dilation=1):
    """Dense reference of :func:`max_pool` (non-submanifold): -inf at inactive sites."""
    D = x.ndim
    k = _ntuple(kernel_size, D, "kernel_size", 1)
    s = k if stride is None else _ntuple(stride, D, "stride", 1)
    p, d = _ntuple(padding, D, "padding", 0), _ntuple(dilation, D, "dilation", 1)
    C = x.features.shape[1]
    dense = x.features.new_full([x.batch_size] + x.spatial_shape + [C], float("-inf"))
    if x.indices.shape[0]:
        dense[tuple(x.indices.long().unbind(1))] = x.features
    dense = dense.movedim(-1, 1)
    pool = {1: F.max_pool1d, 2: F.max_pool2d, 3: F.max_pool3d}[D]
    y = pool(dense, k, s, p, d)
    mask = torch.zeros([x.batch_size, 1] + x.spatial_shape, dtype=x.features.dtype, device=x.features.device)
    if x.indices.shape[0]:
        mask[(x.indices[:, 0].long(), 0) + tuple(x.indices[:, 1:].long().unbind(1))] = 1.0
    ones = torch.ones((1, 1) + k, dtype=mask.dtype, device=mask.device)
    sites = _sites_of(_dense_conv_fn(D, False)(mask, ones, None, s, p, d))
    feats = y.movedim(1, -1)[tuple(sites.unbind(1))] if sites.shape[0] else y.new_zeros(0, C)
    return sites, feats
