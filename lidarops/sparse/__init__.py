"""Sparse convolution on CPU and CUDA, in spconv's data layout.

::

    from lidarops.sparse import SparseConvTensor, nn as spnn
    x = SparseConvTensor(features, indices, spatial_shape, batch_size)   # indices int32 (N, 1 + D)
    net = spnn.SparseSequential(spnn.SubMConv3d(4, 16, 3, indice_key="subm1"), torch.nn.BatchNorm1d(16),
                                torch.nn.ReLU(), spnn.SparseConv3d(16, 32, 3, stride=2, indice_key="down1"))
    y = net(x).dense()

- :class:`SparseConvTensor` features (N, C), indices (N, 1 + D) int32 (batch in column 0), kernel-map
  cache ``indice_dict``.
- :mod:`lidarops.sparse.functional`: kernel maps (``conv_out_indices``, ``kernel_map``,
  ``build_kernel_map``), ``sparse_conv`` (gather-GEMM-scatter over a map), ``conv``, ``max_pool``.
- :class:`GraphedSparseNet`: a sparse network replayed as one CUDA graph while its sites stay the same.
- :mod:`lidarops.sparse.nn`: ``SubMConv2d/3d``, ``SparseConv2d/3d``, ``SparseConvTranspose2d/3d``,
  ``SparseInverseConv2d/3d``, ``SparseMaxPool2d/3d``, ``SparseSequential``, ``ToDense``.

Weights are ``[Cout, *kernel, Cin]`` (spconv 2.x). The drop-in face for spconv code is
:mod:`lidarops.compat.spconv`.
"""
from lidarops.sparse import functional, nn
from lidarops.sparse.functional import build_kernel_map, conv, kernel_map, max_pool, sparse_conv
from lidarops.sparse.graph import GraphedSparseNet
from lidarops.sparse.nn import (SparseConv2d, SparseConv3d, SparseConvTranspose2d, SparseConvTranspose3d,
                                SparseInverseConv2d, SparseInverseConv3d, SparseMaxPool2d, SparseMaxPool3d,
                                SparseConvBNReLU, SparseModule, SparseSequential, SubMConv2d, SubMConv3d, ToDense)
from lidarops.sparse.tensor import KernelMap, SparseConvTensor

__all__ = [
    "SparseConvTensor", "KernelMap", "functional", "nn", "build_kernel_map", "kernel_map", "conv", "max_pool",
    "sparse_conv", "SubMConv2d", "SubMConv3d", "SparseConv2d", "SparseConv3d", "SparseConvTranspose2d",
    "SparseConvTranspose3d", "SparseInverseConv2d", "SparseInverseConv3d", "SparseMaxPool2d", "SparseMaxPool3d",
    "SparseModule", "SparseSequential", "SparseConvBNReLU", "ToDense", "GraphedSparseNet",
]
