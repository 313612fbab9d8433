"""Every name and keyword that CHANGELOG.md (0.2.0, "Deprecated names") renamed still works, with one
``DeprecationWarning`` naming its new home; the names it keeps importable from their 0.1 module ("still importable
from ...") are the new objects. The moved module paths are tests/test_layering.py's.

The suite turns lidarops' deprecation warnings into errors (pyproject.toml, ``filterwarnings``), so that no other
test uses an old name by accident; the checks here record the warnings themselves."""
from __future__ import annotations

import importlib
import sys
import warnings

import numpy as np
import pytest
import torch


def _get(path: str):
    """The object at ``package.module.name``."""
    module, name = path.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def _moved_module_get(path: str):
    """``from <moved module> import name``: importing the module path that moved is what warns."""
    module = path.rsplit(".", 1)[0]
    sys.modules.pop(module, None)
    return _get(path)


RANGE = (0.0, 0.0, 0.0, 2.0, 1.0, 1.0)
POINTS = torch.tensor([[0.1, 0.2, 0.3, 1.0], [1.5, 0.5, 0.5, 0.5], [1.6, 0.4, 0.2, 0.25]])


def _voxelize(**grid):
    return tuple(_get("lidarops.ops.voxelize.voxelize")(POINTS, (1.0, 1.0, 1.0), max_points_per_voxel=4,
                                                        max_voxels=8, **grid))


def _scene_boxes(method: str, *args, **heading):
    from lidarops.data.scene import Ground, _StaticBuilder

    builder = _StaticBuilder(Ground())
    getattr(builder, method)(*args, **heading)
    return builder.boxes


def _grid():
    return _get("lidarops.ops.pillars.PillarGrid")((0.0, 0.0, -1.0, 4.0, 2.0, 1.0), (0.5, 0.5))


# (the 0.1 name, its use, the same with the 0.2 name, the 0.2 name as the warning gives it); CHANGELOG.md's order
RENAMED = [
    ("lidarops.models.pointpillars.PointPillarsBackbone", lambda: _get("lidarops.models.pointpillars.PointPillarsBackbone"),
     lambda: _get("lidarops.models.BaseBEVBackbone"), "lidarops.models.bev_backbone.BaseBEVBackbone"),
    ("lidarops.models.PointPillarsBackbone", lambda: _get("lidarops.models.PointPillarsBackbone"),
     lambda: _get("lidarops.models.BaseBEVBackbone"), "lidarops.models.bev_backbone.BaseBEVBackbone"),
    ("lidarops.models.pointpillars.PillarFeatureNet", lambda: _get("lidarops.models.pointpillars.PillarFeatureNet"),
     lambda: _get("lidarops.models.sscater_pointpillars.PillarFeatureNet"),
     "lidarops.models.sscater_pointpillars.PillarFeatureNet"),
    ("lidarops.models.pointpillars.scatter_to_bev", lambda: _get("lidarops.models.pointpillars.scatter_to_bev"),
     lambda: _get("lidarops.models.map_to_bev.scatter_to_bev"), "lidarops.models.map_to_bev.scatter_to_bev"),
    ("lidarops.models.pointpillars.backbone_layers", lambda: _get("lidarops.models.pointpillars.backbone_layers"),
     lambda: _get("lidarops.models.bev_backbone.backbone_layers"), "lidarops.models.bev_backbone.backbone_layers"),
    ("lidarops.models.pointpillars.BackboneLayer", lambda: _get("lidarops.models.pointpillars.BackboneLayer"),
     lambda: _get("lidarops.models.bev_backbone.BackboneLayer"), "lidarops.models.bev_backbone.BackboneLayer"),
    ("lidarops.sscater.SSCATeRPointPillars", lambda: _get("lidarops.sscater.SSCATeRPointPillars"),
     lambda: _get("lidarops.models.SSCATeRPointPillars"), "lidarops.models.sscater_pointpillars.SSCATeRPointPillars"),
    ("lidarops.models.load_config", lambda: _get("lidarops.models.load_config"),
     lambda: _get("lidarops.config.load_config"), "lidarops.config.load_config"),
    ("lidarops.models.config.load_config", lambda: _get("lidarops.models.config.load_config"),
     lambda: _get("lidarops.config.load_config"), "lidarops.config.load_config"),
    ("lidarops.models.config.merge_config", lambda: _get("lidarops.models.config.merge_config"),
     lambda: _get("lidarops.config.merge_config"), "lidarops.config.merge_config"),
    ("lidarops.models.detector.CheckpointMismatchError",
     lambda: _moved_module_get("lidarops.models.detector.CheckpointMismatchError"),
     lambda: _get("lidarops.checkpoint.CheckpointError"), "lidarops.checkpoint"),
    ("lidarops.data.detection.DEFAULT_CLASS_NAMES", lambda: _get("lidarops.data.detection.DEFAULT_CLASS_NAMES"),
     lambda: _get("lidarops.conventions.KITTI_CLASSES"), "lidarops.conventions.KITTI_CLASSES"),
    # keywords
    ("voxelize(point_range=)", lambda: _voxelize(point_range=RANGE), lambda: _voxelize(point_cloud_range=RANGE),
     "point_cloud_range="),
    ("voxel_grid_shape(point_range=)",
     lambda: _get("lidarops.ops.voxelize.voxel_grid_shape")((0.5, 0.5, 1.0), point_range=RANGE),
     lambda: _get("lidarops.ops.voxelize.voxel_grid_shape")((0.5, 0.5, 1.0), point_cloud_range=RANGE),
     "point_cloud_range="),
    ("PillarGrid(point_range=)", lambda: _get("lidarops.ops.pillars.PillarGrid")(point_range=RANGE, voxel_size=(0.5, 0.5)),
     lambda: _get("lidarops.ops.pillars.PillarGrid")(point_cloud_range=RANGE, voxel_size=(0.5, 0.5)),
     "point_cloud_range="),
    ("PillarGrid(pillar_size=)", lambda: _get("lidarops.ops.pillars.PillarGrid")(point_cloud_range=RANGE, pillar_size=(0.5, 0.5)),
     lambda: _get("lidarops.ops.pillars.PillarGrid")(point_cloud_range=RANGE, voxel_size=(0.5, 0.5)), "voxel_size="),
    ("PillarGrid.point_range", lambda: _grid().point_range, lambda: _grid().point_cloud_range,
     "PillarGrid.point_cloud_range"),
    ("scene box(yaw=)", lambda: _scene_boxes("box", 1.0, 2.0, 0.5, 4.0, 2.0, 1.5, yaw=0.4),
     lambda: _scene_boxes("box", 1.0, 2.0, 0.5, 4.0, 2.0, 1.5, heading=0.4), "heading="),
    ("scene box_on_ground(yaw=)", lambda: _scene_boxes("box_on_ground", 1.0, 2.0, 4.0, 2.0, 1.5, yaw=0.4),
     lambda: _scene_boxes("box_on_ground", 1.0, 2.0, 4.0, 2.0, 1.5, heading=0.4), "heading="),
]

#: names CHANGELOG.md keeps importable from their 0.1 module ("still importable from ..."): (old, new)
KEPT = [*[(f"lidarops.data.detection.{n}", f"lidarops.data.augment.{n}")
          for n in ("flip_along_x", "flip_along_y", "rotate_world", "scale_world", "GtDatabase", "GtSampler",
                    "build_gt_database")],
        ("lidarops.data.detection.collate_batch", "lidarops.data.collate_batch"),
        ("lidarops.data.detection.kitti_difficulty", "lidarops.data.formats.kitti.kitti_difficulty"),
        ("lidarops.train.checkpoint.save_checkpoint", "lidarops.checkpoint.save_checkpoint"),
        ("lidarops.train.checkpoint.check_plain", "lidarops.checkpoint.check_plain"),
        *[(f"lidarops.stream.{n}", f"lidarops.ops.pillars.{n}") for n in ("pillarize", "PillarGrid", "Pillars")]]


def _same(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and torch.equal(a, b)
    return a == b


@pytest.mark.parametrize("old, use_old, use_new, new", [pytest.param(*case, id=case[0]) for case in RENAMED])
def test_renamed_name_or_keyword_works_and_warns_once(old, use_old, use_new, new):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = use_old()
    deprecations = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert len(deprecations) == 1, f"{old}: expected one DeprecationWarning, got {deprecations}"
    assert "is deprecated: use" in deprecations[0] and new in deprecations[0], \
        f"{old}: the warning does not name {new}: {deprecations[0]}"
    assert _same(got, use_new()), f"{old} does not give what {new} gives"


@pytest.mark.parametrize("old, new", [pytest.param(*case, id=case[0]) for case in KEPT])
def test_kept_name_is_the_new_object(old, new):
    assert _get(old) is _get(new)


def test_old_and_new_keyword_together_are_an_error():
    with pytest.raises(TypeError, match="give point_cloud_range= only"):
        _voxelize(point_range=RANGE, point_cloud_range=RANGE)


def test_collate_detection_keeps_the_old_format_and_warns_once():
    """``lidarops.data.datasets.collate_detection`` (CHANGELOG: "the old function keeps the 0.1 format, with a
    warning"): 0-based labels, ``boxes``, ``batch_index``."""
    from lidarops.data.datasets import collate_detection

    item = {"points": np.ones((3, 4), np.float32), "gt_boxes": np.array([[1, 2, 3, 4, 5, 6, 0.5, 2]], np.float32),
            "frame_id": 7}
    with pytest.deprecated_call(match="collate_detection is deprecated: use lidarops.data.collate_batch") as caught:
        batch = collate_detection([item])
    assert len([w for w in caught if issubclass(w.category, DeprecationWarning)]) == 1
    assert batch["labels"].tolist() == [[1]] and batch["boxes"].shape == (1, 1, 7) and batch["frame_index"] == [7]
    assert batch["batch_index"].tolist() == [0, 0, 0] and batch["points"].shape == (3, 4)


def test_a_deprecated_name_fails_a_test():
    """pyproject.toml's ``filterwarnings``: outside ``pytest.warns`` / ``deprecated_call`` an old name raises."""
    with pytest.raises(DeprecationWarning, match="PointPillarsBackbone is deprecated: use"):
        _get("lidarops.models.pointpillars.PointPillarsBackbone")
