"""``SparseConvTensor`` (spconv's layout) and ``KernelMap``, the cached rulebook of one convolution."""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field
from typing import Optional, Sequence

import torch
from torch import Tensor

from lidarops.ops.validation import describe, run_value_checks, value_checks_enabled

__all__ = ["SparseConvTensor", "KernelMap"]


#: The layer call on a kernel map from which it runs with its row order (:meth:`KernelMap.layer_order`).
ORDER_FROM_CALL = 2


@dataclass(eq=False)
class KernelMap:
    """The rulebook of one sparse convolution: which input row feeds which output row through which
    kernel offset. Cached in ``SparseConvTensor.indice_dict`` under the layer's ``indice_key``.

    Attributes:
        kind (str): ``"subm"``, ``"conv"``, ``"transposed"``, ``"pool"`` (a max-pool map, like conv) or
            ``"inverse"`` (the swapped map of a conv, from :meth:`inverse`).
        indices (Tensor[N_in, 1 + D] int32): input sites.
        out_indices (Tensor[N_out, 1 + D] int32): output sites (for strided and transposed
            convolutions sorted by linear index: batch, then row-major coordinates).
        spatial_shape, out_spatial_shape (tuple[int, ...]): grids of the input and the output.
        kernel_size, stride, padding, dilation (tuple[int, ...]): geometry of the convolution.
        neighbors (Tensor[N_out, K] int32): ``neighbors[o, k]`` is the input row that feeds output
            row ``o`` through kernel offset ``k`` (row-major over the kernel window, the order of
            ``weight[Cout, *kernel, Cin]``), or -1.
    """

    kind: str
    indices: Tensor
    out_indices: Tensor
    spatial_shape: tuple
    out_spatial_shape: tuple
    kernel_size: tuple
    stride: tuple
    padding: tuple
    dilation: tuple
    neighbors: Tensor
    _neighbors_t: Optional[Tensor] = field(default=None, repr=False)
    _inverse: Optional["KernelMap"] = field(default=None, repr=False)
    _order: Optional[Tensor] = field(default=None, repr=False)
    _layers: int = field(default=0, repr=False)  # layers that ran on this map (layer_order)
    _sites: Optional[object] = field(default=None, repr=False)  # what a reuse checks its sites by (_MapSites)

    @property
    def kernel_volume(self) -> int:
        return int(math.prod(self.kernel_size))

    @property
    def neighbors_t(self) -> Tensor:
        """Tensor[N_in, K] int32: the transposed map, ``neighbors_t[i, k] = o`` where ``neighbors[o, k] = i``."""
        if self._neighbors_t is None:
            self._neighbors_t = torch.ops.lidarops.sparse_kernel_map_transpose(self.neighbors, self.indices.shape[0])
        return self._neighbors_t

    @property
    def order(self) -> Optional[Tensor]:
        """Tensor[N_out] int32 or None: the order in which the fused CUDA kernel processes the output
        rows (grouped by which kernel offsets they have, so that a tile skips absent offsets); None on
        CPU, whose kernel lists the pairs of each offset instead."""
        if self.neighbors.device.type != "cuda":
            return None
        if self._order is None:
            self._order = torch.ops.lidarops.sparse_kernel_map_order(self.neighbors)
        return self._order

    def layer_order(self) -> Optional[Tensor]:
        """The :attr:`order` a layer call runs on this map with. The first :data:`ORDER_FROM_CALL` - 1 calls run
        without it (unless it was made already): sorting the rows costs about five launches, more host time than
        it saves a few layers of an eager forward, which waits on the host; from that call on (a map cached and
        reused, or shared by many layers through ``indice_key``) the order is made once and used; never while a
        CUDA graph is being captured, where it would be made inside the graph."""
        self._layers += 1
        if self._order is None and self._layers >= ORDER_FROM_CALL and self.neighbors.device.type == "cuda" \
                and not torch.cuda.is_current_stream_capturing():
            return self.order
        return self._order

    def inverse(self) -> "KernelMap":
        """The map of the inverse convolution: from this map's output sites back to its input sites,
        with the same kernel offsets (no flip)."""
        if self._inverse is None:
            self._inverse = KernelMap(
                kind="inverse", indices=self.out_indices, out_indices=self.indices,
                spatial_shape=self.out_spatial_shape, out_spatial_shape=self.spatial_shape,
                kernel_size=self.kernel_size, stride=self.stride, padding=self.padding, dilation=self.dilation,
                neighbors=self.neighbors_t, _neighbors_t=self.neighbors, _inverse=self)
        return self._inverse

    # spconv's IndiceData names, for code that inspects indice_dict
    @property
    def is_subm(self) -> bool:
        return self.kind == "subm"

    @property
    def ksize(self) -> list:
        return list(self.kernel_size)


_INT32_MAX = 2**31 - 1
_MAX_SITES = 2**62  # batch_size * prod(spatial_shape): the kernel maps' int64 site keys


def _int(v, name: str, lo: int, hi: int) -> int:
    """An int in [lo, hi]: Python and NumPy ints and one-element integer tensors; not bools or floats
    (a float would be truncated: 10.7 -> 10)."""
    if type(v) is int and lo <= v <= hi:  # what nearly every caller passes
        return v
    if isinstance(v, Tensor) and v.numel() == 1 and not (v.is_floating_point() or v.is_complex() or v.dtype == torch.bool):
        v = v.reshape(()).item()
    try:
        if isinstance(v, (bool, Tensor)):
            raise TypeError
        v = operator.index(v)
    except TypeError:
        raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {v!r}") from None
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be an int in [{lo}, {hi}], got {v}")
    return v


def _spatial_shape(spatial_shape, ndim: int) -> tuple:
    """``ndim`` ints in [1, 2^31 - 1] (coordinates are int32)."""
    if isinstance(spatial_shape, (str, bytes)) or not hasattr(spatial_shape, "__len__"):
        raise ValueError(f"spatial_shape must be a sequence of {ndim} ints, got {spatial_shape!r}")
    if len(spatial_shape) != ndim:
        raise ValueError(f"spatial_shape must hold {ndim} positive ints (one per coordinate column of indices), "
                         f"got {list(spatial_shape)!r}")
    return tuple(_int(v, f"spatial_shape[{d}]", 1, _INT32_MAX) for d, v in enumerate(spatial_shape))


def _range_check(indices: Tensor, batch_size: int, spatial_shape: list, duplicates: bool = False) -> None:
    """One host sync: every row of ``indices`` lies in ``[0, batch_size) x [0, spatial_shape)`` (and, with
    ``duplicates``, no site is given twice: a dense map or a 1 x 1 convolution would keep one row of two)."""
    idx = indices.long()
    bound = torch.tensor([batch_size] + spatial_shape, device=idx.device)
    outside = (idx < 0) | (idx >= bound)

    def message() -> str:
        row = int(torch.nonzero(outside.any(1))[0, 0])
        return (f"indices lie outside batch_size {batch_size} / spatial_shape {spatial_shape}: row {row} is "
                f"{idx[row].tolist()} (batch, coordinates)")

    checks = [(outside.any(), message)]
    if duplicates and idx.shape[0] > 1:
        cells = math.prod([batch_size] + spatial_shape)
        if cells < 2**62:  # linear keys fit int64 (rows outside are told apart by the check above first)
            strides = torch.tensor([math.prod(([batch_size] + spatial_shape)[d + 1:]) for d in range(idx.shape[1])],
                                   device=idx.device)
            keys = torch.sort((idx.clamp(min=0) * strides).sum(1)).values
            repeated = keys[1:] == keys[:-1]
        else:
            rows = torch.unique(idx, dim=0)
            repeated = torch.tensor([rows.shape[0] < idx.shape[0]], device=idx.device)

        def dup_message() -> str:
            uniq, counts = torch.unique(idx, dim=0, return_counts=True)
            return (f"indices hold site {uniq[counts > 1][0].tolist()} (batch, coordinates) more than once: each site "
                    "must appear once (a dense map or a 1 x 1 submanifold convolution would keep only one of its rows)")

        checks.append((repeated.any(), dup_message))
    run_value_checks(checks)


def _sites_key(indices: Tensor, batch_size: int, spatial_shape) -> Optional[tuple]:
    """What a check of ``indices`` on a grid is remembered by: its version counter and the grid. None for an
    inference tensor (no version counter: never remembered) and while compiling (nothing is remembered)."""
    if indices.is_inference() or torch.compiler.is_compiling():
        return None
    return (indices._version, batch_size, tuple(spatial_shape), "sites")


def sites_checked(indices: Tensor, batch_size: int, spatial_shape) -> bool:
    """Whether ``indices`` are known to lie in the grid with each site once, at their current version:
    checked before (:func:`check_sites`, a kernel map's validation) or made by a layer (a convolution's
    output sites, ``from_dense``)."""
    key = _sites_key(indices, batch_size, spatial_shape)
    return key is not None and getattr(indices, "_lidarops_checked", None) == key


def mark_sites_checked(indices: Tensor, batch_size: int, spatial_shape) -> None:
    """Remember that ``indices`` hold valid, unique sites of the grid (until changed in place)."""
    key = _sites_key(indices, batch_size, spatial_shape)
    if key is not None:
        indices._lidarops_checked = key


def check_sites(x: "SparseConvTensor") -> None:
    """The sites of ``x`` lie in its grid and each appears once: checked once per indices tensor and shape
    (a layer with a cached map returns the same indices tensor every call: no host synchronisation after the
    first; sites a layer made, or a kernel map already checked, are not checked again); an in-place change
    re-checks. Inference tensors keep no version counter: checked every time. Edits through ``.data`` bypass
    the version counter (as they do autograd's checks): make a new tensor."""
    if (value_checks_enabled() and x.indices.numel()
            and not sites_checked(x.indices, x.batch_size, x.spatial_shape)):
        _range_check(x.indices, x.batch_size, x.spatial_shape, duplicates=True)
        mark_sites_checked(x.indices, x.batch_size, x.spatial_shape)


def _as_int32(indices: Tensor, batch_size: int, spatial_shape: list) -> Tensor:
    """int32 indices; other integer dtypes are range-checked before the conversion (which would wrap)."""
    if indices.dtype == torch.int32:
        return indices
    if value_checks_enabled() and indices.numel():
        _range_check(indices, batch_size, spatial_shape)
    return indices.to(torch.int32)


class SparseConvTensor:
    """Sparse feature map in spconv's layout.

    Args:
        features (Tensor[N, C]): one feature row per active site.
        indices (Tensor[N, 1 + D] int32): ``(batch, c_0, ..., c_{D-1})`` of each row, coordinates in
            the order of ``spatial_shape`` (``(z, y, x)`` for voxels, ``(y, x)`` for pillars). Sites must
            be unique and inside the grid; the first kernel map built on them checks both (once per
            indices tensor and version: one host synchronisation on CUDA, which a layer makes once its
            convolution is queued, raising before it returns). Other integer
            dtypes (int64 coordinates) are checked against ``batch_size`` and ``spatial_shape`` first
            (one value check, skipped under ``lidarops.validation(False)``) and then converted to
            int32, so that no out-of-range value wraps around (``.int()`` would wrap silently).
        spatial_shape (Sequence[int]): the grid, D ints in [1, 2^31 - 1] (floats are refused, not
            truncated).
        batch_size (int): number of samples, in [0, 2^31 - 1]; samples may have no sites.
            ``batch_size * prod(spatial_shape)`` must be below 2^62.
        indice_dict (dict, optional): kernel-map cache shared with the tensors this one derives from.

    Raises:
        ValueError: naming the argument: indices that are not an integer (N, 1 + D) tensor or hold
            values outside the grid (non-int32 indices), a spatial_shape or batch_size that is not
            made of ints in range, features that are not an (N, C) tensor on the indices' device.

    Attributes:
        indice_dict (dict[str, KernelMap]): kernel maps registered by the layers that produced this
            tensor, keyed by ``indice_key``; layers with the same key reuse them (spconv's rule).
    """

    def __init__(self, features: Tensor, indices: Tensor, spatial_shape: Sequence[int], batch_size: int,
                 grid: Optional[Tensor] = None, voxel_num: Optional[Tensor] = None,
                 indice_dict: Optional[dict] = None, benchmark: bool = False, **unused):
        if not isinstance(indices, Tensor):
            raise ValueError(f"indices must be a torch.Tensor, got {type(indices).__name__}")
        if indices.dim() != 2 or indices.shape[1] < 2:
            raise ValueError(f"indices must be (N, 1 + D) int32 with the batch index in column 0, got {describe(indices)}")
        if indices.is_floating_point() or indices.is_complex() or indices.dtype == torch.bool:
            raise ValueError(f"indices must be an integer tensor (int32, spconv's layout), got {describe(indices)}")
        ndim = indices.shape[1] - 1
        self.spatial_shape = list(_spatial_shape(spatial_shape, ndim))
        batch_size = _int(batch_size, "batch_size", 0, _INT32_MAX)
        if batch_size * math.prod(self.spatial_shape) >= _MAX_SITES:
            raise ValueError(f"batch_size * prod(spatial_shape) must be below 2^62, got {batch_size} * "
                             f"prod({self.spatial_shape}) = {batch_size * math.prod(self.spatial_shape):.4g}")
        self.batch_size = batch_size
        self.indices = _as_int32(indices, batch_size, self.spatial_shape)
        self.features = features
        self.indice_dict = {} if indice_dict is None else indice_dict
        self.grid = grid
        self.voxel_num = voxel_num
        self.benchmark = benchmark
        self.benchmark_record = {}
        self.thrust_allocator = None

    @classmethod
    def _derived(cls, features: Tensor, indices: Tensor, spatial_shape: Sequence[int], batch_size: int,
                 indice_dict: dict, grid=None, voxel_num=None, benchmark: bool = False) -> "SparseConvTensor":
        """A tensor from parts that are already valid (those of another SparseConvTensor or of a kernel
        map): only the features are checked. The layers make one per call, so it skips __init__'s checks
        (host time of eager forwards)."""
        out = cls.__new__(cls)
        out.indices = indices
        out.spatial_shape = list(spatial_shape)
        out.batch_size = batch_size
        out.features = features
        out.indice_dict = indice_dict
        out.grid = grid
        out.voxel_num = voxel_num
        out.benchmark = benchmark
        out.benchmark_record = {}
        out.thrust_allocator = None
        return out

    # features are checked on every assignment (replace_feature, or ``x.features = ...`` in old code)
    @property
    def features(self) -> Tensor:
        return self._features

    @features.setter
    def features(self, value: Tensor) -> None:
        if not isinstance(value, Tensor):
            raise ValueError(f"features must be a torch.Tensor, got {type(value).__name__}")
        if value.dim() != 2 or value.shape[0] != self.indices.shape[0]:
            raise ValueError(f"features must be (N, C) with N = {self.indices.shape[0]} rows (one per row of indices), "
                             f"got {describe(value)}")
        if value.device != self.indices.device:
            raise ValueError(f"features are on {value.device} but indices are on {self.indices.device}")
        self._features = value

    def __repr__(self) -> str:
        return (f"SparseConvTensor(features={tuple(self.features.shape)}, dtype={self.features.dtype}, "
                f"spatial_shape={self.spatial_shape}, batch_size={self.batch_size}, device={self.features.device})")

    @property
    def ndim(self) -> int:
        """Number of spatial dimensions D."""
        return len(self.spatial_shape)

    @property
    def device(self) -> torch.device:
        return self.features.device

    @property
    def dtype(self) -> torch.dtype:
        return self.features.dtype

    @property
    def spatial_size(self) -> int:
        """Number of sites of one sample's grid, ``prod(spatial_shape)``."""
        return int(math.prod(self.spatial_shape))

    def find_indice_pair(self, key) -> Optional[KernelMap]:
        """The kernel map registered under ``key``, or None."""
        if key is None:
            return None
        return self.indice_dict.get(key)

    def replace_feature(self, features: Tensor) -> "SparseConvTensor":
        """A tensor with the same sites (and kernel-map cache) and new features ``(N, C')``."""
        out = SparseConvTensor._derived(features, self.indices, self.spatial_shape, self.batch_size, self.indice_dict,
                                        self.grid, self.voxel_num, self.benchmark)
        out.benchmark_record = self.benchmark_record
        return out

    def shadow_copy(self) -> "SparseConvTensor":
        return self.replace_feature(self.features)

    def minus(self) -> "SparseConvTensor":
        return self.replace_feature(-self.features)

    def _other_features(self, other) -> Tensor:
        if isinstance(other, SparseConvTensor):
            if other.indices is not self.indices and other.indices.shape != self.indices.shape:
                raise ValueError(f"cannot add sparse tensors with different sites ({tuple(self.indices.shape)} and "
                                 f"{tuple(other.indices.shape)} indices)")
            return other.features
        if isinstance(other, Tensor):
            return other
        raise TypeError(f"unsupported operand type {type(other).__name__}")

    def __add__(self, other) -> "SparseConvTensor":
        return self.replace_feature(self.features + self._other_features(other))

    __radd__ = __add__

    def __iadd__(self, other) -> "SparseConvTensor":
        self.features = self.features + self._other_features(other)
        return self

    def dense(self, channels_first: bool = True) -> Tensor:
        """Dense tensor with zeros at inactive sites.

        Returns:
            Tensor[B, C, *spatial_shape] (``channels_first=True``) or Tensor[B, *spatial_shape, C].
            Differentiable with respect to ``features``.
        """
        C = self.features.shape[1]
        check_sites(self)
        if channels_first and self.features.is_floating_point():
            # the registered op moves 32 x 32 tiles through shared memory on CUDA: coalesced writes into
            # the channel planes, about twice as fast as index_put_ through a channels-last view
            return torch.ops.lidarops.sparse_to_dense(self.features, self.indices, self.batch_size,
                                                      self.spatial_shape)
        out = self.features.new_zeros([self.batch_size] + self.spatial_shape + [C])
        out = out.index_put(tuple(self.indices.long().unbind(1)), self.features)
        return out.movedim(-1, 1).contiguous() if channels_first else out  # integer or bool features

    @classmethod
    def from_dense(cls, x: Tensor, channels_first: bool = False) -> "SparseConvTensor":
        """Sparse tensor of the sites of ``x`` whose feature vector is not all zero (spconv's rule).

        Args:
            x (Tensor[B, *spatial, C]): channels last, as spconv's ``from_dense``; or
                Tensor[B, C, *spatial] with ``channels_first=True``.

        Returns:
            SparseConvTensor with sites in row-major order; features differentiable with respect to x.
        """
        if not isinstance(x, Tensor) or x.dim() < 3:
            raise ValueError(f"x must be a (B, *spatial, C) tensor, got {describe(x)}")
        if channels_first:
            x = x.movedim(1, -1)
        active = (x != 0).any(-1)
        idx = torch.nonzero(active)
        features = x[tuple(idx.unbind(1))]
        out = cls(features, idx.to(torch.int32), list(x.shape[1:-1]), x.shape[0])
        mark_sites_checked(out.indices, out.batch_size, out.spatial_shape)  # nonzero's sites: in the grid, once each
        return out
