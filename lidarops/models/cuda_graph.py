"""PointPillars inference replayed as one CUDA graph.

A frame's eager :meth:`PointPillars.predict` launches a few hundred kernels and reads back to the host
several times (the number of pillars, the boxes above the score threshold, the boxes NMS keeps); at
PointPillars' size the GPU then waits on the host. :class:`GraphedPointPillars` records the whole
inference once, for frames of up to ``capacity`` points, and replays it: padded voxelization
(``lidarops.voxelize(..., padded=True)``), the network, the decode and :func:`postprocess_padded`
(score threshold and rotated NMS with fixed-size outputs). The only host read is the number of boxes,
after the replay.

    graphed = GraphedPointPillars(model, capacity=150_000, precision="fp16")
    det = graphed(points)          # (P, 4) x, y, z, intensity on the model's device
    det["boxes"], det["scores"], det["labels"]

With ``batch_size=B`` one replay runs B frames (each voxelized on its own, the network and the
post-processing on the batch): ``graphed([p0, p1, ...])`` returns a list of such dicts, and
:meth:`GraphedPointPillars.replay` leaves the padded outputs on the device (the frame index's detector
source gathers its counts there).

The detections are :meth:`PointPillars.predict`'s (the same kernels in float32; fp16 / TF32 round like
their eager autocast runs). Only the dense backbone can be captured: the sparse one builds its kernel
maps with host reads.

:func:`inference_copy` is the optimized copy (BatchNorm and padding folded, channels-last) these graphs record under
autocast; on the CPU ``predict`` runs it without a graph (:func:`copy_predict`).
"""
from __future__ import annotations

import contextlib
import copy
import math
import numbers
from collections import OrderedDict
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

import lidarops
from lidarops._cuda_graphs import graph_capacity, record_graph, uncached_autocast
from lidarops.models.anchor_head import AnchorHeadSingle
from lidarops.models.counternet import CounterNet
from lidarops.models.map_to_bev import PointPillarScatter
from lidarops.models.pointpillars import PointPillars, _check_batch, eager_predict
from lidarops.models.postprocess import postprocess_padded
from lidarops.ops.pillars import MAX_ABS_INTENSITY
from lidarops.ops.validation import check_tensor, describe, value_checks_enabled

__all__ = ["GraphedCounterNet", "GraphedPointPillars", "PRECISIONS", "copy_predict", "graphed_predict", "inference_copy",
           "padded_counting", "padded_inference"]

PRECISIONS = ("fp32", "tf32", "fp16")


@contextlib.contextmanager
def precision_mode(precision: str | None, device_type: str = "cuda", autocast: bool = True):
    """``"fp32"``: float32 without TF32; ``"tf32"``: TF32 matmuls and convolutions; ``"fp16"``: float16
    autocast (``autocast=False``: no autocast, for a model already converted with ``.half()``); None: torch's
    settings as they are."""
    if precision is None:
        yield
        return
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    old = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = precision == "tf32"
    ctx = torch.autocast(device_type=device_type, dtype=torch.float16) \
        if precision == "fp16" and autocast else contextlib.nullcontext()
    try:
        with ctx:
            yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = old


def padded_inference(model: PointPillars, points: Tensor, max_pillars: int | None = None) -> dict[str, Tensor]:
    """:meth:`PointPillars.predict` on a batch of frames padded to one size, with outputs of sizes fixed by
    the shapes and nothing read back to the host: the body :class:`GraphedPointPillars` records, usable
    eagerly too (any device).

    The frames are voxelized by one call, stacked along z (frame b's points in the b-th slab of a pillar's
    height: the pillars are the per-frame ones, each frame keeping its own first ``max_voxels_test``), and the
    pillars of the whole batch are packed into ``max_pillars`` rows, frame after frame, so the pillar net and
    the scatter work on the pillars there are rather than on every frame's capacity.

    Args:
        model: an eval-mode PointPillars with ``backbone_mode="dense"``.
        points (Tensor[B, N, C]): frame b's points in ``points[b]``; rows outside the point range (the
            padding: x beyond it) are left out as voxelization leaves them out.
        max_pillars: pillar rows for the whole batch (default ``B * min(max_voxels_test, N)``, which always
            holds them). A batch with more pillars sets ``overflow``: its detections are then incomplete.

    Returns:
        dict of :func:`postprocess_padded`'s ``boxes (B, K, 7)``, ``scores``, ``labels``, ``count (B,)``;
        ``bad (B,)`` bool: frames whose features fail the eager call's value check; ``bad_boxes (B,)`` bool:
        frames with a box the eager post-processing's NMS would refuse (:func:`lidarops.ops.boxes.unsupported_boxes`
        among the anchors at or above the score threshold); ``pillars`` (0-d int64):
        the rows the batch needs; ``overflow`` (0-d bool): more than ``max_pillars``.
    """
    if not isinstance(model, PointPillars) or model.config.backbone_mode != "dense":
        raise ValueError(f"model must be a PointPillars with backbone_mode='dense', got {type(model).__name__}"
                         + (f" ({model.config.backbone_mode!r})" if isinstance(model, PointPillars) else ""))
    cfg = model.config
    points, rows = _padded_points(model, cfg, points, max_pillars)
    c = cfg.num_point_features
    stage = torch.profiler.record_function  # ranges for benchmarks/profile/detector.py; nothing in a graph
    x, needed = _padded_bev(model, cfg, points, rows)
    with lidarops.validation(False):
        with stage("head"):
            x = model.dense_head(x)
        with stage("decode"):
            x, bad_boxes = _decode_candidates(model.dense_head, x, cfg)
        with stage("postprocess"):
            out = postprocess_padded(*x, cfg)
            out["bad_boxes"] = _bad_boxes(*x, cfg) if bad_boxes is None else bad_boxes
    out["bad"] = _bad_features(points, c)
    out["pillars"] = needed
    out["overflow"] = needed > rows
    return out


def _padded_points(model, cfg, points: Tensor, max_pillars: int | None) -> tuple[Tensor, int]:
    """A padded batch checked for a graph body (``points`` in the weights' dtype) and its pillar rows."""
    from lidarops.ops.voxelize import voxel_grid_shape

    check_tensor(points, "points")
    c = cfg.num_point_features
    if points.dim() != 3 or points.shape[2] < c or not points.is_floating_point() or points.shape[0] < 1:
        raise ValueError(f"points must be a floating (B >= 1, N, C >= {c}) tensor (frame b's x, y, z, intensity in "
                         f"points[b]), got {describe(points)}")
    param = next(model.parameters())
    if points.device != param.device:
        raise ValueError(f"points is on {points.device} but the model is on {param.device}")
    points = points.to(param.dtype)  # as predict does: the weights' dtype
    B, N, _ = points.shape
    nz, ny, nx = voxel_grid_shape(cfg.voxel_size, cfg.point_cloud_range)
    if nz != 1:
        raise ValueError(f"the padded batch needs pillars (one voxel along z), got a grid of {nz} along z")
    per_frame = min(cfg.max_voxels_test, max(N, 1))
    if max_pillars is not None and (isinstance(max_pillars, bool) or not isinstance(max_pillars, int)
                                    or max_pillars < 1):
        raise ValueError(f"max_pillars must be an int >= 1 or None, got {max_pillars!r}")
    return points, B * min(per_frame, nx * ny) if max_pillars is None else max_pillars


def _padded_bev(model, cfg, points: Tensor, rows: int) -> tuple[Tensor, Tensor]:
    """The BEV features of a padded batch through a PointPillars floor (``vfe``, ``map_to_bev``,
    ``backbone_2d``), with a profiler range per stage, and the pillar rows the batch needs (0-d)."""
    stage = torch.profiler.record_function
    with stage("voxelize"):
        voxels, count, coords, needed = _batch_pillars(points, cfg, rows)
    with lidarops.validation(False):
        with stage("pfn"):
            x = model.vfe(voxels, count, coords)
        with stage("scatter"):
            x = model.map_to_bev(x, coords, points.shape[0])
        with stage("backbone"):
            return model.backbone_2d(x), needed


def _decode_candidates(head, raw: Mapping[str, Tensor], cfg) -> tuple[tuple[Tensor, Tensor], Tensor | None]:
    """The decoded anchors :func:`postprocess_padded` needs, and the frames whose boxes the eager NMS may refuse
    (None: :func:`_bad_boxes` of every decoded anchor decides).

    With one NMS over all classes (PointPillars' setting) only the ``nms_pre_maxsize`` best anchors above the score
    threshold can take part: they are chosen first (a stable sort of each frame's best-class scores, the anchors
    below the threshold or NaN last) and only they are decoded, in the order the NMS visits them, so the NMS keeps
    the same boxes. The eager NMS also checks the boxes of every anchor above the threshold: a frame is flagged
    where one of those anchors' raw regressions exceeds :attr:`AnchorHeadSingle.safe_regression`, within which
    every decoded box is accepted (the eager call then decides)."""
    pre = cfg.nms_pre_maxsize
    bound = getattr(head, "safe_regression", 0.0)
    if cfg.multi_classes_nms or pre < 1 or bound <= 0 or head.box_coder.box_size != 7 or head.conv_dir_cls is None:
        return head.decode(raw), None
    B = raw["cls_preds"].shape[0]
    cls = raw["cls_preds"].view(B, -1, head.num_class).float()
    A = cls.shape[1]
    scores = torch.sigmoid(cls).max(dim=-1).values  # postprocess's scores
    above = scores >= cfg.score_thresh
    order = torch.sort(torch.where(above, scores, -math.inf), dim=1, descending=True, stable=True).indices
    cand = order[:, :min(A, pre)]

    def rows(t: Tensor) -> Tensor:
        t = t.reshape(B, A, -1)
        return torch.gather(t, 1, cand[..., None].expand(-1, -1, t.shape[-1]))

    box = raw["box_preds"].reshape(B, A, -1)
    bad = ((~(box.abs() <= bound)).any(-1) & above).any(1)
    picked = {"cls_preds": rows(cls), "box_preds": rows(box), "dir_cls_preds": rows(raw["dir_cls_preds"])}
    return head.decode(picked, head.anchors_flat[cand]), bad


def _bad_boxes(cls_logits: Tensor, boxes: Tensor, cfg) -> Tensor:
    """``(B,)`` bool: frames where the eager post-processing would refuse a box: the NMS checks the boxes of the
    anchors with some class at or above the score threshold, which a graph cannot read back."""
    from lidarops.ops.boxes import unsupported_boxes

    B, A, _ = boxes.shape
    above = (torch.sigmoid(cls_logits) >= cfg.score_thresh).any(-1)
    return (unsupported_boxes(boxes.reshape(B * A, 7)).view(B, A) & above).any(1)


def _bad_features(points: Tensor, c: int) -> Tensor:
    """``(B,)`` bool: frames whose features fail the eager call's value check."""
    feats = points[:, :, 3:c]
    return ~(feats.abs() <= MAX_ABS_INTENSITY).flatten(1).all(1) if feats.shape[2] else \
        torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)


def _batch_pillars(points: Tensor, cfg, rows: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The pillars of a padded batch (:func:`padded_inference`) packed into ``rows`` rows: ``voxels (rows, P, C)``,
    ``num_points (rows,)``, ``coords (rows, 4)`` int32 (frame, 0, y, x; -1 for the rows left over) and the rows
    needed (0-d)."""
    from lidarops.ops.voxelize import voxel_assignment, voxel_grid_shape

    B, N, _ = points.shape
    vs, pr = [float(v) for v in cfg.voxel_size], [float(v) for v in cfg.point_cloud_range]
    _, ny, nx = voxel_grid_shape(vs, pr)
    per_frame = min(cfg.max_voxels_test, max(N, 1))
    flat = points.reshape(B * N, points.shape[2])[:, :cfg.num_point_features]
    # frame b's in-range points in the middle of the b-th slab; the op's own z test, in its float32
    # arithmetic (lidarops/voxelize.h); out-of-range z becomes NaN, which no slab holds
    xyz = flat[:, :3].float()
    z = xyz[:, 2]
    # (Python scalars: a CUDA graph capture refuses a copy from the host; float32 tensors keep float32 math)
    inside = (z >= pr[2]) & (z < pr[5]) & (torch.floor((z - pr[2]) / vs[2]) == 0)
    slab = ((torch.arange(B, dtype=torch.float64, device=points.device) + 0.5) * vs[2] + pr[2]).float()
    xyz = torch.cat([xyz[:, :2], torch.where(inside.view(B, N), slab[:, None], math.nan).view(B * N, 1)], 1)
    # every pillar of every frame gets a row here (16 bytes a row): none is dropped before the per-frame cap
    coords, nums, point_voxel, point_slot = voxel_assignment(
        xyz, vs, pr[:5] + [pr[2] + B * vs[2]], cfg.max_points_per_voxel, B * min(N, nx * ny) if N else 1)
    T = coords.shape[0]
    valid = coords[:, 0] >= 0
    owner = coords[:, 0].long().clamp(min=0)
    # rows come frame after frame (first seen, frames stacked in order): a row's rank within its frame
    held = torch.zeros(B, dtype=torch.int64, device=points.device).index_add_(0, owner, valid.long())
    start = torch.cumsum(held, 0) - held
    keep = valid & (torch.arange(T, device=points.device) - start[owner] < per_frame)
    new = torch.cumsum(keep.long(), 0) - 1
    needed = keep.sum()
    keep = keep & (new < rows)
    target = torch.where(keep, new, rows)  # row `rows`: a spare for everything not kept
    remap = torch.cat([target, target.new_full((1,), rows)])
    pv = remap[torch.where(point_voxel >= 0, point_voxel, T)]
    pv = torch.where(pv < rows, pv, -1)
    voxels = torch.ops.lidarops.voxelize_scatter(flat, pv, point_slot, rows, cfg.max_points_per_voxel)
    packed = torch.full((rows + 1, 4), -1, dtype=coords.dtype, device=points.device)
    packed.index_copy_(0, target, torch.cat([coords[:, :1], torch.zeros_like(coords[:, :1]), coords[:, 1:]], 1))
    count = torch.zeros(rows + 1, dtype=nums.dtype, device=points.device).index_copy_(0, target, nums)
    return voxels, count[:rows], packed[:rows], needed


def inference_copy(model: nn.Module) -> nn.Module:
    """A copy of an eval-mode model for inference only: each ``Conv2d`` / ``ConvTranspose2d`` followed by a
    ``BatchNorm2d`` in an ``nn.Sequential`` folded into one convolution with a bias (``torch.nn.utils.fusion``),
    and 4-D weights channels-last, so that cuDNN runs the BEV network without layout transposes or separate
    BatchNorm passes; in a CounterNet the count head's first convolution also reads the backbone's upsampled maps
    one by one instead of their concatenation, and in a PointPillars the anchor head's three 1 x 1 convolutions
    run as one, reading the maps the same way; the pillar scatter hands over its map channels-last, without a
    transposing copy. A ``ZeroPad2d`` before an unpadded convolution becomes the convolution's padding (no padded
    copy of the map), a 1 x 1 ``ConvTranspose2d`` of stride 1 a ``Conv2d``, and each ``Conv2d`` followed by a
    ``ReLU`` one :class:`_ConvReLU` (on CUDA in half precision, one cuDNN call that adds the bias and applies the
    ReLU as it writes the output). The same function up to rounding; the model itself is not changed."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    if not isinstance(model, nn.Module):
        raise TypeError(f"model must be a torch.nn.Module, got {type(model).__name__}")
    copy_ = copy.deepcopy(model).eval()
    for seq in [m for m in copy_.modules() if isinstance(m, nn.Sequential)]:
        for i in range(len(seq) - 1):
            conv, bn = seq[i], seq[i + 1]
            if isinstance(conv, (nn.Conv2d, nn.ConvTranspose2d)) and isinstance(bn, nn.BatchNorm2d) \
                    and bn.track_running_stats:
                seq[i] = fuse_conv_bn_eval(conv, bn, transpose=isinstance(conv, nn.ConvTranspose2d))
                seq[i + 1] = nn.Identity()
        _fold_pads(seq)
        for i, m in enumerate(seq):
            if _pointwise_transpose(m):
                seq[i] = _as_conv(m)
    # the head reads the three upsampled maps one by one instead of their 384-channel concatenation, which
    # would be written and read once more: CounterNet's count head, PointPillars' anchor head (its three 1 x 1
    # convolutions as one)
    if isinstance(copy_, CounterNet) and copy_.config.floor_config().backbone_mode == "dense":
        copy_.count_head.shared_conv[0] = _PartsConv2d(copy_.count_head.shared_conv[0], _by_parts(copy_))
    if isinstance(copy_, PointPillars) and copy_.config.backbone_mode == "dense" \
            and type(copy_.dense_head) is AnchorHeadSingle:
        _MergedAnchorHead.convert(copy_.dense_head, _by_parts(copy_))
    for scatter in [m for m in copy_.modules() if isinstance(m, PointPillarScatter)]:
        scatter.channels_last = True  # the pseudo-image as the scattered rows lie: no transposing copy
    for seq in [m for m in copy_.modules() if isinstance(m, nn.Sequential)]:
        _fuse_relus(seq)
    return copy_.to(memory_format=torch.channels_last)


def _fold_pads(seq: nn.Sequential) -> None:
    """``ZeroPad2d(p)`` then an unpadded ``Conv2d`` as the ``Conv2d`` padded by ``p`` (the same zeros)."""
    for i in range(len(seq) - 1):
        pad, conv = seq[i], seq[i + 1]
        if type(pad) is nn.ZeroPad2d and type(conv) is nn.Conv2d and conv.padding == (0, 0) \
                and conv.padding_mode == "zeros" and len(set(pad.padding)) == 1:
            conv.padding = (pad.padding[0],) * 2
            seq[i] = nn.Identity()


def _pointwise_transpose(m: nn.Module) -> bool:
    return (type(m) is nn.ConvTranspose2d and m.kernel_size == (1, 1) and m.stride == (1, 1) and m.padding == (0, 0)
            and m.output_padding == (0, 0) and m.dilation == (1, 1) and m.groups == 1)


def _as_conv(m: nn.ConvTranspose2d) -> nn.Conv2d:
    """A 1 x 1 transposed convolution of stride 1 as the ``Conv2d`` it equals (its weight's two first axes swapped)."""
    conv = nn.Conv2d(m.in_channels, m.out_channels, 1, bias=m.bias is not None).to(m.weight)
    with torch.no_grad():
        conv.weight.copy_(m.weight.transpose(0, 1))
        if m.bias is not None:
            conv.bias.copy_(m.bias)
    return conv


def _fuse_relus(seq: nn.Sequential) -> None:
    """Each ``Conv2d`` followed (past any ``Identity``) by a ``ReLU`` as one :class:`_ConvReLU`."""
    mods = list(seq)
    for i, m in enumerate(mods):
        if type(m) is not nn.Conv2d:
            continue
        j = i + 1
        while j < len(mods) and type(mods[j]) is nn.Identity:
            j += 1
        if j < len(mods) and type(mods[j]) is nn.ReLU:
            seq[i], seq[j] = _ConvReLU(m), nn.Identity()


class _ConvReLU(nn.Module):
    """``relu(conv(x))``. On CUDA in float16 or bfloat16 (the input's dtype, or autocast's, which it casts to as
    autocast would) one cuDNN call adds the bias and applies the ReLU in the convolution's epilogue, so the map is
    not read and written twice more; elsewhere, and where autograd must see the result, the two modules' calls."""

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.conv = conv
        self.in_channels, self.out_channels = conv.in_channels, conv.out_channels
        self.fusable = conv.padding_mode == "zeros" and not isinstance(conv.padding, str)  # what cuDNN's call takes

    def forward(self, x: Tensor) -> Tensor:
        conv = self.conv
        w = conv.weight
        autocast = x.is_cuda and torch.is_autocast_enabled("cuda")
        dt = torch.get_autocast_dtype("cuda") if autocast else x.dtype
        if (self.fusable and x.is_cuda and dt in (torch.float16, torch.bfloat16) and (autocast or w.dtype == dt)
                and torch.backends.cudnn.enabled
                and not (torch.is_grad_enabled() and (x.requires_grad or w.requires_grad))):
            b = conv.bias if conv.bias is not None else w.new_zeros(conv.out_channels)
            return torch.cudnn_convolution_relu(x.to(dt), w.to(dt), b.to(dt), conv.stride, conv.padding,
                                                conv.dilation, conv.groups)
        return torch.relu(conv(x))


def _cast_convolutions(copy_: nn.Module, dtype: torch.dtype | None) -> None:
    """The convolutions of a private :func:`inference_copy` recorded under an autocast to ``dtype`` (float16 or
    bfloat16) take their weights in that dtype once, rather than autocast casting each one at every replay: the
    same values reach the same kernels."""
    if dtype not in (torch.float16, torch.bfloat16):
        return
    for m in copy_.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            m.to(dtype)


def _by_parts(model: nn.Module) -> list[int]:
    """Make ``model.backbone_2d`` return its upsampled maps as :class:`_Parts`; their channel counts."""
    sizes = [d[0].out_channels for d in model.backbone_2d.deblocks]
    model.backbone_2d = _PartsBackbone(model.backbone_2d)
    return sizes


class _Parts(list):
    """A backbone's upsampled maps, not yet concatenated along the channels."""


class _PartsBackbone(nn.Module):
    """A dense ``BaseBEVBackbone`` returning its upsampled maps as :class:`_Parts` (for :class:`_PartsConv2d`)."""

    def __init__(self, backbone: nn.Module):
        super().__init__()
        self.inner = backbone
        self.out_channels = backbone.out_channels

    def forward(self, x: Tensor) -> _Parts:
        parts = _Parts()
        for block, deblock in zip(self.inner.blocks, self.inner.deblocks):
            x = block(x)
            parts.append(deblock(x))
        return parts


class _PartsConv2d(nn.Module):
    """A convolution of the concatenation of :class:`_Parts` as the sum of each part's convolution with its slice
    of the input channels (a tensor input is convolved whole)."""

    def __init__(self, conv: nn.Conv2d, sizes: Sequence[int]):
        super().__init__()
        self.whole = conv
        self.parts = nn.ModuleList()
        start = 0
        for c in sizes:
            part = nn.Conv2d(c, conv.out_channels, conv.kernel_size, conv.stride, conv.padding, conv.dilation,
                             bias=False)
            part.weight = nn.Parameter(conv.weight.detach()[:, start:start + c].clone())
            self.parts.append(part)
            start += c
        self.pointwise = (conv.kernel_size == (1, 1) and conv.stride == (1, 1) and conv.padding == (0, 0)
                          and conv.groups == 1)

    def forward(self, x):
        if not isinstance(x, _Parts):
            return self.whole(x)
        whole = self.whole
        if self.pointwise and all(p.dim() == 4 and p.is_contiguous(memory_format=torch.channels_last) for p in x):
            # channels-last maps are (cells, channels) matrices: one GEMM per part, each adding the last's result
            # in its epilogue (no separate sums or bias pass)
            N, _, H, W = x[0].shape
            rows = [p.permute(0, 2, 3, 1).reshape(-1, p.shape[1]) for p in x]
            ws = [conv.weight.reshape(conv.out_channels, -1).t() for conv in self.parts]
            out = rows[0] @ ws[0] if whole.bias is None else torch.addmm(whole.bias, rows[0], ws[0])
            for r, w in zip(rows[1:], ws[1:]):
                out = torch.addmm(out, r, w)
            return out.view(N, H, W, -1).permute(0, 3, 1, 2)
        out = self.parts[0](x[0])
        for conv, part in zip(self.parts[1:], x[1:]):
            out = out + conv(part)
        return out if self.whole.bias is None else out + self.whole.bias.view(1, -1, 1, 1).to(out.dtype)


class _MergedAnchorHead(AnchorHeadSingle):
    """An ``AnchorHeadSingle`` whose class, box and direction convolutions (1 x 1, on the same map) run as one
    convolution with their output channels stacked, reading :class:`_Parts` (its weights are copies: the
    three convolutions stay, unused, for code that reads them)."""

    @classmethod
    def convert(cls, head: AnchorHeadSingle, sizes: Sequence[int]) -> None:
        convs = [head.conv_cls, head.conv_box] + ([head.conv_dir_cls] if head.conv_dir_cls is not None else [])
        merged = nn.Conv2d(convs[0].in_channels, sum(c.out_channels for c in convs), 1).to(convs[0].weight)
        with torch.no_grad():
            merged.weight.copy_(torch.cat([c.weight for c in convs]))
            merged.bias.copy_(torch.cat([c.bias for c in convs]))
        head.__class__ = cls
        head.merged = _PartsConv2d(merged, sizes)
        head.merged_splits = [c.out_channels for c in convs]

    def forward(self, features) -> dict[str, Tensor]:
        out = self.merged(features).permute(0, 2, 3, 1)  # channels-last memory: a view, no copy
        names = ("cls_preds", "box_preds", "dir_cls_preds")
        return self._check_grid({n: t.contiguous() for n, t in zip(names, out.split(self.merged_splits, dim=-1))})


class _GraphedFrames:
    """What the graphed models share: a padded input of ``batch_size`` frames of up to ``capacity`` points,
    a graph of ``body(points)`` recorded once on it, and :meth:`replay` copying frames into the input."""

    what = "model"

    def __init__(self, model, floor, capacity: int, precision: str | None, batch_size: int,
                 max_pillars: int | None, body, optimize: bool = False):
        if not isinstance(optimize, bool):
            raise ValueError(f"optimize must be True or False, got {optimize!r}")
        param = next(model.parameters())
        if param.device.type != "cuda":
            raise ValueError(f"{type(self).__name__} needs the model on a CUDA device, got {param.device}")
        if floor.backbone_mode != "dense":
            raise ValueError(f"{type(self).__name__} needs backbone_mode='dense', got {floor.backbone_mode!r}: the "
                             "sparse backbone builds its kernel maps with host reads, which a CUDA graph cannot hold")
        for name, value in (("capacity", capacity), ("batch_size", batch_size)) + \
                (() if max_pillars is None else (("max_pillars", max_pillars),)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if precision is not None and precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS} or None, got {precision!r}")
        self.model, self.capacity, self.precision, self.batch_size = model.eval(), capacity, precision, batch_size
        self.max_pillars, self.optimize = max_pillars, optimize
        self.device, self.dtype = param.device, param.dtype
        # kept: the graph reads the copy's weights at every replay
        self._graphed_model = graphed = inference_copy(model) if optimize else model
        if optimize and self.dtype == torch.float32:  # the autocast the graph is recorded under, if any
            if precision == "fp16":
                _cast_convolutions(graphed, torch.float16)
            elif precision is None and torch.is_autocast_enabled("cuda"):
                _cast_convolutions(graphed, torch.get_autocast_dtype("cuda"))
        self._features = c = floor.num_point_features
        # rows past the frame: outside the point range, so voxelization leaves them out
        self._pad = torch.zeros(c, device=self.device, dtype=self.dtype)
        self._pad[0] = floor.point_cloud_range[3] + 1000.0
        self._points = self._pad.expand(batch_size, capacity, c).clone()
        self._filled = [0] * batch_size  # rows holding each slot's last frame's points
        half_model = self.dtype == torch.float16

        def run():
            with torch.no_grad(), precision_mode(precision, autocast=not half_model), uncached_autocast():
                return body(graphed, self._points)

        # thread_local: a DataLoader's pin-memory thread allocating pinned buffers meanwhile (the index
        # build) must not invalidate this capture, as the default global mode lets it
        self._graph, self._out = record_graph(run, self.device, warmups=2, capture_error_mode="thread_local")

    def _check(self, points: Tensor, name: str) -> None:
        check_tensor(points, name)
        c = self._features
        if points.dim() != 2 or points.shape[1] < c or not points.is_floating_point():
            raise ValueError(f"{name} must be a floating (P, C >= {c}) tensor (x, y, z, intensity), got {describe(points)}")
        if points.device != self.device:
            raise ValueError(f"{name} is on {points.device} but the model is on {self.device}")
        if points.shape[0] > self.capacity:
            raise ValueError(f"{name} has {points.shape[0]} rows, more than capacity={self.capacity}: build a "
                             f"{type(self).__name__} with a larger capacity")

    def _replay(self, frames: Sequence[Tensor], name: str | None = None) -> dict[str, Tensor]:
        """``name``: what a one-frame call's errors call its frame (default ``frames[i]``)."""
        if not isinstance(frames, (list, tuple)) or not 1 <= len(frames) <= self.batch_size:
            raise ValueError(f"frames must be a list of 1 to batch_size={self.batch_size} point tensors, "
                             f"got {type(frames).__name__}" + (f" of {len(frames)}" if isinstance(frames, (list, tuple))
                                                               else ""))
        for i, f in enumerate(frames):
            self._check(f, name or f"frames[{i}]")
        c = self._features
        for b in range(self.batch_size):
            p = frames[b].shape[0] if b < len(frames) else 0
            if p:
                self._points[b, :p].copy_(frames[b][:, :c])
            if self._filled[b] > p:  # the rows of a larger previous frame become padding again
                self._points[b, p:self._filled[b]].copy_(self._pad.expand(self._filled[b] - p, c))
            self._filled[b] = p
        self._graph.replay()
        return self._out

    def _eager(self, frames: Sequence[Tensor]) -> list[dict]:
        """The model's own eager ``predict``, frame by frame, in the graph's precision."""
        with precision_mode(self.precision, autocast=self.dtype != torch.float16), eager_predict():
            return [self.model.predict({"points": torch.nn.functional.pad(f[:, :self._features], (1, 0)),
                                        "batch_size": 1})[0] for f in frames]

    def _raise_bad(self, frames: Sequence[Tensor], bad: Sequence) -> None:
        """With the value checks on, the eager call's error for a frame the graph flagged."""
        if value_checks_enabled():
            floor = self._floor()
            for f, b in zip(frames, bad):
                if b:
                    _check_batch({"points": torch.nn.functional.pad(f[:, :self._features], (1, 0)), "batch_size": 1},
                                 floor, False, self.dtype)

    def __call__(self, points: Tensor | Sequence[Tensor]) -> dict[str, Tensor] | list[dict[str, Tensor]]:
        one = isinstance(points, Tensor)
        frames = [points] if one else points
        out = self._replay(frames, "points" if one else None)
        reads = out["read"][:len(frames)].tolist()  # the one host read: (rows, bad, redo, pillars) per frame
        self.last_reads = reads
        if any(r[2] for r in reads):  # rows too few (or a merge unsettled): the eager call, in the graph's precision
            results = self._eager(frames)
        else:
            self._raise_bad(frames, [r[1] for r in reads])
            results = self._frame_results(out, reads)
        return results[0] if one else results

    def _frame_results(self, out: dict[str, Tensor], reads: list) -> list[dict[str, Tensor]]:
        """Each frame's results, cut from the padded outputs by its row of ``read``."""
        raise NotImplementedError

    def _floor(self):
        raise NotImplementedError


class GraphedPointPillars(_GraphedFrames):
    """A PointPillars model's inference on one frame, or on ``batch_size`` frames at once, as a replayed
    CUDA graph.

    Args:
        model (PointPillars): an eval-mode model on a CUDA device, ``backbone_mode="dense"``. Its
            weights are read by the graph at each replay (updating them in place is seen; replacing
            the parameter tensors is not).
        capacity (int): the most points a frame may have; memory and the voxelization's time grow with it.
        precision (str | None): ``"fp32"`` (default), ``"tf32"`` or ``"fp16"`` (float16 autocast), fixed at
            capture; None: torch's TF32 settings as they are at capture.
        batch_size (int): frames per replay (default 1): voxelized together (each keeping its own pillars),
            the network and the post-processing run on the batch.
        max_pillars (int | None): pillar rows of a replay, all frames together (:func:`padded_inference`);
            default ``batch_size * min(max_voxels_test, capacity)``, which always holds them. Fewer rows make
            the pillar net's work smaller; a replay whose frames need more is redone eagerly by a call (and
            reported by :meth:`replay`'s ``overflow``).
        optimize (bool): record a private :func:`inference_copy` of the model (BatchNorm folded into the
            convolutions, channels-last, each convolution and its ReLU one cuDNN call in half precision; under fp16
            its convolutions' weights are cast once): faster, especially in fp16; the outputs round differently
            from the eager call's (float32 or float16 rounding), and later in-place updates of the model's weights
            are not seen. Default False.

    Calling it with ``points (Tensor[P, C])`` (``C >= config.num_point_features``: x, y, z, intensity;
    more columns are ignored; ``P <= capacity``; the model's device) returns one dict of ``boxes (K, 7)``,
    ``scores (K,)``, ``labels (K,)`` (1-based into ``config.class_names``), as :meth:`PointPillars.predict`
    gives for that frame; with a list of up to ``batch_size`` such frames, a list of such dicts.
    :meth:`replay` leaves the padded outputs on the device, for callers that gather them there. The graph
    also checks the points' features as the eager call does; with ``lidarops.validation`` on (the default)
    a bad frame raises the eager call's ``ValueError`` (the flag comes back with the number of boxes: still
    one host read). The graph keeps the thresholds and capacities of ``model.config`` as they were when it was
    made: after changing the config, make a new one (``predict``'s own graphs are made again by themselves).
    """

    def __init__(self, model: PointPillars, capacity: int = 150_000, precision: str | None = "fp32",
                 batch_size: int = 1, max_pillars: int | None = None, optimize: bool = False):
        if not isinstance(model, PointPillars):
            raise TypeError(f"model must be a PointPillars, got {type(model).__name__}")

        def body(model, points):
            out = padded_inference(model, points, max_pillars)
            # the one host read: each frame's number of boxes and value check, whether the replay must be redone
            # eagerly (pillar rows too few, or a box the eager NMS refuses: its error names the box), the pillars
            redo = out["overflow"].expand(batch_size) | out["bad_boxes"]
            out["read"] = torch.stack([out["count"], out["bad"].to(torch.int64), redo.to(torch.int64),
                                       out["pillars"].expand(batch_size)], 1)
            return out

        super().__init__(model, model.config, capacity, precision, batch_size, max_pillars, body, optimize)

    def _floor(self):
        return self.model.config

    def replay(self, frames: Sequence[Tensor]) -> dict[str, Tensor]:
        """Runs the graph on up to ``batch_size`` frames (each ``Tensor[P, C]`` as for a call) and returns its
        padded outputs on the device without reading anything back: ``boxes (B, K, 7)``, ``scores``,
        ``labels``, ``count (B,)``, ``bad (B,)``, ``pillars`` and ``overflow`` (0-d: the pillar rows the frames
        needed, more than ``max_pillars``: the detections are then incomplete), ``bad_boxes (B,)`` and
        ``read (B, 4)`` (count, bad, redo: overflow or bad boxes, pillars), row b for frame b (rows past the frames
        given: empty frames). They are overwritten by the next replay: gather or copy them first (work queued on the
        current stream before the next replay is)."""
        return self._replay(frames)

    def _frame_results(self, out: dict[str, Tensor], reads: list) -> list[dict[str, Tensor]]:
        return [{"boxes": out["boxes"][b, :k].clone(), "scores": out["scores"][b, :k].clone(),
                 "labels": out["labels"][b, :k].clone()} for b, (k, *_) in enumerate(reads)]


def padded_counting(model: CounterNet, points: Tensor, max_pillars: int | None = None, max_peaks: int = 256,
                    merge_iterations: int = 16, exact_otsu: bool = False) -> dict[str, Tensor]:
    """:meth:`CounterNet.predict` on a batch of frames padded to one size, with outputs of sizes fixed by the
    shapes and nothing read back to the host: the body :class:`GraphedCounterNet` records, usable eagerly too
    (any device).

    The pillars as :func:`padded_inference` packs them, the network, then per region the threshold
    ``max(Otsu, THRESHOLD)`` and the peaks as :meth:`CounterNet.postprocess` finds them. Each frame's peaks
    (regions in order, then class, row, column) fill ``max_peaks`` rows. With overlapping regions the centres
    are merged as :func:`~lidarops.models.counting.merge_centres` merges them (greedy by decreasing score,
    same class within ``MERGE_RADIUS``), here as a fixed point: a centre is kept when no kept centre before it
    conflicts with it, iterated ``merge_iterations`` times from "all kept"; after t rounds every centre at the
    end of a chain of fewer than t conflicts has its greedy answer, and a frame still changing is flagged.

    Args:
        model: an eval-mode CounterNet whose floor has ``backbone_mode="dense"``.
        points (Tensor[B, N, C]): as :func:`padded_inference`'s.
        max_pillars: as :func:`padded_inference`'s.
        max_peaks (int >= 1): peak rows per frame; a frame with more sets ``peak_overflow`` (its counts stay
            exact without overlap, where they are the peaks' number; with overlap they come from the rows).
        merge_iterations (int >= 1): rounds of the merge (with overlap).
        exact_otsu (bool): :func:`~lidarops.models.counting.otsu_threshold`'s ``exact``; the default False
            keeps the threshold on the device (``True``, the eager call's, reads its sums back to the host:
            no graph can hold it). The two differ only where two splits tie to within rounding.

    Returns:
        dict of ``counts (B, C)`` int64, ``centres (B, max_peaks, 4)`` (x, y, class 0-based, score; the rows
        :meth:`CounterNet.postprocess` gives first, zeros after), ``num_centres (B,)``, ``features (B, S)``;
        ``bad (B,)`` bool as :func:`padded_inference`'s; ``peaks (B,)`` the peaks found before any merge;
        ``peak_overflow (B,)`` bool (more than ``max_peaks``); ``unmerged (B,)`` bool (the merge still changing
        after ``merge_iterations``); ``pillars`` and ``overflow`` (0-d) as :func:`padded_inference`'s.
    """
    from lidarops.models.counting import find_peaks, otsu_threshold

    if not isinstance(model, CounterNet) or model.config.floor_config().backbone_mode != "dense":
        raise ValueError(f"model must be a CounterNet with backbone_mode='dense', got {type(model).__name__}")
    for name, value in (("max_peaks", max_peaks), ("merge_iterations", merge_iterations)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    if not isinstance(exact_otsu, bool):
        raise ValueError(f"exact_otsu must be True or False, got {exact_otsu!r}")
    cfg = model.config
    floor = cfg.floor_config()
    points, rows = _padded_points(model, floor, points, max_pillars)
    B, K = points.shape[0], max_peaks
    stage = torch.profiler.record_function  # ranges for a profile; nothing in a graph
    x, needed = _padded_bev(model, floor, points, rows)
    with lidarops.validation(False), stage("counting"):
        with stage("head"):
            shared, logits = model.count_head(x, model.region_boxes)
            heatmaps = [torch.sigmoid(x) for x in logits]
        C = heatmaps[0].shape[1]
        dev = heatmaps[0].device
        ct = torch.float64 if heatmaps[0].dtype == torch.float64 else torch.float32
        vs, stride, pcr = floor.voxel_size, cfg.feature_map_stride, floor.point_cloud_range
        masks, scores, xs, ys, classes = [], [], [], [], []
        counts = torch.zeros(B, C, dtype=torch.int64, device=dev)
        for pred, (y0, y1, x0, x1) in zip(heatmaps, model.region_boxes):
            thresh = pred.new_full((B, 1, 1, 1), cfg.threshold)
            if cfg.otsu:
                otsu = otsu_threshold(pred.reshape(B, -1), exact=exact_otsu).nan_to_num(cfg.threshold)
                thresh = torch.maximum(thresh, otsu.view(B, 1, 1, 1))
            peaks = find_peaks(pred, thresh, cfg.peak_radius)
            counts += peaks.sum(dim=(2, 3))
            h, w = pred.shape[2:]
            # postprocess's arithmetic, operation for operation: float64 from the region's origin, then the
            # heatmap's compute dtype
            col = (torch.arange(w, device=dev, dtype=torch.float64) + 0.5) * vs[0] * stride + \
                (pcr[0] + x0 * vs[0] * stride)
            row = (torch.arange(h, device=dev, dtype=torch.float64) + 0.5) * vs[1] * stride + \
                (pcr[1] + y0 * vs[1] * stride)
            xs.append(col.to(ct).expand(C, h, w).reshape(-1))
            ys.append(row.to(ct)[:, None].expand(C, h, w).reshape(-1))
            classes.append(torch.arange(C, device=dev, dtype=ct)[:, None, None].expand(C, h, w).reshape(-1))
            masks.append(peaks.reshape(B, -1))
            scores.append(pred.reshape(B, -1).to(ct))
        mask, score = torch.cat(masks, 1), torch.cat(scores, 1)  # (B, L): regions, then class, row, column
        table = torch.stack([torch.cat(xs), torch.cat(ys), torch.cat(classes)], 1)  # (L, 3)
        L = mask.shape[1]
        # the first K peaks of each frame, in order: the k-th is the first cell whose running count reaches k + 1
        # (a search per row, not a scatter of every cell, whose non-peaks would all collide on one spare slot)
        running = torch.cumsum(mask, 1, dtype=torch.int32)
        found = running[:, -1].long()
        wanted = torch.arange(1, K + 1, device=dev, dtype=torch.int32).expand(B, K).contiguous()
        cell = torch.searchsorted(running, wanted)  # L where a frame has fewer peaks
        valid = cell < L
        at = cell.clamp(max=L - 1)
        centres = torch.cat([table[at], torch.gather(score, 1, at)[:, :, None]], 2)
        centres = torch.where(valid[:, :, None], centres, 0)
        unmerged = torch.zeros(B, dtype=torch.bool, device=dev)
        if cfg.delta > 0:
            # merge_centres: by decreasing score, stable; the rows past the peaks stay last
            order = torch.sort(torch.where(valid, centres[:, :, 3], -math.inf), dim=1, descending=True,
                               stable=True).indices
            centres = torch.gather(centres, 1, order[:, :, None].expand(B, K, 4))
            valid = torch.gather(valid, 1, order)
            xy = centres[:, :, :2].to(torch.float64)
            near = torch.hypot(xy[:, :, None, 0] - xy[:, None, :, 0], xy[:, :, None, 1] - xy[:, None, :, 1]) \
                <= cfg.merge_radius
            later = torch.ones(K, K, dtype=torch.bool, device=dev).triu(1)  # [i, j]: j comes after i
            conflict = near & later & (centres[:, :, None, 2] == centres[:, None, :, 2]) & valid[:, :, None] \
                & valid[:, None, :]
            keep = valid
            for _ in range(merge_iterations):
                last = keep
                keep = valid & ~(conflict & keep[:, :, None]).any(1)
            unmerged = (keep != last).any(1)
            counts = torch.zeros(B, C, dtype=torch.int64, device=dev).scatter_add_(
                1, torch.where(keep, centres[:, :, 2].long(), 0), keep.long())
            # the kept rows first, in their order
            slot = torch.where(keep, torch.cumsum(keep, 1) - 1, K)
            packed = centres.new_zeros(B, K + 1, 4).scatter_(1, slot[:, :, None].expand(B, K, 4), centres)
            centres, valid = packed[:, :K], keep
        out = {"counts": counts, "centres": centres, "num_centres": valid.sum(1), "features": shared.amax(dim=(2, 3)),
               "bad": _bad_features(points, floor.num_point_features), "peaks": found, "peak_overflow": found > K,
               "unmerged": unmerged, "pillars": needed, "overflow": needed > rows}
    return out


class GraphedCounterNet(_GraphedFrames):
    """A CounterNet's counting of ``batch_size`` frames at once as a replayed CUDA graph: voxelization, the
    network, the thresholds, the peaks and (with overlapping regions) the merge (:func:`padded_counting`), with
    one host read per replay.

    Args:
        model (CounterNet): an eval-mode model on a CUDA device whose floor is dense; its weights are read at
            each replay (in-place updates are seen).
        capacity, precision, batch_size, max_pillars, optimize: as :class:`GraphedPointPillars`'.
        max_peaks (int): peak rows per frame (:func:`padded_counting`).
        merge_iterations (int): rounds of the merge.

    Calling it with a frame ``points (Tensor[P, C])`` or a list of up to ``batch_size`` frames returns what
    :meth:`CounterNet.predict` returns for each: ``counts (C,)``, ``centres (K, 4)``, ``features (S,)``. A
    replay whose frames need more pillar rows or peak rows than the graph holds, or whose merge has not settled,
    is redone by the eager ``predict``. The counts are the eager call's except where Otsu's threshold ties
    between two splits to within rounding (the graph computes it on the device: ``exact=False``). The graph keeps
    ``model.config`` as it was when it was made: after changing the config, make a new one.
    """

    def __init__(self, model: CounterNet, capacity: int = 150_000, precision: str | None = "fp32",
                 batch_size: int = 1, max_pillars: int | None = None, max_peaks: int = 256,
                 merge_iterations: int = 16, optimize: bool = False):
        if not isinstance(model, CounterNet):
            raise TypeError(f"model must be a CounterNet, got {type(model).__name__}")
        self.max_peaks = max_peaks

        def body(model, points):
            out = padded_counting(model, points, max_pillars, max_peaks, merge_iterations)
            redo = out["overflow"].expand(batch_size) | out["peak_overflow"] | out["unmerged"]
            # the one host read: each frame's centres and value check, and whether the replay must be redone
            out["read"] = torch.stack([out["num_centres"], out["bad"].to(torch.int64), redo.to(torch.int64),
                                       out["pillars"].expand(batch_size)], 1)
            return out

        super().__init__(model, model.config.floor_config(), capacity, precision, batch_size, max_pillars, body,
                         optimize)

    def _floor(self):
        return self.model.config.floor_config()

    def replay(self, frames: Sequence[Tensor]) -> dict[str, Tensor]:
        """Runs the graph on up to ``batch_size`` frames and returns :func:`padded_counting`'s outputs on the
        device, with ``read (B, 4)``: centres, bad, redo (pillar or peak rows too few, or the merge unsettled:
        these outputs are then not the eager call's), pillars. Overwritten by the next replay."""
        return self._replay(frames)

    def _frame_results(self, out: dict[str, Tensor], reads: list) -> list[dict[str, Tensor]]:
        return [{"counts": out["counts"][b].clone(), "centres": out["centres"][b, :k].clone(),
                 "features": out["features"][b].clone()} for b, (k, *_) in enumerate(reads)]


# PointPillars.predict's graphs (graphed_predict): frames padded to a power of two of points from MIN_CAPACITY, so that
# a stream of scans of similar sizes shares one graph; frames above MAX_CAPACITY run eagerly. KEEP_GRAPHS per model,
# the least recently used dropped first (each holds its own activations); after MAX_RECORDINGS (calls cycling
# through more sizes than are kept) new sizes run eagerly rather than record a graph per call.
MIN_CAPACITY = 1 << 14
MAX_CAPACITY = 1 << 21
KEEP_GRAPHS = 3
MAX_RECORDINGS = 12
# Pillar rows of a predict graph: a power of two at least ROWS_HEADROOM times the most pillars its frames have needed
# (counted before the recording, then read back with each replay's results), and at least MIN_ROWS. A replay whose
# frames need more is redone eagerly and the next call records the graph again with more rows: the pillar net and
# the scatter then work on the pillars there are rather than on every frame's capacity.
ROWS_HEADROOM = 1.25
MIN_ROWS = 1 << 10
# Under a CUDA autocast to float16 / bfloat16 the caller has asked for reduced precision: predict then records an
# inference_copy (BatchNorm folded, channels-last; cuDNN's half-precision kernels run without layout transposes),
# recorded again when a weight changes in place. Its detections agree with the eager call's to that precision.
OPTIMIZE_UNDER_AUTOCAST = True


class _PredictGraphs:
    """A model's predict graphs, keyed by what they were recorded under. Not copied or pickled with the model: a
    graph records its model's tensors."""

    def __init__(self):
        self.places: list = []  # (module's _parameters or _buffers, name) of every tensor the graphs read
        self.children: tuple = ()
        self.tensors: tuple = ()
        self.seen: set = set()
        self.graphs: OrderedDict = OrderedDict()
        self.recorded = 0
        self.pillars: dict = {}  # graph key -> the most pillar rows its frames have needed
        self.config = None  # a copy of the model's config the graphs and the copy were made with

    def config_changed(self, model: nn.Module) -> bool:
        """Whether ``model.config`` differs from the one the graphs and the copy were made with (they hold its
        thresholds and capacities: a user's ``model.config.score_thresh = 0.5`` must be seen). A new one is kept,
        copied, so that a later change in place is seen too."""
        if self.config is not None and model.config == self.config:
            return False
        self.config = copy.deepcopy(model.config)
        return True

    def current(self, model: nn.Module) -> tuple:
        """The model's tensors as the graphs would read them: data pointers, in the order of :attr:`places`
        (listed again when a top-level module was replaced)."""
        children = tuple(model._modules.values())
        if children != self.children or not self.places:
            self.children = children
            self.places = [(d, name) for m in model.modules() for d in (m._parameters, m._buffers)
                           for name, t in d.items() if t is not None]
        return tuple(d[name].data_ptr() if d.get(name) is not None else 0 for d, name in self.places)

    def versions(self) -> tuple | None:
        """The in-place version counters of the tensors of :attr:`places` (an optimized graph reads a copy, so a
        change must be seen here); None when one is an inference tensor, which keeps no counter."""
        try:
            return tuple(d[name]._version if d.get(name) is not None else -1 for d, name in self.places)
        except RuntimeError:
            return None

    def __deepcopy__(self, memo):
        return _PredictGraphs()

    def __reduce__(self):
        return _PredictGraphs, ()


def copy_predict(model: nn.Module, batch: Mapping) -> list[dict] | None:
    """``predict`` of a PointPillars or a CounterNet on the CPU through an :func:`inference_copy` of the eval-mode
    model (BatchNorm folded into the convolutions, the padding into the convolutions, channels-last maps, the
    head's convolutions as one): the same results up to float rounding, in about 55-60 % of the time. The copy is
    made at the first call and again when the model's tensors are replaced or updated in place (their version
    counters), or None where the model itself must run: a model off the CPU, an autocast on the CPU, tensors
    without version counters (made under ``torch.inference_mode``), where an update could not be seen. No
    autograd graph is recorded."""
    points = batch.get("points") if isinstance(batch, Mapping) else None
    if not isinstance(points, Tensor) or points.device.type != "cpu" or torch.is_autocast_enabled("cpu"):
        return None
    param = next(model.parameters(), None)
    if param is None or param.device.type != "cpu":
        return None
    cache = model.__dict__.get("_predict_copy")
    if cache is None:
        cache = model._predict_copy = _PredictGraphs()
    state = (cache.current(model), cache.versions())
    if state[1] is None:
        return None
    made = cache.graphs.get("copy")
    if cache.config_changed(model) or made is None or made[0] != state:
        with torch.no_grad():
            cache.graphs["copy"] = made = (state, inference_copy(model))
    with torch.no_grad():
        return made[1].postprocess(made[1](batch), batch)


def _predict_rows(needed: int, full: int) -> int:
    """Pillar rows for a predict graph whose frames have needed ``needed`` (:data:`ROWS_HEADROOM`)."""
    return min(full, max(MIN_ROWS, 1 << math.ceil(math.log2(ROWS_HEADROOM * needed + 1))))


def graphed_predict(model: PointPillars, batch: Mapping) -> list[dict] | None:
    """:meth:`PointPillars.predict` on CUDA as a replayed :class:`GraphedPointPillars` (the eval-mode model, dense
    backbone), or None where the eager call must run: the first call with frames of a size (a graph is recorded
    from the second), anything the eager call would refuse (it raises its own error), frames over
    :data:`MAX_CAPACITY` points, a CUDA graph being captured, lidarops without CUDA kernels.

    The graph is recorded under torch's TF32 and autocast settings of the call and again when they change, or
    when the model's tensors are replaced (``.to()``, ``.half()``); in-place updates of the weights
    (``load_state_dict``, an optimizer's step) are seen by the replays. Under a CUDA autocast to float16 or
    bfloat16 the graph records an :func:`inference_copy` (:data:`OPTIMIZE_UNDER_AUTOCAST`), recorded again after
    an in-place update (the tensors' version counters). Its pillar rows are sized from the pillars its frames need
    (:data:`ROWS_HEADROOM`), recorded again with more when a batch needs more (that batch is redone eagerly)."""
    from lidarops import extension

    points, cfg = batch["points"], model.config
    c = cfg.num_point_features
    B = batch.get("batch_size")
    if (torch.cuda.is_current_stream_capturing() or not extension.cuda_available() or points.dim() != 2
            or points.shape[1] < 1 + c or not points.is_floating_point() or isinstance(B, bool)
            or not isinstance(B, numbers.Integral) or not 1 <= B <= max(points.shape[0], 1)):
        return None
    B = int(B)
    param = next(model.parameters())
    if points.device != param.device:
        return None
    frame = points[:, 0]
    if B == 1:
        frames, biggest = [points[:, 1:1 + c]], points.shape[0]
        bad_index = (frame != 0).any() if value_checks_enabled() and points.shape[0] else None
    else:
        # the frames' sizes and the frame-index check in one read; the eager call names what is wrong
        bad = ~((frame >= 0) & (frame < B) & (frame == frame.round()))
        counts = torch.bincount(frame.long().clamp(0, B - 1), minlength=B)
        *sizes, flagged = torch.cat([counts, bad.any().long()[None]]).tolist()
        if flagged or min(sizes) == 0:
            return None
        order = torch.argsort(frame, stable=True)
        frames, biggest, bad_index = list(torch.split(points[order, 1:1 + c], sizes)), max(sizes), None
    capacity = graph_capacity(biggest, MIN_CAPACITY)
    if capacity > MAX_CAPACITY:
        return None
    cache = model.__dict__.get("_predict_graphs")
    if cache is None:
        cache = model._predict_graphs = _PredictGraphs()
    tensors = cache.current(model)
    config_changed = cache.config_changed(model)  # the graphs hold its thresholds, the pillar counts its sizes
    if config_changed or cache.tensors != tensors:  # new tensors: every graph recorded the old ones
        cache.graphs.clear()
        cache.seen.clear()
        cache.tensors = tensors
        if config_changed:
            cache.pillars.clear()
    autocast = torch.is_autocast_enabled("cuda")
    versions = cache.versions() if (OPTIMIZE_UNDER_AUTOCAST and autocast and torch.get_autocast_dtype("cuda")
                                    in (torch.float16, torch.bfloat16)) else None
    optimize = versions is not None
    key = (capacity, B, param.dtype, torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32,
           autocast, torch.get_autocast_dtype("cuda"), optimize)
    full = B * min(cfg.max_voxels_test, capacity)  # rows that always hold the frames' pillars
    graphed = cache.graphs.get(key)
    if graphed is not None and optimize and graphed._copied_at != versions:
        del cache.graphs[key]  # its copy holds the weights from before an in-place update: record it again
        graphed = None
    if graphed is not None and graphed.max_pillars < _predict_rows(cache.pillars.get(key, 0), full):
        del cache.graphs[key]  # its frames have needed more pillar rows than it has: record it again with more
        graphed = None
    if graphed is None:
        if key not in cache.seen or cache.recorded >= MAX_RECORDINGS:
            cache.seen.add(key)  # a single call (a CLI run on one scan) is not worth a graph's recording
            return None
        if key not in cache.pillars:
            from lidarops.models.pointpillars import voxelize_frames

            try:  # the pillars these frames need (a recording costs far more than this eager count)
                with torch.no_grad():
                    cache.pillars[key] = int(voxelize_frames(points.to(param.dtype), B, cfg, False)[0].shape[0])
            except (ValueError, RuntimeError):  # a bad value: the eager call names it
                return None
        while len(cache.graphs) >= KEEP_GRAPHS:
            cache.graphs.popitem(last=False)
        was_training = model.training  # replays run in eval mode whatever the mode; recording sets it
        try:
            with torch.inference_mode(False):  # buffers the replays of calls outside inference mode may write too
                graphed = GraphedPointPillars(model, capacity=capacity, precision=None, batch_size=B, optimize=optimize,
                                              max_pillars=_predict_rows(cache.pillars[key], full))
        finally:
            model.train(was_training)
        graphed._copied_at = versions  # the tensors' versions its copy was made at (None: no copy)
        cache.graphs[key] = graphed
        cache.recorded += 1
    cache.graphs.move_to_end(key)
    try:
        out = graphed(frames)
    except ValueError:  # a bad value: the eager call names it by the batch's own rows
        return None
    # the rows these frames needed (a replay short of rows was redone eagerly; the next call records more)
    cache.pillars[key] = max(cache.pillars.get(key, 0), int(graphed.last_reads[0][3]))
    if bad_index is not None and bool(bad_index):  # read after the replay's own: the device is done by then
        return None
    return out
