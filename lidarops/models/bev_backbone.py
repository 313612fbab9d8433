"""PointPillars' 2D backbone (``backbone_2d``), OpenPCDet's ``BaseBEVBackbone``, dense and sparse (Lang et
al., CVPR 2019).

- :class:`BaseBEVBackbone`: three blocks of 3x3 convolutions, the first of each block strided,
  transposed-convolution upsampling to a common grid, concatenated. The module tree and parameter names
  are OpenPCDet's (``blocks.i.j``, ``deblocks.i.j``), so its PointPillars checkpoints load;
  ``mode="sparse"`` runs the same parameters as the Sparse-PointPillars layout (a strided sparse
  convolution at the start of each block, submanifold convolutions after it, sparse transposed
  upsampling) and returns the same dense map shape.
- :meth:`BaseBEVBackbone.delta_layers`: its convolutions in sparse terms (:class:`BackboneLayer`), what
  SSCATeR's :class:`lidarops.sscater.DeltaBackbone` recycles.

Sparse semantics: a site is active when the sparse network reaches it (pillars with points; a strided
convolution's output where any active input lies under its kernel; a transposed convolution's children
of active inputs; submanifold layers keep their input's sites). Inactive sites are zero in the returned
map, so ``mode="sparse"`` and ``mode="dense"`` differ wherever BatchNorm's shift or a convolution of
zeros would make an inactive site non-zero in the dense network.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from lidarops._moved import moved_attributes
from lidarops.ops.validation import check_tensor, describe

__all__ = ["BaseBEVBackbone", "backbone_layers", "BackboneLayer"]

# the name of lidarops 0.1
__getattr__ = moved_attributes(__name__, {"PointPillarsBackbone": (__name__, "BaseBEVBackbone")})


class BackboneLayer:
    """One convolution of the backbone in sparse terms (what SSCATeR and the sparse mode run).

    Attributes:
        kind (str): ``"down"`` (strided 3x3, padding 1: regular sparse convolution), ``"subm"`` (3x3,
            submanifold) or ``"up"`` (transposed, kernel = stride: each input site feeds its stride^2
            children).
        conv (nn.Conv2d | nn.ConvTranspose2d), norm (nn.BatchNorm2d): the modules holding the parameters.
        stride (int), block (int): index of the block (or of the upsampling branch for ``"up"``).
    """

    def __init__(self, kind: str, conv: nn.Module, norm: nn.BatchNorm2d, stride: int, block: int):
        self.kind, self.conv, self.norm, self.stride, self.block = kind, conv, norm, stride, block

    def sparse_weight(self) -> Tensor:
        """Weight in lidarops.sparse's layout [Cout, kh, kw, Cin]."""
        w = self.conv.weight
        if self.kind == "up":  # ConvTranspose2d: [Cin, Cout, kh, kw]
            return w.permute(1, 2, 3, 0).contiguous()
        return w.permute(0, 2, 3, 1).contiguous()

    def folded_norm(self) -> tuple[Tensor, Tensor]:
        """Eval-mode BatchNorm as (scale, shift): y = x * scale + shift."""
        n = self.norm
        scale = n.weight / torch.sqrt(n.running_var + n.eps)
        return scale, n.bias - n.running_mean * scale


def backbone_layers(backbone: "BaseBEVBackbone") -> list[BackboneLayer]:
    """The backbone's convolutions in execution order: each block's layers, then the upsampling ones."""
    layers = []
    for b, block in enumerate(backbone.blocks):
        mods = list(block)
        convs = [(i, m) for i, m in enumerate(mods) if isinstance(m, nn.Conv2d)]
        for j, (i, conv) in enumerate(convs):
            norm = mods[i + 1]
            layers.append(BackboneLayer("down" if j == 0 else "subm", conv, norm, conv.stride[0], b))
    for b, deblock in enumerate(backbone.deblocks):
        conv, norm = deblock[0], deblock[1]
        layers.append(BackboneLayer("up", conv, norm, conv.stride[0], b))
    return layers


class BaseBEVBackbone(nn.Module):
    """PointPillars' 2D backbone (OpenPCDet's ``BaseBEVBackbone``), dense or sparse.

    Args:
        in_channels (int): channels of the pillar pseudo-image.
        layer_nums (Sequence[int]): 3x3 convolutions after the strided one, per block.
        layer_strides (Sequence[int]): stride of each block's first convolution (2 in the sparse mode).
        num_filters (Sequence[int]): channels of each block.
        upsample_strides (Sequence[int]): stride (= kernel) of each block's transposed convolution.
        num_upsample_filters (Sequence[int]): channels after upsampling, concatenated in the output.
        mode (str): ``"dense"`` (the original network on a dense pseudo-image) or ``"sparse"``.

    Shape:
        dense: ``forward(Tensor[B, in_channels, H, W])`` (a ``SparseConvTensor`` is densified first);
        sparse: ``forward(SparseConvTensor)`` with 2D indices (batch, y, x) and features
        (P, in_channels). Both return Tensor[B, sum(num_upsample_filters), H / s0 * u0, W / s0 * u0]
        ((B, 384, H/2, W/2) with the defaults). The sparse mode's map is in ``torch.channels_last``
        memory (same shape and values; ``.contiguous()`` gives channels-first memory).
    """

    def __init__(self, in_channels: int = 64, layer_nums: Sequence[int] = (3, 5, 5),
                 layer_strides: Sequence[int] = (2, 2, 2), num_filters: Sequence[int] = (64, 128, 256),
                 upsample_strides: Sequence[int] = (1, 2, 4), num_upsample_filters: Sequence[int] = (128, 128, 128),
                 mode: str = "dense"):
        super().__init__()
        if not (len(layer_nums) == len(layer_strides) == len(num_filters) == len(upsample_strides)
                == len(num_upsample_filters)):
            raise ValueError("layer_nums, layer_strides, num_filters, upsample_strides and num_upsample_filters "
                             "must have the same length")
        self.mode = self._check_mode(mode)
        self.in_channels = in_channels
        self.layer_strides = tuple(int(s) for s in layer_strides)
        self.upsample_strides = tuple(int(s) for s in upsample_strides)
        self.blocks, self.deblocks = nn.ModuleList(), nn.ModuleList()
        c_in = in_channels
        for c, n, s, u, cu in zip(num_filters, layer_nums, layer_strides, upsample_strides, num_upsample_filters):
            layers = [nn.ZeroPad2d(1), nn.Conv2d(c_in, c, 3, stride=s, padding=0, bias=False),
                      nn.BatchNorm2d(c, eps=1e-3, momentum=0.01), nn.ReLU()]
            for _ in range(n):
                layers += [nn.Conv2d(c, c, 3, padding=1, bias=False), nn.BatchNorm2d(c, eps=1e-3, momentum=0.01),
                           nn.ReLU()]
            self.blocks.append(nn.Sequential(*layers))
            if u < 1:
                raise ValueError(f"upsample_strides must be >= 1, got {tuple(upsample_strides)}")
            self.deblocks.append(nn.Sequential(nn.ConvTranspose2d(c, cu, u, stride=u, bias=False),
                                               nn.BatchNorm2d(cu, eps=1e-3, momentum=0.01), nn.ReLU()))
            c_in = c
        self.out_channels = int(sum(num_upsample_filters))

    def delta_layers(self) -> list[BackboneLayer]:
        """The convolutions in execution order, in sparse terms (:func:`backbone_layers`): what
        :class:`lidarops.sscater.DeltaBackbone` takes."""
        return backbone_layers(self)

    @staticmethod
    def _check_mode(mode: str) -> str:
        if mode not in ("dense", "sparse"):
            raise ValueError(f"mode must be 'dense' or 'sparse', got {mode!r}")
        return mode

    def output_shape(self, shape: Sequence[int]) -> tuple[int, int]:
        """(H_out, W_out) of the returned map for an input grid (H, W); ValueError when the upsampling
        branches would reach different grids (e.g. H or W not divisible by 8 with the defaults)."""
        H, W = int(shape[0]), int(shape[1])
        outs = []
        for s, u in zip(self.layer_strides, self.upsample_strides):
            H, W = (H + 2 - 3) // s + 1, (W + 2 - 3) // s + 1
            outs.append((H * u, W * u))
        if len(set(outs)) != 1:
            raise ValueError(f"the grid {tuple(int(v) for v in shape)} gives upsampled maps of different sizes "
                             f"{outs}: choose H and W divisible by the product of layer_strides")
        return outs[0]

    def forward(self, x, mode: Optional[str] = None) -> Tensor:
        mode = self.mode if mode is None else self._check_mode(mode)
        from lidarops.sparse import SparseConvTensor  # lazy: the dense mode needs no extension
        if mode == "dense":
            if isinstance(x, SparseConvTensor):
                x = x.dense(channels_first=True)
            check_tensor(x, "x")
            if x.dim() != 4 or x.shape[1] != self.in_channels:
                raise ValueError(f"x must be (B, {self.in_channels}, H, W), got {describe(x)}")
            self.output_shape(x.shape[2:])
            ups = []
            for block, deblock in zip(self.blocks, self.deblocks):
                x = block(x)
                ups.append(deblock(x))
            return torch.cat(ups, dim=1)
        if not isinstance(x, SparseConvTensor) or x.ndim != 2:
            raise ValueError(f"mode='sparse' takes a 2D SparseConvTensor, got {type(x).__name__}"
                             + (f" with {x.ndim} spatial dims" if isinstance(x, SparseConvTensor) else ""))
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"x.features must be (P, {self.in_channels}), got {describe(x.features)}")
        self.output_shape(x.spatial_shape)
        return self._forward_sparse(x)

    def _forward_sparse(self, x) -> Tensor:
        layers = backbone_layers(self)
        block_out = {}
        for layer in layers:
            if layer.kind == "down":  # every map under a key: GraphedSparseNet can record the forward
                x = _conv_norm_relu(x, layer, "conv", stride=layer.stride, padding=1, indice_key=f"down{layer.block}")
            elif layer.kind == "subm":
                x = _conv_norm_relu(x, layer, "subm", indice_key=f"subm{layer.block}")
            else:
                break
            block_out[layer.block] = x
        ups = [_conv_norm_relu(block_out[layer.block], layer, "transposed", stride=layer.stride,
                               indice_key=f"up{layer.block}") for layer in layers if layer.kind == "up"]
        # one zero map in channels_last memory, each branch's rows written into its channel slice: no
        # per-branch dense map, transposing copy or concatenation (they were most of the CPU time)
        H, W = ups[0].spatial_shape
        out = ups[0].features.new_zeros(x.batch_size, H, W, sum(u.features.shape[1] for u in ups))
        c0 = 0
        for u in ups:
            c1 = c0 + u.features.shape[1]
            b, y, xx = u.indices.long().unbind(1)
            out[b, y, xx, c0:c1] = u.features
            c0 = c1
        return out.permute(0, 3, 1, 2)  # (B, C, H, W), channels_last memory


def _conv_norm_relu(x, layer: BackboneLayer, kind: str, **kw):
    """The layer's sparse convolution, BatchNorm and ReLU: fused into the convolution's kernel in eval
    mode without gradients (lidarops.sparse.functional.conv's epilogue), else three steps."""
    from lidarops.sparse import functional as Fs
    n = layer.norm
    if not Fs.fusable_norm(x, n, layer.conv.weight):
        return _norm_relu(Fs.conv(x, layer.sparse_weight(), None, kind, **kw), layer)
    scale, shift = Fs.norm_affine(n)
    w = Fs.cached_by_version(layer.conv, "_lidarops_sparse_weight", (layer.conv.weight,), layer.sparse_weight)
    return Fs.conv(x, w, None, kind, **kw, scale=scale, shift=shift, relu=True)


def _norm_relu(x, layer: BackboneLayer):
    """BatchNorm2d's parameters applied to the (N, C) features of the active sites, then ReLU."""
    n = layer.norm
    f = x.features
    if n.training and f.shape[0] <= 1:  # no batch statistics from 0 or 1 site: the running ones, if any
        if f.shape[0]:
            f = F.batch_norm(f, n.running_mean, n.running_var, n.weight, n.bias, False, 0.0, n.eps)
    else:  # the module itself: its momentum rule (None: a cumulative average), counter and SyncBatchNorm
        f = n(f[:, :, None, None]).flatten(1)
    return x.replace_feature(torch.relu(f))
