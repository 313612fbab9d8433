"""Sparse convolution modules: ``SubMConv2d/3d``, ``SparseConv2d/3d``, ``SparseConvTranspose2d/3d``,
``SparseInverseConv2d/3d``, ``SparseMaxPool2d/3d``, ``SparseSequential``, ``ToDense`` and feature-wise
wrappers (``SparseBatchNorm``, ``SparseReLU``, ``SparseIdentity``).

Weights are ``[Cout, *kernel, Cin]`` (spconv 2.x), so spconv state_dicts load unchanged; see
:mod:`lidarops.compat.spconv` for the face that also reproduces spconv's kernel-size-1 computation.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from typing import Optional

import torch
from torch import Tensor, nn

from lidarops import extension
from lidarops.sparse import functional as Fs
from lidarops.sparse.tensor import SparseConvTensor

__all__ = [
    "SparseModule", "SparseConvolution", "SubMConv1d", "SubMConv2d", "SubMConv3d", "SparseConv1d", "SparseConv2d",
    "SparseConv3d", "SparseConvTranspose1d", "SparseConvTranspose2d", "SparseConvTranspose3d", "SparseInverseConv1d",
    "SparseInverseConv2d", "SparseInverseConv3d", "SparseMaxPool", "SparseMaxPool1d", "SparseMaxPool2d",
    "SparseMaxPool3d", "SparseSequential", "SparseConvBNReLU", "ToDense", "SparseBatchNorm", "SparseReLU",
    "SparseIdentity",
]


class SparseModule(nn.Module):
    """Marker: ``SparseSequential`` hands these modules the whole ``SparseConvTensor``; any other
    module gets only the features."""

    def __init__(self, name: Optional[str] = None):
        super().__init__()
        self.name = name


def _expand(v, ndim: int, name: str, minimum: int) -> tuple:
    return Fs._ntuple(v, ndim, name, minimum)


class SparseConvolution(SparseModule):
    """Sparse convolution layer.

    Args:
        ndim (int): spatial dimensions D.
        in_channels, out_channels (int).
        kernel_size, stride, padding, dilation, output_padding: ints or D-tuples.
        bias (bool).
        kind (str): ``"subm"``, ``"conv"``, ``"transposed"`` or ``"inverse"`` (see
            :mod:`lidarops.sparse.functional`).
        indice_key (str, optional): kernel-map cache key (spconv's reuse rule).
        method (str): coordinate table for new kernel maps: ``"auto"``, ``"dense"`` or ``"hash"``.
        algo (str): the CUDA kernel choice, one of :data:`lidarops.sparse.functional.CONV_ALGOS`
            (default ``"auto"``; spconv's ``algo``).

    Attributes:
        weight (Parameter[Cout, *kernel, Cin]), bias (Parameter[Cout] or None).

    Shape:
        ``SparseConvTensor`` with features (N, Cin) -> ``SparseConvTensor`` with features (N_out, Cout).
    """

    def __init__(self, ndim: int, in_channels: int, out_channels: int, kernel_size=3, stride=1, padding=0,
                 dilation=1, bias: bool = True, kind: str = "conv", output_padding=0,
                 indice_key: Optional[str] = None, method: str = "auto", name: Optional[str] = None,
                 algo: str = "auto"):
        super().__init__(name=name)
        if kind not in Fs._KINDS:
            raise ValueError(f"kind must be one of {Fs._KINDS}, got {kind!r}")
        for v, n in ((in_channels, "in_channels"), (out_channels, "out_channels")):
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{n} must be a positive int, got {v!r}")
        Fs._method(method)
        Fs._conv_algo(algo)
        if bias not in (True, False):  # "no" would be truthy
            raise ValueError(f"bias must be True or False, got {bias!r}")
        if indice_key is not None and not isinstance(indice_key, str):
            raise ValueError(f"indice_key must be a str or None, got {indice_key!r}")
        self.ndim = ndim
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = _expand(kernel_size, ndim, "kernel_size", 1)
        self.stride = _expand(stride, ndim, "stride", 1)
        self.padding = _expand(padding, ndim, "padding", 0)
        self.dilation = _expand(dilation, ndim, "dilation", 1)
        self.output_padding = _expand(output_padding, ndim, "output_padding", 0)
        self.kind = kind
        self.indice_key = indice_key
        self.method = method
        self.algo = algo
        self.weight = nn.Parameter(torch.empty(out_channels, *self.kernel_size, in_channels))
        if bias:
            self.bias = nn.Parameter(torch.empty(out_channels))
        else:
            self.register_parameter("bias", None)
        self.reset_parameters()

    # spconv names
    @property
    def subm(self) -> bool:
        return self.kind == "subm"

    @property
    def transposed(self) -> bool:
        return self.kind == "transposed"

    @property
    def inverse(self) -> bool:
        return self.kind == "inverse"

    def reset_parameters(self) -> None:
        """PyTorch's convolution initialisation: U(-1/sqrt(fan_in), 1/sqrt(fan_in)), fan_in = Cin * K."""
        bound = 1.0 / math.sqrt(self.in_channels * math.prod(self.kernel_size))
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def extra_repr(self) -> str:
        s = f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, kind={self.kind!r}"
        if self.kind in ("conv", "transposed"):
            s += f", stride={self.stride}, padding={self.padding}"
        if any(d != 1 for d in self.dilation):
            s += f", dilation={self.dilation}"
        if self.bias is None:
            s += ", bias=False"
        if self.indice_key is not None:
            s += f", indice_key={self.indice_key!r}"
        if self.algo != "auto":
            s += f", algo={self.algo!r}"
        return s

    def _out_spatial_shape(self, x: SparseConvTensor):
        return None

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return self._conv(x)

    def _conv(self, x: SparseConvTensor, scale: Optional[Tensor] = None, shift: Optional[Tensor] = None,
              relu: bool = False, with_bias: bool = True) -> SparseConvTensor:
        """The layer, with :func:`lidarops.sparse.functional.conv`'s epilogue (used by SparseSequential to
        fuse a following BatchNorm in eval mode and ReLU; ``with_bias=False`` when ``shift`` holds the
        bias already)."""
        if not isinstance(x, SparseConvTensor):
            raise ValueError(f"{type(self).__name__} takes a SparseConvTensor, got {type(x).__name__}")
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__} expects {self.in_channels} input channels, got features "
                             f"{tuple(x.features.shape)}")
        return Fs.conv(x, _param(self, "weight"), _param(self, "bias") if with_bias else None, self.kind, self.stride,
                       self.padding, self.dilation, self.output_padding, self.indice_key, self._out_spatial_shape(x),
                       self.method, scale=scale, shift=shift, relu=relu, algo=self.algo)


def _subm(ndim):
    class _SubM(SparseConvolution):
        __doc__ = f"""Submanifold {ndim}D convolution: outputs exactly at the input sites, the dense convolution
        with stride 1 and ``padding = dilation * (k // 2)`` read there. ``stride`` must be 1 and
        ``padding`` is ignored (accepted for spconv's signature)."""

        def __init__(self, in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, bias=True,
                     indice_key=None, method="auto", name=None, algo="auto"):
            if any(s != 1 for s in _expand(stride, ndim, "stride", 1)):
                raise ValueError(f"a submanifold convolution has stride 1, got stride={stride!r}")
            super().__init__(ndim, in_channels, out_channels, kernel_size, 1, 0, dilation, bias, "subm",
                             indice_key=indice_key, method=method, name=name, algo=algo)
    _SubM.__name__ = _SubM.__qualname__ = f"SubMConv{ndim}d"
    return _SubM


def _regular(ndim):
    class _Conv(SparseConvolution):
        __doc__ = f"""Regular sparse {ndim}D convolution: outputs wherever an input site lies in the receptive
        field; equals ``F.conv{ndim}d`` on the dense tensor at those sites."""

        def __init__(self, in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, bias=True,
                     indice_key=None, method="auto", name=None, algo="auto"):
            super().__init__(ndim, in_channels, out_channels, kernel_size, stride, padding, dilation, bias, "conv",
                             indice_key=indice_key, method=method, name=name, algo=algo)
    _Conv.__name__ = _Conv.__qualname__ = f"SparseConv{ndim}d"
    return _Conv


def _transposed(ndim):
    class _ConvT(SparseConvolution):
        __doc__ = f"""Transposed sparse {ndim}D convolution (generative upsampling): equals
        ``F.conv_transpose{ndim}d`` (weight ``w.permute(D + 1, 0, 1..D)``) at every site an input reaches."""

        def __init__(self, in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, bias=True,
                     indice_key=None, output_padding=0, method="auto", name=None, algo="auto"):
            super().__init__(ndim, in_channels, out_channels, kernel_size, stride, padding, dilation, bias,
                             "transposed", output_padding=output_padding, indice_key=indice_key, method=method,
                             name=name, algo=algo)
    _ConvT.__name__ = _ConvT.__qualname__ = f"SparseConvTranspose{ndim}d"
    return _ConvT


def _inverse(ndim):
    class _Inv(SparseConvolution):
        __doc__ = f"""Inverse sparse {ndim}D convolution: back to the input sites of the strided convolution
        registered under ``indice_key`` (same kernel size), by its swapped kernel map."""

        def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=True, method="auto", name=None,
                     algo="auto"):
            if indice_key is None:
                raise ValueError("SparseInverseConv needs the indice_key of the convolution it inverts")
            super().__init__(ndim, in_channels, out_channels, kernel_size, bias=bias, kind="inverse",
                             indice_key=indice_key, method=method, name=name, algo=algo)
    _Inv.__name__ = _Inv.__qualname__ = f"SparseInverseConv{ndim}d"
    return _Inv


SubMConv1d, SubMConv2d, SubMConv3d = _subm(1), _subm(2), _subm(3)
SparseConv1d, SparseConv2d, SparseConv3d = _regular(1), _regular(2), _regular(3)
SparseConvTranspose1d, SparseConvTranspose2d, SparseConvTranspose3d = _transposed(1), _transposed(2), _transposed(3)
SparseInverseConv1d, SparseInverseConv2d, SparseInverseConv3d = _inverse(1), _inverse(2), _inverse(3)


class SparseMaxPool(SparseModule):
    """Sparse max pooling over the active sites of each window (see :func:`lidarops.sparse.functional.max_pool`).

    Args:
        ndim (int), kernel_size, stride (default kernel_size), padding, dilation, subm (bool),
        indice_key (str, optional), method (str).
    """

    def __init__(self, ndim: int, kernel_size, stride=None, padding=0, dilation=1, subm: bool = False,
                 indice_key: Optional[str] = None, method: str = "auto", name: Optional[str] = None):
        super().__init__(name=name)
        self.ndim = ndim
        self.kernel_size = _expand(kernel_size, ndim, "kernel_size", 1)
        self.stride = self.kernel_size if stride is None else _expand(stride, ndim, "stride", 1)
        self.padding = _expand(padding, ndim, "padding", 0)
        self.dilation = _expand(dilation, ndim, "dilation", 1)
        self.subm = subm
        self.indice_key = indice_key
        self.method = method

    def extra_repr(self) -> str:
        return (f"kernel_size={self.kernel_size}, stride={self.stride}, padding={self.padding}, "
                f"dilation={self.dilation}, subm={self.subm}")

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return Fs.max_pool(x, self.kernel_size, self.stride, self.padding, self.dilation, self.subm,
                           self.indice_key, self.method)


def _pool(ndim):
    class _Pool(SparseMaxPool):
        def __init__(self, kernel_size, stride=None, padding=0, dilation=1, indice_key=None, subm=False,
                     method="auto", name=None):
            super().__init__(ndim, kernel_size, stride, padding, dilation, subm, indice_key, method, name)
    _Pool.__name__ = _Pool.__qualname__ = f"SparseMaxPool{ndim}d"
    return _Pool


SparseMaxPool1d, SparseMaxPool2d, SparseMaxPool3d = _pool(1), _pool(2), _pool(3)


class SparseSequential(SparseModule):
    """Sequential container for sparse networks (spconv's rules).

    ``SparseModule`` children receive the ``SparseConvTensor``; any other module (``nn.BatchNorm1d``,
    ``nn.ReLU``, ``nn.Linear`` ...) is applied to its features (after ``ToDense``, to the dense tensor).
    BatchNorm is skipped on a tensor without sites (its statistics are undefined there).

    Inference fusion: a sparse convolution followed by a BatchNorm in eval mode (and a ReLU) runs as one
    convolution whose kernel applies the BatchNorm's affine map and the ReLU to its float accumulator
    (:func:`lidarops.sparse.functional.norm_affine`), when no gradient is needed and no forward hook is
    set on those modules: two to four fewer kernel launches per layer and no pass over the features.

    Accepts modules positionally, an ``OrderedDict``, or keyword arguments.
    """

    def __init__(self, *args, **kwargs):
        super().__init__()
        if len(args) == 1 and isinstance(args[0], OrderedDict):
            for key, module in args[0].items():
                self.add_module(key, module)
        else:
            for i, module in enumerate(args):
                self.add_module(str(i), module)
        for key, module in kwargs.items():
            if key in self._modules:
                raise ValueError(f"module name {key!r} exists")
            self.add_module(key, module)

    def __getitem__(self, idx: int) -> nn.Module:
        n = len(self._modules)
        if not -n <= idx < n:
            raise IndexError(f"index {idx} is out of range for {n} modules")
        return list(self._modules.values())[idx % n]

    def __len__(self) -> int:
        return len(self._modules)

    def __iter__(self):
        return iter(self._modules.values())

    def add(self, module: nn.Module, name: Optional[str] = None) -> None:
        name = str(len(self._modules)) if name is None else name
        if name in self._modules:
            raise KeyError(f"module name {name!r} exists")
        self.add_module(name, module)

    def forward(self, x):
        modules = list(self._modules.values())
        i = 0
        while i < len(modules):
            module = modules[i]
            i += 1
            if isinstance(module, SparseConvolution) and isinstance(x, SparseConvTensor):
                if module.kind == "subm" and module.indice_key is not None:
                    chained = _subm_chain(modules, i - 1, x)
                    if chained is not None:
                        x, i = chained
                        continue
                fused = _fusable(modules, i - 1, x)
                if fused:  # conv -> BatchNorm (eval) [-> ReLU] in one kernel
                    # the bias folded into shift (read from the dict, not through nn.Module.__getattr__)
                    scale, shift = Fs.norm_affine(modules[i], _param(module, "bias"))
                    x = module._conv(x, scale, shift, fused == 3, with_bias=False)
                    i += fused - 1
                    continue
            if isinstance(module, SparseModule):
                x = module(x)
            elif isinstance(x, SparseConvTensor):
                if x.features.shape[0] == 0 and isinstance(module, nn.modules.batchnorm._BatchNorm):
                    continue
                x = x.replace_feature(module(x.features))
            else:
                x = module(x)
        return x


class SparseConvBNReLU(SparseModule):
    """A sparse convolution, a BatchNorm and (optionally) a ReLU as one module: in eval mode without gradients the
    three run as one convolution whose kernel applies the BatchNorm's affine map, the bias and the ReLU to its float
    accumulator; otherwise (training, gradients, float64, ``torch.compile``) as the three modules in turn, with the
    BatchNorm's own statistics and updates. What ``SparseSequential(conv, norm, nn.ReLU())`` does by recognising
    the pattern, as an explicit module.

    Args:
        conv (SparseConvolution): the convolution (any kind; its ``indice_key`` rules apply).
        norm (nn.BatchNorm1d or SparseBatchNorm): over ``conv.out_channels`` features.
        relu (bool): apply a ReLU (default True).

    State dict: ``conv.*`` and ``norm.*``, so the parts' checkpoints load unchanged.
    """

    def __init__(self, conv: SparseConvolution, norm: nn.Module, relu: bool = True):
        super().__init__()
        if not isinstance(conv, SparseConvolution):
            raise ValueError(f"conv must be a sparse convolution (SparseConvolution), got {type(conv).__name__}")
        if not isinstance(norm, nn.modules.batchnorm._BatchNorm) or norm.num_features != conv.out_channels:
            raise ValueError(f"norm must be a BatchNorm over conv's {conv.out_channels} output channels, got {norm!r}")
        if not isinstance(relu, bool):
            raise ValueError(f"relu must be True or False, got {relu!r}")
        self.conv, self.norm, self.relu = conv, norm, relu

    def extra_repr(self) -> str:
        return f"relu={self.relu}"

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        conv, norm = self._modules["conv"], self._modules["norm"]
        # (hooks on this module run either way; hooks on its parts need the parts to run)
        if isinstance(x, SparseConvTensor) and _fusable([conv, norm], 0, x):
            scale, shift = Fs.norm_affine(norm, _param(conv, "bias"))
            return conv._conv(x, scale, shift, self.relu, with_bias=False)
        y = conv(x)
        if y.features.shape[0]:  # skipped without sites, as in SparseSequential (no batch statistics there)
            y = y.replace_feature(norm(y.features))
        return y.replace_feature(torch.relu(y.features)) if self.relu else y


def _fusable(modules: list, i: int, x: SparseConvTensor) -> int:
    """How many modules from ``modules[i]`` (a sparse convolution) run as one fused convolution: 3 for
    conv -> BatchNorm in eval mode -> ReLU, 2 without the ReLU, 0 when they cannot (no BatchNorm
    after it, BatchNorm in training mode or without running statistics, gradients needed, float64
    features, spconv's kernel-size-1 shortcut, or inside torch.compile)."""
    conv = modules[i]
    # the instance's and the class's dicts, not getattr (a missing attribute goes through nn.Module.__getattr__
    # and an exception)
    if i + 1 >= len(modules) or conv.__dict__.get("conv1x1", getattr(type(conv), "conv1x1", False)):
        return 0
    bn = modules[i + 1]
    if not Fs.fusable_norm(x, bn, _param(conv, "weight"), _param(conv, "bias")):
        return 0
    relu = i + 2 < len(modules) and type(modules[i + 2]) in (nn.ReLU, SparseReLU)
    n = 3 if relu else 2
    for m in modules[i:i + n]:
        if m._forward_hooks or m._forward_pre_hooks:
            return 0  # the fused path does not call these modules, so their hooks would not run
    return 0 if _global_hooks() else n


def _subm_chain(modules: list, i: int, x: SparseConvTensor) -> Optional[tuple]:
    """The fused SubM layers from ``modules[i]`` on that share its ``indice_key``, kernel, dilation and ``algo``, each
    fusable with its BatchNorm (:func:`_fusable`), run as one op call (``sparse_conv_affine_chain``) on their map,
    built (and registered) or reused as the first layer's call would: the same kernels as layer by layer, without
    each layer's Python. Returns ``(x, i)`` past them, or None where ``modules[i]`` cannot start a chain (float64,
    autocast, a 1 x 1 kernel, a layer that does not fit ``x`` or would raise: the layer path runs it and raises)."""
    first = modules[i]
    f = x.features
    key, ksize, dilation, algo = first.indice_key, first.kernel_size, first.dilation, first.algo
    if f.dtype == torch.float64 or len(ksize) != x.ndim or Fs._autocast_on(f):
        return None
    K = math.prod(ksize)
    if K == 1:  # spconv's 1 x 1 rule: a matrix product, no map
        return None
    cin = f.shape[1]
    weights, scales, shifts, relus = [], [], [], []
    while i < len(modules):
        conv = modules[i]
        if not (isinstance(conv, SparseConvolution) and conv.kind == "subm" and conv.indice_key == key
                and conv.kernel_size == ksize and conv.dilation == dilation and conv.algo == algo
                and conv.in_channels == cin):
            break
        fused = _fusable(modules, i, x)
        w = _param(conv, "weight")
        if not fused or w.dtype != f.dtype or w.device != f.device or w.shape[1:] != (*ksize, cin):
            break
        scale, shift = Fs.norm_affine(modules[i + 1], _param(conv, "bias"))
        weights.append(w.reshape(w.shape[0], K, cin))
        scales.append(scale)
        shifts.append(shift)
        relus.append(fused == 3)
        cin = w.shape[0]
        i += fused
    if not weights:
        return None
    extension.check_device(f, "features")
    km, cache, pending = Fs._kernel_map_for(x, "subm", ksize, first.stride, first.padding, dilation, 0, key, None,
                                            first.method, defer=True)
    x = Fs._subm_chain(x, km, cache, weights, scales, shifts, relus, algo)
    if pending is not None:
        Fs._settle(pending)
    return x, i


_MISSING = object()


def _param(module: nn.Module, name: str):
    """``module.<name>`` read from its parameter dict when it is there (a parameter, or None for no bias): the
    attribute goes through ``nn.Module.__getattr__``, host time on every layer; a parametrized weight is not in
    the dict and is read as an attribute."""
    p = module._parameters.get(name, _MISSING)
    return getattr(module, name) if p is _MISSING else p


def _global_hooks() -> bool:
    m = nn.modules.module
    return bool(m._global_forward_hooks or m._global_forward_pre_hooks)


class ToDense(SparseModule):
    """``SparseConvTensor`` -> dense ``Tensor[B, C, *spatial_shape]``."""

    def forward(self, x: SparseConvTensor) -> Tensor:
        return x.dense(channels_first=True)


class SparseBatchNorm(nn.BatchNorm1d, SparseModule):
    """BatchNorm1d over the features of a ``SparseConvTensor`` (or of a plain (N, C) tensor)."""

    def forward(self, x):
        if isinstance(x, SparseConvTensor):
            if x.features.shape[0] == 0:
                return x
            return x.replace_feature(super().forward(x.features))
        return super().forward(x)


class SparseReLU(nn.ReLU, SparseModule):
    def forward(self, x):
        if isinstance(x, SparseConvTensor):
            return x.replace_feature(super().forward(x.features))
        return super().forward(x)


class SparseIdentity(nn.Identity, SparseModule):
    def forward(self, x):
        return x
