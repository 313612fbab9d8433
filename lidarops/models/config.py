"""Model configs: the typed dataclasses models are built from, read from OpenPCDet-schema dicts
(``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``) that :func:`lidarops.config.load_config` returns::

    from lidarops.config import load_config
    model_cfg = PointPillarsConfig.from_openpcdet(load_config("configs/pointpillars/pointpillars_synth.yaml"))

Every numeric field is validated when the dataclass is built; a bad one raises :class:`ConfigError`
naming the key.
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

from lidarops._moved import moved_attributes
from lidarops.config import ConfigError

__all__ = ["PointPillarsConfig", "ConfigError"]

__getattr__ = moved_attributes(__name__, {"load_config": "lidarops.config", "merge_config": "lidarops.config"})


def _get(d: Mapping, path: str, default: Any = dataclasses.MISSING) -> Any:
    cur: Any = d
    for part in path.split("."):
        if not isinstance(cur, Mapping) or part not in cur:
            if default is dataclasses.MISSING:
                raise ConfigError(f"config key {path} is missing")
            return default
        cur = cur[part]
    return cur


def _expect(value: Any, allowed: Sequence, key: str) -> None:
    if value not in allowed:
        raise ConfigError(f"{key} = {value!r} is not supported by lidarops' PointPillars; supported: "
                          + ", ".join(repr(a) for a in allowed))


def _by_split(value: Any, split: str, key: str) -> int:
    if isinstance(value, Mapping):
        if split not in value:
            raise ConfigError(f"{key} must give a value for '{split}', got {dict(value)}")
        value = value[split]
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ConfigError(f"{key} must be a positive int (or {{train: .., test: ..}}), got {value!r}")
    return value


@dataclass
class PointPillarsConfig:
    """Everything :class:`lidarops.models.PointPillars` is built from (OpenPCDet ``pointpillar.yaml``).

    Attributes mirror OpenPCDet's keys in lower case; :meth:`from_openpcdet` reads a full config
    (``CLASS_NAMES``, ``DATA_CONFIG``, ``MODEL``), :meth:`to_dict` / :meth:`from_dict` round-trip the
    resolved values (what checkpoints store).
    """

    class_names: list[str] = field(default_factory=lambda: ["Car", "Pedestrian", "Cyclist"])
    point_cloud_range: list[float] = field(default_factory=lambda: [0.0, -39.68, -3.0, 69.12, 39.68, 1.0])
    voxel_size: list[float] = field(default_factory=lambda: [0.16, 0.16, 4.0])
    max_points_per_voxel: int = 32
    max_voxels_train: int = 16000
    max_voxels_test: int = 40000
    num_point_features: int = 4  # x, y, z, intensity
    # VFE (PillarVFE)
    vfe_num_filters: list[int] = field(default_factory=lambda: [64])
    with_distance: bool = False
    use_absolute_xyz: bool = True
    use_norm: bool = True
    # BACKBONE_2D (BaseBEVBackbone)
    layer_nums: list[int] = field(default_factory=lambda: [3, 5, 5])
    layer_strides: list[int] = field(default_factory=lambda: [2, 2, 2])
    num_filters: list[int] = field(default_factory=lambda: [64, 128, 256])
    upsample_strides: list[int] = field(default_factory=lambda: [1, 2, 4])
    num_upsample_filters: list[int] = field(default_factory=lambda: [128, 128, 128])
    backbone_mode: str = "dense"  # lidarops: "dense" (OpenPCDet's layout) or "sparse"
    # DENSE_HEAD (AnchorHeadSingle)
    anchor_generator_config: list[dict] = field(default_factory=lambda: [
        {"class_name": "Car", "anchor_sizes": [[3.9, 1.6, 1.56]], "anchor_rotations": [0, 1.57],
         "anchor_bottom_heights": [-1.78], "align_center": False, "feature_map_stride": 2,
         "matched_threshold": 0.6, "unmatched_threshold": 0.45},
        {"class_name": "Pedestrian", "anchor_sizes": [[0.8, 0.6, 1.73]], "anchor_rotations": [0, 1.57],
         "anchor_bottom_heights": [-0.6], "align_center": False, "feature_map_stride": 2,
         "matched_threshold": 0.5, "unmatched_threshold": 0.35},
        {"class_name": "Cyclist", "anchor_sizes": [[1.76, 0.6, 1.73]], "anchor_rotations": [0, 1.57],
         "anchor_bottom_heights": [-0.6], "align_center": False, "feature_map_stride": 2,
         "matched_threshold": 0.5, "unmatched_threshold": 0.35},
    ])
    use_direction_classifier: bool = True
    dir_offset: float = 0.78539
    dir_limit_offset: float = 0.0
    num_dir_bins: int = 2
    norm_by_num_examples: bool = False
    cls_weight: float = 1.0
    loc_weight: float = 2.0
    dir_weight: float = 0.2
    code_weights: list[float] = field(default_factory=lambda: [1.0] * 7)
    # POST_PROCESSING
    score_thresh: float = 0.1
    multi_classes_nms: bool = False
    nms_thresh: float = 0.01
    nms_pre_maxsize: int = 4096
    nms_post_maxsize: int = 500

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ derived
    @property
    def grid_size(self) -> tuple[int, int, int]:
        """(nx, ny, nz) pillars of the range (OpenPCDet's ``grid_size``)."""
        r, v = self.point_cloud_range, self.voxel_size
        return tuple(int(round((r[i + 3] - r[i]) / v[i])) for i in range(3))

    @property
    def num_class(self) -> int:
        return len(self.class_names)

    # ------------------------------------------------------------------ checks
    def validate(self) -> None:
        if not self.class_names or len(set(self.class_names)) != len(self.class_names):
            raise ConfigError(f"CLASS_NAMES must be distinct names, got {self.class_names}")
        if len(self.point_cloud_range) != 6 or len(self.voxel_size) != 3:
            raise ConfigError(f"POINT_CLOUD_RANGE needs 6 values and VOXEL_SIZE 3, got {self.point_cloud_range} "
                              f"and {self.voxel_size}")
        for i, axis in enumerate("xyz"):
            extent = self.point_cloud_range[i + 3] - self.point_cloud_range[i]
            cells = extent / self.voxel_size[i] if self.voxel_size[i] > 0 else math.nan
            if not (extent > 0 and cells >= 1 and abs(cells - round(cells)) < 1e-4):
                raise ConfigError(f"POINT_CLOUD_RANGE must hold a whole number of VOXEL_SIZE cells along {axis}: "
                                  f"extent {extent:g} / {self.voxel_size[i]:g} = {cells:g}")
        if self.grid_size[2] != 1:
            raise ConfigError(f"PointPillars needs one voxel in z (VOXEL_SIZE z = the range's z extent), got "
                              f"{self.grid_size[2]} cells")
        names = [c.get("class_name") for c in self.anchor_generator_config]
        if names != list(self.class_names):
            raise ConfigError(f"ANCHOR_GENERATOR_CONFIG must give one entry per class in CLASS_NAMES order "
                              f"{list(self.class_names)}, got {names}")
        strides = {int(c.get("feature_map_stride", 0)) for c in self.anchor_generator_config}
        feat_stride = self.layer_strides[0] // self.upsample_strides[0] if self.upsample_strides[0] else 0
        if len(strides) != 1 or strides != {feat_stride}:
            raise ConfigError(f"every anchor feature_map_stride must equal the backbone's output stride "
                              f"{feat_stride}, got {sorted(strides)}")
        for i, c in enumerate(self.anchor_generator_config):
            for key in ("anchor_sizes", "anchor_rotations", "anchor_bottom_heights", "matched_threshold",
                        "unmatched_threshold"):
                if key not in c:
                    raise ConfigError(f"ANCHOR_GENERATOR_CONFIG[{i}] ({c.get('class_name')}) lacks {key}")
        if self.backbone_mode not in ("dense", "sparse"):
            raise ConfigError(f"backbone_mode must be 'dense' or 'sparse', got {self.backbone_mode!r}")
        if len(self.code_weights) != 7:
            raise ConfigError(f"code_weights needs 7 values, got {self.code_weights}")
        if self.num_dir_bins < 1 or self.num_point_features < 3:
            raise ConfigError("NUM_DIR_BINS must be >= 1 and the points need at least x, y, z")

    # ------------------------------------------------------------------ conversions
    def to_dict(self) -> dict:
        return copy.deepcopy(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, d: Mapping) -> "PointPillarsConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown PointPillarsConfig keys {unknown}")
        return cls(**copy.deepcopy(dict(d)))

    @classmethod
    def from_openpcdet(cls, cfg: Mapping) -> "PointPillarsConfig":
        """From a full OpenPCDet-schema config dict (``load_config`` of ``pointpillar.yaml`` or a lidarops
        config). Options lidarops does not implement raise :class:`ConfigError` naming the key."""
        model = _get(cfg, "MODEL")
        _expect(_get(model, "VFE.NAME"), ("PillarVFE",), "MODEL.VFE.NAME")
        _expect(_get(model, "MAP_TO_BEV.NAME", "PointPillarScatter"), ("PointPillarScatter",), "MODEL.MAP_TO_BEV.NAME")
        _expect(_get(model, "BACKBONE_2D.NAME"), ("BaseBEVBackbone",), "MODEL.BACKBONE_2D.NAME")
        _expect(_get(model, "DENSE_HEAD.NAME"), ("AnchorHeadSingle",), "MODEL.DENSE_HEAD.NAME")
        head = _get(model, "DENSE_HEAD")
        _expect(bool(head.get("CLASS_AGNOSTIC", False)), (False,), "MODEL.DENSE_HEAD.CLASS_AGNOSTIC")
        assigner = head.get("TARGET_ASSIGNER_CONFIG", {})
        _expect(assigner.get("NAME", "AxisAlignedTargetAssigner"), ("AxisAlignedTargetAssigner",),
                "TARGET_ASSIGNER_CONFIG.NAME")
        _expect(assigner.get("BOX_CODER", "ResidualCoder"), ("ResidualCoder",), "TARGET_ASSIGNER_CONFIG.BOX_CODER")
        _expect(bool(assigner.get("MATCH_HEIGHT", False)), (False,), "TARGET_ASSIGNER_CONFIG.MATCH_HEIGHT")
        if float(assigner.get("POS_FRACTION", -1.0)) > 0:
            raise ConfigError("TARGET_ASSIGNER_CONFIG.POS_FRACTION > 0 (anchor sampling) is not supported; use -1.0")
        post = _get(model, "POST_PROCESSING", {})
        nms = post.get("NMS_CONFIG", {})
        _expect(nms.get("NMS_TYPE", "nms_gpu"), ("nms_gpu",), "POST_PROCESSING.NMS_CONFIG.NMS_TYPE")
        vfe = _get(model, "VFE")
        data = _get(cfg, "DATA_CONFIG", {})
        proc = {p.get("NAME"): p for p in data.get("DATA_PROCESSOR", [])}
        voxel = proc.get("transform_points_to_voxels", {})
        encoding = data.get("POINT_FEATURE_ENCODING", {})
        used = encoding.get("used_feature_list", ["x", "y", "z", "intensity"])
        bb = _get(model, "BACKBONE_2D")
        weights = head.get("LOSS_CONFIG", {}).get("LOSS_WEIGHTS", {})
        kwargs = dict(
            class_names=list(_get(cfg, "CLASS_NAMES")),
            point_cloud_range=[float(v) for v in _get(data, "POINT_CLOUD_RANGE", cls().point_cloud_range)],
            voxel_size=[float(v) for v in voxel.get("VOXEL_SIZE", [0.16, 0.16, 4.0])],
            max_points_per_voxel=int(voxel.get("MAX_POINTS_PER_VOXEL", 32)),
            max_voxels_train=_by_split(voxel.get("MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 40000}), "train",
                                       "MAX_NUMBER_OF_VOXELS"),
            max_voxels_test=_by_split(voxel.get("MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 40000}), "test",
                                      "MAX_NUMBER_OF_VOXELS"),
            num_point_features=len(used),
            vfe_num_filters=[int(v) for v in vfe.get("NUM_FILTERS", [64])],
            with_distance=bool(vfe.get("WITH_DISTANCE", False)),
            use_absolute_xyz=bool(vfe.get("USE_ABSLOTE_XYZ", True)),  # sic: OpenPCDet's spelling
            use_norm=bool(vfe.get("USE_NORM", True)),
            layer_nums=[int(v) for v in _get(bb, "LAYER_NUMS")],
            layer_strides=[int(v) for v in _get(bb, "LAYER_STRIDES")],
            num_filters=[int(v) for v in _get(bb, "NUM_FILTERS")],
            upsample_strides=[int(v) for v in _get(bb, "UPSAMPLE_STRIDES")],
            num_upsample_filters=[int(v) for v in _get(bb, "NUM_UPSAMPLE_FILTERS")],
            backbone_mode=str(bb.get("MODE", "dense")),
            anchor_generator_config=[{k.lower() if k.isupper() else k: copy.deepcopy(v) for k, v in c.items()}
                                     for c in _get(head, "ANCHOR_GENERATOR_CONFIG")],
            use_direction_classifier=bool(head.get("USE_DIRECTION_CLASSIFIER", True)),
            dir_offset=float(head.get("DIR_OFFSET", 0.78539)),
            dir_limit_offset=float(head.get("DIR_LIMIT_OFFSET", 0.0)),
            num_dir_bins=int(head.get("NUM_DIR_BINS", 2)),
            norm_by_num_examples=bool(assigner.get("NORM_BY_NUM_EXAMPLES", False)),
            cls_weight=float(weights.get("cls_weight", 1.0)),
            loc_weight=float(weights.get("loc_weight", 2.0)),
            dir_weight=float(weights.get("dir_weight", 0.2)),
            code_weights=[float(v) for v in weights.get("code_weights", [1.0] * 7)],
            score_thresh=float(post.get("SCORE_THRESH", 0.1)),
            multi_classes_nms=bool(nms.get("MULTI_CLASSES_NMS", False)),
            nms_thresh=float(nms.get("NMS_THRESH", 0.01)),
            nms_pre_maxsize=int(nms.get("NMS_PRE_MAXSIZE", 4096)),
            nms_post_maxsize=int(nms.get("NMS_POST_MAXSIZE", 500)),
        )
        return cls(**kwargs)
