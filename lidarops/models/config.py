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


def _section(d: Mapping, key: str, name: str | None = None, default: Any = dataclasses.MISSING) -> Mapping:
    """``d[key]`` when it is a mapping (``default`` when absent), else a ``ConfigError`` naming the key."""
    value = _get(d, key, default)
    if not isinstance(value, Mapping):
        raise ConfigError(f"{name or key} must be a mapping of keys, got {value!r}")
    return value


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


_INT32 = 2**31 - 1
# field -> (OpenPCDet's key, kind, lo, hi): kind "int", "real", "bool", "ints" / "reals" (a list of them);
# bounds are inclusive except where the check says otherwise
_SPEC: dict[str, tuple] = {
    "point_cloud_range": ("DATA_CONFIG.POINT_CLOUD_RANGE", "reals", None, None),
    "voxel_size": ("transform_points_to_voxels.VOXEL_SIZE", "reals", 0.0, None),
    "max_points_per_voxel": ("MAX_POINTS_PER_VOXEL", "int", 1, _INT32),
    "max_voxels_train": ("MAX_NUMBER_OF_VOXELS.train", "int", 1, _INT32),
    "max_voxels_test": ("MAX_NUMBER_OF_VOXELS.test", "int", 1, _INT32),
    "num_point_features": ("POINT_FEATURE_ENCODING.used_feature_list (its length)", "int", 3, 1024),
    "vfe_num_filters": ("MODEL.VFE.NUM_FILTERS", "ints", 1, 1 << 16),
    "with_distance": ("MODEL.VFE.WITH_DISTANCE", "bool", None, None),
    "use_absolute_xyz": ("MODEL.VFE.USE_ABSLOTE_XYZ", "bool", None, None),
    "use_norm": ("MODEL.VFE.USE_NORM", "bool", None, None),
    "layer_nums": ("MODEL.BACKBONE_2D.LAYER_NUMS", "ints", 0, 256),
    "layer_strides": ("MODEL.BACKBONE_2D.LAYER_STRIDES", "ints", 1, 64),
    "num_filters": ("MODEL.BACKBONE_2D.NUM_FILTERS", "ints", 1, 1 << 16),
    "upsample_strides": ("MODEL.BACKBONE_2D.UPSAMPLE_STRIDES", "ints", 1, 64),
    "num_upsample_filters": ("MODEL.BACKBONE_2D.NUM_UPSAMPLE_FILTERS", "ints", 1, 1 << 16),
    "use_direction_classifier": ("MODEL.DENSE_HEAD.USE_DIRECTION_CLASSIFIER", "bool", None, None),
    "dir_offset": ("MODEL.DENSE_HEAD.DIR_OFFSET", "real", -2 * math.pi, 2 * math.pi),
    "dir_limit_offset": ("MODEL.DENSE_HEAD.DIR_LIMIT_OFFSET", "real", 0.0, 1.0),
    "num_dir_bins": ("MODEL.DENSE_HEAD.NUM_DIR_BINS", "int", 1, 360),
    "norm_by_num_examples": ("TARGET_ASSIGNER_CONFIG.NORM_BY_NUM_EXAMPLES", "bool", None, None),
    "match_height": ("TARGET_ASSIGNER_CONFIG.MATCH_HEIGHT", "bool", None, None),
    "cls_weight": ("LOSS_CONFIG.LOSS_WEIGHTS.cls_weight", "real", 0.0, None),
    "loc_weight": ("LOSS_CONFIG.LOSS_WEIGHTS.loc_weight", "real", 0.0, None),
    "dir_weight": ("LOSS_CONFIG.LOSS_WEIGHTS.dir_weight", "real", 0.0, None),
    "code_weights": ("LOSS_CONFIG.LOSS_WEIGHTS.code_weights", "reals", 0.0, None),
    "score_thresh": ("MODEL.POST_PROCESSING.SCORE_THRESH", "real", 0.0, 1.0),
    "multi_classes_nms": ("POST_PROCESSING.NMS_CONFIG.MULTI_CLASSES_NMS", "bool", None, None),
    "nms_thresh": ("POST_PROCESSING.NMS_CONFIG.NMS_THRESH", "real", 0.0, 1.0),
    "nms_pre_maxsize": ("POST_PROCESSING.NMS_CONFIG.NMS_PRE_MAXSIZE", "int", -1, _INT32),
    "nms_post_maxsize": ("POST_PROCESSING.NMS_CONFIG.NMS_POST_MAXSIZE", "int", -1, _INT32),
}
_OPEN_LOW = {"voxel_size"}  # sizes must be > 0
_OPEN_HIGH = {"score_thresh"}  # a sigmoid score never reaches 1
_ANCHOR_SPEC = {  # per entry of ANCHOR_GENERATOR_CONFIG
    "anchor_sizes": ("reals", 0.0, None), "anchor_rotations": ("reals", None, None),
    "anchor_bottom_heights": ("reals", None, None), "matched_threshold": ("real", 0.0, 1.0),
    "unmatched_threshold": ("real", 0.0, 1.0), "feature_map_stride": ("int", 1, 64),
}


def _check_value(value: Any, key: str, kind: str, lo, hi, lo_open: bool = False, hi_open: bool = False) -> None:
    """One value of a config: its kind (bools are not numbers, floats are not ints) and finite range."""
    what = {"int": "an int", "real": "a finite number", "bool": "true or false"}[kind]
    if kind == "bool":
        ok = isinstance(value, bool)
    elif kind == "int":
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value < hi if hi_open else value <= hi
    if not ok:
        bounds = [f"{'>' if lo_open else '>='} {lo:g}"] if lo is not None else []
        bounds += [f"{'<' if hi_open else '<='} {hi if kind == 'int' else f'{hi:g}'}"] if hi is not None else []
        raise ConfigError(f"{key} must be {what}{' ' if bounds else ''}{' and '.join(bounds)}, got {value!r}")


def _check_fields(cfg: "PointPillarsConfig") -> None:
    for name, (key, kind, lo, hi) in _SPEC.items():
        value = getattr(cfg, name)
        if kind in ("ints", "reals"):
            if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)) or not value:
                raise ConfigError(f"{key} must be a non-empty list of numbers, got {value!r}")
            for i, v in enumerate(value):
                _check_value(v, f"{key}[{i}]", kind[:-1], lo, hi, name in _OPEN_LOW, name in _OPEN_HIGH)
        else:
            _check_value(value, key, kind, lo, hi, name in _OPEN_LOW, name in _OPEN_HIGH)
    for i, entry in enumerate(cfg.anchor_generator_config):
        if not isinstance(entry, Mapping):
            raise ConfigError(f"ANCHOR_GENERATOR_CONFIG[{i}] must be a mapping, got {entry!r}")
        for name, (kind, lo, hi) in _ANCHOR_SPEC.items():
            if name not in entry:
                continue  # a missing key is named by validate()
            key = f"ANCHOR_GENERATOR_CONFIG[{i}].{name}"
            value = entry[name]
            if kind == "reals":
                flat = [v for row in value for v in (row if isinstance(row, (list, tuple)) else [row])] \
                    if isinstance(value, (list, tuple)) else None
                if not flat:
                    raise ConfigError(f"{key} must be a non-empty list of numbers, got {value!r}")
                for v in flat:
                    _check_value(v, key, "real", lo, hi, lo_open=name == "anchor_sizes")
            else:
                _check_value(value, key, kind, lo, hi)
        if "matched_threshold" in entry and "unmatched_threshold" in entry \
                and entry["unmatched_threshold"] > entry["matched_threshold"]:
            raise ConfigError(f"ANCHOR_GENERATOR_CONFIG[{i}]: unmatched_threshold {entry['unmatched_threshold']} must "
                              f"not exceed matched_threshold {entry['matched_threshold']}")


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
    match_height: bool = False
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
        for name, (_, kind, _, _) in _SPEC.items():  # checked numbers; reals stored as floats (0 -> 0.0)
            if kind == "real":
                setattr(self, name, float(getattr(self, name)))
            elif kind == "reals":
                setattr(self, name, [float(v) for v in getattr(self, name)])
            elif kind == "ints":
                setattr(self, name, list(getattr(self, name)))
        self.class_names = list(self.class_names)

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
        """Every field's type, finiteness and range (a ``ConfigError`` naming OpenPCDet's key and the field),
        then the consistency of the grid, the anchors and the backbone."""
        if not isinstance(self.class_names, (list, tuple)) or not all(isinstance(n, str) for n in self.class_names):
            raise ConfigError(f"CLASS_NAMES must be a list of names, got {self.class_names!r}")
        _check_fields(self)
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
        config). Options lidarops does not implement, and values of the wrong type or range, raise
        :class:`ConfigError` naming the key."""
        if not isinstance(cfg, Mapping):
            raise ConfigError(f"a config must be a mapping (OpenPCDet's schema), got {type(cfg).__name__}")
        model = _section(cfg, "MODEL")
        _expect(_get(model, "VFE.NAME"), ("PillarVFE",), "MODEL.VFE.NAME")
        _expect(_get(model, "MAP_TO_BEV.NAME", "PointPillarScatter"), ("PointPillarScatter",), "MODEL.MAP_TO_BEV.NAME")
        _expect(_get(model, "BACKBONE_2D.NAME"), ("BaseBEVBackbone",), "MODEL.BACKBONE_2D.NAME")
        _expect(_get(model, "DENSE_HEAD.NAME"), ("AnchorHeadSingle",), "MODEL.DENSE_HEAD.NAME")
        head = _section(model, "DENSE_HEAD", "MODEL.DENSE_HEAD")
        _expect(head.get("CLASS_AGNOSTIC", False), (False,), "MODEL.DENSE_HEAD.CLASS_AGNOSTIC")
        assigner = _section(head, "TARGET_ASSIGNER_CONFIG", "MODEL.DENSE_HEAD.TARGET_ASSIGNER_CONFIG", {})
        _expect(assigner.get("NAME", "AxisAlignedTargetAssigner"), ("AxisAlignedTargetAssigner",),
                "TARGET_ASSIGNER_CONFIG.NAME")
        _expect(assigner.get("BOX_CODER", "ResidualCoder"), ("ResidualCoder",), "TARGET_ASSIGNER_CONFIG.BOX_CODER")
        pos_fraction = assigner.get("POS_FRACTION", -1.0)
        _check_value(pos_fraction, "TARGET_ASSIGNER_CONFIG.POS_FRACTION", "real", None, None)
        if pos_fraction > 0:
            raise ConfigError("TARGET_ASSIGNER_CONFIG.POS_FRACTION > 0 (anchor sampling) is not supported; use -1.0")
        post = _section(model, "POST_PROCESSING", "MODEL.POST_PROCESSING", {})
        nms = _section(post, "NMS_CONFIG", "MODEL.POST_PROCESSING.NMS_CONFIG", {})
        _expect(nms.get("NMS_TYPE", "nms_gpu"), ("nms_gpu",), "POST_PROCESSING.NMS_CONFIG.NMS_TYPE")
        vfe = _section(model, "VFE", "MODEL.VFE")
        data = _section(cfg, "DATA_CONFIG", "DATA_CONFIG", {})
        processors = data.get("DATA_PROCESSOR", [])
        if not isinstance(processors, list) or not all(isinstance(p, Mapping) for p in processors):
            raise ConfigError(f"DATA_CONFIG.DATA_PROCESSOR must be a list of mappings, got {processors!r}")
        voxel = {p.get("NAME"): p for p in processors}.get("transform_points_to_voxels", {})
        encoding = _section(data, "POINT_FEATURE_ENCODING", "DATA_CONFIG.POINT_FEATURE_ENCODING", {})
        used = encoding.get("used_feature_list", ["x", "y", "z", "intensity"])
        if not isinstance(used, list):
            raise ConfigError(f"POINT_FEATURE_ENCODING.used_feature_list must be a list of names, got {used!r}")
        bb = _section(model, "BACKBONE_2D", "MODEL.BACKBONE_2D")
        weights = _section(_section(head, "LOSS_CONFIG", "MODEL.DENSE_HEAD.LOSS_CONFIG", {}), "LOSS_WEIGHTS",
                           "LOSS_CONFIG.LOSS_WEIGHTS", {})
        anchors = _get(head, "ANCHOR_GENERATOR_CONFIG")
        if not isinstance(anchors, list) or not all(isinstance(c, Mapping) for c in anchors):
            raise ConfigError(f"MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG must be a list of mappings, got {anchors!r}")
        names = _get(cfg, "CLASS_NAMES")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ConfigError(f"CLASS_NAMES must be a list of names, got {names!r}")
        # raw values: __post_init__ checks every type and range (naming the key), then makes reals floats
        kwargs = dict(
            class_names=list(names),
            point_cloud_range=_get(data, "POINT_CLOUD_RANGE", cls().point_cloud_range),
            voxel_size=voxel.get("VOXEL_SIZE", [0.16, 0.16, 4.0]),
            max_points_per_voxel=voxel.get("MAX_POINTS_PER_VOXEL", 32),
            max_voxels_train=_by_split(voxel.get("MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 40000}), "train",
                                       "MAX_NUMBER_OF_VOXELS"),
            max_voxels_test=_by_split(voxel.get("MAX_NUMBER_OF_VOXELS", {"train": 16000, "test": 40000}), "test",
                                      "MAX_NUMBER_OF_VOXELS"),
            num_point_features=len(used),
            vfe_num_filters=vfe.get("NUM_FILTERS", [64]),
            with_distance=vfe.get("WITH_DISTANCE", False),
            use_absolute_xyz=vfe.get("USE_ABSLOTE_XYZ", True),  # sic: OpenPCDet's spelling
            use_norm=vfe.get("USE_NORM", True),
            layer_nums=_get(bb, "LAYER_NUMS"),
            layer_strides=_get(bb, "LAYER_STRIDES"),
            num_filters=_get(bb, "NUM_FILTERS"),
            upsample_strides=_get(bb, "UPSAMPLE_STRIDES"),
            num_upsample_filters=_get(bb, "NUM_UPSAMPLE_FILTERS"),
            backbone_mode=bb.get("MODE", "dense"),
            anchor_generator_config=[{k.lower() if k.isupper() else k: copy.deepcopy(v) for k, v in c.items()}
                                     for c in anchors],
            use_direction_classifier=head.get("USE_DIRECTION_CLASSIFIER", True),
            dir_offset=head.get("DIR_OFFSET", 0.78539),
            dir_limit_offset=head.get("DIR_LIMIT_OFFSET", 0.0),
            num_dir_bins=head.get("NUM_DIR_BINS", 2),
            norm_by_num_examples=assigner.get("NORM_BY_NUM_EXAMPLES", False),
            match_height=assigner.get("MATCH_HEIGHT", False),
            cls_weight=weights.get("cls_weight", 1.0),
            loc_weight=weights.get("loc_weight", 2.0),
            dir_weight=weights.get("dir_weight", 0.2),
            code_weights=weights.get("code_weights", [1.0] * 7),
            score_thresh=post.get("SCORE_THRESH", 0.1),
            multi_classes_nms=nms.get("MULTI_CLASSES_NMS", False),
            nms_thresh=nms.get("NMS_THRESH", 0.01),
            nms_pre_maxsize=nms.get("NMS_PRE_MAXSIZE", 4096),
            nms_post_maxsize=nms.get("NMS_POST_MAXSIZE", 500),
        )
        return cls(**kwargs)
