"""Drop-in face of spconv 2.x (``import spconv.pytorch as spconv``) on lidarops' sparse convolution.

::

    import lidarops.compat.spconv as spconv      # instead of: import spconv.pytorch as spconv

    x = spconv.SparseConvTensor(voxel_features, voxel_coords.int(), sparse_shape, batch_size)
    block = spconv.SparseSequential(
        spconv.SubMConv3d(4, 16, 3, padding=1, bias=False, indice_key="subm1"),
        nn.BatchNorm1d(16, eps=1e-3, momentum=0.01), nn.ReLU())

Same classes, constructor arguments (``indice_key``, ``bias``; ``algo``: spconv's ``ConvAlgo`` accepted
and ignored, one of lidarops' ``CONV_ALGOS`` used; ``groups`` must be 1) and weight layout
``[Cout, *kernel, Cin]``, so OpenPCDet / mmdet3d backbones and spconv state_dicts run unchanged. Reuse
rules of ``indice_key``: a convolution whose key is already in the input's ``indice_dict`` reuses that
kernel map (lidarops checks that it fits the layer and raises ValueError where spconv would silently
use a map of another geometry); a new map is registered in the output's dict; ``SparseInverseConvNd``
inverts the map of its key.

Differences from lidarops.sparse's own modules, reproducing what spconv 2.3.8 computes:

* Kernel size 1 (``prod(kernel_size) == 1`` and, except for submanifold layers, ``prod(stride) == 1``):
  spconv takes a shortcut ``features @ weight.view(Cin, Cout)`` - not the ``[Cout, 1, ..., 1, Cin]``
  layout it documents - keeps the input sites and registers no kernel map; the output grid is
  spconv's formula (it grows by ``2 * padding`` for a padded regular convolution). This face does the
  same, so checkpoints trained with spconv give the same outputs. ``lidarops.sparse.nn`` keeps the
  documented layout.
* ``SparseConvTranspose``: output grid ``(n - 1) * stride - 2 * padding + kernel_size + output_padding``
  (spconv's formula, which ignores dilation).
"""
from __future__ import annotations

import enum
import math
import types
from typing import Optional

import torch
from torch import nn

from lidarops._lazy import lazy_attributes
from lidarops.sparse import nn as spnn
from lidarops.sparse.nn import (SparseBatchNorm, SparseIdentity, SparseModule, SparseReLU, SparseSequential,
                                ToDense)
from lidarops.sparse.tensor import KernelMap, SparseConvTensor

__all__ = [
    "ConvAlgo", "SparseConvTensor", "SparseModule", "SparseSequential", "ToDense", "SparseBatchNorm", "SparseReLU",
    "SparseIdentity", "SparseConvolution", "SparseMaxPool", "is_spconv_module",
    "SubMConv1d", "SubMConv2d", "SubMConv3d", "SubMConv4d", "SparseConv1d", "SparseConv2d", "SparseConv3d",
    "SparseConv4d", "SparseConvTranspose1d", "SparseConvTranspose2d", "SparseConvTranspose3d",
    "SparseConvTranspose4d", "SparseInverseConv1d", "SparseInverseConv2d", "SparseInverseConv3d",
    "SparseInverseConv4d", "SparseMaxPool1d", "SparseMaxPool2d", "SparseMaxPool3d", "SparseMaxPool4d",
]


class ConvAlgo(enum.Enum):
    """spconv's algorithm choice; accepted for compatibility, lidarops picks its own kernels (``algo="auto"``)."""

    Native = 0
    MaskImplicitGemm = 1
    MaskSplitImplicitGemm = 2


def is_spconv_module(module: nn.Module) -> bool:
    return isinstance(module, SparseModule)


def _as_list(v, ndim: int) -> list:
    return list(v) if isinstance(v, (list, tuple)) else [v] * ndim


class SparseConvolution(spnn.SparseConvolution):
    """spconv's ``SparseConvolution`` base class (``spconv.pytorch.conv.SparseConvolution``)."""

    def __init__(self, ndim: int, in_channels: int, out_channels: int, kernel_size=3, stride=1, padding=0,
                 dilation=1, groups=1, bias: bool = True, subm: bool = False, output_padding=0,
                 transposed: bool = False, inverse: bool = False, indice_key: Optional[str] = None, algo=None,
                 fused_bn: bool = False, name=None, **unused):
        if groups != 1:
            raise ValueError(f"spconv's sparse convolutions support groups=1 only, got groups={groups!r}")
        kind = "subm" if subm else "inverse" if inverse else "transposed" if transposed else "conv"
        ks = _as_list(kernel_size, ndim)
        st = _as_list(stride, ndim)
        # spconv's submanifold layers ignore stride and padding; spconv's ConvAlgo names spconv's kernels:
        # lidarops chooses its own, unless given one of its CONV_ALGOS
        super().__init__(ndim, in_channels, out_channels, ks, 1 if subm else st, 0 if subm else padding, dilation,
                         bias, kind, output_padding, indice_key, name=name,
                         algo=algo if isinstance(algo, str) else "auto")
        self.groups = 1
        self.fused_bn = fused_bn
        self.conv1x1 = math.prod(ks) == 1 and (subm or math.prod(st) == 1)

    def reset_parameters(self) -> None:
        """spconv's initialisation: kaiming_uniform(a=sqrt(0.005)) with fan_in = Cin * K."""
        fan_in = self.in_channels * math.prod(self.kernel_size)
        gain = math.sqrt(2.0 / (1.0 + 0.005))
        bound = gain * math.sqrt(3.0 / fan_in)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            b = 1.0 / math.sqrt(fan_in)
            nn.init.uniform_(self.bias, -b, b)

    def _spconv_out_shape(self, shape: list) -> list:
        if self.kind in ("subm", "inverse"):
            return list(shape)
        k, s, p, d = self.kernel_size, self.stride, self.padding, self.dilation
        if self.kind == "transposed":
            op = self.output_padding
            return [(n - 1) * s[i] - 2 * p[i] + k[i] + op[i] for i, n in enumerate(shape)]
        return [(n + 2 * p[i] - d[i] * (k[i] - 1) - 1) // s[i] + 1 for i, n in enumerate(shape)]

    def _out_spatial_shape(self, x: SparseConvTensor):
        if self.kind == "transposed":
            return self._spconv_out_shape(x.spatial_shape)
        return None

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        if not self.conv1x1:
            return super().forward(x)
        if not isinstance(x, SparseConvTensor):
            raise ValueError(f"{type(self).__name__} takes a SparseConvTensor, got {type(x).__name__}")
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__} expects {self.in_channels} input channels, got features "
                             f"{tuple(x.features.shape)}")
        # spconv 2.3.8's kernel-size-1 shortcut, reproduced as computed (see the module docstring)
        out = torch.mm(x.features, self.weight.reshape(self.in_channels, self.out_channels))
        if self.bias is not None:
            out = out + self.bias
        y = x.replace_feature(out)
        y.spatial_shape = self._spconv_out_shape(x.spatial_shape)
        return y


def _make_conv(cls_name: str, ndim: int, **flags):
    def __init__(self, in_channels, out_channels, kernel_size, stride=1, padding=0, dilation=1, groups=1,
                 bias=True, indice_key=None, algo=None, name=None, **unused):
        SparseConvolution.__init__(self, ndim, in_channels, out_channels, kernel_size, stride, padding, dilation,
                                   groups, bias, indice_key=indice_key, algo=algo, name=name, **flags)
    return type(cls_name, (SparseConvolution,), {"__init__": __init__, "__doc__": f"spconv's {cls_name}."})


def _make_inverse(cls_name: str, ndim: int):
    def __init__(self, in_channels, out_channels, kernel_size, indice_key, bias=True, algo=None, name=None,
                 **unused):
        SparseConvolution.__init__(self, ndim, in_channels, out_channels, kernel_size, bias=bias, inverse=True,
                                   indice_key=indice_key, algo=algo, name=name)
    return type(cls_name, (SparseConvolution,), {"__init__": __init__, "__doc__": f"spconv's {cls_name}."})


SubMConv1d, SubMConv2d, SubMConv3d, SubMConv4d = (_make_conv(f"SubMConv{n}d", n, subm=True) for n in (1, 2, 3, 4))
SparseConv1d, SparseConv2d, SparseConv3d, SparseConv4d = (_make_conv(f"SparseConv{n}d", n) for n in (1, 2, 3, 4))
SparseConvTranspose1d, SparseConvTranspose2d, SparseConvTranspose3d, SparseConvTranspose4d = (
    _make_conv(f"SparseConvTranspose{n}d", n, transposed=True) for n in (1, 2, 3, 4))
SparseInverseConv1d, SparseInverseConv2d, SparseInverseConv3d, SparseInverseConv4d = (
    _make_inverse(f"SparseInverseConv{n}d", n) for n in (1, 2, 3, 4))


class SparseMaxPool(spnn.SparseMaxPool):
    """spconv's ``SparseMaxPool`` base class."""

    def __init__(self, ndim: int, kernel_size, stride=None, padding=0, dilation=1, indice_key=None, subm=False,
                 algo=None, name=None, **unused):
        super().__init__(ndim, kernel_size, stride, padding, dilation, subm, indice_key, name=name)
        self.algo = algo

    def forward(self, x):
        y = super().forward(x)
        # spconv 2.3.8 starts each output's running max at zero, not at -inf (its pooled features are
        # max(0, window max); seen on an H100 against our -inf start, and in spconv's indiceMaxPool,
        # which fills the output with zeros). After a ReLU this changes nothing; on signed features
        # it does, and checkpoints trained with spconv saw the clamped values.
        return y.replace_feature(y.features.clamp_min(0))


def _make_pool(cls_name: str, ndim: int):
    def __init__(self, kernel_size, stride=None, padding=0, dilation=1, indice_key=None, algo=None, name=None,
                 **unused):
        SparseMaxPool.__init__(self, ndim, kernel_size, stride, padding, dilation, indice_key, algo=algo, name=name)
    return type(cls_name, (SparseMaxPool,), {"__init__": __init__, "__doc__": f"spconv's {cls_name}."})


SparseMaxPool1d, SparseMaxPool2d, SparseMaxPool3d, SparseMaxPool4d = (
    _make_pool(f"SparseMaxPool{n}d", n) for n in (1, 2, 3, 4))

# spconv's submodule paths used by downstream code (e.g. OpenPCDet's spconv_utils:
# ``isinstance(m, spconv.conv.SparseConvolution)``)
conv = types.SimpleNamespace(
    SparseConvolution=SparseConvolution, SubMConv1d=SubMConv1d, SubMConv2d=SubMConv2d, SubMConv3d=SubMConv3d,
    SubMConv4d=SubMConv4d, SparseConv1d=SparseConv1d, SparseConv2d=SparseConv2d, SparseConv3d=SparseConv3d,
    SparseConv4d=SparseConv4d, SparseConvTranspose1d=SparseConvTranspose1d,
    SparseConvTranspose2d=SparseConvTranspose2d, SparseConvTranspose3d=SparseConvTranspose3d,
    SparseConvTranspose4d=SparseConvTranspose4d, SparseInverseConv1d=SparseInverseConv1d,
    SparseInverseConv2d=SparseInverseConv2d, SparseInverseConv3d=SparseInverseConv3d,
    SparseInverseConv4d=SparseInverseConv4d)
pool = types.SimpleNamespace(SparseMaxPool=SparseMaxPool, SparseMaxPool1d=SparseMaxPool1d,
                             SparseMaxPool2d=SparseMaxPool2d, SparseMaxPool3d=SparseMaxPool3d,
                             SparseMaxPool4d=SparseMaxPool4d)
modules = types.SimpleNamespace(SparseModule=SparseModule, SparseSequential=SparseSequential,
                                is_spconv_module=is_spconv_module, SparseBatchNorm=SparseBatchNorm,
                                SparseReLU=SparseReLU, SparseIdentity=SparseIdentity)
core = types.SimpleNamespace(SparseConvTensor=SparseConvTensor, IndiceData=KernelMap)


# spconv.pytorch.utils.PointToVoxel, loaded on first use
__getattr__, __dir__ = lazy_attributes(__name__, {"PointToVoxel": ("lidarops.compat.spconv_utils", "PointToVoxel"),
                                                  "utils": "lidarops.compat.spconv_utils"}, globals())
