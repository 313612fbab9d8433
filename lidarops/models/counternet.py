"""CounterNet (Zhang et al., MM'25): objects counted per class as the peaks of a BEV heatmap, on PointPillars'
floor (issue 38). Read it top to bottom:

- the floor, PointPillars' own modules with OpenPCDet's names: the batch's points are voxelized into pillars,
  ``vfe`` (:class:`~lidarops.models.pillar_vfe.PillarVFE`), ``map_to_bev``
  (:class:`~lidarops.models.map_to_bev.PointPillarScatter`), ``backbone_2d``
  (:class:`~lidarops.models.bev_backbone.BaseBEVBackbone`) -> BEV features ``(B, F, H, W)``;
- ``count_head`` (:class:`CountHead`): a shared 3x3 conv + BN + ReLU, then per partition of the map (``pt`` in
  1, 2, 4, 9, each region expanded by ``delta`` of its size, :func:`~lidarops.models.counting.partition_boxes`)
  its own heatmap branch (3x3 conv + BN + ReLU, 3x3 conv to one channel per class, bias -2.19) on its region;
  the heatmaps are ``sigmoid`` of the logits, once;
- the loss (:meth:`CounterNet.loss`): per region the CenterNet focal loss against CenterPoint Gaussians at the
  object centres (:func:`~lidarops.models.counting.heatmap_targets`, :func:`~lidarops.models.counting.focal_loss`)
  + ``COUNT_WEIGHT`` x the L1 distance between a differentiable count (:func:`~lidarops.models.counting.soft_count`:
  the local maxima's soft-thresholded heights) and the true count of the region, weighted per region by
  :func:`~lidarops.models.counting.partition_weights`;
- counting (:meth:`CounterNet.postprocess`): per frame and region the threshold ``max(Otsu, THRESHOLD)``
  (:func:`~lidarops.models.counting.otsu_threshold` over the region's heatmap values), local maxima
  (:func:`~lidarops.models.counting.find_peaks`), their centres in metres; with overlapping regions
  (``delta > 0``) the centres found twice are merged (:func:`~lidarops.models.counting.merge_centres`); the
  count of a class is the number of its centres.

::

    model = CounterNet(load_config("configs/counternet/counternet_synth.yaml"))
    out = model(batch)             # training: {"loss", "loss_heatmap", "loss_count", "count_error"}
    frames = model.predict(batch)  # [{"counts": (C,) int64, "centres": (K, 4) x, y, class, score}, ...]
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

import torch
from torch import Tensor, nn

from lidarops.config import ConfigError
from lidarops.models.base import (DictConfig, PredictMixin, as_model_config, load_weights_strict,
                                  model_from_checkpoint)
from lidarops.models.bev_backbone import BaseBEVBackbone
from lidarops.models.config import PointPillarsConfig, _check_value
from lidarops.models.map_to_bev import PointPillarScatter
from lidarops.models.pillar_vfe import PillarVFE
from lidarops.models.pointpillars import _check_batch, _predict_on_cpu_copy, voxelize_frames

__all__ = ["CounterNet", "CounterNetConfig", "CountHead"]

ROAD_CLASSES = ["Car", "Truck", "Bus", "Pedestrian", "Cyclist", "Barrier", "TrafficCone"]
_PARTITIONS = (1, 2, 4, 9)
# field -> (the COUNT_HEAD key, kind, lo, hi, lo open, hi open)
_SPEC: dict[str, tuple] = {
    "shared_channels": ("SHARED_CHANNELS", "int", 1, 4096, False, False),
    "head_channels": ("HEAD_CHANNELS", "int", 1, 4096, False, False),
    "partitions": ("PARTITIONS", "int", 1, 9, False, False),
    "delta": ("OVERLAP", "real", 0.0, 1.0, False, False),
    "threshold": ("THRESHOLD", "real", 0.0, 1.0, True, True),
    "peak_radius": ("PEAK_RADIUS", "int", 0, 64, False, False),
    "min_overlap": ("MIN_OVERLAP", "real", 0.0, 1.0, True, True),
    "min_radius": ("MIN_RADIUS", "int", 0, 64, False, False),
    "count_weight": ("COUNT_WEIGHT", "real", 0.0, None, False, False),
    "count_temperature": ("COUNT_TEMPERATURE", "real", 0.0, None, True, False),
    "merge_radius": ("MERGE_RADIUS", "real", 0.0, None, False, False),
    "feature_map_stride": ("FEATURE_MAP_STRIDE", "int", 1, 64, False, False),
}
_FLAGS = {"otsu": "OTSU"}


@dataclass
class CounterNetConfig(DictConfig):
    """Everything :class:`CounterNet` is built from.

    Attributes:
        floor (dict): the BEV floor, a :class:`PointPillarsConfig` as a dict (class names, point cloud range,
            voxels, ``VFE``, ``BACKBONE_2D``; its anchor head is not built), read from the config's ``MODEL``
            by PointPillars' own reader.
        shared_channels, head_channels (int): [MODEL.COUNT_HEAD.SHARED_CHANNELS, HEAD_CHANNELS] (64, 64).
        partitions (int): [PARTITIONS] ``pt``: 1, 2 (two halves along x), 4 (2 x 2) or 9 (3 x 3) regions.
        delta (float): [OVERLAP] each region grows by this share of its size on every side (0, 0.1-0.3).
        threshold (float): [THRESHOLD] ``t``: a peak's least height (0.5); with ``otsu`` the threshold of a
            region is ``max(Otsu, t)``.
        otsu (bool): [OTSU] per frame and region Otsu thresholds (True).
        peak_radius (int): [PEAK_RADIUS] ``r``: peaks are maxima of their (2r+1)^2 window (2).
        min_overlap (float), min_radius (int): [MIN_OVERLAP, MIN_RADIUS] the Gaussians' radius (0.1, 2).
        count_weight (float): [COUNT_WEIGHT] the count loss's weight (1.0).
        count_temperature (float): [COUNT_TEMPERATURE] of the soft threshold of the differentiable count (0.05).
        merge_radius (float): [MERGE_RADIUS] metres within which centres of one class found by two overlapping
            regions are one object (default: one cell of the feature map, the seed's gamma).
        feature_map_stride (int): [FEATURE_MAP_STRIDE] voxel cells per heatmap cell: the backbone's output
            stride (PointPillars' default backbone: 2).
    """

    floor: dict = field(default_factory=lambda: _floor_dict(ROAD_CLASSES))
    shared_channels: int = 64
    head_channels: int = 64
    partitions: int = 1
    delta: float = 0.0
    threshold: float = 0.5
    otsu: bool = True
    peak_radius: int = 2
    min_overlap: float = 0.1
    min_radius: int = 2
    count_weight: float = 1.0
    count_temperature: float = 0.05
    merge_radius: Optional[float] = None
    feature_map_stride: int = 2

    def __post_init__(self) -> None:
        for name, (key, kind, lo, hi, lo_open, hi_open) in _SPEC.items():
            value = getattr(self, name)
            if name == "merge_radius" and value is None:
                continue
            _check_value(value, f"MODEL.COUNT_HEAD.{key}", kind, lo, hi, lo_open, hi_open)
        if self.partitions not in _PARTITIONS:
            raise ConfigError(f"MODEL.COUNT_HEAD.PARTITIONS must be one of {list(_PARTITIONS)}, got {self.partitions!r}")
        if not isinstance(self.otsu, bool):
            raise ConfigError(f"MODEL.COUNT_HEAD.OTSU must be true or false, got {self.otsu!r}")
        for name in ("delta", "threshold", "min_overlap", "count_weight", "count_temperature"):
            setattr(self, name, float(getattr(self, name)))
        self.floor = self.floor_config().to_dict()
        if self.merge_radius is None:
            self.merge_radius = float(self.floor_config().voxel_size[0] * self.feature_map_stride)
        self.merge_radius = float(self.merge_radius)

    def floor_config(self) -> PointPillarsConfig:
        return PointPillarsConfig.from_dict(self.floor)

    @property
    def class_names(self) -> list[str]:
        return list(self.floor["class_names"])

    @property
    def num_classes(self) -> int:
        return len(self.floor["class_names"])

    @classmethod
    def from_openpcdet(cls, cfg: Mapping) -> "CounterNetConfig":
        """From a whole config dict: ``CLASS_NAMES``, ``DATA_CONFIG`` (range, voxels), ``MODEL`` with ``NAME:
        CounterNet``, the floor's ``VFE``, ``MAP_TO_BEV``, ``BACKBONE_2D`` and ``COUNT_HEAD``."""
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"a config must be a mapping (OpenPCDet's schema), got {type(cfg).__name__}")
        model = cfg.get("MODEL")
        if not isinstance(model, Mapping) or model.get("NAME") != "CounterNet":
            raise ConfigError("MODEL.NAME must be 'CounterNet' for CounterNetConfig, got "
                              f"{model.get('NAME') if isinstance(model, Mapping) else model!r}")
        unknown = sorted(set(model) - {"NAME", "VFE", "MAP_TO_BEV", "BACKBONE_2D", "COUNT_HEAD"})
        if unknown:
            raise ConfigError(f"unknown MODEL keys {unknown} for CounterNet; known: BACKBONE_2D, COUNT_HEAD, "
                              "MAP_TO_BEV, NAME, VFE")
        head = model.get("COUNT_HEAD", {})
        if not isinstance(head, Mapping):
            raise ConfigError(f"MODEL.COUNT_HEAD must be a mapping, got {head!r}")
        keys = {key: name for name, (key, *_r) in _SPEC.items()} | {v: k for k, v in _FLAGS.items()}
        unknown = sorted(set(head) - set(keys) - {"NAME"})
        if unknown:
            raise ConfigError(f"unknown MODEL.COUNT_HEAD keys {unknown}; known: {sorted(keys)}")
        kwargs = {keys[k]: v for k, v in head.items() if k in keys}
        kwargs["floor"] = _floor_of(cfg).to_dict()
        return cls(**kwargs)


def _floor_dict(class_names: list[str]) -> dict:
    return PointPillarsConfig(class_names=list(class_names), anchor_generator_config=_placeholder_anchors(
        class_names)).to_dict()


def _placeholder_anchors(class_names) -> list[dict]:
    # PointPillarsConfig describes an anchor head too; CounterNet builds none, so one anchor per class stands in
    return [{"class_name": n, "anchor_sizes": [[1.0, 1.0, 1.0]], "anchor_rotations": [0.0], "anchor_bottom_heights": [0.0],
             "align_center": False, "feature_map_stride": 2, "matched_threshold": 0.6, "unmatched_threshold": 0.45}
            for n in class_names]


def _floor_of(cfg: Mapping) -> PointPillarsConfig:
    """The BEV floor read by PointPillars' own reader (its keys, checks and defaults)."""
    model = dict(cfg["MODEL"])
    model.pop("COUNT_HEAD", None)
    names = cfg.get("CLASS_NAMES")
    if not isinstance(names, list):
        raise ConfigError(f"CLASS_NAMES must be a list of names, got {names!r}")
    model.update(NAME="PointPillar", DENSE_HEAD={"NAME": "AnchorHeadSingle",
                                                  "ANCHOR_GENERATOR_CONFIG": _placeholder_anchors(names)})
    return PointPillarsConfig.from_openpcdet({**cfg, "MODEL": model})


class CountHead(nn.Module):
    """A shared 3x3 conv + BN + ReLU on the BEV features, then one heatmap branch per region (3x3 conv + BN +
    ReLU, 3x3 conv to ``num_classes``, bias -2.19 so that every cell starts at sigmoid = 0.1)."""

    def __init__(self, in_channels: int, num_classes: int, shared_channels: int = 64, head_channels: int = 64,
                 regions: int = 1):
        super().__init__()
        self.shared_conv = nn.Sequential(nn.Conv2d(in_channels, shared_channels, 3, padding=1, bias=False),
                                         nn.BatchNorm2d(shared_channels), nn.ReLU())
        self.heatmaps = nn.ModuleList()
        for _ in range(regions):
            branch = nn.Sequential(nn.Conv2d(shared_channels, head_channels, 3, padding=1, bias=False),
                                   nn.BatchNorm2d(head_channels), nn.ReLU(),
                                   nn.Conv2d(head_channels, num_classes, 3, padding=1))
            nn.init.constant_(branch[-1].bias, -2.19)
            self.heatmaps.append(branch)

    def forward(self, bev: Tensor, boxes) -> tuple[Tensor, list[Tensor]]:
        """``(shared features (B, S, H, W), [logits of region p on its box (B, C, h_p, w_p)])``; ``boxes``: the
        regions' ``[y0, y1, x0, x1]``, a (P, 4) tensor or a list of P such sequences."""
        shared = self.shared_conv(bev)
        out = []
        for branch, (y0, y1, x0, x1) in zip(self.heatmaps, boxes.tolist() if isinstance(boxes, Tensor) else boxes):
            out.append(branch(shared[:, :, y0:y1, x0:x1]))
        return shared, out


class CounterNet(PredictMixin, nn.Module):
    """CounterNet: per-class object counts of each frame (a :class:`lidarops.train.TrainableModel`).

    Batch (OpenPCDet's, as :class:`~lidarops.models.pointpillars.PointPillars`): ``points (P, 1 + C)``,
    ``batch_size``, in training ``gt_boxes (B, M, 8)`` (class id 1-based into ``class_names``, 0 = padding).

    ``forward(batch)``: in training ``{"loss", "loss_heatmap", "loss_count", "count_error"}`` (``count_error``
    the mean absolute error of the differentiable counts, logged); in eval mode ``{"heatmaps": [(B, C, h_p,
    w_p) probabilities per region], "features": (B, S) the shared features' global max}``. :meth:`postprocess`
    turns them into per-frame counts and centres.
    """

    def __init__(self, config: "CounterNetConfig | Mapping | str | Path | None" = None):
        super().__init__()
        cfg = self.config = as_model_config(config, CounterNetConfig)
        floor = cfg.floor_config()
        self.vfe = PillarVFE(floor.num_point_features, floor.voxel_size, floor.point_cloud_range,
                             floor.vfe_num_filters, floor.with_distance, floor.use_absolute_xyz, floor.use_norm)
        self.map_to_bev = PointPillarScatter(self.vfe.out_channels, floor.grid_size)
        self.backbone_2d = BaseBEVBackbone(self.vfe.out_channels, floor.layer_nums, floor.layer_strides,
                                           floor.num_filters, floor.upsample_strides, floor.num_upsample_filters,
                                           mode=floor.backbone_mode)
        nx, ny, _ = floor.grid_size
        self.map_size = (ny // cfg.feature_map_stride, nx // cfg.feature_map_stride)  # (H, W) of the heatmaps
        from lidarops.models.counting import partition_boxes

        regions = partition_boxes(*self.map_size, cfg.partitions, cfg.delta)
        self.register_buffer("regions", regions, persistent=False)
        # the same boxes as Python ints: slicing by them reads nothing back from the device (a CUDA graph holds it)
        self.region_boxes: list[tuple[int, int, int, int]] = [tuple(r) for r in regions.tolist()]
        self.count_head = CountHead(self.backbone_2d.out_channels, cfg.num_classes, cfg.shared_channels,
                                    cfg.head_channels, cfg.partitions)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_config(cls, config) -> "CounterNet":
        return cls(config)

    @classmethod
    def from_checkpoint(cls, path: "str | Path", config=None, map_location: Any = "cpu",
                        check_finite: bool = True) -> "CounterNet":
        """A model with the weights and config of a lidarops checkpoint (``lidarops train``'s ``final.pth``)."""
        return model_from_checkpoint(cls, path, config, map_location, check_finite)

    def load_weights(self, state_dict: Mapping[str, Tensor], source: str = "state dict",
                     check_finite: bool = True) -> None:
        """Strict loading with one error naming the keys that differ (and, with ``check_finite``, NaN or inf)."""
        load_weights_strict(self, state_dict, source, check_finite)

    # ---------------------------------------------------------------- the network
    def network(self, voxels: Tensor, num_points: Tensor, coords: Tensor, batch_size: int) -> tuple[Tensor, list[Tensor]]:
        """Pillars -> ``(shared features, [logits per region])``."""
        features = self.vfe(voxels, num_points, coords)
        bev = self.backbone_2d(self.map_to_bev(features, coords, batch_size))
        return self.count_head(bev, self.region_boxes)

    def forward(self, batch: Mapping[str, Any]) -> dict:
        floor = self.config.floor_config()
        weights = self.vfe.pfn_layers[0].linear.weight.dtype
        points, batch_size = _check_batch(batch, floor, self.training, weights)
        shared, logits = self.network(*voxelize_frames(points, batch_size, floor, self.training), batch_size)
        heatmaps = [torch.sigmoid(x) for x in logits]
        if not self.training:
            return {"heatmaps": heatmaps, "features": shared.amax(dim=(2, 3))}
        return self.loss(heatmaps, batch["gt_boxes"])

    def targets(self, gt_boxes: Tensor) -> Tensor:
        """The CenterPoint heatmap of the whole map ``(B, C, H, W)``."""
        from lidarops.models.counting import heatmap_targets

        floor = self.config.floor_config()
        return heatmap_targets(gt_boxes, self.config.num_classes, floor.point_cloud_range, floor.voxel_size,
                               floor.grid_size[:2], self.config.feature_map_stride, self.config.min_overlap,
                               self.config.min_radius)

    def loss(self, heatmaps: list[Tensor], gt_boxes: Tensor) -> dict[str, Tensor]:
        """Focal loss per region (averaged over the regions) + ``count_weight`` x the region-weighted L1 count loss."""
        from lidarops.models.counting import focal_loss, partition_weights, soft_count

        cfg = self.config
        target = self.targets(gt_boxes).to(heatmaps[0].dtype)
        hm_losses, count_errors, true_counts = [], [], []
        for pred, (y0, y1, x0, x1) in zip(heatmaps, self.region_boxes):
            t = target[:, :, y0:y1, x0:x1]
            hm_losses.append(focal_loss(pred, t))
            true = (t == 1).sum(dim=(2, 3)).to(pred.dtype)  # (B, C): the centres in this region
            soft = soft_count(pred, cfg.threshold, cfg.peak_radius, cfg.count_temperature)
            count_errors.append((soft - true).abs().mean(dim=1))  # (B,)
            true_counts.append(true.sum(dim=1))
        weights = partition_weights(torch.stack(true_counts, dim=1)).detach()  # (B, P)
        loss_count = (weights * torch.stack(count_errors, dim=1)).sum(dim=1).mean()
        loss_hm = torch.stack(hm_losses).mean()
        loss = loss_hm + cfg.count_weight * loss_count
        return {"loss": loss, "loss_heatmap": loss_hm.detach(), "loss_count": loss_count.detach(),
                "count_error": torch.stack(count_errors, dim=1).mean().detach()}

    def _predict_replayed(self, batch: Mapping[str, Any]) -> list[dict] | None:
        # on the CPU: the inference copy (BatchNorm and padding folded, channels-last), as PointPillars' predict
        if self.config.floor_config().backbone_mode != "dense":
            return None
        return _predict_on_cpu_copy(self, batch)

    @torch.no_grad()
    def postprocess(self, raw: Mapping[str, Any], batch: Mapping[str, Any] | None = None) -> list[dict]:
        """Per frame: ``counts`` (C,) int64, ``centres`` (K, 4) [x, y, class, score] in metres, ``features``
        (S,) (for model selection) and, when the batch holds ``gt_boxes``, ``true_counts`` (C,): the labelled
        objects whose centre lies in the map (what the evaluator scores against)."""
        from lidarops.models.counting import find_peaks, merge_centres, otsu_threshold, peak_centres

        cfg = self.config
        floor = cfg.floor_config()
        heatmaps = raw["heatmaps"]
        B, C = heatmaps[0].shape[:2]
        centres: list[list[Tensor]] = [[] for _ in range(B)]
        vs = floor.voxel_size
        for pred, (y0, y1, x0, x1) in zip(heatmaps, self.region_boxes):
            thresh = pred.new_full((B, 1, 1, 1), cfg.threshold)
            if cfg.otsu:
                otsu = otsu_threshold(pred.reshape(B, -1)).nan_to_num(cfg.threshold)
                thresh = torch.maximum(thresh, otsu.view(B, 1, 1, 1))
            peaks = find_peaks(pred, thresh, cfg.peak_radius)
            origin = [floor.point_cloud_range[0] + x0 * vs[0] * cfg.feature_map_stride,
                      floor.point_cloud_range[1] + y0 * vs[1] * cfg.feature_map_stride]
            region_range = origin + list(floor.point_cloud_range[2:])
            for b, c in enumerate(peak_centres(pred, peaks, region_range, vs, cfg.feature_map_stride)):
                centres[b].append(c)
        out = []
        for b in range(B):
            c = torch.cat(centres[b]) if centres[b] else heatmaps[0].new_zeros(0, 4)
            if cfg.delta > 0 and c.shape[0]:
                c = merge_centres(c, cfg.merge_radius)
            # index_add_, not bincount: on CUDA bincount reads its maximum back to the host, once per frame
            counts = torch.zeros(C, dtype=torch.int64, device=c.device).index_add_(
                0, c[:, 2].long(), torch.ones(c.shape[0], dtype=torch.int64, device=c.device))
            out.append({"counts": counts, "centres": c, "features": raw["features"][b]})
        if batch is not None and isinstance(batch.get("gt_boxes"), Tensor):
            for b, true in enumerate(self.true_counts(batch["gt_boxes"])):
                out[b]["true_counts"] = true
        return out

    def true_counts(self, gt_boxes: Tensor) -> Tensor:
        """``(B, C)`` int64: labelled objects per class whose centre lies in the map (the counter's view)."""
        floor = self.config.floor_config()
        x0, y0, _, x1, y1, _ = floor.point_cloud_range
        cls = gt_boxes[..., 7].long()
        inside = (cls > 0) & (gt_boxes[..., 0] >= x0) & (gt_boxes[..., 0] < x1) & (gt_boxes[..., 1] >= y0) \
            & (gt_boxes[..., 1] < y1)
        C = self.config.num_classes
        onehot = torch.nn.functional.one_hot((cls - 1).clamp(min=0), C) * inside.unsqueeze(-1)
        return onehot.sum(dim=1)
