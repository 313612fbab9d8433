"""Models built on lidarops' ops, each readable top to bottom in one file, built from parts named by role.

Detectors and their parts (OpenPCDet's names, so checkpoints and habits carry over):

* :class:`PointPillars` (:mod:`~lidarops.models.pointpillars`): the detector; its parts ``vfe``
  (:class:`PillarVFE`), ``map_to_bev`` (:class:`PointPillarScatter`), ``backbone_2d``
  (:class:`BaseBEVBackbone`, dense or sparse) and ``dense_head`` (:class:`AnchorHeadSingle`) are importable
  on their own; the box machinery is :mod:`~lidarops.models.anchors`, the losses
  :mod:`~lidarops.models.losses`, the post-processing :mod:`~lidarops.models.postprocess`.
* :class:`GraphedPointPillars` (:mod:`~lidarops.models.cuda_graph`): its inference as one CUDA graph.
* :class:`SSCATeRPointPillars` (:mod:`~lidarops.models.sscater_pointpillars`): a LiDAR stream through
  SSCATeR's recycling backbone.
* :class:`PointPillarsConfig` (:mod:`~lidarops.models.config`): the typed config (YAML through
  :func:`lidarops.config.load_config`).

Classification: :class:`PointNet` (:mod:`~lidarops.models.pointnet`), the classifier CAS-Net's
experiments put behind a sampler.

CAS-Net, learned point cloud simplification (:mod:`~lidarops.models.casnet`): :class:`CASNet` and its
parts (:class:`OffsetAttention`; the losses :func:`chamfer_distance`, :func:`selection_cosine_loss`), and
the samplers behind one interface ``sampler(points, m) -> indices`` (:class:`RandomSampler`,
:class:`FPSSampler`, :class:`ChunkedFPSSampler`, :class:`CASNetSampler`; :mod:`~lidarops.models.samplers`).

Files: :func:`load_model` builds whatever model a checkpoint names (through :data:`MODELS`);
:mod:`~lidarops.models.weights` holds the shipped ones (``weights.load("pointpillars_synth")``).
Submodules are imported on first use.
"""
from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from lidarops._lazy import lazy_attributes
from lidarops._moved import moved_attributes

__all__ = ["MODELS", "model_class", "load_model", "PointPillars", "PointPillarsConfig", "GraphedPointPillars",
           "SSCATeRPointPillars", "PillarVFE", "PointPillarScatter", "BaseBEVBackbone", "AnchorHeadSingle",
           "weights", "PointNet", "PointNetConfig", "CASNet", "CASNetPointNet", "CASNetPointNetConfig", "CASNetPointPillars", "CASNetPointPillarsConfig", "load_casnet", "CounterNet", "CounterNetConfig", "SelectedCounter", "CASNetSampler", "segment_and_sample", "casnet_loss", "OffsetAttention",
           "chamfer_distance", "selection_cosine_loss", "RandomSampler", "FPSSampler", "ChunkedFPSSampler",
           "sample_features"]

#: Every model a checkpoint can name, by ``model_class`` (the class name lidarops writes) and by the
#: ``MODEL.NAME`` of OpenPCDet's configs: name -> (module, class). The one table; models register nothing.
MODELS: dict[str, tuple[str, str]] = {
    "PointPillars": ("lidarops.models.pointpillars", "PointPillars"),
    "PointPillar": ("lidarops.models.pointpillars", "PointPillars"),  # OpenPCDet's MODEL.NAME
    "PointNet": ("lidarops.models.pointnet", "PointNet"),
    "CASNetPointNet": ("lidarops.models.casnet_pointnet", "CASNetPointNet"),
    "CASNetPointPillars": ("lidarops.models.casnet_pointpillars", "CASNetPointPillars"),
    "CASNet": ("lidarops.models.casnet", "CASNet"),
    "CounterNet": ("lidarops.models.counternet", "CounterNet"),
}


def model_class(name: str) -> type:
    """The model class :data:`MODELS` names ``name``; ``ValueError`` listing the known names."""
    entry = MODELS.get(name) if isinstance(name, str) else None
    if entry is None:
        raise ValueError(f"unknown model {name!r}: lidarops builds {sorted(MODELS)}")
    return getattr(importlib.import_module(entry[0]), entry[1])


def load_model(path: "str | Path", config: Any = None, map_location: Any = "cpu", check_finite: bool = True):
    """The model a checkpoint holds, built from the class and config it records and loaded with its weights
    (strict: every key and shape must fit), in eval mode.

    Args:
        path: a checkpoint lidarops wrote (a training run's ``final.pth``, a shipped or exported model) or,
            with ``config``, an OpenPCDet checkpoint.
        config: the model config for a file that records none (an OpenPCDet checkpoint); its ``MODEL.NAME``
            picks the class.
        map_location: as ``torch.load``; a device (``"cuda"``, ``torch.device(...)``) also puts the model there.
        check_finite (bool): refuse weights holding NaN or infinite values (naming the tensors).

    Raises:
        FileNotFoundError, lidarops.checkpoint.CheckpointError: no such file, not a checkpoint, or weights
            that do not fit (the message names the keys).
        ValueError: a model class lidarops does not know.
    """
    from lidarops.checkpoint import CheckpointError, model_record, read_checkpoint

    ckpt = read_checkpoint(path, map_location)
    record = model_record(ckpt, str(path))
    name = record.model_class
    if name == "SelectedCounter":  # CounterNets behind a per-frame choice: their checkpoints, not weights
        from lidarops.models.counternet_selection import SelectedCounter

        return SelectedCounter.load(path, map_location).eval()
    if name is not None and name not in MODELS:
        raise CheckpointError(f"{path}: model_class {name!r} is not a model this lidarops builds "
                              f"({', '.join(sorted(MODELS))}); a newer lidarops may")
    if name is None:
        if config is None:
            raise CheckpointError(f"{path} records no model (an OpenPCDet checkpoint?): pass config=... (a YAML "
                                  "path or dict whose MODEL.NAME names the model)")
        cfg = config
        if isinstance(config, (str, Path)):
            from lidarops.config import load_config

            cfg = load_config(config)
        name = cfg.get("MODEL", {}).get("NAME", "PointPillars") if isinstance(cfg, dict) else type(cfg).__name__
        name = "PointPillars" if name == "PointPillarsConfig" else name
    cls = model_class(name)
    return cls.from_checkpoint(path, config=config, map_location=map_location, check_finite=check_finite).eval()


__getattr__, __dir__ = lazy_attributes(__name__, {
    "PointPillars": ("lidarops.models.pointpillars", "PointPillars"),
    "PointPillarsConfig": ("lidarops.models.config", "PointPillarsConfig"),
    "GraphedPointPillars": ("lidarops.models.cuda_graph", "GraphedPointPillars"),
    "SSCATeRPointPillars": ("lidarops.models.sscater_pointpillars", "SSCATeRPointPillars"),
    "PillarVFE": ("lidarops.models.pillar_vfe", "PillarVFE"),
    "PointPillarScatter": ("lidarops.models.map_to_bev", "PointPillarScatter"),
    "BaseBEVBackbone": ("lidarops.models.bev_backbone", "BaseBEVBackbone"),
    "AnchorHeadSingle": ("lidarops.models.anchor_head", "AnchorHeadSingle"),
    "PointNet": ("lidarops.models.pointnet", "PointNet"),
    "PointNetConfig": ("lidarops.models.pointnet", "PointNetConfig"),
    "CASNet": ("lidarops.models.casnet", "CASNet"),
    "CASNetPointNet": ("lidarops.models.casnet_pointnet", "CASNetPointNet"),
    "CASNetPointNetConfig": ("lidarops.models.casnet_pointnet", "CASNetPointNetConfig"),
    "CASNetPointPillars": ("lidarops.models.casnet_pointpillars", "CASNetPointPillars"),
    "CASNetPointPillarsConfig": ("lidarops.models.casnet_pointpillars", "CASNetPointPillarsConfig"),
    "load_casnet": ("lidarops.models.casnet", "load_casnet"),
    "CounterNet": ("lidarops.models.counternet", "CounterNet"),
    "CounterNetConfig": ("lidarops.models.counternet", "CounterNetConfig"),
    "SelectedCounter": ("lidarops.models.counternet_selection", "SelectedCounter"),
    "CASNetSampler": ("lidarops.models.casnet", "CASNetSampler"),
    "segment_and_sample": ("lidarops.models.casnet", "segment_and_sample"),
    "casnet_loss": ("lidarops.models.casnet", "casnet_loss"),
    "OffsetAttention": ("lidarops.models.offset_attention", "OffsetAttention"),
    "chamfer_distance": ("lidarops.models.casnet_losses", "chamfer_distance"),
    "selection_cosine_loss": ("lidarops.models.casnet_losses", "selection_cosine_loss"),
    "RandomSampler": ("lidarops.models.samplers", "RandomSampler"),
    "FPSSampler": ("lidarops.models.samplers", "FPSSampler"),
    "ChunkedFPSSampler": ("lidarops.models.samplers", "ChunkedFPSSampler"),
    "sample_features": ("lidarops.models.samplers", "sample_features"),
    "weights": "lidarops.models.weights",
}, globals())
__getattr__ = moved_attributes(__name__, {"PointPillarsBackbone": ("lidarops.models.bev_backbone", "BaseBEVBackbone")},
                               fallback=__getattr__)
